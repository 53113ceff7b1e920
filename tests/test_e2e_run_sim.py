"""End to end: ``comp-daemon run --sim`` as a process, driven over HTTP as the cell's users drive it.

1. The calibration engineer uploads a campaign made by ``comp-daemon sim sample``, fits a
   kinematic model, activates it; the MES posts a batch with an ``Idempotency-Key`` (and resends
   it); every target completes over HTTP with its final joint errors; SIGTERM ends the process
   with 0 and leaves nothing running.
2. ``kill -9`` in the middle of a batch, then a restart on the same data folder: every target is
   accounted for (done, interrupted, or queued and then done), none is lost, none runs twice, and
   the MES's resend after the crash queues nothing new.

Angles in degrees; times in seconds.
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from e2e_daemon import (
    TOKENS,
    DaemonProcess,
    alive,
    cmdline,
    describe,
    fit_and_activate,
    sample_campaign,
    target_rows,
    upload_campaign,
    wait_until,
)

from comp_daemon.sim.scenario import load_scenario

pytestmark = pytest.mark.slow

SETTLE_TOLERANCE_DEG = 0.001  # controller.settle_tolerance_deg (default)
ACTIVE = ("compensating", "moving", "settling")
FINISHED = ("done", "failed", "cancelled", "interrupted")
LIFECYCLE = ["target.compensating", "target.moving", "target.settling", "target.done"]


@pytest.fixture
def daemon(tmp_path: Path) -> Iterator[DaemonProcess]:
    d = DaemonProcess(tmp_path)
    try:
        yield d
    finally:
        d.cleanup()


def mes_targets() -> list[dict[str, Any]]:
    """Drilling points as the MES sends them: wanted TCP positions (base frame, mm) and one axis pose."""
    points: list[dict[str, Any]] = [
        {"pose_id": f"hole-{k}", "tx": 1800.0, "ty": ty, "tz": 1000.0 + 20.0 * k}
        for k, ty in enumerate((-150.0, 0.0, 150.0))
    ]
    points.append({"pose_id": "axes", "a1": 6.0, "a2": -86.0, "a3": 121.0, "a4": 2.0, "a5": -40.0, "a6": 1.0})
    return points


def batch_states(client: httpx.Client, batch_id: int) -> list[dict[str, Any]]:
    r = client.get(f"/api/batches/{batch_id}")
    assert r.status_code == 200, r.text
    targets: list[dict[str, Any]] = r.json()["targets"]
    return targets


def target_events(client: httpx.Client, target_id: int) -> list[str]:
    events = client.get("/api/events/log", params={"target_id": target_id, "limit": 1000}).json()
    return [e["kind"] for e in events if e["kind"].startswith("target.")]


def assert_done_with_errors(target: dict[str, Any]) -> None:
    assert target["state"] == "done", target
    assert target["reason"] is None
    errors = target["final_joint_errors_deg"]
    assert set(errors) == {"A1", "A2", "A3"}, errors  # the joints with grating scales
    assert all(abs(v) <= SETTLE_TOLERANCE_DEG for v in errors.values()), errors
    assert len(target["commanded_axes_deg"]) == 6


def assert_clean_exit(d: DaemonProcess, code: int, children: list[int]) -> None:
    assert code == 0, d.tail()
    state = json.loads((d.data_dir / "daemon-state.json").read_text())
    assert state["reason"] == "SIGTERM"
    assert state["last_reply"] == {"ak_deg": [0.0] * 6, "stop": True}
    assert children, "the simulated cell should have been a child of the daemon"
    wait_until(lambda: not any(alive(p) for p in children), 10, "the daemon's children to end")
    text = d.log_text()
    assert "Traceback" not in text, text[-4000:]
    for line in text.splitlines():
        if line.startswith("{"):
            assert json.loads(line)["level"] not in ("error", "critical"), line


def test_campaign_fit_activate_and_a_batch_of_targets_over_http(
    daemon: DaemonProcess, tmp_path: Path
) -> None:
    campaign = sample_campaign(tmp_path / "campaign.csv", n=60, seed=1)
    daemon.start("--calibrate-gratings")
    daemon.wait_http()
    # the loop runs and the gratings get calibrated; a model is what is missing
    daemon.wait_ready(60, allow=["no model is active"])

    with daemon.client("engineer") as eng, daemon.client("operator") as mes, daemon.client("viewer") as view:
        # the MES cannot upload, the viewer cannot post targets, nobody writes without a token
        with daemon.client(None) as anon:
            assert anon.post("/api/batches", json={"targets": mes_targets()}).status_code == 401
        assert (
            view.post(
                "/api/batches", json={"targets": mes_targets()}, headers={"Idempotency-Key": "x"}
            ).status_code
            == 403
        )
        assert (
            mes.post("/api/datasets", content=b"a1\n1\n", headers={"Content-Type": "text/csv"}).status_code
            == 403
        )

        dataset = upload_campaign(eng, campaign, "cell-campaign")
        assert dataset["rows"] == 60 and dataset["summary"]["split"]["fit"] > 0

        job = fit_and_activate(eng, dataset["id"], "kinematic")
        table2 = job["result"]["stats"]["table2"]
        assert table2["model"]["3d"]["mean"] < table2["nominal"]["3d"]["mean"], table2
        active = view.get("/api/models/active").json()
        assert active["job_id"] == job["id"] and active["active"] is True
        assert daemon.wait_ready(10) == {"ready": True, "reasons": []}

        # the MES posts its batch, then resends it (it did not see the answer): one batch, queued once
        body = {"targets": mes_targets()}
        r = mes.post("/api/batches", json=body, headers={"Idempotency-Key": "mes-order-4711"})
        assert r.status_code == 201, r.text
        batch = r.json()
        ids = [t["id"] for t in batch["targets"]]
        assert len(ids) == 4
        again = mes.post("/api/batches", json=body, headers={"Idempotency-Key": "mes-order-4711"})
        assert again.status_code == 200, again.text
        assert [t["id"] for t in again.json()["targets"]] == ids
        changed = {"targets": mes_targets()[:3]}
        conflict = mes.post("/api/batches", json=changed, headers={"Idempotency-Key": "mes-order-4711"})
        assert conflict.status_code == 409 and conflict.json()["error"] == "idempotency_conflict"

        # watch them complete over HTTP, one at a time in queue order
        seen_active: list[int] = []

        def all_finished() -> list[dict[str, Any]] | None:
            targets = batch_states(view, batch["id"])
            running = [t["id"] for t in targets if t["state"] in ACTIVE]
            assert len(running) <= 1, target_rows(targets)
            if running and (not seen_active or seen_active[-1] != running[0]):
                seen_active.append(running[0])
            return targets if all(t["state"] in FINISHED for t in targets) else None

        try:
            targets = wait_until(all_finished, 60, "the batch to finish", every_s=0.05)
        except AssertionError:
            raise AssertionError(f"{target_rows(batch_states(view, batch['id']))}\n{daemon.tail()}") from None
        for t in targets:
            assert_done_with_errors(t)
            assert target_events(view, t["id"]) == LIFECYCLE
        assert seen_active == sorted(seen_active)  # queue order (some may pass between two polls)
        assert len(view.get("/api/targets", params={"limit": 100}).json()) == 4

        status = view.get("/api/status").json()
        assert status["daemon"]["state"] == "idle", status["daemon"]
        assert status["daemon"]["loop"]["cycles"] > 0
        metrics = httpx.get(f"{daemon.base_url}/metrics").text
        assert 'comp_daemon_targets_finished_total{state="done"} 4.0' in metrics, metrics[-3000:]

    children = daemon.children()
    code = daemon.sigterm()
    assert_clean_exit(daemon, code, children)


def test_kill_9_during_a_batch_loses_and_repeats_nothing(daemon: DaemonProcess, tmp_path: Path) -> None:
    campaign = sample_campaign(tmp_path / "campaign.csv", n=40, seed=2)
    daemon.start("--calibrate-gratings")
    daemon.wait_http()
    daemon.wait_ready(60, allow=["no model is active"])
    key = "mes-order-kill-9"
    home = [float(v) for v in load_scenario("kr210-cell").campaign.home_deg]
    body = {
        "targets": [
            {
                "pose_id": f"p{k}",
                **{
                    f"a{i + 1}": v + (4.0 * (k + 1) * (-1) ** k if i == 0 else 0.0)
                    for i, v in enumerate(home)
                },
            }
            for k in range(6)
        ]
    }
    with daemon.client("engineer") as eng, daemon.client("operator") as mes:
        fit_and_activate(eng, upload_campaign(eng, campaign)["id"], "nominal")
        r = mes.post("/api/batches", json=body, headers={"Idempotency-Key": key})
        assert r.status_code == 201, r.text
        batch_id = r.json()["id"]
        ids = [t["id"] for t in r.json()["targets"]]

        # kill -9 while the third target is under way
        def third_active() -> bool:
            targets = batch_states(mes, batch_id)
            assert all(t["state"] != "failed" for t in targets), target_rows(targets)
            return targets[2]["state"] in ("moving", "settling")

        wait_until(third_active, 60, "the third target to move", every_s=0.02)
    children = daemon.kill9()
    cells = [p for p in children if "comp_daemon.sim.cell" in cmdline(p)]
    assert len(cells) == 1, describe(children)
    # the simulated cell notices that its parent is gone and ends (it would go on sending telegrams);
    # an idle job worker and multiprocessing's resource tracker stay until someone ends them (under
    # systemd the unit's control group does), here the test by pid
    wait_until(lambda: not alive(cells[0]), 15, lambda: f"the simulated cell to end: {describe(cells)}")
    daemon.end_orphans()

    daemon.start()  # same data folder; the grating calibration and the model are on disk
    daemon.wait_http()
    with daemon.client("operator") as mes:
        # right after recovery: nothing lost, the target under way is marked for the operator
        after = {t["id"]: t for t in batch_states(mes, batch_id)}
        assert sorted(after) == ids
        assert after[ids[0]]["state"] == "done" and after[ids[1]]["state"] == "done"
        third = after[ids[2]]
        assert third["state"] == "interrupted", target_rows(list(after.values()))
        assert "interrupted by a restart of the daemon" in third["reason"]
        for tid in ids[3:]:
            assert after[tid]["state"] in ("queued", *ACTIVE, "done"), target_rows(list(after.values()))

        # the MES resends the batch it is unsure about: the stored one comes back, nothing is queued
        r = mes.post("/api/batches", json=body, headers={"Idempotency-Key": key})
        assert r.status_code == 200, r.text
        assert [t["id"] for t in r.json()["targets"]] == ids

        # the queued targets run once the daemon is ready; the interrupted one is not redone
        def rest_done() -> list[dict[str, Any]] | None:
            targets = batch_states(mes, batch_id)
            return targets if all(t["state"] in FINISHED for t in targets) else None

        try:
            targets = {t["id"]: t for t in wait_until(rest_done, 60, "the rest of the batch")}
        except AssertionError:
            raise AssertionError(f"{target_rows(batch_states(mes, batch_id))}\n{daemon.tail()}") from None
        assert targets[ids[2]]["state"] == "interrupted"
        for tid in ids[:2] + ids[3:]:
            assert_done_with_errors(targets[tid])
        assert len(mes.get("/api/targets", params={"limit": 100}).json()) == len(ids)

        # none repeated: each target was claimed and moved once, the interrupted one never finished
        for tid in ids:
            kinds = Counter(target_events(mes, tid))
            assert kinds["target.compensating"] == 1 and kinds["target.moving"] == 1, (tid, kinds)
            assert kinds["target.done"] == (0 if tid == ids[2] else 1), (tid, kinds)
        log = mes.get("/api/events/log", params={"limit": 1000}).json()
        recovered = [e for e in log if e["kind"] == "store.recovered"]
        assert len(recovered) >= 1

        # the operator checked the part and puts the interrupted target back: it runs at the end
        r = mes.post(f"/api/targets/{ids[2]}/requeue")
        assert r.status_code == 200, r.text
        done = wait_until(
            lambda: (t := mes.get(f"/api/targets/{ids[2]}").json())["state"] in FINISHED and t,
            30,
            "the requeued target",
        )
        assert_done_with_errors(done)
    assert TOKENS["operator"] not in daemon.log_text()  # tokens are never logged

    children = daemon.children()
    code = daemon.sigterm()
    assert_clean_exit(daemon, code, children)
