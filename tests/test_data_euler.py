"""A 6-DOF probe's orientation exported as Euler angles (columns e1, e2, e3), read with a stated
convention (``--euler``) into the quaternion columns; scipy's Rotation is the reference."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from comp_daemon.cli import main
from comp_daemon.data.dataset import DatasetError, read_dataset, read_dataset_json
from comp_daemon.data.euler import euler_to_quaternion, parse_euler
from comp_daemon.data.options import ReadOptions
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.robot.description import load_robot

N = 40
RNG = np.random.default_rng(7)
ROTATIONS = Rotation.random(N, random_state=11)


def _same_rotation(q_wxyz: np.ndarray, reference: Rotation) -> None:
    ref = reference.as_quat()[:, [3, 0, 1, 2]]  # scipy writes w last
    assert np.all(q_wxyz[:, 0] >= 0.0)
    # q and -q are one rotation
    assert np.max(np.minimum(np.abs(q_wxyz - ref), np.abs(q_wxyz + ref)).max(axis=1)) < 1e-12


def _scipy_seq(convention: str) -> str:
    kind, axes = convention.split("-")[:2]
    return axes.upper() if kind == "intrinsic" else axes


def _probe_file(convention: str, sep: str = ",", radians: bool = False, comma: bool = False) -> str:
    """A campaign whose probe orientations are ROTATIONS written as e1, e2, e3 in ``convention``."""
    e = ROTATIONS.as_euler(_scipy_seq(convention), degrees=not radians)

    def num(v: float) -> str:
        text = repr(float(v))
        return text.replace(".", ",") if comma else text

    kr = KinematicParams.from_robot(load_robot("kr210"))
    a_deg = np.array([[10.0 + i, -90.0 + i, 90.0 - i, 5.0, 20.0 + i / 2, -3.0 * i] for i in range(N)])
    positions = tcp_position_mm(kr, axes_deg_to_q_rad(a_deg, kr.sign))
    lines = [sep.join(["a1", "a2", "a3", "a4", "a5", "a6", "x", "y", "z", "e1", "e2", "e3", "sigma_mm"])]
    for i in range(N):
        axes, xyz = list(a_deg[i]), list(positions[i])
        if radians:
            axes = list(np.radians(axes))
        lines.append(sep.join([*map(num, axes), *map(num, xyz), *map(num, e[i]), num(0.01)]))
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize(
    "convention", ["intrinsic-zyx", "extrinsic-xyz", "intrinsic-zyz", "extrinsic-zxz", "intrinsic-xyz"]
)
def test_euler_columns_read_into_the_quaternion_of_the_stated_convention(convention: str) -> None:
    data = read_dataset(_probe_file(convention), options=ReadOptions.of(euler=convention))
    assert data.probe_q_wxyz is not None
    _same_rotation(data.probe_q_wxyz, ROTATIONS)
    assert not data.extra  # e1, e2, e3 became qw..qz, nothing kept as text


def test_the_conversion_matches_scipy_for_every_sequence() -> None:
    e = RNG.uniform(-180.0, 180.0, (200, 3))
    for axes in ("xyz", "xzy", "yxz", "yzx", "zxy", "zyx", "xyx", "xzx", "yxy", "yzy", "zxz", "zyz"):
        for intrinsic in (True, False):
            q = euler_to_quaternion(e, axes, intrinsic=intrinsic)
            _same_rotation(q, Rotation.from_euler(axes.upper() if intrinsic else axes, e, degrees=True))


def test_intrinsic_zyx_is_kukas_abc_and_the_mirror_of_extrinsic_xyz() -> None:
    abc = np.array([[30.0, -20.0, 45.0]])
    intrinsic = euler_to_quaternion(abc, "zyx", intrinsic=True)
    extrinsic = euler_to_quaternion(abc[:, ::-1], "xyz", intrinsic=False)
    assert np.allclose(intrinsic, extrinsic, atol=1e-15)
    a, b, c = np.radians(abc[0])
    rz = Rotation.from_rotvec([0, 0, a]).as_matrix()
    ry = Rotation.from_rotvec([0, b, 0]).as_matrix()
    rx = Rotation.from_rotvec([c, 0, 0]).as_matrix()
    _same_rotation(intrinsic, Rotation.from_matrix([rz @ ry @ rx]))


def test_angle_units_decimal_comma_and_a_unit_of_their_own() -> None:
    # radians for every angle column, from --units
    text = _probe_file("intrinsic-zyx", radians=True)
    got = read_dataset(text, options=ReadOptions.of(units="mm,rad", euler="intrinsic-zyx"))
    assert got.probe_q_wxyz is not None and got.a_deg is not None
    _same_rotation(got.probe_q_wxyz, ROTATIONS)
    assert got.a_deg[1, 0] == pytest.approx(11.0)
    # e1..e3 in radians while the axes are degrees: the convention's own unit
    e_rad = _probe_file("intrinsic-zyx").splitlines()
    e = ROTATIONS.as_euler("ZYX")
    rows = [e_rad[0]] + [
        ",".join(line.split(",")[:9] + [repr(float(v)) for v in e[i]] + ["0.01"])
        for i, line in enumerate(e_rad[1:])
    ]
    got = read_dataset("\n".join(rows) + "\n", options=ReadOptions.of(euler="intrinsic-zyx-rad"))
    assert got.probe_q_wxyz is not None and got.a_deg is not None
    _same_rotation(got.probe_q_wxyz, ROTATIONS)
    assert got.a_deg[1, 0] == pytest.approx(11.0)
    # a European export: ';' and decimal commas, the Euler cells too
    text = _probe_file("extrinsic-xyz", sep=";", comma=True)
    got = read_dataset(text, options=ReadOptions.of(decimal_comma=True, euler="extrinsic-xyz"))
    assert got.probe_q_wxyz is not None
    _same_rotation(got.probe_q_wxyz, ROTATIONS)


def test_json_records_with_euler_angles() -> None:
    e = ROTATIONS.as_euler("ZYX", degrees=True)
    records = [
        {
            "a1": 10.0 + i,
            "a2": -90.0,
            "a3": 90.0,
            "a4": 0.0,
            "a5": 20.0,
            "a6": 0.0,
            "x": 1500.0 + i,
            "y": 10.0 * i,
            "z": 1200.0,
            "e1": e[i, 0],
            "e2": e[i, 1],
            "e3": e[i, 2],
        }
        for i in range(N)
    ]
    got = read_dataset_json(json.dumps(records), options=ReadOptions.of(euler="intrinsic-zyx"))
    assert got.probe_q_wxyz is not None
    _same_rotation(got.probe_q_wxyz, ROTATIONS)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("zyx", "'zyx' is ambiguous: .*intrinsic-zyx.*extrinsic-zyx"),
        ("ZYX", "ambiguous"),
        ("intrinsic-zzy", "same axis"),
        ("intrinsic-zy", "expected intrinsic-AXES or extrinsic-AXES"),
        ("euler", "expected intrinsic-AXES"),
        ("extrinsic-xyz-grad", "expected intrinsic-AXES"),
    ],
)
def test_ambiguous_or_unknown_conventions_are_refused_by_name(text: str, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        parse_euler(text)


def test_files_the_option_does_not_fit_are_refused_naming_the_column() -> None:
    text = _probe_file("intrinsic-zyx")
    with pytest.raises(DatasetError, match="--euler CONVENTION") as caught:
        read_dataset(text)  # e1..e3 beside x, y, z without a convention
    assert (caught.value.row, caught.value.column) == (1, "e1")
    no_e3 = "\n".join(",".join([*line.split(",")[:11], "0.01"]) for line in text.splitlines()) + "\n"
    no_e3 = no_e3.replace("e1,e2,0.01", "e1,e2,sigma_mm", 1)
    with pytest.raises(DatasetError, match="column missing: --euler intrinsic-zyx") as caught:
        read_dataset(no_e3, options=ReadOptions.of(euler="intrinsic-zyx"))
    assert caught.value.column == "e3"
    lines = text.splitlines()
    both = [lines[0] + ",qw,qx,qy,qz"] + [line + ",1,0,0,0" for line in lines[1:]]
    with pytest.raises(DatasetError, match="given twice") as caught:
        read_dataset("\n".join(both) + "\n", options=ReadOptions.of(euler="intrinsic-zyx"))
    assert caught.value.column == "qw"
    bad = text.splitlines()
    bad[3] = ",".join([*bad[3].split(",")[:10], "abc", *bad[3].split(",")[11:]])
    with pytest.raises(DatasetError, match="'abc' is not a number") as caught:
        read_dataset("\n".join(bad) + "\n", options=ReadOptions.of(euler="intrinsic-zyx"))
    assert (caught.value.row, caught.value.column) == (4, "e2")


def test_data_check_reads_euler_angles(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "probe.csv"
    path.write_text(_probe_file("intrinsic-zyx"), "utf-8")
    args = ["data", "check", str(path), "--robot", "kr210", "--kind", "any"]
    assert main(args) == 2
    assert "--euler CONVENTION" in capsys.readouterr().err
    assert main([*args, "--euler", "intrinsic-zyx"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["probe_orientation"] is True
    assert "intrinsic-zyx" in summary["read_as"]
    assert main([*args, "--euler", "zyx"]) == 2
    assert "ambiguous" in capsys.readouterr().err
