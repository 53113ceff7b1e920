"""The assembled daemon against the simulated cell in its child process: real UDP, ptys, TCP, HTTP.

One daemon run covers: grating calibration on the cell, a target posted over HTTP executed to
settled, a grating CRC fault during a target (freeze, target failed, nothing else lost), the next
target done again (checked against the hidden robot), a converter unplugged and plugged back
between targets (the queue waits, then goes on), and a clean stop.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from comp_daemon.daemon.app import Daemon, SimOptions
from comp_daemon.models.artifact import model_document
from comp_daemon.models.nominal import NominalModel
from comp_daemon.rt.safety import FaultKind, SafetyState
from comp_daemon.service.config import load_settings
from comp_daemon.service.store import ModelDraft
from comp_daemon.sim_client import floats

pytestmark = pytest.mark.slow

TOKEN = "integration-operator-token-0123456789"


def write_config(tmp_path: Path) -> Path:
    cfg = tmp_path / "config.toml"
    cfg.write_text(
        f"""
[http]
port = 0
[store]
data_dir = "{tmp_path / "data"}"
synchronous = "normal"
[rsi]
listen_port = 0
# a loaded CI machine may answer late now and then; the controller's late-reply stop is the
# simulated controller's own test
timeout_count = 1000
[encoders]
# a loaded 2-core test machine leaves the simulated cell unscheduled for 150 ms and more now and
# then, and its gratings answer late meanwhile; staleness itself is test_rt_encoder_reader.py's test
stale_after_ms = 400
[log]
level = "WARNING"
[[auth.tokens]]
name = "mes"
role = "operator"
token = "{TOKEN}"
""",
        encoding="utf-8",
    )
    return cfg


def activate_nominal_model(daemon: Daemon) -> int:
    assert daemon.store is not None
    doc = model_document(NominalModel(daemon.robot), data_sha256="0" * 64, frame="base")
    record = daemon.store.add_model(ModelDraft("nominal", None, doc, {}, None))
    daemon.store.activate_model(record.id, by="test")
    return record.id


def udp_socket_holders(port: int) -> set[int]:
    """PIDs holding the IPv4 UDP socket bound to ``port`` (from /proc: its inode among their fds)."""
    inodes = set()
    for line in Path("/proc/net/udp").read_text().splitlines()[1:]:
        fields = line.split()
        if int(fields[1].split(":")[1], 16) == port:
            inodes.add(fields[9])
    wanted = {f"socket:[{inode}]" for inode in inodes}
    holders = set()
    for pid in (int(p) for p in os.listdir("/proc") if p.isdigit()):
        try:
            fds = os.listdir(f"/proc/{pid}/fd")
        except OSError:
            continue
        for fd in fds:
            try:
                if os.readlink(f"/proc/{pid}/fd/{fd}") in wanted:
                    holders.add(pid)
                    break
            except OSError:  # closed while we looked
                continue
    return holders


async def wait_for(cond: Any, timeout_s: float, what: str) -> None:
    async with asyncio.timeout(timeout_s):
        while not cond():
            await asyncio.sleep(0.02)
    assert cond(), what


async def target_state(client: httpx.AsyncClient, tid: int) -> dict[str, Any]:
    r = await client.get(f"/api/targets/{tid}")
    r.raise_for_status()
    doc: dict[str, Any] = r.json()
    return doc


async def until_state(
    client: httpx.AsyncClient, tid: int, states: set[str], timeout_s: float
) -> dict[str, Any]:
    async with asyncio.timeout(timeout_s):
        while True:
            doc = await target_state(client, tid)
            if doc["state"] in states:
                return doc
            await asyncio.sleep(0.05)


async def test_daemon_on_the_simulated_cell(tmp_path: Path) -> None:
    settings = load_settings(write_config(tmp_path))
    daemon = Daemon(settings, sim=SimOptions(scenario="kr210-cell", seed=3))
    run = asyncio.create_task(daemon.run())
    try:
        async with asyncio.timeout(60):
            await daemon.started.wait()
        runtime, sim = daemon.realtime.runtime, daemon.sim
        assert runtime is not None and sim is not None and daemon.sim_info is not None
        await wait_for(runtime.rsi_alive, 10, "RSI telegrams")
        reasons = daemon.view.readiness_reasons()
        assert any("no grating calibration" in r for r in reasons)

        # seed 000 step 1 on the cell: three poses, each approached from both sides
        home = np.array(daemon.sim_info.home_deg)
        poses = []
        for k, d in enumerate((-12.0, 0.0, 12.0)):
            pose = home.copy()
            pose[:3] += d * np.array([1.0, (-1.0) ** k, 0.5])
            poses.append(tuple(pose))
        cal = await daemon.gratings.calibrate(poses, settle_cycles=15, sample_cycles=8)
        assert cal.version == 1 and (tmp_path / "data" / "gratings" / "grating-cal-v0001.json").is_file()
        for m in cal.joints:
            assert m.n_readings == 6
            assert m.scale == pytest.approx(1.0, abs=5e-4)  # ratio error and radius within tolerance
            assert m.residual_max_deg < 0.02  # half the backlash, gravity deflection, noise
        await wait_for(lambda: not daemon.view.readiness_reasons(), 5, "ready")
        await asyncio.to_thread(activate_nominal_model, daemon)

        async with httpx.AsyncClient(
            base_url=f"http://127.0.0.1:{daemon.http_port}", headers={"Authorization": f"Bearer {TOKEN}"}
        ) as client:
            targets = []
            for k in range(3):
                a = home.copy()
                a[0] += 8.0 * (k + 1)
                a[1] += 3.0 * (-1) ** k
                a[2] -= 2.0 * k
                targets.append({f"a{i + 1}": round(float(v), 4) for i, v in enumerate(a)})
            r = await client.post(
                "/api/batches", json={"targets": targets}, headers={"Idempotency-Key": "integration-1"}
            )
            assert r.status_code == 201, r.text
            ids = [t["id"] for t in r.json()["targets"]]

            # target 1: executed to settled
            first = await until_state(client, ids[0], {"done", "failed"}, 30)
            assert first["state"] == "done", first["reason"]
            errors = first["final_joint_errors_deg"]
            assert set(errors) == {"A1", "A2", "A3"}
            assert all(abs(v) <= 0.001 for v in errors.values())
            assert len(first["commanded_axes_deg"]) == 6

            # target 2: a CRC fault on A2 once it is under way → freeze, failed, no stop
            await wait_for(
                lambda: (
                    daemon.targets.executor is not None
                    and daemon.targets.executor.current_target_id == ids[1]
                ),
                30,
                "t2",
            )
            await sim.command("fault 2 bad_crc")
            second = await until_state(client, ids[1], {"done", "failed"}, 30)
            assert second["state"] == "failed", second
            assert second["reason"].startswith("feedback_fault: A2: crc"), second["reason"]
            assert runtime.core.state is SafetyState.FAULT
            assert runtime.core.fault is not None and runtime.core.fault.kind is FaultKind.FEEDBACK_FAULT
            assert not runtime.core.stop and runtime.last_ak_deg == (0.0,) * 6
            status = json.loads(await sim.command("status"))
            assert status["controller"]["state"] == "running"  # the robot was not stopped
            await sim.command("clear 2")

            # target 3 runs again once the grating is back (a freeze does not latch)
            third = await until_state(client, ids[2], {"done", "failed"}, 30)
            assert third["state"] == "done", (third["state"], third["reason"])
            out = floats(await sim.command("joints"))
            info = daemon.sim_info
            slope = math.degrees(info.resolution_nm * 1e-6 / info.radius_mm)
            for m in cal.joints:
                count = round((out[m.joint - 1] - info.zero_deg) / slope)
                assert m.angle_deg(count) == pytest.approx(
                    third["commanded_axes_deg"][m.joint - 1], abs=0.0011
                )
            # a converter unplugged between targets: the next target waits (nothing claimed, the
            # reason shown), and runs once the device is back and the reader has reconnected
            await sim.command("unplug 1")
            await wait_for(
                lambda: any("grating A1" in r for r in daemon.view.readiness_reasons()), 5, "A1 gone"
            )
            r = await client.post(
                "/api/batches", json={"targets": [targets[0]]}, headers={"Idempotency-Key": "integration-2"}
            )
            assert r.status_code == 201, r.text
            fourth_id = r.json()["targets"][0]["id"]
            await asyncio.sleep(0.5)
            assert (await target_state(client, fourth_id))["state"] == "queued"
            assert daemon.targets.executor is not None and "grating A1" in (
                daemon.targets.executor.blocked_reason or ""
            )
            await sim.command("replug 1")
            fourth = await until_state(client, fourth_id, {"done", "failed"}, 30)
            assert fourth["state"] == "done", fourth["reason"]

            snap = (await client.get("/api/status")).json()
            assert snap["daemon"]["state"] == "idle", snap["daemon"]
            # the RSI path ran in a process of its own, and the operator is told so
            rtp = daemon.realtime.process
            assert rtp is not None and rtp.proc is not None and rtp.alive
            assert rtp.proc.pid != os.getpid()
            assert f"own process (pid {rtp.proc.pid})" in snap["daemon"]["loop"]["realtime"], snap["daemon"]
            rsi_port = daemon.realtime.rsi_address[1] if daemon.realtime.rsi_address else -1
            assert udp_socket_holders(rsi_port) == {rtp.proc.pid}  # the child holds the RSI socket
        stats = daemon.realtime.rsi_stats
        assert stats is not None and stats.handler_errors == 0 and stats.answered > 100
        assert stats.latency.count == stats.answered  # every reply's latency reached the daemon
    finally:
        daemon.request_stop("test over")
        code = await asyncio.wait_for(run, 30)
    assert code == 0
    assert rtp.proc.returncode == 0  # stopped with the daemon
    state = json.loads((tmp_path / "data" / "daemon-state.json").read_text())
    assert state["state"] == "stopping" and state["last_reply"]["ak_deg"] == [0.0] * 6
