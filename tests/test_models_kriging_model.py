"""The error-similarity model of seed 001 on a simulated campaign: residual kriging over a kinematic fit."""

from __future__ import annotations

import json

import numpy as np
import pytest

from comp_daemon.kinematics.params import N_PARAMS, KinematicParams
from comp_daemon.models.effects import EffectParams, twin_tcp_mm
from comp_daemon.models.kinematic import calibrate_kinematic
from comp_daemon.models.kriging import JointStateMetric, KrigingModel, fit_kriging
from comp_daemon.models.nominal import NominalModel
from comp_daemon.models.registry import model_from_payload
from comp_daemon.robot.description import load_robot

ROBOT = load_robot("kr210")
Campaign = tuple[np.ndarray, np.ndarray, np.ndarray]
LO = np.array([-30.0, -110.0, 90.0, -60.0, -90.0, -90.0])
HI = np.array([30.0, -60.0, 150.0, 60.0, -20.0, 90.0])


def _campaign(n: int, seed: int, backlash_deg: float = 0.004) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Axis values in a joint box, random approach directions (as seed 001's simulation), TCPs of a
    robot with geometric errors, backlash and gravity compliance under a 150 kg payload, tracker noise."""
    rng = np.random.default_rng(seed)
    a = LO + rng.random((n, 6)) * (HI - LO)
    d = rng.choice([-1.0, 1.0], (n, 6))
    g = np.random.default_rng(100)
    dx = np.zeros(N_PARAMS)
    dx[:30] = g.normal(0.0, 1.0, 30) * np.tile([np.deg2rad(0.005), 0.15, 0.15, np.deg2rad(0.005), 0.0], 6)
    effects = EffectParams(
        backlash_deg=np.full(6, backlash_deg),
        compliance_rad_per_nm=np.array([2.0, 2.0, 3.0, 10.0, 10.0, 10.0]) * 6e-8,
    )
    p = twin_tcp_mm(ROBOT, KinematicParams.from_robot(ROBOT).apply(dx), effects, a, d, 150.0)
    return a, d, p + rng.normal(0.0, 0.01, p.shape)


@pytest.fixture(scope="module")
def campaign() -> Campaign:
    return _campaign(400, 7)


def _rms(err: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def test_direction_aware_kriging_beats_direction_blind_on_held_out_points(campaign: Campaign) -> None:
    a, d, p = campaign
    fit, chk = slice(0, 250), slice(250, 400)
    kin = calibrate_kinematic(ROBOT, a[fit], p[fit], frame="base", payload_kg=150.0).model
    blind = fit_kriging(kin, a[fit], p[fit], dir=d[fit], payload_kg=150.0, direction="blind")
    aware = fit_kriging(kin, a[fit], p[fit], dir=d[fit], payload_kg=150.0, direction="aware")
    assert not blind.model.metric.direction_aware
    assert aware.model.metric.direction_aware
    rms_kin = _rms(p[chk] - kin.predict_tcp_mm(a[chk], d[chk], 150.0))
    rms_blind = _rms(p[chk] - blind.model.predict_tcp_mm(a[chk], d[chk], 150.0))
    rms_aware = _rms(p[chk] - aware.model.predict_tcp_mm(a[chk], d[chk], 150.0))
    assert rms_aware < 0.75 * rms_blind
    assert rms_blind <= 1.02 * rms_kin  # blind kriging cannot learn the backlash part
    # the leave-one-out criterion that chose the separation saw the same ordering
    assert aware.loo_rms_mm < blind.loo_rms_mm


def test_the_prediction_is_the_base_plus_the_kriged_residual_and_interpolates(campaign: Campaign) -> None:
    a, d, p = campaign
    base = NominalModel(ROBOT)
    fitted = fit_kriging(base, a[:120], p[:120], dir=d[:120], direction="aware", nugget=False)
    model = fitted.model
    # no nugget: the model reproduces the sampling points
    np.testing.assert_allclose(model.predict_tcp_mm(a[:120], d[:120]), p[:120], atol=1e-6)
    res = model.predict_residual_mm(a[200:210], d[200:210])
    assert isinstance(res, np.ndarray)
    np.testing.assert_allclose(
        model.predict_tcp_mm(a[200:210], d[200:210]), base.predict_tcp_mm(a[200:210]) + res
    )
    w = model.weights(a[200:210], d[200:210], axis=2)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-9)
    # a single pose (6,) is the batch of one
    one = model.predict_tcp_mm(a[205], d[205])
    np.testing.assert_allclose(one[0], model.predict_tcp_mm(a[200:210], d[200:210])[5], rtol=1e-12)


def test_blind_metric_ignores_the_query_direction(campaign: Campaign) -> None:
    a, d, p = campaign
    fitted = fit_kriging(NominalModel(ROBOT), a[:100], p[:100], dir=d[:100], direction="blind")
    r1 = fitted.model.predict_residual_mm(a[300:305], d[300:305])
    r2 = fitted.model.predict_residual_mm(a[300:305], -d[300:305])
    np.testing.assert_array_equal(r1, r2)
    assert fitted.candidates == (((0.0,) * 6, fitted.loo_rms_mm),)


def test_model_round_trips_through_json_bit_exact(campaign: Campaign) -> None:
    a, d, p = campaign
    kin = calibrate_kinematic(ROBOT, a[:150], p[:150], frame="base", payload_kg=150.0).model
    model = fit_kriging(kin, a[:150], p[:150], dir=d[:150], payload_kg=150.0).model
    text = json.dumps({"kind": model.kind, "payload": model.to_payload()})
    stored = json.loads(text)
    assert stored["kind"] == "kriging"
    again = model_from_payload(stored["kind"], ROBOT, stored["payload"], None, model.registration)
    assert isinstance(again, KrigingModel)
    q, qd = a[300:400], d[300:400]
    np.testing.assert_array_equal(again.predict_tcp_mm(q, qd, 150.0), model.predict_tcp_mm(q, qd, 150.0))
    np.testing.assert_array_equal(again.metric.dir_separation_deg, model.metric.dir_separation_deg)
    assert again.base.kind == "kinematic"
    broken = json.loads(text)["payload"]
    del broken["samples"]
    with pytest.raises(ValueError, match="missing field 'samples'"):
        model_from_payload("kriging", ROBOT, broken, None, model.registration)
    with pytest.raises(ValueError, match="base_loader"):
        KrigingModel.from_payload(ROBOT, stored["payload"], None, model.registration)


def test_metric_distance_is_joint_distance_plus_direction_separation() -> None:
    m = JointStateMetric(dir_separation_deg=np.array([10.0, 0.0, 0.0, 0.0, 0.0, 5.0]))
    a = np.array([[0.0, 0, 0, 0, 0, 0], [3.0, 4.0, 0, 0, 0, 0]])
    d = np.array([[1.0, 1, 1, 1, 1, 1], [-1.0, 1, 1, 1, 1, -1]])
    dist = m.distances(a, d)
    assert dist[0, 1] == pytest.approx(np.sqrt(25.0 + 100.0 + 25.0))
    unknown = m.distances(a[:1], np.zeros((1, 6)), a[:1], d[:1])
    assert unknown[0, 0] == pytest.approx(np.sqrt(25.0 + 6.25))  # an unknown direction sits half way
    with pytest.raises(ValueError, match="dir: values must be -1, \\+1"):
        m.embed(a, np.full((2, 6), 2.0))
    with pytest.raises(ValueError, match="dir_separation_deg"):
        JointStateMetric(dir_separation_deg=np.full(6, -1.0))


def test_fit_refuses_bad_input(campaign: Campaign) -> None:
    a, d, p = campaign
    base = NominalModel(ROBOT)
    with pytest.raises(ValueError, match=r"measured positions must have shape \(50, 3\)"):
        fit_kriging(base, a[:50], p[:49])
    with pytest.raises(ValueError, match=r"dir: expected shape \(50, 6\)"):
        fit_kriging(base, a[:50], p[:50], dir=d[:40])
    with pytest.raises(ValueError, match="not valid in joint space"):
        fit_kriging(base, a[:50], p[:50], dir=d[:50], variogram="spherical")
    with pytest.raises(ValueError, match="direction must be"):
        fit_kriging(base, a[:50], p[:50], dir=d[:50], direction="sideways")  # type: ignore[arg-type]
