"""Targets compensated by the store's active model, as the executor gets them."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from comp_daemon.daemon.compensation import ActiveModelCompensator
from comp_daemon.data.target import Target
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import N_PARAMS, PARAM_NAMES, KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.artifact import model_document
from comp_daemon.models.compensation import CompensationLimits
from comp_daemon.models.kinematic import KinematicModel
from comp_daemon.models.nominal import NominalModel
from comp_daemon.models.registry import fit_model
from comp_daemon.robot.description import load_robot
from comp_daemon.rt.executor import CompensationError, ModelMissingError
from comp_daemon.service.schemas import TARGET_MOVING
from comp_daemon.service.store import ModelDraft, Store

HOME = [5.0, -85.0, 120.0, 3.0, -40.0, 10.0]


@pytest.fixture
def store(tmp_path: Path) -> Iterator[Store]:
    with Store(tmp_path / "s.sqlite3") as s:
        yield s


def activate(store: Store, artifact: dict[str, Any], kind: str = "kinematic") -> int:
    record = store.add_model(ModelDraft(kind, None, artifact, {}, None))
    store.activate_model(record.id)
    return record.id


def test_without_a_model_the_target_fails_as_model_missing(store: Store) -> None:
    comp = ActiveModelCompensator(store, load_robot("kr210"), [0, 1, 2])
    with pytest.raises(ModelMissingError, match="no model is active"):
        comp(Target(axes_deg=tuple(HOME)))


def test_a_kinematic_model_moves_the_command_so_its_prediction_hits_the_target(store: Store) -> None:
    robot = load_robot("kr210")
    dx = np.random.default_rng(4).normal(0.0, 1.0, N_PARAMS) * np.where(
        [n.startswith(("theta", "alpha", "beta", "base_r")) for n in PARAM_NAMES], 1e-4, 0.1
    )
    model = KinematicModel(robot, KinematicParams.from_robot(robot).apply(dx))
    model_id = activate(store, model_document(model, data_sha256="a" * 64, frame="base"))
    comp = ActiveModelCompensator(store, robot, [0, 1, 2], current_axes=lambda: tuple(HOME))
    request = Target(axes_deg=tuple(HOME))
    out = comp(request)
    assert out.model_id == model_id
    assert out.loop_target_deg == out.commanded_deg[:3]
    wanted = tcp_position_mm(
        KinematicParams.from_robot(robot), axes_deg_to_q_rad(np.array([HOME]), robot.sign)
    )
    predicted = model.predict_tcp_mm(np.array([out.commanded_deg]))
    np.testing.assert_allclose(predicted, wanted, atol=1e-6)
    assert np.abs(np.subtract(out.commanded_deg, HOME)).max() > 1e-4  # the model did change it
    # the same wanted TCP given as a position reaches the same prediction
    tcp = Target(tcp_mm=tuple(wanted[0]))
    by_position = comp(tcp)
    np.testing.assert_allclose(model.predict_tcp_mm(np.array([by_position.commanded_deg])), wanted, atol=1e-6)


def test_the_daemon_compensator_applies_its_configured_limits(store: Store) -> None:
    robot = load_robot("kr210")
    dx = np.random.default_rng(4).normal(0.0, 1.0, N_PARAMS) * np.where(
        [n.startswith(("theta", "alpha", "beta", "base_r")) for n in PARAM_NAMES], 1e-4, 0.1
    )
    activate(
        store,
        model_document(
            KinematicModel(robot, KinematicParams.from_robot(robot).apply(dx)),
            data_sha256="a" * 64,
            frame="base",
        ),
    )
    request = Target(axes_deg=tuple(HOME))
    loose = ActiveModelCompensator(store, robot, [0, 1, 2], current_axes=lambda: tuple(HOME))
    change = np.abs(np.subtract(loose(request).commanded_deg, HOME)).max()
    tight = ActiveModelCompensator(
        store,
        robot,
        [0, 1, 2],
        current_axes=lambda: tuple(HOME),
        limits=CompensationLimits(max_axis_change_deg=change / 2),
    )
    with pytest.raises(ValueError, match=r"A[1-6].*(limit|change)"):
        tight(request)


def test_an_artifact_that_is_not_a_model_document_is_refused(store: Store) -> None:
    robot = load_robot("kr210")
    nominal = NominalModel(robot)
    activate(store, {"kind": "nominal", "order": None, "payload": nominal.to_payload()}, "nominal")
    comp = ActiveModelCompensator(store, robot, [0, 1, 2])
    with pytest.raises(ModelMissingError, match="not a comp-daemon model document"):
        comp(Target(axes_deg=tuple(HOME)))


def test_unusable_models_and_requests_are_refused_by_name(store: Store) -> None:
    robot = load_robot("kr210")
    other = load_robot("irb120")
    activate(store, model_document(NominalModel(other), data_sha256="b" * 64, frame="base"), "nominal")
    comp = ActiveModelCompensator(store, robot, [0, 1, 2])
    with pytest.raises(ModelMissingError, match="fitted for robot"):
        comp(Target(axes_deg=tuple(HOME)))
    activate(store, model_document(NominalModel(robot), data_sha256="c" * 64, frame="base"), "nominal")
    with pytest.raises(CompensationError, match="unreachable within joint limits"):
        comp(Target(tcp_mm=(9000.0, 0.0, 500.0)))


def _fitted_kinematic(robot: Any) -> tuple[Any, dict[str, Any]]:
    """A kinematic model fitted on noisy poses of a perturbed robot: it has a parameter covariance."""
    rng = np.random.default_rng(6)
    truth = KinematicParams.from_robot(robot).apply(rng.normal(size=N_PARAMS) * 3e-4)
    lim = robot.axis_limits_deg
    a = lim.mean(axis=1) + rng.uniform(-0.4, 0.4, (80, 6)) * np.minimum((lim[:, 1] - lim[:, 0]) / 2, 90.0)
    measured = tcp_position_mm(truth, axes_deg_to_q_rad(a, truth.sign)) + rng.normal(size=(80, 3)) * 0.02
    model = fit_model("kinematic", robot, a, measured, frame="base").model
    return model, model_document(model, data_sha256="d" * 64, frame="base")


def test_the_compensation_info_carries_its_model_mapping_and_uncertainty(store: Store) -> None:
    robot = load_robot("kr210")
    model, doc = _fitted_kinematic(robot)
    activate(store, doc)
    request = Target(axes_deg=tuple(HOME))
    comp = ActiveModelCompensator(store, robot, [0, 1, 2], current_axes=lambda: tuple(HOME))
    out = comp(request)
    assert out.info is not None and out.info["mapping"] == "six-axis"
    direction = np.zeros((1, 6))  # the seed is the current pose: no motion, and no direction
    sigma = model.predict_std_mm(np.array([out.commanded_deg]), direction)
    assert sigma is not None
    assert out.info["predicted_sigma_mm"] == pytest.approx(float(np.linalg.norm(sigma[0])), rel=1e-12)
    assert 1e-4 < out.info["predicted_sigma_mm"] < 0.1
    # the compensator only computes; the executor hands the info to the store with the move
    assert not [e for e in store.list_events() if e.kind == TARGET_MOVING]


def test_the_nominal_model_has_no_uncertainty_to_report(store: Store) -> None:
    robot = load_robot("kr210")
    activate(store, model_document(NominalModel(robot), data_sha256="e" * 64, frame="base"), "nominal")
    out = ActiveModelCompensator(store, robot, [0, 1, 2])(Target(axes_deg=tuple(HOME)))
    assert out.info is not None and "predicted_sigma_mm" not in out.info


def test_the_seed000_mapping_keeps_the_wrist_of_the_nominal_solution(store: Store) -> None:
    robot = load_robot("kr210")
    model, doc = _fitted_kinematic(robot)
    activate(store, doc)
    request = Target(axes_deg=tuple(HOME))
    six = ActiveModelCompensator(store, robot, [0, 1, 2], current_axes=lambda: tuple(HOME))(request)
    seed000 = ActiveModelCompensator(
        store, robot, [0, 1, 2], current_axes=lambda: tuple(HOME), mapping="three-axis"
    )(request)
    assert seed000.info is not None and seed000.info["mapping"] == "three-axis"
    np.testing.assert_allclose(seed000.commanded_deg[3:], HOME[3:], atol=1e-9)
    assert np.abs(np.subtract(six.commanded_deg[3:], HOME[3:])).max() > 1e-4
    for out in (six, seed000):  # both put the model's predicted TCP on the nominal one
        wanted = tcp_position_mm(
            KinematicParams.from_robot(robot), axes_deg_to_q_rad(np.array([HOME]), robot.sign)
        )
        np.testing.assert_allclose(model.predict_tcp_mm(np.array([out.commanded_deg])), wanted, atol=1e-5)
    with pytest.raises(ValueError, match="mapping must be one of six-axis, three-axis"):
        ActiveModelCompensator(store, robot, [0, 1, 2], mapping="paper")  # type: ignore[arg-type]
