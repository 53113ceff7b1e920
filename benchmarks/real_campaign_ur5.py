"""Convert the public UR5 laser-tracker campaign of Jacobi (2025) into the project's data set CSV.

Source: ``3D_UR5_uncalibrated_grid_cleaned.csv`` of the repository ``pauljac7700/serial_robots_datasets``
(MIT licence; copyright and licence in ``benchmarks/real_campaigns/ur5_jacobi/LICENSE``). 1 000 poses
of a Universal Robots UR5 measured with a laser tracker (one reflector, 1.5 in SMR). Columns:
``step_order, x_t, y_t, z_t, x_dif, y_dif, z_dif, joint_1 … joint_6``: the wanted TCP position in
the robot base frame (mm; the nominal forward kinematics of the commanded joints), the difference
between it and the measured position (mm), the commanded joint angles (deg).

Conversion (``shared/spec/dataset.md``):

* ``a1 … a6`` = ``joint_1 … joint_6`` (deg; the UR5's joint angles are its DH angles, sign +1,
  offset 0, see ``ur5.toml`` beside the data);
* ``x, y, z`` = ``x_t − x_dif`` … : the measured TCP. The source names the difference "target minus
  actual" (its README defines its residuals as ``P_target − FK(θ_cmd)``); ``--sign plus`` takes
  ``x_t + x_dif`` instead. The frame is the robot's base frame (the source registered the tracker
  to it before the campaign), so the diagnosis runs with ``--frame base`` or ``auto``;
* ``pose_id`` = ``P`` + ``step_order`` (the measuring order: the campaign clock is then the row order,
  there is no ``t_s``); ``payload_kg`` 0 (the reflector only); no ``dir`` (backlash cannot be
  tested), no ``temp_c``, no ``split`` (check rows are drawn by the readers, 30 %, fixed seed).

The converter checks the source: 13 numeric columns, ``step_order`` 0 … n−1, and that the wanted
positions are the nominal forward kinematics of the commanded joints (a typing or transfer fault in
a joint or target column shows as a pose that does not fit).

Run::

    python -m benchmarks.real_campaign_ur5 [SOURCE.csv] --out ur5_campaign.csv

without ``SOURCE`` it reads the copy in ``benchmarks/real_campaigns/ur5_jacobi/``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from comp_daemon.data.dataset import Dataset, write_dataset
from comp_daemon.kinematics.params import KinematicParams
from comp_daemon.models.effects import EffectParams, MassModel, twin_tcp_mm
from comp_daemon.robot.description import load_robot

HERE = Path(__file__).resolve().parent / "real_campaigns" / "ur5_jacobi"
SOURCE = HERE / "ur5_grid_uncalibrated.csv"
ROBOT = HERE / "ur5.toml"
COLUMNS = (
    "step_order",
    "x_t",
    "y_t",
    "z_t",
    "x_dif",
    "y_dif",
    "z_dif",
    *(f"joint_{j}" for j in range(1, 7)),
)
#: the wanted positions must match the nominal UR5 (the robot file's) to this RMS, mm; the
#: source's own nominal differs from the published one by about 0.09 mm in d5
TARGET_MATCH_RMS_MM = 0.5


def read_source(path: Path) -> NDArray[np.float64]:
    """The source table (n, 13) in :data:`COLUMNS` order; ValueError naming the fault."""
    lines = path.read_text(encoding="utf-8").splitlines()
    header = [h.strip() for h in lines[0].split(",")]
    if tuple(header) != COLUMNS:
        raise ValueError(f"{path}: expected the columns {', '.join(COLUMNS)}, got {', '.join(header)}")
    rows = []
    for k, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        cells = line.split(",")
        if len(cells) != len(COLUMNS):
            raise ValueError(f"{path}: row {k} has {len(cells)} cells, expected {len(COLUMNS)}")
        try:
            rows.append([float(c) for c in cells])
        except ValueError:
            raise ValueError(f"{path}: row {k} has a cell that is not a number") from None
    table = np.array(rows, dtype=float)
    if not np.array_equal(table[:, 0], np.arange(len(table))):
        raise ValueError(f"{path}: step_order is not 0 … {len(table) - 1} in order")
    return table


def convert(table: NDArray[np.float64], *, sign: str = "minus", source: str = "ur5") -> Dataset:
    """The data set of the source table (see the module docstring)."""
    target = table[:, 1:4]
    dif = table[:, 4:7]
    measured = np.round(target - dif if sign == "minus" else target + dif, 6)
    return Dataset(
        a_deg=table[:, 7:13],
        xyz_mm=measured,
        pose_id=tuple(f"P{int(s):04d}" for s in table[:, 0]),
        source=source,
    )


def target_mismatch_mm(table: NDArray[np.float64]) -> float:
    """RMS distance (mm) between the wanted positions and the nominal UR5 TCP of the joints."""
    robot = load_robot(ROBOT)
    tcp = twin_tcp_mm(
        MassModel.from_robot(robot),
        KinematicParams.from_robot(robot),
        EffectParams.zeros(1),
        table[:, 7:13],
        None,
        np.zeros(len(table)),
        None,
    )
    return float(np.sqrt(np.mean(np.sum((tcp - table[:, 1:4]) ** 2, axis=1))))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", nargs="?", default=str(SOURCE), help="the source CSV")
    parser.add_argument("--out", required=True, help="the data set CSV to write")
    parser.add_argument("--sign", choices=("minus", "plus"), default="minus", help="measured = x_t ∓ x_dif")
    args = parser.parse_args(argv)
    table = read_source(Path(args.source))
    mismatch = target_mismatch_mm(table)
    if mismatch > TARGET_MATCH_RMS_MM:
        print(
            f"{args.source}: the wanted positions miss the nominal UR5 by {mismatch:.3f} mm RMS: "
            "not the campaign this converter knows",
            file=sys.stderr,
        )
        return 1
    dataset = convert(table, sign=args.sign, source=Path(args.source).name)
    write_dataset(dataset, args.out)
    print(
        f"{len(table)} poses written to {args.out} (wanted positions vs nominal UR5: {mismatch:.3f} mm RMS)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
