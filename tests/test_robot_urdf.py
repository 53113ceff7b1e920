"""URDF robots: read into the description (UR5e as ur_description writes it), the UR presets
against their published DH tables, the calibrated kinematics written back as URDF (round trips to
1e-6 mm), and the refusals of URDFs the description cannot hold."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.data.dataset import Dataset, write_dataset
from comp_daemon.export.urdf import geometry_tcp_mm, urdf_text
from comp_daemon.kinematics.forward import chain, gravity_torques_nm
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.artifact import load_model
from comp_daemon.models.kinematic import KinematicModel
from comp_daemon.robot.description import RobotDescriptionError, load_robot, parse_robot_toml
from comp_daemon.robot.urdf import (
    description_fk,
    description_from_urdf,
    description_urdf,
    parse_urdf,
    urdf_chain,
)

UR5E_URDF = Path(__file__).parent / "data" / "ur5e.urdf"

# Universal Robots' published standard DH tables (m): d1..d6, a1..a6; alpha = 90, 0, 0, 90, -90, 0 deg
UR_DH = {
    "ur3": ([0.1519, 0, 0, 0.11235, 0.08535, 0.0819], [0, -0.24365, -0.21325, 0, 0, 0]),
    "ur5": ([0.089159, 0, 0, 0.10915, 0.09465, 0.0823], [0, -0.425, -0.39225, 0, 0, 0]),
    "ur10": ([0.1273, 0, 0, 0.163941, 0.1157, 0.0922], [0, -0.612, -0.5723, 0, 0, 0]),
    "ur3e": ([0.15185, 0, 0, 0.13105, 0.08535, 0.0921], [0, -0.24355, -0.2132, 0, 0, 0]),
    "ur5e": ([0.1625, 0, 0, 0.1333, 0.0997, 0.0996], [0, -0.425, -0.3922, 0, 0, 0]),
    "ur10e": ([0.1807, 0, 0, 0.17415, 0.11985, 0.11655], [0, -0.6127, -0.57155, 0, 0, 0]),
    "ur16e": ([0.1807, 0, 0, 0.17415, 0.11985, 0.11655], [0, -0.4784, -0.36, 0, 0, 0]),
}
UR_ALPHA = [math.pi / 2, 0, 0, math.pi / 2, -math.pi / 2, 0]


def _standard_dh_mm(d_m: list[float], a_m: list[float], q_rad: np.ndarray) -> np.ndarray:
    """Flange position by the textbook standard DH product, written out independently."""
    t = np.eye(4)
    for d, a, alpha, q in zip(d_m, a_m, UR_ALPHA, q_rad, strict=True):
        ct, st, ca, sa = math.cos(q), math.sin(q), math.cos(alpha), math.sin(alpha)
        t = t @ np.array(
            [[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d], [0, 0, 0, 1]]
        )
    return 1000.0 * t[:3, 3]


@pytest.mark.parametrize("name", sorted(UR_DH))
def test_ur_presets_are_the_published_dh_tables(name: str) -> None:
    robot = load_robot(name)
    d, a = UR_DH[name]
    rng = np.random.default_rng(3)
    a_deg = np.concatenate([np.zeros((1, 6)), rng.uniform(-180, 180, (20, 6))])
    got = description_fk(robot, a_deg)[:, :3, 3]
    want = np.array([_standard_dh_mm(d, a, np.radians(row)) for row in a_deg])
    assert np.max(np.abs(got - want)) < 1e-9
    # at zero the arm is stretched along -x of the base: x = a2 + a3, y = -(d4 + d6), z = d1 - d5
    assert got[0] == pytest.approx(1000 * np.array([a[1] + a[2], -(d[3] + d[5]), d[0] - d[4]]), abs=1e-9)


def test_ur5_zero_pose_is_the_pendants() -> None:
    # the UR5 (CB3) teach pendant shows the tool flange at (-817.25, -191.45, -5.49) mm at zero joint values
    flange = description_fk(load_robot("ur5"), np.zeros((1, 6)))[0, :3, 3]
    assert flange == pytest.approx([-817.25, -191.45, -5.491], abs=1e-9)


def test_ur5_preset_is_the_real_campaigns_hand_written_file() -> None:
    """The UR5 of the public real campaign was described by hand (benchmarks/…/ur5.toml, with the
    campaign's tool); its flange is the preset's at every pose."""
    hand = load_robot(Path(__file__).parents[1] / "benchmarks" / "real_campaigns" / "ur5_jacobi" / "ur5.toml")
    a_deg = np.random.default_rng(6).uniform(-180, 180, (50, 6))
    assert np.max(np.abs(description_fk(hand, a_deg) - description_fk(load_robot("ur5"), a_deg))) < 1e-9


def _wrapper(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "robot.toml"
    path.write_text(f'[urdf]\nfile = "{UR5E_URDF}"\n{body}', "utf-8")
    return path


def test_ur5e_urdf_in_the_controllers_base_is_the_preset(tmp_path: Path) -> None:
    robot = load_robot(_wrapper(tmp_path, 'base_link = "base"\nrepeatability_mm = 0.03\n'))
    preset = load_robot("ur5e")
    a_deg = np.random.default_rng(0).uniform(-360, 360, (50, 6))
    diff = np.abs(description_fk(robot, a_deg) - description_fk(preset, a_deg))
    # the URDF's origins carry ur_description's rounded pi/2 (1.570796327): a few 1e-7 mm
    assert diff[:, :3, 3].max() < 1e-5 and diff[:, :3, :3].max() < 1e-8
    assert robot.link_mass_kg == pytest.approx(preset.link_mass_kg)
    # the centres of mass, in other frames, give the preset's static gravity torques
    q = axes_deg_to_q_rad(a_deg, preset.sign)
    taus = [
        gravity_torques_nm(
            KinematicParams.from_robot(r),
            axes_deg_to_q_rad(a_deg, r.sign),
            r.link_mass_kg,
            r.link_com_mm,
            0.0,
            chain(KinematicParams.from_robot(r), axes_deg_to_q_rad(a_deg, r.sign)),
        )
        for r in (robot, preset)
    ]
    assert q.shape == (50, 6)
    assert np.max(np.abs(taus[0] - taus[1])) < 1e-6
    assert robot.repeatability_mm == 0.03


def test_bare_urdf_is_in_its_root_link() -> None:
    """Without a wrapper the base frame is the root link: ur_description's base_link, turned
    180° about z from the controller's base."""
    robot = load_robot(UR5E_URDF)
    a_deg = np.random.default_rng(1).uniform(-360, 360, (20, 6))
    turn = np.diag([-1.0, -1.0, 1.0])
    got = description_fk(robot, a_deg)[:, :3, 3]
    want = description_fk(load_robot("ur5e"), a_deg)[:, :3, 3] @ turn.T
    assert np.max(np.abs(got - want)) < 1e-5
    assert [j.min_deg for j in robot.joints] == pytest.approx([-360, -360, -180, -360, -360, -360])


def test_cli_takes_a_urdf_where_it_takes_a_robot(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["robot", "fk", str(UR5E_URDF), "0", "0", "0", "0", "0", "0"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["flange_mm"] == pytest.approx([817.2, 232.9, 62.8], abs=1e-5)
    assert main(["robot", "show", str(UR5E_URDF), "--format", "toml"]) == 0
    text = capsys.readouterr().out
    again = parse_robot_toml(text, "shown")
    assert again.to_dict() == load_robot(UR5E_URDF).to_dict()


def test_urdf_to_description_to_urdf_keeps_the_fk() -> None:
    source = parse_urdf(UR5E_URDF.read_text("utf-8"), "ur5e")
    robot = description_from_urdf(source)
    written = parse_urdf(description_urdf(robot), "written")
    q = np.random.default_rng(2).uniform(-2 * np.pi, 2 * np.pi, (64, 6))
    want = urdf_chain(source, "base_link", "tool0").fk(q)
    got = urdf_chain(written, "base_link", "tool0").fk(q)
    assert np.max(np.abs(got[:, :3, 3] - want[:, :3, 3])) < 1e-6
    assert np.max(np.abs(got[:, :3, :3] - want[:, :3, :3])) < 1e-9
    # and the description read from the written URDF is the same robot
    again = description_from_urdf(written)
    assert np.max(np.abs(description_fk(again, np.degrees(q)) - description_fk(robot, np.degrees(q)))) < 1e-6


def _calibrated(robot_name: str = "ur5e") -> KinematicModel:
    robot = load_robot(robot_name)
    rng = np.random.default_rng(7)
    dx = rng.normal(size=N_PARAMS) * 1e-3
    dx[30:33] *= 100.0  # a base offset of ~0.1 mm, a tool of ~50 mm below
    params = KinematicParams.from_robot(robot).apply(dx)
    params = params.apply(np.r_[np.zeros(36), [12.0, -3.0, 85.0]])
    reg = np.eye(4)
    c, s = math.cos(0.9), math.sin(0.9)
    reg[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    reg[:3, 3] = [2500.0, -800.0, 300.0]
    return KinematicModel(robot, params.with_base(reg @ params.world_T_base), None, reg)


def test_calibrated_model_to_urdf_keeps_the_tcp() -> None:
    model = _calibrated()
    text, diff = urdf_text(model, ["robot: test"])
    assert diff < 1e-6
    back = urdf_chain(parse_urdf(text, "export"), "base_link", "tcp")
    a_deg = np.random.default_rng(4).uniform(-360, 360, (100, 6))
    got = back.fk(np.radians(a_deg))[:, :3, 3]
    assert np.max(np.abs(got - geometry_tcp_mm(model, a_deg))) < 1e-6
    # the registration is not in the robot: the URDF is in the robot base frame
    nominal = description_fk(model.robot, a_deg)[:, :3, 3]
    assert np.max(np.linalg.norm(got - nominal, axis=1)) < 200.0  # the tool, not 2.6 m of tracker frame


def test_export_params_urdf_of_a_fitted_model(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    robot = load_robot("ur5e")
    truth = _calibrated()
    rng = np.random.default_rng(11)
    a_deg = rng.uniform(-170, 170, (120, 6))
    xyz = truth.predict_tcp_mm(a_deg) + rng.normal(size=(120, 3)) * 0.005
    data = tmp_path / "ur5e.csv"
    write_dataset(Dataset(a_deg=a_deg, xyz_mm=xyz, split=np.where(np.arange(120) < 90, "fit", "check")), data)
    model_path, out = tmp_path / "model.json", tmp_path / "ur5e_calibrated.urdf"
    assert main(["fit", str(data), "--robot", "ur5e", "--model", "kinematic", "--out", str(model_path)]) == 0
    capsys.readouterr()
    args = [
        "export",
        "params",
        "--model",
        str(model_path),
        "--format",
        "urdf",
        "-o",
        str(out),
        "--robot",
        "ur5e",
    ]
    assert main(args) == 0
    assert "read back: TCP within" in capsys.readouterr().out
    model = load_model(model_path, robot).model
    assert isinstance(model, KinematicModel)
    back = urdf_chain(parse_urdf(out.read_text("utf-8"), str(out)), "base_link", "tcp")
    got = back.fk(np.radians(a_deg))[:, :3, 3]
    assert np.max(np.abs(got - geometry_tcp_mm(model, a_deg))) < 1e-6
    # the calibrated chain's root is off the robot base (the fitted base frame): a description,
    # whose joint 1 turns about the base's z axis, cannot hold it, and says so
    with pytest.raises(RobotDescriptionError, match="not the z axis of base_link 'base_link'"):
        load_robot(_tip(tmp_path, out))


def _tip(tmp_path: Path, urdf: Path) -> Path:
    path = tmp_path / "calibrated.toml"
    path.write_text(f'[urdf]\nfile = "{urdf.name}"\ntip_link = "tcp"\n', "utf-8")
    return path


def test_axis_mapping_of_the_wrapper(tmp_path: Path) -> None:
    """q_urdf = radians(sign·A + offset): the description's FK at A is the URDF's at q."""
    sign, offset = [1, -1, -1, 1, -1, 1], [0.0, 90.0, 0.0, -90.0, 0.0, 10.0]
    robot = load_robot(_wrapper(tmp_path, f"axis_sign = {sign}\naxis_offset_deg = {offset}\n"))
    source = urdf_chain(parse_urdf(UR5E_URDF.read_text("utf-8"), "ur5e"))
    lim = robot.axis_limits_deg
    a_deg = np.random.default_rng(5).uniform(lim[:, 0], lim[:, 1], (40, 6))
    q = np.radians(a_deg * sign + np.array(offset))
    assert np.max(np.abs(description_fk(robot, a_deg) - source.fk(q))) < 1e-6
    # joint 2: q in ±360°, A = (q - 90)·(-1) in [-270, 450]
    assert (robot.joints[1].min_deg, robot.joints[1].max_deg) == pytest.approx((-270.0, 450.0))


def _six_axis_urdf(tilt_deg: float = 0.0, joint3: str = "revolute", n: int = 6, about: str = "x") -> str:
    """A small arm whose axes 2 and 3 are parallel (or tilted by ``tilt_deg`` about x or y of link 2)."""
    tilt = math.radians(tilt_deg)
    origins = [
        ("0 0 0.3", "0 0 0"),
        ("0.05 0 0", "1.5707963267948966 0 0"),
        ("0.3 0 0", f"{tilt!r} 0 0" if about == "x" else f"0 {tilt!r} 0"),
        ("0.02 0.25 0", "-1.5707963267948966 0 0"),
        ("0 0 0", "1.5707963267948966 0 0"),
        ("0 -0.08 0", "-1.5707963267948966 0 0"),
    ][:n]
    parts = ['<robot name="arm">', '<link name="base"/>']
    for i, (xyz, rpy) in enumerate(origins, start=1):
        kind = joint3 if i == 3 else "revolute"
        parts += [
            f'<link name="l{i}"><inertial><origin xyz="0.01 0 0"/><mass value="{i}"/></inertial></link>',
            f'<joint name="j{i}" type="{kind}"><parent link="{"base" if i == 1 else f"l{i - 1}"}"/>'
            f'<child link="l{i}"/><origin xyz="{xyz}" rpy="{rpy}"/><axis xyz="0 0 1"/>'
            '<limit lower="-3" upper="3" effort="1" velocity="1"/></joint>',
        ]
    return "\n".join([*parts, "</robot>"])


def test_nearly_parallel_axes_take_hayatis_form() -> None:
    """0.2° between axes 2 and 3: the standard common normal would lie metres away; the
    description takes d = 0, the tilt about the normal in alpha and across it in beta, and its FK
    is the URDF's (checked on loading)."""
    across = description_from_urdf(parse_urdf(_six_axis_urdf(0.2, about="y"), "across"))
    assert abs(across.joints[1].beta_deg) == pytest.approx(0.2, abs=1e-9)
    assert across.joints[1].d_mm == 0.0 and across.joints[1].alpha_deg == pytest.approx(0.0, abs=1e-9)
    along = description_from_urdf(parse_urdf(_six_axis_urdf(0.2, about="x"), "along"))
    assert abs(along.joints[1].alpha_deg) == pytest.approx(0.2, abs=1e-9) and along.joints[1].beta_deg == 0.0
    for robot in (across, along):
        assert max(abs(j.d_mm) for j in robot.joints) < 1000.0 and robot.joints[1].a_mm == pytest.approx(
            300.0
        )
    parallel = description_from_urdf(parse_urdf(_six_axis_urdf(0.0), "parallel"))
    assert parallel.joints[1].beta_deg == 0.0 and parallel.joints[1].d_mm == 0.0


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("<robot", "not valid XML"),
        ("<robot_model/>", "root element is <robot_model>"),
        (_six_axis_urdf(joint3="prismatic"), "joint 'j3' is prismatic"),
        (_six_axis_urdf(n=5), "5 revolute joints from 'base' to 'l5'"),
        (
            _six_axis_urdf().replace('<limit lower="-3" upper="3" effort="1" velocity="1"/>', "", 1),
            "needs <limit",
        ),
        (_six_axis_urdf().replace('xyz="0 0 0.3"', 'xyz="0.1 0 0.3"'), "not the z axis of base_link 'base'"),
        (_six_axis_urdf().replace('"0.05 0 0"', '"0.05 0 zero"'), "expected 3 numbers"),
        (_six_axis_urdf().replace('<child link="l4"/>', '<child link="l9"/>'), "link 'l9' is not defined"),
        (
            '<robot xmlns:xacro="http://www.ros.org/wiki/xacro" name="x"><xacro:macro name="m"/></robot>',
            "xacro",
        ),
    ],
)
def test_bad_urdfs_are_refused_by_name(text: str, match: str) -> None:
    with pytest.raises(RobotDescriptionError, match=match):
        description_from_urdf(parse_urdf(text, "arm.urdf"))


@pytest.mark.parametrize(
    ("body", "match"),
    [
        ("axis_sign = [1, 1, 1, 1, 1, 2]\n", "axis_sign: each must be 1 or -1"),
        ("axis_offset_rad = [0, 0, 0, 0, 0, 0]\n", "'axis_offset_rad' is in rad"),
        ('tip_link = "hand"\n', "tip_link 'hand' is not a link"),
        ("repeatability_mm = 0\n", "repeatability_mm: must be > 0"),
    ],
)
def test_bad_wrappers_are_refused_by_name(tmp_path: Path, body: str, match: str) -> None:
    with pytest.raises(RobotDescriptionError, match=match):
        load_robot(_wrapper(tmp_path, body))
