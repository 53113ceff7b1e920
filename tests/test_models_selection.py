"""Effects kept only where they earn their place out of fold; the papers' forms kept whole with :all."""

from __future__ import annotations

import numpy as np
import pytest

from comp_daemon.estimation.selection import judge
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams
from comp_daemon.models.compliance import ComplianceModel
from comp_daemon.models.effects import EffectParams, twin_tcp_mm
from comp_daemon.models.kinematic import KinematicModel
from comp_daemon.models.kriging import KrigingModel
from comp_daemon.models.registry import fit_model, parse_model_name
from comp_daemon.robot.description import load_robot

KR = load_robot("kr210")
N, N_FIT = 260, 160


def _axes(n: int, seed: int) -> np.ndarray:
    lim = KR.axis_limits_deg
    mid, half = lim.mean(axis=1), (lim[:, 1] - lim[:, 0]) / 2
    return mid + np.random.default_rng(seed).uniform(-0.5, 0.5, (n, 6)) * np.minimum(half, 70.0)


def _campaign(effects: dict[str, float], seed: int) -> dict[str, np.ndarray]:
    """Geometric errors and the named effects; payload 0, 60 or 120 kg by row; noise 0.01 mm."""
    rng = np.random.default_rng(seed)
    a = _axes(N, seed + 1)
    d = rng.choice([-1.0, 1.0], (N, 6))
    payload = np.array([0.0, 60.0, 120.0])[np.arange(N) % 3]
    truth = KinematicParams.from_robot(KR).apply(rng.normal(size=N_PARAMS) * 3e-4)
    eff = EffectParams.zeros().with_values(list(effects), list(effects.values()))
    p = twin_tcp_mm(KR, truth, eff, a, d, payload) + rng.normal(size=(N, 3)) * 0.01
    return {"a": a, "d": d, "payload": payload, "p": p}


def _check_rms(c: dict[str, np.ndarray], model: object) -> float:
    assert hasattr(model, "predict_tcp_mm")
    s = slice(N_FIT, N)
    err = c["p"][s] - model.predict_tcp_mm(c["a"][s], c["d"][s], c["payload"][s])
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def _fit(name: str, c: dict[str, np.ndarray]):  # type: ignore[no-untyped-def]
    s = slice(0, N_FIT)
    return fit_model(name, KR, c["a"][s], c["p"][s], dir=c["d"][s], payload_kg=c["payload"][s])


@pytest.fixture(scope="module")
def geometric() -> dict[str, np.ndarray]:
    return _campaign({}, 0)


@pytest.fixture(scope="module")
def backlash() -> dict[str, np.ndarray]:
    return _campaign({"h1": 0.006, "h2": 0.005, "h3": 0.006, "h5": 0.005}, 1)


@pytest.fixture(scope="module")
def payloads() -> dict[str, np.ndarray]:
    return _campaign({"C2": 3e-8, "C3": 4e-8}, 2)


def test_the_rule_keeps_a_part_whose_gain_exceeds_its_standard_error() -> None:
    rng = np.random.default_rng(0)
    base = rng.uniform(0.5, 1.5, 400)
    kept = judge("backlash", base - 0.2, base, "test")
    assert kept.kept and kept.gain_mm2 == pytest.approx(0.2) and "backlash kept" in kept.reason
    noise = rng.normal(0.0, 0.05, 400)
    useless = judge("ratio", base + np.abs(noise), base, "test")  # never better
    assert not useless.kept and "ratio dropped" in useless.reason
    assert not judge("x", np.zeros(1), np.ones(1), "test").kept  # no spread known: not shown


def test_effects_absent_from_the_campaign_are_dropped_and_cost_nothing(
    geometric: dict[str, np.ndarray],
) -> None:
    kin = _fit("kinematic", geometric)
    full = _fit("kinematic+ratio+backlash+compliance", geometric)
    sel = full.info["selection"]
    assert sel["kept"] == [] and set(sel["dropped"]) == {"ratio", "backlash", "compliance"}
    assert all(not d["kept"] and "dropped" in d["reason"] for d in sel["decisions"])
    assert isinstance(full.model, KinematicModel) and full.model.effects is None
    assert _check_rms(geometric, full.model) == pytest.approx(_check_rms(geometric, kin.model), rel=1e-9)
    # the paper's form keeps every effect, and pays for it on the check rows
    paper = _fit("kinematic:all+ratio+backlash+compliance", geometric)
    assert paper.info["selection"]["dropped"] == [] and paper.model.effects is not None
    assert _check_rms(geometric, paper.model) > _check_rms(geometric, kin.model)
    # a kriging stage with nothing to krig falls back to its base
    kg = _fit("kriging-backlash", geometric)
    assert "kriging" in kg.info["selection"]["dropped"] and kg.info["model_kind"] == "kinematic"
    assert isinstance(_fit("kriging-backlash:all", geometric).model, KrigingModel)


def test_an_effect_present_is_kept_and_the_absent_ones_beside_it_dropped(
    backlash: dict[str, np.ndarray],
) -> None:
    fitted = _fit("kinematic+ratio+backlash+compliance", backlash)
    sel = fitted.info["selection"]
    assert sel["kept"] == ["backlash"] and set(sel["dropped"]) == {"ratio", "compliance"}
    kin = _fit("kinematic", backlash)
    assert _check_rms(backlash, fitted.model) < 0.5 * _check_rms(backlash, kin.model)


def test_compliance_kind_fits_the_geometry_with_the_compliance(
    payloads: dict[str, np.ndarray], geometric: dict[str, np.ndarray]
) -> None:
    kin = _check_rms(payloads, _fit("kinematic", payloads).model)
    comp = _fit("compliance", payloads)
    paper = _fit("compliance:paper", payloads)
    assert isinstance(comp.model, ComplianceModel) and comp.model.geometric
    assert comp.info["selection"]["kept"] == ["compliance"]
    assert comp.model.compliance_rad_per_nm[1] == pytest.approx(3e-8, rel=0.2)
    assert _check_rms(payloads, comp.model) < 0.6 * kin < 0.6 * _check_rms(payloads, paper.model)
    assert not paper.model.geometric and paper.info["selection"]["dropped"] == []
    # where there is no compliance the kind is the kinematic calibration
    plain = _fit("compliance", geometric)
    assert plain.info["selection"]["dropped"] == ["compliance"]
    assert not np.any(plain.model.compliance_rad_per_nm)
    kin_geo = _check_rms(geometric, _fit("kinematic", geometric).model)
    assert _check_rms(geometric, plain.model) == pytest.approx(kin_geo, rel=1e-6)


def test_option_names_round_trip() -> None:
    for name in ("kinematic:all+ratio+backlash", "kriging:k=40:aniso:all", "compliance:paper", "poe:paper"):
        assert parse_model_name(name).name == name
    assert parse_model_name("kriging:all:aniso").name == "kriging:aniso:all"
