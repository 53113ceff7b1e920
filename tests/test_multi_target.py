"""Several targets (reflectors) per pose: the reader, the simulator, 6-DOF identification, the noise
floor from the targets' mutual distances, the flange's position and orientation errors, the service."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from comp_daemon.cli import main
from comp_daemon.data.columns import DatasetError
from comp_daemon.data.dataset import Dataset, dataset_to_csv, read_dataset
from comp_daemon.data.readers import dataset_from_records, parse_dataset
from comp_daemon.diagnosis.ladder import diagnose
from comp_daemon.diagnosis.report import render_report_html
from comp_daemon.diagnosis.result import DiagnoseOptions
from comp_daemon.diagnosis.targets import flange_pose_errors, noise_from_targets
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams, axes_deg_to_q_rad
from comp_daemon.kinematics.so3 import rotvec_to_matrix
from comp_daemon.models.base import ErrorModel
from comp_daemon.models.effects import EffectParams, effect_param_names
from comp_daemon.models.fitting import FitOptions
from comp_daemon.models.kinematic import KinematicProblem, calibrate_kinematic
from comp_daemon.models.registry import fit_spec, parse_model_name
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.sim.campaign import reflector_offsets_mm, run_campaign
from comp_daemon.sim.scenario import Scenario, load_scenario

HEADER = "a1,a2,a3,a4,a5,a6,x,y,z,x2,y2,z2,x3,y3,z3,note\n"
ROW = "0,10,20,0,30,0,1,2,3,4,5,6,7,8,9,hi\n"


# ---------------------------------------------------------------------------------------------
# Data
# ---------------------------------------------------------------------------------------------
def test_reader_gives_every_target_and_writes_them_back() -> None:
    ds = parse_dataset(HEADER + ROW + ROW.replace(",1,2,3,", ",1.5,2,3,"))
    assert ds.n_reflectors == 3
    assert ds.reflectors_mm is not None and ds.reflectors_mm.shape == (2, 3, 3)
    assert ds.reflectors_mm[1, 0].tolist() == [1.5, 2.0, 3.0]
    assert ds.reflectors_mm[0, 2].tolist() == [7.0, 8.0, 9.0]
    assert dict(ds.extra) == {"note": ("hi", "hi")}
    again = parse_dataset(dataset_to_csv(ds))
    assert again == ds and again.reflectors_mm is not None
    assert np.array_equal(again.reflectors_mm, ds.reflectors_mm)
    one = ds.subset([1]).reflectors_mm
    assert one is not None and one.shape == (1, 3, 3)
    assert ds.summary()["reflectors"] == 3
    records = [
        {
            "a1": 0,
            "a2": 0,
            "a3": 0,
            "a4": 0,
            "a5": 0,
            "a6": 0,
            "x": 1,
            "y": 2,
            "z": 3,
            "x2": 4,
            "y2": 5,
            "z2": 6,
        }
    ]
    js = dataset_from_records(records)
    assert js.more_xyz_mm is not None and js.more_xyz_mm.tolist() == [[[4.0, 5.0, 6.0]]]


def test_single_target_campaigns_are_unchanged() -> None:
    ds = parse_dataset("a1,a2,a3,a4,a5,a6,x,y,z\n0,0,0,0,0,0,1,2,3\n")
    assert ds.more_xyz_mm is None and ds.n_reflectors == 1
    assert ds.reflectors_mm is not None and ds.reflectors_mm.shape == (1, 1, 3)
    assert ds.columns == ("a1", "a2", "a3", "a4", "a5", "a6", "x", "y", "z")


@pytest.mark.parametrize(
    ("text", "row", "column", "words"),
    [
        (HEADER.replace(",z3,", ",q3,") + ROW, 1, "z3", "target 3 come together"),
        (HEADER.replace("x2,y2,z2,", "") + ROW.replace("4,5,6,", ""), 1, "x2", "without gaps"),
        (HEADER.replace(",x2,", ",X2,") + ROW, 1, "X2", "did you mean 'x2'"),
        ("a1,a2,a3,a4,a5,a6,x2,y2,z2\n0,0,0,0,0,0,1,2,3\n", 1, "x", "column missing"),
        (HEADER + ROW + ROW.replace(",8,", ",nan,"), 3, "y3", "non-finite"),
        (HEADER + ROW.replace(",5,", ",,"), 2, "y2", "empty cell"),
    ],
)
def test_reader_refuses_broken_targets_naming_row_and_column(
    text: str, row: int, column: str, words: str
) -> None:
    with pytest.raises(DatasetError) as err:
        parse_dataset(text)
    assert err.value.row == row and err.value.column == column
    assert words in str(err.value)


def test_dataset_refuses_further_targets_without_the_first() -> None:
    with pytest.raises(ValueError, match="need the first one"):
        Dataset(a_deg=np.zeros((1, 6)), more_xyz_mm=np.zeros((1, 1, 3)))
    with pytest.raises(ValueError, match="non-finite"):
        Dataset(a_deg=np.zeros((1, 6)), xyz_mm=np.zeros((1, 3)), more_xyz_mm=np.full((1, 1, 3), np.nan))


# ---------------------------------------------------------------------------------------------
# Simulator
# ---------------------------------------------------------------------------------------------
def test_sim_sample_targets_writes_rigid_reflectors(tmp_path: Path) -> None:
    out = tmp_path / "three.csv"
    assert main(["sim", "sample", "--scenario", "kr210-geometric", "--n", "40", "--targets", "3",
                 "--out", str(out)]) == 0  # fmt: skip
    ds = read_dataset(out)
    assert ds.n_reflectors == 3 and "z3" in ds.columns
    pts = ds.reflectors_mm
    assert pts is not None
    offsets = reflector_offsets_mm(np.zeros(3), 3)
    sigma = load_scenario("kr210-geometric").noise.tracker_sigma_mm
    for i, j in ((0, 1), (0, 2), (1, 2)):
        d = np.linalg.norm(pts[:, i] - pts[:, j], axis=1)
        true = float(np.linalg.norm(offsets[i] - offsets[j]))
        assert 100.0 <= true <= 200.0
        assert abs(float(d.mean()) - true) < 5 * sigma  # rigid on the flange, up to the noise
        assert 0.3 * sigma < float(d.std()) < 3 * sigma  # each reflector has its own noise
    single = run_campaign(load_scenario("kr210-geometric"), 40)
    assert single.more_xyz_mm is None
    same = run_campaign(load_scenario("kr210-geometric"), 40, targets=1)
    assert single.xyz_mm is not None and same.xyz_mm is not None
    assert np.array_equal(single.xyz_mm, same.xyz_mm)


def test_real_like_scenario_has_three_reflectors_and_a_5_um_tracker() -> None:
    sc = load_scenario("real-like")
    assert sc.campaign.targets == 3 and sc.noise.tracker_sigma_mm == pytest.approx(0.005)


# ---------------------------------------------------------------------------------------------
# Identification
# ---------------------------------------------------------------------------------------------
def _rms(model: ErrorModel, a_deg: np.ndarray, ref_mm: np.ndarray) -> float:
    e = model.predict_tcp_mm(a_deg) - ref_mm
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


def _wrist_campaign(sigma_mm: float, n: int, seed: int) -> tuple[Scenario, Dataset]:
    """The real-like robot (wrist errors) without its non-geometric effects, three reflectors."""
    sc = load_scenario("real-like")
    sc = dataclasses.replace(
        sc, effects=EffectParams.zeros(), noise=dataclasses.replace(sc.noise, tracker_sigma_mm=sigma_mm)
    )
    return sc, run_campaign(sc, n, seed=seed, targets=3)


def test_multi_target_jacobian_matches_finite_differences() -> None:
    robot = load_scenario("real-like").robot
    rng = np.random.default_rng(2)
    a = rng.uniform(-40, 40, size=(12, 6))
    a[:, 4] = rng.uniform(20, 80, size=12)
    nominal = KinematicParams.from_robot(robot)
    more_meas = rng.normal(size=(12, 2, 3))  # only the Jacobian matters here
    problem = KinematicProblem(
        robot,
        nominal,
        EffectParams.zeros(),
        np.arange(N_PARAMS),
        [],
        a,
        np.zeros((12, 3)),
        None,
        0.0,
        None,
        more_measured_mm=more_meas,
        more_start_mm=reflector_offsets_mm(nominal.tool_xyz_mm, 3)[1:],
    )
    x = rng.normal(scale=1e-3, size=N_PARAMS + 6)
    jac = problem.jacobian(x)
    assert jac.shape == (12 * 3 * 3, N_PARAMS + 6)
    h = 1e-6
    numeric = np.stack(
        [(problem.residual(x + h * e) - problem.residual(x - h * e)) / (2 * h) for e in np.eye(x.size)],
        axis=1,
    )
    assert np.allclose(jac, numeric, atol=1e-5 * np.abs(numeric).max())


def test_multi_target_compliance_columns_carry_the_payload_at_the_tcp() -> None:
    """With a payload and a compliance, every target's columns are the derivative of its residual:
    the gravity torques of the further targets' rows carry the payload at the TCP, as the residual's
    twin has it (not at the target), so the calibration's steps are exact Gauss–Newton steps."""
    robot = load_scenario("real-like").robot
    rng = np.random.default_rng(4)
    a = rng.uniform(-40, 40, size=(12, 6))
    a[:, 4] = rng.uniform(20, 80, size=12)
    nominal = KinematicParams.from_robot(robot)
    names = effect_param_names(["ratio", "compliance"], (1, 2, 3, 4, 5, 6))
    problem = KinematicProblem(
        robot,
        nominal,
        EffectParams.zeros(),
        np.arange(N_PARAMS),
        names,
        a,
        np.zeros((12, 3)),
        None,
        rng.uniform(2.0, 5.0, size=12),
        None,
        more_measured_mm=rng.normal(size=(12, 2, 3)),
        more_start_mm=reflector_offsets_mm(nominal.tool_xyz_mm, 3)[1:],
    )
    x = np.zeros(N_PARAMS + len(names) + 6)
    x[N_PARAMS : N_PARAMS + 6] = rng.normal(scale=1e-4, size=6)  # ratio errors
    x[N_PARAMS + 6 : N_PARAMS + 12] = rng.uniform(1e-7, 5e-7, size=6)  # compliances, rad/(N m)
    jac = problem.jacobian(x)
    cols = np.arange(N_PARAMS, N_PARAMS + len(names))
    h = np.where(cols < N_PARAMS + 6, 1e-7, 1e-9)
    numeric = np.stack(
        [
            (problem.residual(x + hk * np.eye(x.size)[k]) - problem.residual(x - hk * np.eye(x.size)[k]))
            / (2 * hk)
            for k, hk in zip(cols, h, strict=True)
        ],
        axis=1,
    )
    scale = np.abs(numeric).max(axis=0)
    assert np.all(np.abs(jac[:, cols] - numeric) <= 1e-5 * scale + 1e-9)


def test_six_dof_identification_beats_position_only_on_check_rows() -> None:
    wins = []
    for seed in (0, 1, 2):
        sc, ds = _wrist_campaign(0.02, 300, seed)
        assert ds.a_deg is not None and ds.xyz_mm is not None and ds.more_xyz_mm is not None
        fit, check = ds.fit_rows()[:45], ds.check_rows()
        a, p = ds.a_deg, ds.xyz_mm
        position_only = calibrate_kinematic(sc.robot, a[fit], p[fit])
        six_dof = calibrate_kinematic(sc.robot, a[fit], p[fit], more_targets_mm=ds.more_xyz_mm[fit])
        assert six_dof.targets == 3 and position_only.targets == 1
        truth_params = sc.true_params()
        truth = tcp_position_mm(truth_params, axes_deg_to_q_rad(a[check], truth_params.sign))
        measured = (_rms(position_only.model, a[check], p[check]), _rms(six_dof.model, a[check], p[check]))
        model_error = (_rms(position_only.model, a[check], truth), _rms(six_dof.model, a[check], truth))
        assert measured[1] < measured[0]
        assert model_error[1] < 0.8 * model_error[0]
        wins.append(model_error[1] / model_error[0])
        # the offsets found are the reflectors' (150 mm from the TCP in the flange's x-y plane)
        more = six_dof.model.more_targets_mm
        assert more is not None
        tool = six_dof.model.params.tool_xyz_mm
        assert np.allclose(np.linalg.norm(more - tool, axis=1), 150.0, atol=0.05)
    assert float(np.mean(wins)) < 0.75


def test_every_model_kind_fits_a_multi_target_campaign() -> None:
    sc, ds = _wrist_campaign(0.005, 90, 3)
    assert ds.a_deg is not None and ds.xyz_mm is not None
    fit, check = ds.fit_rows(), ds.check_rows()
    for name in ("kinematic", "kinematic+ratio+backlash", "chebyshev", "compliance", "poe", "kriging"):
        rows = MeasuredRows.of_dataset(ds).take(fit)
        assert rows.more_xyz_mm is not None and rows.more_xyz_mm.shape == (len(fit), 2, 3)
        fitted = fit_spec(parse_model_name(name), sc.robot, rows, FitOptions())
        pred = fitted.model.predict_tcp_mm(
            ds.a_deg[check], None if ds.dir is None else ds.dir[check].astype(np.float64)
        )
        rms = float(np.sqrt(np.mean(np.sum((pred - ds.xyz_mm[check]) ** 2, axis=1))))
        assert rms < 0.1, name
        if name.startswith("kinematic") or name == "kriging":
            info = fitted.info if name != "kriging" else fitted.info["base"]
            assert info["targets"] == 3 and len(info["more_targets_mm"]) == 2
        std = fitted.model.predict_std_mm(ds.a_deg[check][:3])
        assert std is None or np.all(np.isfinite(std))


# ---------------------------------------------------------------------------------------------
# Noise floor and flange errors
# ---------------------------------------------------------------------------------------------
def test_distance_spread_estimates_sigma() -> None:
    rng = np.random.default_rng(4)
    true = reflector_offsets_mm(np.array([0.0, 0.0, 200.0]), 3)
    rots = [np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(2000)]
    pts = np.array([true @ r.T for r in rots]) + rng.normal(scale=0.004, size=(2000, 3, 3))
    found = noise_from_targets(pts)
    assert found is not None
    assert found[0] == pytest.approx(0.004, rel=0.05)
    assert found[1] == pytest.approx(np.sqrt(3) * found[0])
    two = noise_from_targets(pts[:, :2])  # one distance is evidence enough
    assert two is not None and two[0] == pytest.approx(0.004, rel=0.1)
    assert noise_from_targets(pts[:, :1]) is None and noise_from_targets(None) is None
    # the robot's own repeatability (the whole flange moving) leaves the distances alone
    shaken = pts + rng.normal(scale=0.05, size=(2000, 1, 3))
    shaken_found = noise_from_targets(shaken)
    assert shaken_found is not None and shaken_found[0] == pytest.approx(found[0], rel=1e-9)


def test_flange_pose_error_of_a_known_motion() -> None:
    rng = np.random.default_rng(5)
    origin = rng.normal(scale=500.0, size=(4, 3))
    offsets = reflector_offsets_mm(np.array([0.0, 0.0, 180.0]), 3)
    twin = origin[:, None, :] + offsets[None]
    angle_deg, shift = 0.02, np.array([0.01, -0.02, 0.005])
    turn = rotvec_to_matrix(np.deg2rad(angle_deg) * np.array([0.6, 0.0, 0.8]))
    # the flange turned about its own origin, then shifted
    measured = origin[:, None, :] + offsets[None] @ turn.T + shift
    position, angle = flange_pose_errors(origin, twin, measured)
    assert np.allclose(angle, angle_deg, rtol=1e-6)
    assert np.allclose(position, np.linalg.norm(shift), rtol=1e-6)


def test_diagnosis_noise_floor_from_targets_and_flange_errors(tmp_path: Path) -> None:
    sc = load_scenario("real-like")
    ds = run_campaign(sc, 300, seed=11)
    assert ds.n_reflectors == 3
    diag = diagnose(ds, sc.robot)
    truth = np.sqrt(3.0) * sc.noise.tracker_sigma_mm
    assert diag.noise_floor_source == "targets"
    assert diag.noise_floor_mm is not None and abs(diag.noise_floor_mm - truth) < 0.3 * truth
    doc = diag.to_json()
    assert doc["noise_floor_source"] == "targets"
    flange = doc["where"]["flange"]
    assert flange["targets"] == 3 and flange["rows"] == "check"
    assert 0 < flange["position_rms_mm"] <= flange["position_max_mm"]
    assert 0 < flange["orientation_rms_deg"] <= flange["orientation_max_deg"]
    # the geometric step fits every target: it leaves no more of the wrist's orientation error
    # (real-like has wrist errors) than a 6-DOF calibration on every target's position does
    six = flange["six_dof"]
    assert flange["orientation_rms_deg"] < 1.3 * six["orientation_rms_deg"]
    assert six["position_rms_mm"] < 1.2 * flange["position_rms_mm"]
    assert "orientation" in doc["where"]["summary"]
    page = render_report_html(diag)
    assert "flange (3 targets, check rows)" in page and "orientation (deg)" in page
    # an explicit declared uncertainty overrides the targets' evidence (which a probe's virtual
    # reflectors, exact by construction, would turn into a floor of nothing)
    declared = diagnose(ds, sc.robot, DiagnoseOptions(tracker_sigma_mm=0.05))
    assert declared.noise_floor_source == "declared"
    assert declared.noise_floor_mm == pytest.approx(np.sqrt(3.0) * 0.05)
    # one target: no such evidence, and no flange section
    single = dataclasses.replace(ds, more_xyz_mm=None)
    plain = diagnose(single, sc.robot).to_json()
    assert plain["noise_floor_mm"] is None and "flange" not in plain["where"]
    out = tmp_path / "d.json"
    data = tmp_path / "three.csv"
    data.write_text(dataset_to_csv(ds))
    assert main(["diagnose", str(data), "--robot", "irb120", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["noise_floor_source"] == "targets"
