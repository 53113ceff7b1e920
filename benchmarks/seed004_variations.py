"""Seed 004's simulation under controlled departures from the paper, one assumption at a time.

Run: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python -m benchmarks.seed004_variations`` (a
markdown table; about 3–4 s per variation and seed: the full table over five seeds takes some
minutes, ``--only`` picks variations). Every variation is
:func:`benchmarks.seed004_compliance.reproduce_seed004` with the paper's set-up except for the one
named assumption (:data:`VARIATIONS`; :data:`PAIRS` change two at once); each is run over several
random seeds (the pose set and the link-5 noise change with the seed) and the columns give mean ±
standard deviation over the seeds of the mean PSD distance error (mm), then of the improved
model's identified C2 (×1e-5 rad/(N m); the paper's is 5.92). The last column counts the seeds in
which the paper's scheme (7-pose calibrations, averaged) puts the improved model below the
original one.
Results and their discussion: ``docs/models-001-004.md``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from benchmarks.seed004_compliance import (
    SEED004_COMPLIANCE_RAD_PER_NM,
    SEED004_ZERO_OFFSETS_DEG,
    PsdSetup,
    Seed004Result,
    reproduce_seed004,
)

__all__ = [
    "C2_COLUMNS",
    "COLUMNS",
    "PAIRS",
    "VARIATIONS",
    "Variation",
    "VariationRow",
    "main",
    "run_variation",
]


@dataclass(frozen=True, slots=True)
class Variation:
    """One departure from the paper's simulation: its name, what it changes, the keyword arguments."""

    name: str
    changes: str
    kwargs: dict[str, Any]


def _comp(scale: float) -> tuple[float, ...]:
    return tuple(scale * c for c in SEED004_COMPLIANCE_RAD_PER_NM)


_WALL = PsdSetup(
    center_mm=np.array([1100.0, 0.0, 400.0]),
    normal=np.array([-1.0, 0.0, 0.0]),
    standoff_mm=(400.0, 700.0),
    seed_deg=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
)

VARIATIONS: tuple[Variation, ...] = (
    Variation("paper", "the paper's set-up: s = 1 mm, U(0, 1), 30 × 7 poses averaged, P unknown", {}),
    Variation("noise_0.1", "noise scale s = 0.1 mm", {"link5_noise_mm": 0.1}),
    Variation("noise_0.3", "noise scale s = 0.3 mm", {"link5_noise_mm": 0.3}),
    Variation("noise_0.5", "noise scale s = 0.5 mm", {"link5_noise_mm": 0.5}),
    Variation("noise_2", "noise scale s = 2 mm", {"link5_noise_mm": 2.0}),
    Variation("centred", "noise s·(U(0, 1) − 0.5): zero mean", {"noise": "centred"}),
    Variation("noise_per_cal", "one noise draw per 7 poses (per calibration)", {"noise_block": 7}),
    Variation("median", "median of the 30 results instead of the mean", {"averaging": "median"}),
    Variation("per_cal_14", "14 poses per calibration (15 averaged)", {"poses_per_calibration": 14}),
    Variation("per_cal_30", "30 poses per calibration (7 averaged)", {"poses_per_calibration": 30}),
    Variation("per_cal_70", "70 poses per calibration (3 averaged)", {"poses_per_calibration": 70}),
    Variation("known_point", "PSD centre given to the calibration (θ1 identifiable)", {"known_point": True}),
    Variation("line_error", "error = distance of the PSD centre from the beam", {"error": "line"}),
    Variation("c2_only", "improved model identifies C2 only", {"compliance_joints": (2,)}),
    Variation("c_negative", "C2, C3 with the paper's negative sign", {"compliance_rad_per_nm": _comp(-1.0)}),
    Variation("c_x2", "C2, C3 twice the paper's (or τ twice ours)", {"compliance_rad_per_nm": _comp(2.0)}),
    Variation("c_x3", "C2, C3 three times the paper's", {"compliance_rad_per_nm": _comp(3.0)}),
    Variation("payload_3kg", "3 kg at the TCP in every pose", {"payload_kg": 3.0}),
    Variation(
        "offsets_mrad",
        "zero offsets (0, −1, −2, −1, 1, −2) in mrad, not degrees",
        {"zero_offsets_deg": tuple(np.rad2deg(1e-3 * np.asarray(SEED004_ZERO_OFFSETS_DEG)))},
    ),
    Variation("cone_15", "beams within 15° of the PSD normal", {"setup": PsdSetup(cone_deg=15.0)}),
    Variation("cone_70", "beams within 70° of the PSD normal", {"setup": PsdSetup(cone_deg=70.0)}),
    Variation("psd_wall", "PSD on a wall at x = 1100 mm, stand-off 400–700 mm", {"setup": _WALL}),
)

# two departures at once: the pairs that bring both of the paper's numbers back
PAIRS: tuple[Variation, ...] = (
    Variation(
        "per_cal_30+c_x2",
        "30 poses per calibration and C twice the paper's",
        {"poses_per_calibration": 30, "compliance_rad_per_nm": _comp(2.0)},
    ),
    Variation(
        "noise_per_cal+c_x2",
        "one noise draw per calibration and C twice the paper's",
        {"noise_block": 7, "compliance_rad_per_nm": _comp(2.0)},
    ),
    Variation(
        "per_cal_30+cone_70",
        "30 poses per calibration and beams within 70°",
        {"poses_per_calibration": 30, "setup": PsdSetup(cone_deg=70.0)},
    ),
)

COLUMNS: tuple[tuple[str, Callable[[Seed004Result], float]], ...] = (
    ("uncompensated", lambda r: r.uncompensated_mm),
    ("true model", lambda r: r.true_model_mm),
    ("original, averaged", lambda r: r.zero_offset_mm),
    ("improved, averaged", lambda r: r.compliance_mm),
    ("original, all poses", lambda r: r.zero_offset_joint_mm),
    ("improved, all poses", lambda r: r.compliance_joint_mm),
)
# the improved model's C2 (rad/(N m), ×1e-5; the paper's is 5.92), averaged and from all poses
C2_COLUMNS: tuple[tuple[str, Callable[[Seed004Result], float]], ...] = (
    ("C2 averaged", lambda r: 1e5 * r.compliance_model.compliance_rad_per_nm[1]),
    ("C2 all poses", lambda r: 1e5 * r.compliance_joint_model.compliance_rad_per_nm[1]),
)


@dataclass(frozen=True, slots=True)
class VariationRow:
    """A variation's results over the seeds: mean distance errors (mm) and the improved model's C2."""

    variation: Variation
    seeds: tuple[int, ...]
    values_mm: np.ndarray  # (n_seeds, len(COLUMNS))
    c2: np.ndarray  # (n_seeds, len(C2_COLUMNS)), rad/(N m) ×1e-5

    def improved_wins(self) -> int:
        """Seeds in which the averaged improved model beats the averaged original one."""
        return int(np.sum(self.values_mm[:, 3] < self.values_mm[:, 2]))

    def markdown(self) -> str:
        mean, sd = self.values_mm.mean(axis=0), self.values_mm.std(axis=0)
        many = len(self.seeds) > 1
        cells = [f"{m:.3f} ± {s:.3f}" if many else f"{m:.3f}" for m, s in zip(mean, sd, strict=True)]
        c_mean, c_sd = self.c2.mean(axis=0), self.c2.std(axis=0)
        cells += [f"{m:.1f} ± {s:.1f}" if many else f"{m:.1f}" for m, s in zip(c_mean, c_sd, strict=True)]
        wins = f"{self.improved_wins()}/{len(self.seeds)}"
        return f"| {self.variation.name} | {self.variation.changes} | {' | '.join(cells)} | {wins} |"

    @staticmethod
    def _by_column(values: np.ndarray) -> dict[str, float]:
        return {name: round(float(v), 4) for (name, _), v in zip(COLUMNS, values, strict=True)}

    def table(self) -> dict[str, Any]:
        return {
            "changes": self.variation.changes,
            "seeds": list(self.seeds),
            "mean_mm": self._by_column(self.values_mm.mean(axis=0)),
            "sd_mm": self._by_column(self.values_mm.std(axis=0)),
            "per_seed_mm": self.values_mm.round(4).tolist(),
            "improved_wins_averaged": self.improved_wins(),
            "C2_1e-5_rad_per_nm": {
                name: self.c2[:, k].round(2).tolist() for k, (name, _) in enumerate(C2_COLUMNS)
            },
        }


def run_variation(variation: Variation, seeds: Sequence[int]) -> VariationRow:
    """``reproduce_seed004`` with the variation's arguments, once per seed."""
    values, c2 = [], []
    for seed in seeds:
        result = reproduce_seed004(seed=seed, **variation.kwargs)
        values.append([get(result) for _, get in COLUMNS])
        c2.append([get(result) for _, get in C2_COLUMNS])
    return VariationRow(variation=variation, seeds=tuple(seeds), values_mm=np.array(values), c2=np.array(c2))


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m benchmarks.seed004_variations``: the table of one-at-a-time departures."""
    everything = (*VARIATIONS, *PAIRS)
    names = [v.name for v in everything]
    parser = argparse.ArgumentParser(description="Seed 004's simulation, one assumption varied at a time")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument(
        "--only", nargs="+", choices=names, default=names, metavar="NAME", help=", ".join(names)
    )
    parser.add_argument("--json", action="store_true", help="JSON instead of a markdown table")
    args = parser.parse_args(argv)
    chosen = [v for v in everything if v.name in args.only]
    if not args.json:
        head = " | ".join(n for n, _ in (*COLUMNS, *C2_COLUMNS))
        print(f"| variation | changes | {head} | improved wins (averaged) |")
        print("|" + "---|" * (len(COLUMNS) + len(C2_COLUMNS) + 3))
    out: dict[str, Any] = {}
    for variation in chosen:
        row = run_variation(variation, args.seeds)
        if args.json:
            out[variation.name] = row.table()
        else:
            print(row.markdown(), flush=True)
    if args.json:
        print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
