"""``comp-daemon export``: parameter listings and target lists, each read back to the values it came from."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.data.dataset import Dataset, read_dataset, write_dataset
from comp_daemon.export.formats import PARAM_FORMATS, TARGET_FORMATS, write_targets
from comp_daemon.export.params import model_of
from comp_daemon.export.targets import TargetList
from comp_daemon.kinematics.kuka_abc import abc_deg_to_matrix, matrix_to_abc_deg
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams
from comp_daemon.models.artifact import load_model
from comp_daemon.models.compensation import CompensationLimits, compensate, nominal_targets
from comp_daemon.models.effects import EffectParams, twin_tcp_mm
from comp_daemon.models.kinematic import KinematicModel
from comp_daemon.robot.description import FLANGE_R_KUKA_TOOL, load_robot

KR = load_robot("kr210")


def _axes(n: int, seed: int) -> np.ndarray:
    lim = KR.axis_limits_deg
    mid, half = lim.mean(axis=1), (lim[:, 1] - lim[:, 0]) / 2
    return mid + np.random.default_rng(seed).uniform(-0.5, 0.5, (n, 6)) * np.minimum(half, 90.0)


def _campaign(path: Path, world_T_base: np.ndarray) -> Path:
    """A synthetic campaign of a KR 210 with geometric errors, backlash and ratio errors, measured
    in a frame ``world_T_base`` away from the robot's base."""
    rng = np.random.default_rng(0)
    n = 160
    a = _axes(n, 1)
    dirs = rng.choice([-1, 1], size=(n, 6))
    truth = KinematicParams.from_robot(KR).apply(rng.normal(size=N_PARAMS) * 3e-4)
    eff = EffectParams.zeros().with_values(["h2", "h3", "eps2"], [0.005, 0.004, 1e-4])
    p = twin_tcp_mm(KR, truth, eff, a, dirs.astype(float)) + rng.normal(size=(n, 3)) * 0.01
    p = p @ world_T_base[:3, :3].T + world_T_base[:3, 3]
    split = np.where(np.arange(n) < 100, "fit", "check")
    write_dataset(Dataset(a_deg=a, xyz_mm=p, dir=dirs, split=split), path)
    return path


def _tracker_frame() -> np.ndarray:
    t = np.eye(4)
    c, s = np.cos(np.radians(170.0)), np.sin(np.radians(170.0))
    t[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.array(
        [[1.0, 0.0, 0.0], [0.0, np.cos(0.02), -np.sin(0.02)], [0.0, np.sin(0.02), np.cos(0.02)]]
    )
    t[:3, 3] = [4210.5, -1830.25, -512.0]
    return t


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Fitted artifacts: kinematic with ratio and backlash (base frame), plain kinematic (tracker
    frame), Chebyshev (base frame)."""
    root = tmp_path_factory.mktemp("export")
    base = _campaign(root / "base.csv", np.eye(4))
    tracker = _campaign(root / "tracker.csv", _tracker_frame())
    out = {}
    for name, data, model in (
        ("effects", base, "kinematic+ratio+backlash"),
        ("tracker", tracker, "kinematic"),
        ("chebyshev", base, "chebyshev"),
    ):
        out[name] = root / f"{name}.json"
        args = ["fit", str(data), "--robot", "kr210", "--model", model, "--out", str(out[name])]
        assert main(args) == 0
    out["data"] = base
    return out


@pytest.fixture(scope="module")
def program(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A nominal program of 8 poses away from the wrist singularity, with approach directions."""
    a = _axes(40, 5)
    a = a[np.abs(a[:, 4]) > 10.0][:8]
    dirs = np.where(np.arange(48).reshape(8, 6) % 3 == 0, 1, -1)
    path = tmp_path_factory.mktemp("program") / "program.csv"
    write_dataset(Dataset(a_deg=a, dir=dirs, pose_id=tuple(f"hole-{i}" for i in range(8))), path)
    return path


def _compensated(model: KinematicModel, program: Path) -> tuple[np.ndarray, np.ndarray]:
    targets = read_dataset(program, kind="targets")
    assert targets.a_deg is not None and targets.dir is not None
    wanted, rot = nominal_targets(model, targets.a_deg)
    dirs = targets.dir.astype(float)
    # a tracker-frame fit moves axis 1 by up to 0.8 deg near its axis: the limits are not under test here
    limits = CompensationLimits(max_axis_change_deg=5.0)
    res = compensate(model, wanted, rot, a_seed_deg=targets.a_deg, dir=dirs, tol_mm=1e-9, limits=limits)
    return res.a_deg, dirs


@pytest.mark.parametrize("fmt", sorted(PARAM_FORMATS))
@pytest.mark.parametrize("which", ["effects", "tracker"])
def test_a_parameter_listing_read_back_compensates_as_its_model(
    models: dict[str, Path], program: Path, tmp_path: Path, fmt: str, which: str
) -> None:
    out = tmp_path / f"params.{fmt}"
    assert main(["export", "params", "--model", str(models[which]), "--format", fmt, "-o", str(out)]) == 0
    original = load_model(models[which]).model
    assert isinstance(original, KinematicModel)
    listing = PARAM_FORMATS[fmt][1](out.read_text(), str(out))
    rebuilt = model_of(listing, KR)
    a0, dirs = _compensated(original, program)
    a1, _ = _compensated(rebuilt, program)
    moved = np.linalg.norm(original.predict_tcp_mm(a1, dirs) - original.predict_tcp_mm(a0, dirs), axis=1)
    assert moved.max() < 1e-6
    assert np.abs(a1 - a0).max() < 1e-9
    assert listing.info.robot == KR.name and listing.info.fit_rms_mm is not None
    if which == "effects":
        assert listing.effects is not None and abs(listing.effects["h2"] - 0.005) < 1e-3
    else:  # the tracker frame is the registration; the chain's root stays near the robot base
        np.testing.assert_allclose(listing.meas_T_base, _tracker_frame(), atol=0.5)
        assert np.abs(listing.base_T_root[:3, 3]).max() < 1.0


def test_the_csv_listing_gives_delta_and_sigma_in_listing_units(
    models: dict[str, Path], tmp_path: Path
) -> None:
    out = tmp_path / "params.csv"
    args = ["export", "params", "--model", str(models["effects"]), "--format", "csv", "-o", str(out)]
    assert main([*args, "--data", str(models["data"])]) == 0
    text = out.read_text()
    assert "# check RMS: 0.0" in text
    rows = {line.split(",")[0]: line.split(",") for line in text.splitlines() if not line.startswith("#")}
    assert rows["name"] == ["name", "nominal", "identified", "delta", "unit", "sigma"]
    alpha2 = rows["alpha2"]
    assert alpha2[4] == "deg" and float(alpha2[3]) == pytest.approx(float(alpha2[2]) - float(alpha2[1]))
    assert 0 < float(alpha2[5]) < 0.01  # deg, not rad
    assert rows["theta1"][5] == ""  # not identified (dependent on base_rz): no sigma
    assert rows["h2"][4] == "deg" and rows["eps2"][4] == "1"
    # the rotation sigma of the base frame in deg
    assert 0 < float(rows["base_rz"][5]) < 0.01


def test_an_edited_listing_changes_the_model(models: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "params.kuka"
    assert (
        main(["export", "params", "--model", str(models["effects"]), "--format", "kuka", "-o", str(out)]) == 0
    )
    text = out.read_text()
    line = next(line for line in text.splitlines() if line.startswith("DECL CD_MDH CD_AX2="))
    edited = text.replace(line, line.replace("{A 1150.", "{A 1151."))
    a = _axes(5, 9)
    before = model_of(PARAM_FORMATS["kuka"][1](text, "x"), KR).predict_tcp_mm(a)
    after = model_of(PARAM_FORMATS["kuka"][1](edited, "x"), KR).predict_tcp_mm(a)
    assert np.linalg.norm(after - before, axis=1).min() > 0.1
    with pytest.raises(ValueError, match="not those of robot"):
        model_of(PARAM_FORMATS["kuka"][1](text, "x"), load_robot("irb120"))


@pytest.mark.parametrize("fmt", sorted(TARGET_FORMATS))
@pytest.mark.parametrize("which", ["effects", "chebyshev"])
def test_a_target_list_read_back_gives_the_compensated_axes(
    models: dict[str, Path], program: Path, tmp_path: Path, fmt: str, which: str
) -> None:
    corrected = tmp_path / "corrected.csv"
    assert main(["compensate", str(models[which]), str(program), "--out", str(corrected)]) == 0
    expected = read_dataset(corrected, kind="targets")
    out = tmp_path / f"targets.{fmt}"
    args = ["export", "targets", "--model", str(models[which]), "--targets", str(program), "--format", fmt]
    assert main([*args, "-o", str(out)]) == 0
    back = TARGET_FORMATS[fmt](out.read_text(), str(out))
    assert expected.a_deg is not None and expected.target_xyz_mm is not None and expected.dir is not None
    assert np.abs(back.a_deg - expected.a_deg).max() < 1e-6
    model = load_model(models[which]).model
    dirs = expected.dir.astype(float)
    reached = model.predict_tcp_mm(back.a_deg, dirs)
    assert np.linalg.norm(reached - model.predict_tcp_mm(expected.a_deg, dirs), axis=1).max() < 1e-6
    np.testing.assert_allclose(back.xyz_mm, expected.target_xyz_mm, atol=1e-9)
    # the nominal Cartesian target is the nominal program's pose
    program_a = read_dataset(program, kind="targets").a_deg
    assert program_a is not None
    p_nom, r_nom = nominal_targets(model, program_a)
    np.testing.assert_allclose(back.xyz_mm, p_nom, atol=1e-6)
    np.testing.assert_allclose(back.flange_R, r_nom, atol=1e-9)
    if fmt == "csv":  # a target file of the data set spec: compensating it again changes nothing
        again = read_dataset(out, kind="targets")
        assert again.a_deg is not None and np.abs(again.a_deg - expected.a_deg).max() == 0.0
    names = tuple(f"hole_{i}" for i in range(8))
    assert back.names == (tuple(f"hole-{i}" for i in range(8)) if fmt == "csv" else names)


def test_targets_with_an_orientation_keep_it(models: dict[str, Path], tmp_path: Path) -> None:
    model = load_model(models["effects"]).model
    a = _axes(40, 7)
    a = a[np.abs(a[:, 4]) > 10.0][:4]
    p, r = nominal_targets(model, a)
    abc = matrix_to_abc_deg(r @ FLANGE_R_KUKA_TOOL)
    targets = tmp_path / "cart.csv"
    write_dataset(Dataset(a_deg=None, target_xyz_mm=p, target_abc_deg=abc), targets)
    out = tmp_path / "cart.dat"
    args = ["export", "targets", "--model", str(models["effects"]), "--targets", str(targets)]
    assert main([*args, "--format", "krl", "-o", str(out)]) == 0
    back = TARGET_FORMATS["krl"](out.read_text(), str(out))
    assert back.names == ("P1", "P2", "P3", "P4")
    np.testing.assert_allclose(back.flange_R, abc_deg_to_matrix(abc) @ FLANGE_R_KUKA_TOOL.T, atol=1e-12)
    np.testing.assert_allclose(model.predict_tcp_mm(back.a_deg), p, atol=1e-6)
    assert "DEFDAT cart PUBLIC" in out.read_text()


@pytest.mark.parametrize(
    ("fmt", "axis_decl", "pose_decl"),
    [("krl", "E6AXIS XA_", "E6POS XP_"), ("rapid", "CONST jointtarget j", "CONST robtarget p")],
)
def test_a_controller_target_list_needs_both_declarations_of_every_target(
    fmt: str, axis_decl: str, pose_decl: str
) -> None:
    a = _axes(2, 3)
    r = np.broadcast_to(np.eye(3), (2, 3, 3))
    text = write_targets(fmt, TargetList(("hole_a", "hole_b"), a, np.ones((2, 3)), r), "m")
    assert TARGET_FORMATS[fmt](text, "t").names == ("hole_a", "hole_b")
    without_pose = "\n".join(line for line in text.splitlines() if f"{pose_decl}hole_b" not in line)
    with pytest.raises(ValueError, match=f"^t: no {pose_decl}hole_b$"):
        TARGET_FORMATS[fmt](without_pose, "t")
    without_axes = "\n".join(line for line in text.splitlines() if axis_decl not in line)
    with pytest.raises(ValueError, match=f"^t: no {axis_decl}<name> declarations$"):
        TARGET_FORMATS[fmt](without_axes, "t")


def test_export_refusals_are_user_errors(
    models: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "x.kuka"
    assert (
        main(["export", "params", "--model", str(models["chebyshev"]), "--format", "kuka", "-o", str(out)])
        == 2
    )
    assert "no kinematic parameters" in capsys.readouterr().err
    assert not out.exists()
    near = tmp_path / "near.csv"  # A5 = 0.5 deg: the wrist singularity
    write_dataset(Dataset(a_deg=np.array([[10.0, -90.0, 10.0, 20.0, 0.5, 30.0]])), near)
    args = [
        "export",
        "targets",
        "--model",
        str(models["effects"]),
        "--targets",
        str(near),
        "--format",
        "rapid",
    ]
    assert main([*args, "-o", str(tmp_path / "near.mod")]) == 2
    assert "compensation refused" in capsys.readouterr().err
    assert not (tmp_path / "near.mod").exists()
    other = ["export", "params", "--model", str(models["effects"]), "--format", "abb", "--robot", "irb120"]
    assert main([*other, "-o", str(tmp_path / "y.cfg")]) == 2
    assert "not for" in capsys.readouterr().err
