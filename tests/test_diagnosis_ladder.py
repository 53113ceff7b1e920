"""The ladder: numbers that can be recomputed independently, recovery, skips with reasons, refusals."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.optimize
from diagnosis_campaigns import NOISE_FLOOR_MM, make_campaign

from comp_daemon.data.dataset import Dataset
from comp_daemon.diagnosis import DiagnoseOptions, diagnose
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.effects import EffectParams, effect_param_names, twin_tcp_mm

REQUIRED = (
    "robot",
    "rows",
    "baseline",
    "steps",
    "unmodelled",
    "where",
    "unexplained_rms_mm",
    "noise_floor_mm",
)


def step_names(step: dict, harmonics: int = 2) -> list[str]:
    joints = [int(j) for j in step["joints"]]
    return effect_param_names(step["effect"], joints, harmonics) if step["effect"] != "geometric" else []


def independent_check_rms(ds: Dataset, robot, names: list[str]) -> float:
    """Fit all 39 geometric parameters and the named effects with scipy (central differences, trust
    region) on the fit rows, and return the RMS 3-D error on the check rows; no code of the
    diagnosis involved."""
    nominal = KinematicParams.from_robot(robot)
    fit, check = ds.fit_rows(), ds.check_rows()
    dirs = np.asarray(ds.dir, dtype=float)
    zero = EffectParams.zeros(2)
    scale = np.ones(N_PARAMS + len(names))
    scale[N_PARAMS:] = [
        1e-8 if n.startswith("C") else 1e-5 if n in ("kappa",) or n.startswith("eps") else 1e-3 for n in names
    ]

    def model(x: np.ndarray, rows: np.ndarray) -> np.ndarray:
        params = nominal.apply(x[:N_PARAMS] * scale[:N_PARAMS])
        eff = zero.with_values(names, x[N_PARAMS:] * scale[N_PARAMS:]) if names else zero
        return twin_tcp_mm(
            robot, params, eff, ds.a_deg[rows], dirs[rows], ds.payload_kg[rows], ds.temp_c[rows]
        )

    def resid(x: np.ndarray) -> np.ndarray:
        return (model(x, fit) - ds.xyz_mm[fit]).reshape(-1)

    # central differences and the Jacobian's own scaling: forward differences (MINPACK's lm) stop
    # 1e-4 (relative) off the optimum along the weakly determined directions, and where depends on
    # the last bits of the forward kinematics. With a compliance the cost has a flat valley (the
    # compliance against the geometry) along which the solver creeps without meeting its tolerances:
    # from 200 to 400 evaluations its cost falls by 0.03 %, and from 200 to 2 000 the check RMS
    # moves by 1e-5 (relative), well inside the comparison's 1e-4; 200 take 12 s instead of 126 s
    sol = scipy.optimize.least_squares(
        resid,
        np.zeros(len(scale)),
        method="trf",
        jac="3-point",
        x_scale="jac",
        xtol=1e-15,
        ftol=1e-15,
        gtol=1e-15,
        max_nfev=200,
    )
    err = np.linalg.norm(model(sol.x, check) - ds.xyz_mm[check], axis=1)
    return float(np.sqrt(np.mean(err**2)))


def test_json_has_every_required_field_and_consistent_ladder() -> None:
    camp = make_campaign("kr210", 51, [("backlash", 3, 8 * NOISE_FLOOR_MM)])
    doc = diagnose(camp.dataset, camp.robot).to_json()
    for key in REQUIRED:
        assert key in doc
    assert doc["robot"] == "KUKA KR 210 R2700 extra"
    assert doc["rows"] == {"fit": len(camp.dataset.fit_rows()), "check": len(camp.dataset.check_rows())}
    assert doc["baseline"]["effect"] == "nominal"
    assert doc["steps"][0]["effect"] == "geometric"
    before = doc["baseline"]["check_rms_mm"]
    for step in doc["steps"]:
        assert set(step) >= {
            "effect",
            "joints",
            "significant",
            "check_rms_mm",
            "check_max_mm",
            "shrink_pct",
            "params",
        }
        assert step["check_max_mm"] >= step["check_rms_mm"]
        assert step["shrink_pct"] == pytest.approx(100 * (1 - step["check_rms_mm"] / before), abs=0.02)
        before = step["check_rms_mm"]
    assert doc["unmodelled"] == ["backlash"]
    assert set(doc["where"]["axis_rms_mm"]) == {"x", "y", "z"}
    assert doc["where"]["joints"] == [3]
    assert "backlash on A3" in doc["where"]["summary"]
    last = [s for s in doc["steps"] if s["significant"]][-1]
    assert doc["unexplained_rms_mm"] == last["check_rms_mm"]


def test_check_rms_and_shrink_agree_with_an_independent_recomputation() -> None:
    camp = make_campaign(
        "kr210", 52, [("compliance", 2, 6 * NOISE_FLOOR_MM)], n_poses=150, repeat_fraction=0.0
    )
    ds, robot = camp.dataset, camp.robot
    doc = diagnose(ds, robot).to_json()
    check = ds.check_rows()
    nominal = KinematicParams.from_robot(robot)
    p_nom = tcp_position_mm(nominal, axes_deg_to_q_rad(ds.a_deg[check], nominal.sign))
    base_rms = float(np.sqrt(np.mean(np.sum((p_nom - ds.xyz_mm[check]) ** 2, axis=1))))
    assert doc["baseline"]["check_rms_mm"] == pytest.approx(base_rms, rel=1e-5)
    names: list[str] = []
    before = base_rms
    for step in doc["steps"][:2]:
        names = names + step_names(step)
        rms = independent_check_rms(ds, robot, names)
        assert step["check_rms_mm"] == pytest.approx(rms, rel=1e-4), step["effect"]
        assert step["shrink_pct"] == pytest.approx(100.0 * (1.0 - rms / before), abs=0.02)
        before = rms
    assert doc["steps"][1]["effect"] == "compliance"


def test_noise_free_effects_are_recovered_exactly() -> None:
    camp = make_campaign(
        "kr210",
        53,
        [("backlash", 2, 5 * NOISE_FLOOR_MM), ("ratio", 3, 5 * NOISE_FLOOR_MM)],
        noise_mm=0.0,
        n_poses=150,
    )
    diag = diagnose(camp.dataset, camp.robot)
    assert sorted(diag.unmodelled) == ["backlash", "ratio"]
    final = diag.final_step.fit.effects
    assert final.backlash_deg[1] == pytest.approx(camp.effects.backlash_deg[1], rel=1e-6)
    assert final.ratio[2] == pytest.approx(camp.effects.ratio[2], rel=1e-6)
    assert diag.unexplained_rms_mm < 1e-6


def test_effects_without_their_data_are_skipped_with_the_reason() -> None:
    camp = make_campaign("kr210", 54, [("backlash", 2, 5 * NOISE_FLOOR_MM)], with_dir=False, with_temp=False)
    # the campaign's directions are drawn at random, not the pose order's: inference is turned off
    doc = diagnose(camp.dataset, camp.robot, DiagnoseOptions(infer_directions=False)).to_json()
    reasons = {(s["effect"], tuple(s["joints"])): s["reason"] for s in doc["skipped"]}
    assert "dir" in reasons[("backlash", (1, 2, 3, 4, 5, 6))]
    assert "temp_c" in reasons[("thermal", ())]
    assert "vertical" in reasons[("compliance", (1,))]
    assert "backlash" not in doc["unmodelled"]
    assert "Not tested for lack of data" in doc["where"]["summary"]


def test_compliance_is_tested_with_zero_payload_and_joint6_skipped_on_a_tool_on_its_axis() -> None:
    camp = make_campaign("irb120", 55, [("compliance", 3, 5 * NOISE_FLOOR_MM)], payloads=(0.0,))
    doc = diagnose(camp.dataset, camp.robot).to_json()
    assert doc["unmodelled"] == ["compliance"] and doc["joints"] == [3]
    skipped = {(s["effect"], tuple(s["joints"])) for s in doc["skipped"]}
    assert ("backlash", (6,)) in skipped and ("cyclic", (6,)) in skipped


def test_noise_floor_from_repeats_else_declared_else_none_never_the_fit_residual() -> None:
    with_repeats = make_campaign("kr210", 56, [], repeat_fraction=0.5)
    doc = diagnose(with_repeats.dataset, with_repeats.robot).to_json()
    assert doc["noise_floor_source"] == "repeats"
    assert doc["noise_floor_mm"] == pytest.approx(NOISE_FLOOR_MM, rel=0.15)
    without = make_campaign("kr210", 56, [], repeat_fraction=0.0)
    diag = diagnose(without.dataset, without.robot)
    doc = diag.to_json()
    assert doc["noise_floor_source"] is None and doc["noise_floor_mm"] is None
    assert "could not be compared with noise" in doc["where"]["summary"]
    declared = diagnose(without.dataset, without.robot, DiagnoseOptions(tracker_sigma_mm=0.01)).to_json()
    assert declared["noise_floor_source"] == "declared"
    assert declared["noise_floor_mm"] == pytest.approx(0.01 * np.sqrt(3.0))
    assert "could not be compared" not in declared["where"]["summary"]


def test_without_split_column_check_rows_are_drawn_reproducibly() -> None:
    camp = make_campaign("kr210", 57, [])
    ds = camp.dataset
    import dataclasses

    no_split = dataclasses.replace(ds, split=None)
    a = diagnose(no_split, camp.robot).to_json()
    b = diagnose(no_split, camp.robot).to_json()
    assert a["split"]["drawn"] and "held out" in a["split"]["message"]
    assert a["rows"]["fit"] + a["rows"]["check"] == len(ds)
    assert a["steps"] == b["steps"]


def test_refusals_name_what_is_wrong() -> None:
    camp = make_campaign("kr210", 58, [], n_poses=60, repeat_fraction=0.0)
    import dataclasses

    all_fit = dataclasses.replace(camp.dataset, split=np.full(len(camp.dataset), "fit"))
    with pytest.raises(ValueError, match="no row 'check'"):
        diagnose(all_fit, camp.robot)
    few = camp.dataset.subset(np.arange(30))
    with pytest.raises(ValueError, match="fewer than the 39 parameters"):
        diagnose(few, camp.robot)
    with pytest.raises(ValueError, match="frame"):
        DiagnoseOptions(frame="world")  # type: ignore[arg-type]
