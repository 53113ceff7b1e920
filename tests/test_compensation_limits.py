"""Compensation that tells the truth and never swings the wrist.

The axis changes are measured against the nominal solution (the controller's), for every model
kind; a target near the wrist singularity, one whose compensation changes an axis by more than the
limit, one outside the model's sampled region and one inside the robot's base are refused with the
axis, the size and the reason — by the library, the ``compensate`` command, ``POST /api/batches``
and the daemon's executor alike. The batch check takes JSON numbers only and exactly one form.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Sequence
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from service_client import in_process_service

from comp_daemon.cli import main
from comp_daemon.daemon.compensation import ActiveModelCompensator
from comp_daemon.data.dataset import Dataset, read_dataset, write_dataset
from comp_daemon.kinematics.params import PARAM_NAMES, KinematicParams
from comp_daemon.models.artifact import model_document, save_model
from comp_daemon.models.base import ErrorModel
from comp_daemon.models.chebyshev import fit_chebyshev
from comp_daemon.models.compensation import (
    CompensationLimits,
    CompensationRefused,
    compensate,
    configuration,
    nominal_targets,
    sampling_range_deg,
    wrist_angle_deg,
)
from comp_daemon.models.compliance import ComplianceModel
from comp_daemon.models.effects import EffectParams, twin_tcp_mm
from comp_daemon.models.kinematic import KinematicModel
from comp_daemon.models.kriging import fit_kriging
from comp_daemon.models.nominal import NominalModel
from comp_daemon.robot.description import load_robot
from comp_daemon.rt.executor import TargetExecutor
from comp_daemon.service.api import create_app, open_store
from comp_daemon.service.config import Settings, load_settings
from comp_daemon.service.store import ModelDraft, Store

KR = load_robot("kr210")
SINGULAR = np.array([0.0, -90.0, 90.0, 0.0, 0.0, 0.0])  # the target: A5 = 0
LO = np.array([-40.0, -110.0, 60.0, -60.0, 20.0, -60.0])  # the sampled region of the fitted models
HI = np.array([40.0, -60.0, 130.0, 60.0, 90.0, 60.0])


def _truth() -> tuple[Any, EffectParams]:
    """A KR210 as built: small geometric errors and a reduction-ratio error on joints 2 and 3."""
    rng = np.random.default_rng(7)
    scale = np.array(
        [2e-4 if n.startswith(("theta", "alpha", "beta", "base_r")) else 0.3 for n in PARAM_NAMES]
    )
    params = KinematicParams.from_robot(KR).apply(rng.normal(size=len(PARAM_NAMES)) * scale)
    return params, EffectParams.zeros(1).with_values(["eps2", "eps3"], [1e-4, -1.5e-4])


def _sampled(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(LO, HI, (n, 6))


def _models() -> dict[str, ErrorModel]:
    """One model of every kind, fitted (or set) on the same robot."""
    truth, eff = _truth()
    a = _sampled(120, 1)
    measured = twin_tcp_mm(KR, truth, eff, a)
    kin = KinematicModel(KR, truth)
    return {
        "nominal": NominalModel(KR),
        "kinematic": kin,
        "kinematic+effects": KinematicModel(KR, truth, eff),
        "chebyshev": fit_chebyshev(KR, a, measured, 2).model,
        "kriging": fit_kriging(kin, a, measured, variogram="gaussian").model,
        "compliance": ComplianceModel(KR, np.full(6, 2e-4), np.full(6, 1e-7)),
    }


MODELS = _models()


def _program(n: int, seed: int) -> np.ndarray:
    """Nominal axis values inside the sampled region, away from the singularities."""
    a = np.random.default_rng(seed).uniform(LO + 5.0, HI - 5.0, (n, 6))
    a[:, 4] = np.clip(a[:, 4], 30.0, None)
    return a


# ----------------------------------------------------------------------------------- the library


@pytest.mark.parametrize("kind", sorted(MODELS))
def test_da_is_compensated_minus_nominal_for_every_model_kind(kind: str) -> None:
    model = MODELS[kind]
    a_nominal = _program(12, 2)
    wanted, rot = nominal_targets(model, a_nominal)
    res = compensate(model, wanted, rot, a_seed_deg=a_nominal)
    assert res.converged
    np.testing.assert_allclose(res.a_uncompensated_deg, a_nominal, atol=1e-9)  # the controller's values
    np.testing.assert_array_equal(res.da_deg, res.a_deg - res.a_uncompensated_deg)
    if kind == "nominal":
        assert np.abs(res.da_deg).max() < 1e-9
    else:  # every real model moves the commands, the kinematic one included
        assert np.abs(res.da_deg).max() > 1e-3
    assert np.abs(res.da_deg).max() <= 0.5


def test_a_tcp_target_is_measured_against_the_controllers_own_solution() -> None:
    """Without axis values the nominal solution is the nominal robot's IK from the seed."""
    model = MODELS["kinematic"]
    a_nominal = _program(6, 3)
    wanted, rot = nominal_targets(model, a_nominal)
    seed = a_nominal + 2.0  # a neighbouring pose, e.g. the robot's current one
    res = compensate(model, wanted, rot, a_seed_deg=seed)
    np.testing.assert_allclose(res.a_uncompensated_deg, a_nominal, atol=1e-7)
    assert 1e-3 < np.abs(res.da_deg).max() <= 0.5


@pytest.mark.parametrize("a5", [0.0, 2.0, -4.9])
@pytest.mark.parametrize("kind", ["kinematic", "chebyshev"])
def test_a_target_at_or_near_the_wrist_singularity_is_refused(kind: str, a5: float) -> None:
    model = MODELS[kind]
    a = SINGULAR.copy()
    a[4] = a5
    wanted, rot = nominal_targets(model, a)
    with pytest.raises(CompensationRefused) as info:
        compensate(model, wanted, rot, a_seed_deg=a)
    assert str(info.value).startswith(f"near wrist singularity: A5 = {a5:.1f}°")
    (refusal,) = info.value.refusals
    assert (refusal.index, refusal.axis, refusal.value_deg) == (0, 5, a5)
    # just outside the threshold the same pose is compensated, within the axis limit
    a[4] = 5.5
    wanted, rot = nominal_targets(model, a)
    res = compensate(model, wanted, rot, a_seed_deg=a)
    assert np.abs(res.da_deg).max() <= 0.5


def test_the_wrist_angle_is_a5_on_a_kuka_wrist() -> None:
    a = np.tile(SINGULAR, (5, 1))
    a[:, 4] = [0.0, 1.0, -3.0, 45.0, -120.0]
    np.testing.assert_allclose(
        wrist_angle_deg(KinematicParams.from_robot(KR), a), [0.0, 1.0, 3.0, 45.0, 60.0], atol=1e-9
    )


def test_no_accepted_target_changes_an_axis_by_more_than_the_limit() -> None:
    """Per target: refused exactly when the unbounded compensation changes some axis by more."""
    model = MODELS["chebyshev"]
    a_all = np.random.default_rng(4).uniform(LO, HI, (40, 6))
    a_all[:, 4] = np.random.default_rng(5).uniform(6.0, 40.0, 40)  # wrist angles that cost A4/A6
    wide = CompensationLimits(max_axis_change_deg=10.0)
    tight = CompensationLimits(max_axis_change_deg=0.1)
    accepted = refused = 0
    for a in a_all:
        wanted, rot = nominal_targets(model, a)
        free = compensate(model, wanted, rot, a_seed_deg=a, limits=wide).da_deg[0]
        try:
            res = compensate(model, wanted, rot, a_seed_deg=a, limits=tight)
        except CompensationRefused as exc:
            refused += 1
            (r,) = exc.refusals
            assert r.axis == int(np.argmax(np.abs(free))) + 1 and abs(r.value_deg) > 0.1
            assert f"A{r.axis} would change by {r.value_deg:+.3f}° (limit 0.1° per axis)" == r.reason
            continue
        accepted += 1
        assert np.abs(res.da_deg).max() <= 0.1
        np.testing.assert_allclose(res.da_deg[0], free, atol=1e-9)
    assert accepted and refused


def test_outside_the_models_sampled_region_is_refused_and_global_models_are_not_checked() -> None:
    cheb = MODELS["chebyshev"]
    region = sampling_range_deg(cheb)
    assert region is not None and np.all(region[:, 0] >= LO) and np.all(region[:, 1] <= HI)
    assert sampling_range_deg(MODELS["kinematic"]) is None
    truth, eff = _truth()
    a = _sampled(60, 11)
    assert sampling_range_deg(fit_chebyshev(KR, a, twin_tcp_mm(KR, truth, eff, a), 0).model) is None
    assert sampling_range_deg(MODELS["kriging"]) is not None
    a = _program(1, 6)[0]
    a[0] = region[0, 1] + 3.0  # A1 3° beyond the sampled range
    wanted, rot = nominal_targets(cheb, a)
    with pytest.raises(
        CompensationRefused, match=r"outside the model's validity region: A1 = [\d.]+° is 3\.0\d°"
    ):
        compensate(cheb, wanted, rot, a_seed_deg=a, limits=CompensationLimits(hull_margin_deg=1.0))
    assert compensate(
        cheb, wanted, rot, a_seed_deg=a, limits=CompensationLimits(hull_margin_deg=5.0)
    ).converged
    # the kinematic model is global: the same target is compensated whatever the margin
    res = compensate(
        MODELS["kinematic"], wanted, rot, a_seed_deg=a, limits=CompensationLimits(hull_margin_deg=0.0)
    )
    assert res.region_deg is None


def test_the_base_origin_is_refused_although_the_ik_folds_the_arm_there() -> None:
    with pytest.raises(CompensationRefused, match=r"inside the robot's base") as info:
        compensate(MODELS["kinematic"], np.zeros((1, 3)))
    assert info.value.refusals[0].axis is None


def test_configuration_tells_the_branches_apart() -> None:
    params = KinematicParams.from_robot(KR)
    a = np.tile([0.0, -60.0, 30.0, 10.0, 30.0, 0.0], (4, 1))
    a[1, 4] = -30.0  # wrist flipped
    a[2, 2] = -30.0  # elbow on the other side of the stretched arm (A3 ≈ -2° on a KR 210)
    a[3, 2] = 25.0
    conf = configuration(params, a)
    assert conf[0, 1] != conf[1, 1] and conf[0, 0] == conf[1, 0]
    assert conf[0, 0] != conf[2, 0] and conf[0, 0] == conf[3, 0]


# ------------------------------------------------------------------------------------ the command


def _save(kind: str, path: Path) -> Path:
    save_model(MODELS[kind], path, data_sha256="0" * 64, frame="base")
    return path


@pytest.mark.parametrize("kind", sorted(MODELS))
def test_compensate_writes_da_as_compensated_minus_nominal(
    kind: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    model_path = _save(kind, tmp_path / "model.json")
    program = _program(8, 8)
    write_dataset(Dataset(a_deg=program), tmp_path / "program.csv")
    out = tmp_path / "out.csv"
    assert main(["compensate", str(model_path), str(tmp_path / "program.csv"), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    corrected = read_dataset(out, kind="targets")
    assert corrected.a_deg is not None
    da = np.array([[float(v) for v in corrected.extra[f"da{k + 1}"]] for k in range(6)]).T
    np.testing.assert_allclose(da, corrected.a_deg - program, atol=1e-12)
    biggest = float(printed.split("max axis change ")[1].split(" deg")[0])
    assert biggest == pytest.approx(np.abs(da).max(), abs=1e-4)
    if kind != "nominal":
        assert biggest > 1e-3
    assert ("no sampled region to keep to" in printed) is (kind not in ("chebyshev", "kriging"))


def test_compensate_refuses_a_singular_target_by_row(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    model_path = _save("chebyshev", tmp_path / "cheb.json")
    program = np.vstack([_program(2, 9), SINGULAR])
    write_dataset(Dataset(a_deg=program), tmp_path / "program.csv")
    out = tmp_path / "out.csv"
    # the other rows are compensated; the singular one is listed and the exit status says so
    assert main(["compensate", str(model_path), str(tmp_path / "program.csv"), "--out", str(out)]) == 3
    err = capsys.readouterr().err
    assert "row 4: near wrist singularity: A5 = 0.0°" in err
    assert [int(r) for r in read_dataset(out, kind="targets").extra["target_row"]] == [2, 3]
    out.unlink()
    # the limits are options of the command
    args = ["compensate", str(model_path), str(tmp_path / "program.csv"), "--out", str(out)]
    assert main([*args, "--wrist-singularity-deg", "0", "--max-axis-change-deg", "0.001"]) == 2
    assert "would change by" in capsys.readouterr().err
    assert main([*args, "--max-axis-change-deg", "-1"]) == 2
    assert "max_axis_change_deg must be > 0" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------- the API

TOKEN = "operator-token-0123456789abcdef"
HEADERS = {"Authorization": f"Bearer {TOKEN}"}


def _settings(tmp_path: Path, **overrides: Any) -> Settings:
    base: dict[str, Any] = {
        "store": {"data_dir": str(tmp_path / "data")},
        "auth": {"tokens": [{"name": "mes", "role": "operator", "token": TOKEN}]},
    }
    base.update(overrides)
    return load_settings(None, **base)


@pytest.fixture
async def api(tmp_path: Path) -> AsyncIterator[tuple[httpx.AsyncClient, Store]]:
    async with in_process_service(_settings(tmp_path)) as service:
        yield service


def _axes(a: Sequence[float]) -> dict[str, float]:
    return {f"a{i + 1}": float(v) for i, v in enumerate(a)}


GOOD = _axes([0.0, -90.0, 90.0, 0.0, 45.0, 0.0])


async def _post(client: httpx.AsyncClient, key: str, targets: list[Any]) -> httpx.Response:
    return await client.post(
        "/api/batches", json={"targets": targets}, headers={**HEADERS, "Idempotency-Key": key}
    )


@pytest.mark.parametrize("a5", [0.0, 2.0])
async def test_post_refuses_a_target_near_the_wrist_singularity(api: Any, a5: float) -> None:
    client, store = api
    r = await _post(client, "w", [GOOD, {**GOOD, "a5": a5}])
    assert r.status_code == 422, r.text
    body = r.json()
    assert (body["row"], body["column"]) == (2, "a5")
    assert f"target 2, column 'a5': near wrist singularity: A5 = {a5:.1f}°" in body["message"]
    assert store.list_targets() == []


@pytest.mark.parametrize(
    ("target", "column", "words"),
    [
        ({**GOOD, "a1": True}, "a1", "valid number"),
        ({**GOOD, "a1": "20"}, "a1", "valid number"),
        ({**GOOD, "payload_kg": "3"}, "payload_kg", "valid number"),
        ({**GOOD, "tx": 1500.0, "ty": 0.0, "tz": 1200.0}, "tx", "exactly one form"),
        ({"a1": 1.0, "a2": 2.0}, "a3", "a3 is missing"),
        ({"tx": 1500.0, "ty": 0.0, "tz": 1200.0, "ta": 0.0}, "tb", "tb is missing"),
        ({"pose_id": "p1"}, "tz", "neither axis values"),
        ({"tx": 0, "ty": 0, "tz": 0}, "tx", "inside the robot's base"),
        ({"tx": 9000.0, "ty": 0.0, "tz": 500.0}, "tx", "cannot reach this TCP"),
        (
            {"tx": 2085.0, "ty": 0.0, "tz": 1724.0, "ta": 0.0, "tb": 0.0, "tc": 0.0},  # the TCP of SINGULAR
            "ta",
            "near wrist singularity",
        ),
    ],
)
async def test_post_refuses_what_it_cannot_drive_by_target_and_field(
    api: Any, target: dict[str, Any], column: str, words: str
) -> None:
    client, store = api
    r = await _post(client, "t", [GOOD, target])
    assert r.status_code == 422, r.text
    body = r.json()
    assert (body.get("row"), body.get("column")) == (2, column)
    assert words in body["message"]
    assert store.list_targets() == []


async def test_post_accepts_numbers_and_a_reachable_tcp(api: Any) -> None:
    client, store = api
    tcp = {"tx": 1500.0, "ty": 200.0, "tz": 1200.0, "ta": 0.0, "tb": 60.0, "tc": 0.0}
    r = await _post(client, "ok", [{**GOOD, "a1": 1}, tcp, {"tx": 1500, "ty": 0, "tz": 1000}])
    assert r.status_code == 201, r.text
    assert store.list_targets()[0].request["a1"] == 1.0


async def test_post_uses_the_configured_wrist_threshold(tmp_path: Path) -> None:
    settings = _settings(tmp_path, compensation={"wrist_singularity_deg": 1.0})
    store = open_store(settings)
    app = create_app(settings, store)
    async with app.router.lifespan_context(app):
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://cell") as client:
            assert (await _post(client, "a", [{**GOOD, "a5": 2.0}])).status_code == 201
            assert (await _post(client, "b", [{**GOOD, "a5": 0.5}])).status_code == 422
    store.close()


# ----------------------------------------------------------------------------------- the executor


class _NeverDriven:
    """Motion and loop ports that fail the test if a refused target reaches them."""

    def __init__(self) -> None:
        self.calls: list[str] = []

    async def move_to(self, axes_deg: Sequence[float]) -> None:
        self.calls.append("move_to")

    def arm(self, target_id: str, commanded_deg: Sequence[float], loop_target_deg: Sequence[float]) -> None:
        self.calls.append("arm")

    def release(self) -> None:
        self.calls.append("release")

    async def next_event(self) -> Any:
        raise AssertionError("the loop was used")


@pytest.mark.parametrize("a5", [0.0, 2.0])
async def test_the_executor_fails_a_target_near_the_wrist_singularity(tmp_path: Path, a5: float) -> None:
    with Store(tmp_path / "s.sqlite3") as store:
        doc = model_document(MODELS["chebyshev"], data_sha256="c" * 64, frame="base")
        store.activate_model(store.add_model(ModelDraft("chebyshev", 2, doc, {}, None)).id)
        ports = _NeverDriven()
        executor = TargetExecutor(
            store,
            ActiveModelCompensator(store, KR, [0, 1, 2]),
            ports,
            ports,
            joints=[0, 1, 2],
            readiness=lambda: None,
        )
        a = SINGULAR.copy()
        a[4] = a5
        store.submit_batch("k", "k", [_axes(a.tolist())])
        target = store.claim_next_target()
        assert target is not None
        outcome = await executor.execute(target)
        assert outcome.state == "failed"
        assert outcome.reason is not None
        assert outcome.reason.startswith(f"compensation: near wrist singularity: A5 = {a5:.1f}°")
        assert ports.calls == []
        assert store.get_target(target.id).reason == outcome.reason


def test_a_rotation_the_tracker_cannot_see_does_not_turn_the_wrist() -> None:
    """A flange turned by 0.7° with the tool vector turned back puts every TCP on the same point:
    position data cannot tell it from the nominal geometry, and the compensation leaves A6 alone."""
    nominal = KinematicParams.from_robot(KR)
    turn = np.deg2rad(0.7)
    c, s = np.cos(-turn), np.sin(-turn)
    tool = nominal.tool_xyz_mm
    dx = np.zeros(len(PARAM_NAMES))
    dx[PARAM_NAMES.index("theta6")] = turn
    dx[PARAM_NAMES.index("tool_x") : PARAM_NAMES.index("tool_z") + 1] = [
        c * tool[0] - s * tool[1] - tool[0],
        s * tool[0] + c * tool[1] - tool[1],
        0.0,
    ]
    model = KinematicModel(KR, nominal.apply(dx))
    a_nominal = _program(6, 10)
    wanted, rot = nominal_targets(model, a_nominal)
    np.testing.assert_allclose(model.predict_tcp_mm(a_nominal), wanted, atol=1e-9)
    res = compensate(model, wanted, rot, a_seed_deg=a_nominal)
    assert np.abs(res.da_deg).max() < 1e-6


def test_compensate_maps_onto_joints_1_to_3_with_the_seed000_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    model_path = _save("kinematic", tmp_path / "model.json")
    program = _program(8, 12)
    write_dataset(Dataset(a_deg=program), tmp_path / "program.csv")
    args = ["compensate", str(model_path), str(tmp_path / "program.csv")]
    assert main([*args, "--out", str(tmp_path / "six.csv")]) == 0
    assert "(six-axis mapping)" in capsys.readouterr().out
    assert main([*args, "--out", str(tmp_path / "seed000.csv"), "--mapping", "three-axis"]) == 0
    assert "(three-axis mapping)" in capsys.readouterr().out
    six, seed000 = (read_dataset(tmp_path / f"{k}.csv", kind="targets") for k in ("six", "seed000"))
    assert six.a_deg is not None and seed000.a_deg is not None
    np.testing.assert_allclose(seed000.a_deg[:, 3:], program[:, 3:], atol=1e-9)  # the wrist stays
    assert np.abs(seed000.a_deg[:, :3] - program[:, :3]).max() > 1e-3
    assert np.abs(six.a_deg[:, 3:] - program[:, 3:]).max() > 1e-4
    model = MODELS["kinematic"]  # both put the model's predicted TCP on the nominal one
    wanted = model.predict_tcp_mm(six.a_deg)
    np.testing.assert_allclose(model.predict_tcp_mm(seed000.a_deg), wanted, atol=1e-5)
    # the limits hold for the mapped result too
    tight = [
        *args,
        "--out",
        str(tmp_path / "x.csv"),
        "--mapping",
        "three-axis",
        "--max-axis-change-deg",
        "0.001",
    ]
    assert main(tight) == 2
    assert "would change by" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([*args, "--out", str(tmp_path / "x.csv"), "--mapping", "paper"])
    # the former name is read as the new one, and the note names it
    assert main([*args, "--out", str(tmp_path / "old.csv"), "--mapping", "seed000"]) == 0
    captured = capsys.readouterr()
    assert "(three-axis mapping)" in captured.out
    assert "the joint mapping 'seed000' is now called 'three-axis'" in captured.err
    assert read_dataset(tmp_path / "old.csv", kind="targets") == seed000


def test_the_mapping_is_a_compensation_setting() -> None:
    assert Settings().compensation.mapping == "six-axis"
    assert load_settings(None, compensation={"mapping": "three-axis"}).compensation.mapping == "three-axis"
    with pytest.warns(FutureWarning, match="'seed000' is now called 'three-axis'.*write 'three-axis'"):
        old = load_settings(None, compensation={"mapping": "seed000"})  # an old configuration file
    assert old.compensation.mapping == "three-axis"
    with pytest.raises(ValueError, match="mapping"):
        load_settings(None, compensation={"mapping": "paper"})
    example = Path(__file__).resolve().parents[1] / "config.example.toml"
    assert 'mapping = "six-axis"' in example.read_text(encoding="utf-8")
