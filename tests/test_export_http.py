"""``GET /api/models/{id}/export``: the parameter listings through the service, read back to the model."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from service_client import in_process_service
from test_service_api import auth, make_settings

from comp_daemon.export.formats import PARAM_FORMATS
from comp_daemon.export.params import model_of
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams
from comp_daemon.models.artifact import model_document
from comp_daemon.models.base import ErrorModel
from comp_daemon.models.effects import EffectParams, twin_tcp_mm
from comp_daemon.models.registry import fit_model
from comp_daemon.robot.description import load_robot
from comp_daemon.service.store import ModelDraft, Store

KR = load_robot("kr210")


@pytest.fixture
async def api(tmp_path: Path) -> AsyncIterator[tuple[httpx.AsyncClient, Store]]:
    async with in_process_service(make_settings(tmp_path)) as service:
        yield service


def _data() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(5)
    lim = KR.axis_limits_deg
    a = lim.mean(axis=1) + rng.uniform(-0.4, 0.4, (90, 6)) * np.minimum((lim[:, 1] - lim[:, 0]) / 2, 90.0)
    dirs = rng.choice([-1.0, 1.0], size=(90, 6))
    truth = KinematicParams.from_robot(KR).apply(rng.normal(size=N_PARAMS) * 3e-4)
    eff = EffectParams.zeros().with_values(["h3"], [0.004])
    return a, twin_tcp_mm(KR, truth, eff, a, dirs) + rng.normal(size=(90, 3)) * 0.01, dirs


async def test_listings_through_the_service_read_back_to_the_model(
    api: tuple[httpx.AsyncClient, Store],
) -> None:
    client, store = api
    a, p, dirs = _data()
    ids: dict[str, int] = {}
    models: dict[str, ErrorModel] = {}
    for name in ("kinematic+backlash", "chebyshev"):
        fitted = fit_model(name, KR, a, p, dir=dirs, frame="base")
        fit = {"model": name, **fitted.info}
        doc = model_document(fitted.model, data_sha256="b" * 64, frame="base", fit=fit)
        ids[name] = store.add_model(ModelDraft(fitted.model.kind, fitted.model.order, doc, {}, None)).id
        models[name] = fitted.model
    model = models["kinematic+backlash"]
    kin = f"/api/models/{ids['kinematic+backlash']}/export"
    for fmt in PARAM_FORMATS:
        r = await client.get(f"{kin}?format={fmt}", headers=auth("viewer"))
        assert r.status_code == 200, r.text
        assert f"model-{ids['kinematic+backlash']}-{fmt}." in r.headers["content-disposition"]
        back = model_of(PARAM_FORMATS[fmt][1](r.text, fmt), KR)
        assert "model: kinematic+backlash" in r.text
        diff = back.predict_tcp_mm(a, dirs) - model.predict_tcp_mm(a, dirs)
        assert np.abs(diff).max() < 1e-6
    r = await client.get(f"/api/models/{ids['chebyshev']}/export?format=kuka", headers=auth("viewer"))
    assert r.status_code == 409 and "no kinematic parameters" in r.json()["message"]
    r = await client.get(f"{kin}?format=fanuc", headers=auth("viewer"))
    assert r.status_code == 422
    assert (await client.get("/api/models/999/export", headers=auth("viewer"))).status_code == 404
    assert (await client.get(f"/api/models/{ids['chebyshev']}/export")).status_code == 401
