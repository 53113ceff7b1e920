"""The model's uncertainty with every compensated target, through the executor and the HTTP API.

A batch is posted over HTTP, the executor compensates its target with the daemon's compensator
(a fitted kinematic model: parameter covariance through the Jacobian) and hands it to a loop that
refuses it, so the target ends failed after compensation with its commanded axes. Every door of the
API that returns the target shows the model and ``predicted_sigma_mm``: the norm of the model's
1-σ x, y, z uncertainty at the commanded axes.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Sequence
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from comp_daemon.daemon.compensation import ActiveModelCompensator
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.artifact import model_document
from comp_daemon.models.nominal import NominalModel
from comp_daemon.models.registry import fit_model
from comp_daemon.robot.description import load_robot
from comp_daemon.rt.executor import TargetExecutor
from comp_daemon.service.api import create_app, open_store
from comp_daemon.service.config import load_settings
from comp_daemon.service.store import ModelDraft, Store

KR = load_robot("kr210")
TOKEN = "operator-token-0123456789abcdef"
HEADERS = {"Authorization": f"Bearer {TOKEN}"}
POSE = [5.0, -85.0, 120.0, 3.0, -40.0, 10.0]


class _RefusingLoop:
    """Motion and loop ports whose loop refuses every target (the target fails after compensation)."""

    async def move_to(self, axes_deg: Sequence[float]) -> None:
        raise AssertionError("the robot was moved")

    def arm(self, target_id: str, commanded_deg: Sequence[float], loop_target_deg: Sequence[float]) -> None:
        raise RuntimeError("no loop in this test")

    def release(self) -> None:
        pass

    async def next_event(self) -> Any:
        raise AssertionError("the loop was used")


@pytest.fixture
async def api(tmp_path: Path) -> AsyncIterator[tuple[httpx.AsyncClient, Store]]:
    settings = load_settings(
        None,
        store={"data_dir": str(tmp_path / "data")},
        auth={"tokens": [{"name": "mes", "role": "operator", "token": TOKEN}]},
    )
    store = open_store(settings)
    app = create_app(settings, store)
    async with app.router.lifespan_context(app):
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://cell", headers=HEADERS) as client:
            yield client, store
    store.close()


def _fitted_kinematic() -> Any:
    rng = np.random.default_rng(11)
    truth = KinematicParams.from_robot(KR).apply(rng.normal(size=N_PARAMS) * 3e-4)
    lim = KR.axis_limits_deg
    a = lim.mean(axis=1) + rng.uniform(-0.4, 0.4, (80, 6)) * np.minimum((lim[:, 1] - lim[:, 0]) / 2, 90.0)
    measured = tcp_position_mm(truth, axes_deg_to_q_rad(a, truth.sign)) + rng.normal(size=(80, 3)) * 0.02
    return fit_model("kinematic", KR, a, measured, frame="base").model


async def _run_one(client: httpx.AsyncClient, store: Store, key: str) -> dict[str, Any]:
    """Post one target, let the executor compensate it; returns the batch as the API gives it."""
    r = await client.post(
        "/api/batches",
        json={"targets": [{"pose_id": key, **{f"a{i + 1}": v for i, v in enumerate(POSE)}}]},
        headers={"Idempotency-Key": key},
    )
    assert r.status_code == 201, r.text
    ports = _RefusingLoop()
    executor = TargetExecutor(
        store,
        ActiveModelCompensator(store, KR, [0, 1, 2], current_axes=lambda: tuple(POSE)),
        ports,
        ports,
        joints=[0, 1, 2],
        readiness=lambda: None,
    )
    target = store.claim_next_target()
    assert target is not None
    outcome = await executor.execute(target)
    assert outcome.state == "failed" and "no loop in this test" in (outcome.reason or ""), outcome
    batch: dict[str, Any] = (await client.get(f"/api/batches/{r.json()['id']}")).json()
    return batch


async def test_every_door_shows_the_models_sigma_at_the_commanded_axes(
    api: tuple[httpx.AsyncClient, Store],
) -> None:
    client, store = api
    model = _fitted_kinematic()
    doc = model_document(model, data_sha256="a" * 64, frame="base")
    model_id = store.add_model(ModelDraft("kinematic", None, doc, {}, None)).id
    store.activate_model(model_id)

    batch = await _run_one(client, store, "rib-1")
    (target,) = batch["targets"]
    assert target["commanded_axes_deg"] is not None and target["model_id"] == model_id
    sigma = model.predict_std_mm(np.array([target["commanded_axes_deg"]]), np.zeros((1, 6)))
    expected = float(np.linalg.norm(sigma[0]))
    assert target["predicted_sigma_mm"] == pytest.approx(expected, rel=1e-9)
    assert 1e-4 < expected < 0.1  # 80 poses with 0.02 mm noise: hundredths of a millimetre

    one = (await client.get(f"/api/targets/{target['id']}")).json()
    listed = (await client.get("/api/targets", params={"newest_first": "true"})).json()
    assert one["predicted_sigma_mm"] == target["predicted_sigma_mm"]
    assert [t["predicted_sigma_mm"] for t in listed] == [target["predicted_sigma_mm"]]

    # the nominal model has no uncertainty; a target not compensated yet has none either
    nominal = model_document(NominalModel(KR), data_sha256="b" * 64, frame="base")
    store.activate_model(store.add_model(ModelDraft("nominal", None, nominal, {}, None)).id)
    (plain,) = (await _run_one(client, store, "rib-2"))["targets"]
    assert plain["commanded_axes_deg"] is not None and plain["predicted_sigma_mm"] is None
    r = await client.post(
        "/api/batches",
        json={"targets": [{f"a{i + 1}": v for i, v in enumerate(POSE)}]},
        headers={"Idempotency-Key": "rib-3"},
    )
    (queued,) = r.json()["targets"]
    assert queued["state"] == "queued" and queued["predicted_sigma_mm"] is None and queued["model_id"] is None
