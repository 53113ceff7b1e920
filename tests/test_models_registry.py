"""Every model kind of the registry through the file doors: fit, MODEL.json, compensate, evaluate."""

from __future__ import annotations

import ast
import importlib
import json
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.data.dataset import Dataset, read_dataset, write_dataset
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams
from comp_daemon.models import (
    base,
    chebyshev,
    compliance,
    covariance,
    fitting,
    kinematic,
    kinematic_kind,
    kriging,
    nominal,
)
from comp_daemon.models.artifact import load_model, model_from_artifact, save_model
from comp_daemon.models.compensation import nominal_targets
from comp_daemon.models.effects import EffectParams, twin_tcp_mm
from comp_daemon.models.nominal import NominalModel
from comp_daemon.models.poe import model as poe_model
from comp_daemon.models.registry import (
    ARTIFACT_KINDS,
    KINDS,
    UnknownModelError,
    get_kind,
    max_parameters,
    parse_model_name,
    with_order,
)
from comp_daemon.robot.description import load_robot

KR = load_robot("kr210")
N, N_FIT = 170, 110
# every kind of the table, and the named variants the papers use
MODELS = (
    *KINDS,
    "kinematic+ratio+backlash",
    "chebyshev:1",
    "kriging-backlash+compliance",
    "kriging:k=40:aniso",
    "kriging:all",  # every part kept: the kriging model itself, whatever it earns
    "kriging-backlash:all+compliance",
    "compliance:paper",
)


def _axes(n: int, seed: int) -> np.ndarray:
    lim = KR.axis_limits_deg
    mid, half = lim.mean(axis=1), (lim[:, 1] - lim[:, 0]) / 2
    return mid + np.random.default_rng(seed).uniform(-0.5, 0.5, (n, 6)) * np.minimum(half, 90.0)


def _rigid(angle_deg: float, shift_mm: tuple[float, float, float]) -> np.ndarray:
    c, s = np.cos(np.deg2rad(angle_deg)), np.sin(np.deg2rad(angle_deg))
    t = np.eye(4)
    t[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    t[:3, 3] = shift_mm
    return t


def _campaign(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A robot with geometric errors, backlash, a ratio error and gravity compliance; payload 0 / 100 kg."""
    rng = np.random.default_rng(seed)
    a = _axes(N, seed + 1)
    dirs = rng.choice([-1, 1], size=(N, 6))
    payload = np.where(np.arange(N) % 2 == 0, 0.0, 100.0)
    truth = KinematicParams.from_robot(KR).apply(rng.normal(size=N_PARAMS) * 3e-4)
    eff = EffectParams.zeros().with_values(["h2", "h3", "eps2", "C2", "C3"], [0.005, 0.004, 1e-4, 2e-8, 3e-8])
    p = twin_tcp_mm(KR, truth, eff, a, dirs.astype(float), payload) + rng.normal(size=(N, 3)) * 0.01
    return a, dirs, payload, p


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> Path:
    a, dirs, payload, p = _campaign(0)
    split = np.where(np.arange(N) < N_FIT, "fit", "check")
    path = tmp_path_factory.mktemp("registry") / "campaign.csv"
    write_dataset(Dataset(a_deg=a, xyz_mm=p, dir=dirs, payload_kg=payload, split=split), path)
    return path


def test_every_kind_has_a_loader_and_a_parameter_floor() -> None:
    for name, kind in KINDS.items():
        assert kind.name == name and kind.model_class.kind in ARTIFACT_KINDS
        assert max_parameters(parse_model_name(name)) >= 6
    assert get_kind("kriging-backlash").needed_columns(parse_model_name("kriging-backlash")) == ("dir",)
    assert get_kind("kinematic").needed_columns(parse_model_name("kinematic+backlash+thermal")) == (
        "dir",
        "temp_c",
    )


@pytest.mark.parametrize(
    "module",
    [
        kriging,
        compliance,
        chebyshev,
        kinematic,
        kinematic_kind,
        nominal,
        poe_model,
        base,
        importlib.import_module("comp_daemon.models.kind"),
        fitting,
        covariance,
    ],
)
def test_model_modules_import_neither_the_registry_nor_the_artifact_loader(module: ModuleType) -> None:
    """No import cycle: the registry and the loader sit above the model modules (also lazily)."""
    tree = ast.parse(Path(str(module.__file__)).read_text("utf-8"))
    imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    imported |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    assert not imported & {"comp_daemon.models.artifact", "comp_daemon.models.registry"}


@pytest.mark.parametrize(
    ("name", "fault"),
    [
        ("spline", "known: nominal, kinematic, chebyshev, kriging, kriging-backlash, compliance"),
        ("compliance+backlash", "offered by the kinematic, kriging, kriging-backlash models only"),
        ("kriging:k=2", "takes the options k=N"),
        ("kriging:aniso:aniso", "each once"),
        ("kriging-backlash:3", "takes the options k=N"),
        ("compliance:2", "takes no order"),
        ("chebyshev:x", "0..8 or 'cv'"),
        ("kinematic+ratio+ratio", "named twice"),
        ("kinematic+drift", "drift belongs to one campaign's clock"),
        ("kriging+step", "step belongs to one campaign's clock"),
        ("kinematic+wobble", r"known: backlash, ratio, cyclic, compliance, thermal\)"),
        ("", "empty model name"),
    ],
)
def test_names_the_registry_refuses(name: str, fault: str) -> None:
    with pytest.raises(UnknownModelError, match=fault):
        parse_model_name(name)


@pytest.mark.parametrize(
    ("name", "canonical"),
    [
        ("kriging:aniso:k=64", "kriging:k=64:aniso"),
        ("kriging-backlash+compliance", "kriging-backlash+compliance"),
        ("kriging:k=500+ratio", "kriging:k=500+ratio"),
    ],
)
def test_kriging_options_and_stacks_round_trip(name: str, canonical: str) -> None:
    spec = parse_model_name(name)
    assert spec.name == canonical
    assert parse_model_name(spec.name) == spec


def test_kriging_options_reach_the_spec() -> None:
    spec = parse_model_name("kriging-backlash:k=32:aniso+compliance")
    assert (spec.neighbours, spec.anisotropic, spec.effects) == (32, True, ("compliance",))
    assert parse_model_name("kriging").neighbours is None
    assert max_parameters(parse_model_name("kriging-backlash+compliance")) > max_parameters(
        parse_model_name("kriging-backlash")
    )


def test_order_given_apart_must_agree_with_the_name() -> None:
    assert with_order(parse_model_name("chebyshev"), "cv").order_by_cv
    assert with_order(parse_model_name("chebyshev:2"), 2).order == 2
    with pytest.raises(UnknownModelError, match="contradicts"):
        with_order(parse_model_name("chebyshev:2"), 3)
    with pytest.raises(UnknownModelError, match="takes no order"):
        with_order(parse_model_name("kinematic"), 3)


@pytest.mark.parametrize("name", MODELS)
def test_kind_fits_saves_loads_bit_exact_and_compensates(campaign: Path, tmp_path: Path, name: str) -> None:
    out = tmp_path / "model.json"
    assert main(["fit", str(campaign), "--robot", "kr210", "--model", name, "--out", str(out)]) == 0
    spec = parse_model_name(name)
    loaded = load_model(out, KR)
    model = loaded.model
    fit_doc = loaded.document["fit"]
    if "kriging" in fit_doc.get("selection", {}).get("dropped", ()):  # fell back to its base model
        assert model.kind == "kinematic" and fit_doc["model_kind"] == "kinematic"
    else:
        assert model.kind == get_kind(spec.kind).model_class.kind
    if spec.keep_all:
        assert fit_doc["selection"]["dropped"] == [] and isinstance(model, kriging.KrigingModel)
    assert loaded.document["fit"]["model"] == spec.name and loaded.document["fit"]["rows"] == N_FIT
    assert loaded.document["model"] == json.loads(out.read_text())["model"]

    # written again, read again: the same document content and the same predictions, bit for bit
    again_path = tmp_path / "again.json"
    doc = save_model(
        model, again_path, data_sha256=loaded.data_sha256, frame=loaded.frame, fit=loaded.document["fit"]
    )
    again = load_model(again_path, KR)
    assert doc["model"] == loaded.document["model"] and again.document["model"] == loaded.document["model"]
    stored = model_from_artifact(again.document, KR, "again")
    a, dirs, payload, p = _campaign(0)
    check = slice(N_FIT, N)
    pred = model.predict_tcp_mm(a[check], dirs[check].astype(float), payload[check])
    np.testing.assert_array_equal(
        stored.predict_tcp_mm(a[check], dirs[check].astype(float), payload[check]), pred
    )

    # a model that fitted anything beats the nominal geometry on the check rows
    err = np.linalg.norm(pred - p[check], axis=1).mean()
    raw = np.linalg.norm(NominalModel(KR).predict_tcp_mm(a[check]) - p[check], axis=1).mean()
    if spec.kind != "nominal":
        assert err < 0.5 * raw, (name, err, raw)

    # the compensate door: commands whose predicted TCP (with the rows' directions and payload) is the target
    a_nominal = _axes(6, 7)
    wanted, _ = nominal_targets(model, a_nominal)
    t_dirs = np.tile([1, -1, 1, -1, 1, -1], (6, 1))
    t_payload = np.array([0.0, 100.0, 0.0, 100.0, 0.0, 100.0])
    targets = tmp_path / "targets.csv"
    write_dataset(Dataset(a_deg=None, target_xyz_mm=wanted, dir=t_dirs, payload_kg=t_payload), targets)
    corrected_path = tmp_path / "corrected.csv"
    assert main(["compensate", str(out), str(targets), "--out", str(corrected_path), "--robot", "kr210"]) == 0
    corrected = read_dataset(corrected_path, kind="targets")
    # every fitted kind states the uncertainty of its prediction; the nominal geometry has none
    sigma = corrected.extra.get("predicted_sigma_mm")
    assert (sigma is None) == (spec.kind == "nominal"), name
    if sigma is not None:
        assert all(0.0 < float(v) < 1.0 for v in sigma), (name, sigma)
        np.testing.assert_array_equal(
            stored.predict_std_mm(a[check], dirs[check].astype(float), payload[check]),
            model.predict_std_mm(a[check], dirs[check].astype(float), payload[check]),
        )
    assert corrected.a_deg is not None
    assert corrected.extra["model_kind"] == (model.kind,) * 6
    reached = model.predict_tcp_mm(corrected.a_deg, t_dirs.astype(float), t_payload)
    assert np.linalg.norm(reached - wanted, axis=1).max() < 1e-5


def test_kriging_backlash_refuses_data_without_directions(
    campaign: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Without dir columns and with their inference turned off (by default they are inferred)."""
    ds = read_dataset(campaign)
    no_dir = tmp_path / "no_dir.csv"
    write_dataset(Dataset(a_deg=ds.a_deg, xyz_mm=ds.xyz_mm, split=ds.split), no_dir)
    out = tmp_path / "m.json"
    argv = ["fit", str(no_dir), "--robot", "kr210", "--model", "kriging-backlash", "--out", str(out)]
    assert main([*argv, "--no-infer-dir"]) == 2
    assert "needs the dir1..dir6 column" in capsys.readouterr().err and not out.exists()


def test_nominal_row_of_evaluate_is_registered_to_the_tracker_frame(tmp_path: Path) -> None:
    a, dirs, payload, p = _campaign(3)
    tracker_T_base = _rigid(35.0, (2500.0, -800.0, 300.0))
    p_tracker = p @ tracker_T_base[:3, :3].T + tracker_T_base[:3, 3]
    split = np.where(np.arange(N) < N_FIT, "fit", "check")
    path = tmp_path / "tracker.csv"
    write_dataset(Dataset(a_deg=a, xyz_mm=p_tracker, dir=dirs, payload_kg=payload, split=split), path)
    doc_path = tmp_path / "eval.json"
    args = [
        "evaluate",
        str(path),
        "--robot",
        "kr210",
        "--models",
        "nominal,kinematic",
        "--json",
        str(doc_path),
    ]
    assert main(args) == 0
    doc = json.loads(doc_path.read_text())
    fits, table = doc["fits"], doc["table2"]
    assert fits["nominal"]["frame"] == "tracker" and fits["kinematic"]["frame"] == "tracker"
    # the same rows in the robot base frame: the registered nominal row is as good there, up to the
    # small rotation the rigid fit absorbs of the robot's geometric errors
    base_path = tmp_path / "base.csv"
    write_dataset(Dataset(a_deg=a, xyz_mm=p, dir=dirs, payload_kg=payload, split=split), base_path)
    base_doc_path = tmp_path / "eval_base.json"
    base_args = [
        "evaluate",
        str(base_path),
        "--robot",
        "kr210",
        "--models",
        "nominal",
        "--json",
        str(base_doc_path),
    ]
    assert main([*base_args, "--frame", "tracker"]) == 0
    base_nominal = json.loads(base_doc_path.read_text())["table2"]["nominal"]["3d"]["mean"]
    assert table["nominal"]["3d"]["mean"] == pytest.approx(base_nominal, rel=1e-6)
    assert table["nominal"]["3d"]["mean"] < 5.0  # the frame is 2.6 m and 35° away; only its fit is left
    assert table["kinematic"]["3d"]["mean"] < 0.5 * table["nominal"]["3d"]["mean"]
