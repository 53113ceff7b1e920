"""Model artifacts: bit-exact round trips and clear refusals; Table 2 statistics."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from comp_daemon import __version__
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams
from comp_daemon.kinematics.so3 import rotvec_to_matrix as rotation_from_rotvec
from comp_daemon.models.artifact import (
    ModelArtifactError,
    arrays_sha256,
    load_model,
    model_document,
    parse_model,
    save_model,
)
from comp_daemon.models.base import ErrorModel
from comp_daemon.models.chebyshev import fit_chebyshev
from comp_daemon.models.effects import EffectParams, effect_param_names, twin_tcp_mm
from comp_daemon.models.evaluation import error_statistics, format_table2
from comp_daemon.models.kinematic import calibrate_kinematic
from comp_daemon.models.nominal import NominalModel
from comp_daemon.robot.description import load_robot

KR = load_robot("kr210")


def _data(n: int = 120) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    lim = KR.axis_limits_deg
    a = lim.mean(axis=1) + rng.uniform(-0.5, 0.5, (n, 6)) * np.minimum((lim[:, 1] - lim[:, 0]) / 2, 90)
    dirs = rng.choice([-1.0, 1.0], size=a.shape)
    truth = KinematicParams.from_robot(KR).apply(rng.normal(size=N_PARAMS) * 3e-4)
    world = np.eye(4)
    world[:3, :3] = rotation_from_rotvec(np.array([0.0, 0.0, 0.4]))
    world[:3, 3] = [-3000.0, 1000.0, -500.0]
    eff = EffectParams.zeros(1).with_values(["h2", "eps3", "c2_1"], [0.004, 1e-4, 0.005])
    p = twin_tcp_mm(KR, truth.with_base(world @ truth.world_T_base), eff, a, dirs)
    return a, p + rng.normal(size=p.shape) * 0.01, dirs


@pytest.fixture(scope="module")
def models() -> dict[str, ErrorModel]:
    a, p, dirs = _data()
    kin = calibrate_kinematic(KR, a, p, dir=dirs, effects=["ratio", "backlash"]).model
    cheb = fit_chebyshev(KR, a, p, 2).model
    return {"nominal": NominalModel(KR, cheb.registration), "kinematic": kin, "chebyshev": cheb}


@pytest.mark.parametrize("kind", ["nominal", "kinematic", "chebyshev"])
def test_round_trip_is_bit_exact(kind: str, models: dict[str, ErrorModel], tmp_path: Path) -> None:
    model = models[kind]
    a, _, dirs = _data(30)
    path = tmp_path / "model.json"
    doc = save_model(
        model, path, data_sha256="ab" * 32, frame="tracker", fit={"rms_mm": 0.1, "bad": float("nan")}
    )
    loaded = load_model(path, KR)
    back = loaded.model
    assert back.kind == kind and type(back) is type(model)
    assert loaded.document == json.loads(path.read_text())
    assert doc["fit"]["bad"] is None  # non-finite statistics are written as null
    before = model.predict_tcp_mm(a, dirs)
    after = back.predict_tcp_mm(a, dirs)
    assert before.tobytes() == after.tobytes()
    assert back.registration.tobytes() == model.registration.tobytes()
    assert back.robot.sha256 == KR.sha256
    if kind == "kinematic":
        for field in (
            "theta_offset_rad",
            "d_mm",
            "a_mm",
            "alpha_rad",
            "beta_rad",
            "tool_xyz_mm",
            "world_T_base",
        ):
            assert getattr(back.params, field).tobytes() == getattr(model.params, field).tobytes()  # type: ignore[attr-defined]
        names = effect_param_names(["ratio", "backlash"])
        assert back.effects.get(names).tobytes() == model.effects.get(names).tobytes()  # type: ignore[attr-defined]
    if kind == "chebyshev":
        assert back.coefficients.tobytes() == model.coefficients.tobytes()  # type: ignore[attr-defined]
        assert np.array_equal(back.active, model.active)  # type: ignore[attr-defined]


def test_document_carries_provenance(models: dict[str, ErrorModel]) -> None:
    doc = model_document(models["chebyshev"], data_sha256="cd" * 32, frame="tracker", fit={"rows": 120})
    assert doc["format"] == "comp-daemon-model" and doc["format_version"] == 1
    assert doc["kind"] == "chebyshev" and doc["order"] == 2
    assert doc["robot"]["sha256"] == KR.sha256 and doc["robot"]["name"] == KR.name
    assert doc["library_version"] == __version__
    assert doc["data_sha256"] == "cd" * 32
    assert "E3.eps_x.c2" in doc["model"]["coefficients"]
    assert doc["created_utc"].endswith("+00:00")


def test_corrupt_and_foreign_files_are_refused(models: dict[str, ErrorModel], tmp_path: Path) -> None:
    path = tmp_path / "m.json"
    save_model(models["kinematic"], path, data_sha256="0" * 64, frame="base")
    text = path.read_text()
    doc = json.loads(text)

    edited = dict(doc, model=dict(doc["model"], a_mm=[*doc["model"]["a_mm"][:5], 1.0]))
    with pytest.raises(ModelArtifactError, match="checksum mismatch"):
        parse_model(json.dumps(edited), "m.json")
    with pytest.raises(ModelArtifactError, match="not valid JSON"):
        parse_model(text[: len(text) // 2], "m.json")
    with pytest.raises(ModelArtifactError, match="format_version 2"):
        parse_model(json.dumps(dict(doc, format_version=2)), "m.json")
    with pytest.raises(ModelArtifactError, match="not a comp-daemon model"):
        parse_model(json.dumps({"kind": "kinematic"}), "m.json")
    with pytest.raises(
        ModelArtifactError, match=r"fitted for robot 'KUKA KR 210 R2700 extra'.*not for 'ABB IRB 120'"
    ):
        load_model(path, load_robot("irb120"))
    with pytest.raises(ModelArtifactError, match="cannot read"):
        load_model(tmp_path / "missing.json")


def test_kinematic_payload_field_of_wrong_shape_or_not_finite_is_named(models: dict[str, ErrorModel]) -> None:
    kin = models["kinematic"]
    payload = kin.to_payload()
    with pytest.raises(ValueError, match=r"model field 'a_mm': expected shape \(6,\), got \(5,\)"):
        type(kin).from_payload(KR, dict(payload, a_mm=payload["a_mm"][:5]), None, kin.registration)
    with pytest.raises(ValueError, match="model field 'world_T_base': values must be finite"):
        frame = np.array(payload["world_T_base"])
        frame[0, 0] = np.nan
        type(kin).from_payload(KR, dict(payload, world_T_base=frame.tolist()), None, kin.registration)


def test_error_statistics_are_signed_per_axis_and_absolute_in_3d() -> None:
    measured = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 3.0, 4.0]])
    st = error_statistics(measured, np.zeros((3, 3)))
    assert st["n"] == 3
    assert st["x"]["mean"] == pytest.approx(0.0)
    assert st["x"]["max_abs"] == pytest.approx(1.0)
    assert st["x"]["std"] == pytest.approx(1.0)  # sample standard deviation of (1, -1, 0)
    assert st["3d"]["mean"] == pytest.approx(7.0 / 3.0)
    assert st["3d"]["max"] == pytest.approx(5.0)
    text = format_table2({"nominal": st})
    assert "nominal" in text and "5.000" in text


def test_arrays_hash_depends_on_content_and_shape() -> None:
    a = np.arange(6.0)
    assert arrays_sha256(a) == arrays_sha256(a.copy())
    assert arrays_sha256(a) != arrays_sha256(a.reshape(2, 3))
    assert arrays_sha256(a, None) != arrays_sha256(a)


def test_kriging_and_compliance_models_round_trip_bit_exact(
    models: dict[str, ErrorModel], tmp_path: Path
) -> None:
    from comp_daemon.models.compliance import calibrate_compliance
    from comp_daemon.models.kriging import fit_kriging

    a, p, dirs = _data()
    kriging = fit_kriging(models["kinematic"], a, p, dir=dirs).model
    compliance = calibrate_compliance(KR, a, p, payload_kg=0.0).model
    a_new, _, dirs_new = _data(25)
    for model in (kriging, compliance):
        path = tmp_path / f"{model.kind}.json"
        save_model(model, path, data_sha256="cd" * 32, frame="tracker")
        loaded = load_model(path, KR).model
        assert loaded.kind == model.kind
        np.testing.assert_array_equal(
            loaded.predict_tcp_mm(a_new, dirs_new, 0.0, None),
            model.predict_tcp_mm(a_new, dirs_new, 0.0, None),
        )
