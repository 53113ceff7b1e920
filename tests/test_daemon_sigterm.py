"""``comp-daemon run --sim`` as a process: SIGTERM in the middle of a target.

The daemon calibrates the gratings (``--calibrate-gratings``), takes the first queued target, and
gets SIGTERM while that target is moving or settling. It must exit 0, its last replies must carry
zero corrections and ``Stop = 1``, the target must be marked ``interrupted`` (not done, not lost),
the next one must still be queued, and the final state must be on disk. Meanwhile it reports to a
``$NOTIFY_SOCKET`` as under systemd: ``READY=1``, watchdog pings, ``STOPPING=1``.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from comp_daemon.models.artifact import model_document
from comp_daemon.models.nominal import NominalModel
from comp_daemon.robot.description import load_robot
from comp_daemon.service.store import ModelDraft, Store
from comp_daemon.sim.scenario import load_scenario

pytestmark = pytest.mark.slow


def prepare(tmp_path: Path) -> tuple[Path, Path, list[int]]:
    data = tmp_path / "data"
    cfg = tmp_path / "config.toml"
    cfg.write_text(
        f"""
[http]
port = 0
[store]
data_dir = "{data}"
[rsi]
listen_port = 0
timeout_count = 1000
[encoders]
# a loaded 2-core test machine leaves the simulated cell unscheduled for 150 ms and more now and
# then, and its gratings answer late meanwhile; staleness itself is test_rt_encoder_reader.py's test
stale_after_ms = 400
[log]
level = "INFO"
format = "console"
""",
        encoding="utf-8",
    )
    db = data / "comp-daemon.sqlite3"
    robot = load_robot("kr210")
    home = load_scenario("kr210-cell").campaign.home_deg
    with Store(db) as store:
        doc = model_document(NominalModel(robot), data_sha256="0" * 64, frame="base")
        store.activate_model(store.add_model(ModelDraft("nominal", None, doc, {}, None)).id)
        targets = []
        for k, d in enumerate((35.0, -30.0)):
            a = [float(v) for v in home]
            a[0] += d
            a[1] += 2.0 * (-1) ** k
            targets.append({f"a{i + 1}": round(v, 4) for i, v in enumerate(a)})
        _, stored, _ = store.submit_batch("sigterm-batch", "sigterm", targets)
    return cfg, db, [t.id for t in stored]


def drain(sock: socket.socket, into: list[str]) -> None:
    while True:
        try:
            into.append(sock.recv(4096).decode())
        except BlockingIOError:
            return


def target_states(db: Path) -> dict[int, tuple[str, str | None]]:
    conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5.0)
    try:
        return {row[0]: (row[1], row[2]) for row in conn.execute("SELECT id, state, reason FROM targets")}
    finally:
        conn.close()


def test_sigterm_mid_target(tmp_path: Path) -> None:
    cfg, db, ids = prepare(tmp_path)
    log = (tmp_path / "daemon.log").open("w")
    # systemd's side of Type=notify with WatchdogSec=0.2 s: a datagram socket the daemon reports to
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(tmp_path / "notify.sock"))
    notify.setblocking(False)
    env = dict(os.environ, NOTIFY_SOCKET=str(tmp_path / "notify.sock"), WATCHDOG_USEC="200000")
    messages: list[str] = []
    proc = subprocess.Popen(
        [sys.executable, "-m", "comp_daemon", "run", "--config", str(cfg), "--sim", "--calibrate-gratings"],
        stdout=log,
        stderr=subprocess.STDOUT,
        env=env,
    )
    try:
        deadline = time.monotonic() + 60.0
        state = "queued"
        while time.monotonic() < deadline and proc.poll() is None:
            drain(notify, messages)
            state = target_states(db)[ids[0]][0]
            if state in ("moving", "settling"):
                break
            time.sleep(0.02)
        assert state in ("moving", "settling"), (state, (tmp_path / "daemon.log").read_text()[-3000:])
        time.sleep(0.1)
        proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + 30.0
        while proc.poll() is None and time.monotonic() < deadline:
            drain(notify, messages)
            time.sleep(0.02)
        code = proc.wait(timeout=1)
        drain(notify, messages)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        log.close()
    text = (tmp_path / "daemon.log").read_text()
    assert code == 0, text[-3000:]
    notify.close()
    assert messages and messages[0].startswith("READY=1"), messages[:3]
    assert sum(m == "WATCHDOG=1" for m in messages) >= 10  # every 0.1 s while healthy
    assert any(m.startswith("STOPPING=1") for m in messages)
    assert messages.index(next(m for m in messages if m.startswith("STOPPING=1"))) > 0

    states = target_states(db)
    first_state, first_reason = states[ids[0]]
    assert first_state == "interrupted", (states, text[-2000:])
    assert first_reason is not None and first_reason.startswith("shutdown")
    assert states[ids[1]] == ("queued", None)  # never started, nothing lost

    final = json.loads((tmp_path / "data" / "daemon-state.json").read_text())
    assert final["reason"] == "SIGTERM"
    assert final["state"] == "stopping"
    assert final["last_reply"] == {"ak_deg": [0.0] * 6, "stop": True}
    assert final["replies_after_shutdown"] >= 1
    assert final["grating_calibration_version"] == 1
    assert any(f["kind"] == "shutdown" and f["target_id"] == str(ids[0]) for f in final["faults"])
    assert "Stop=1 from the sensor" in text  # the simulated controller ended RSI on our request
    with Store(db) as store:
        kinds = [e.kind for e in store.list_events(limit=1000)]
    assert "daemon.stopped" in kinds and "gratings.calibrated" in kinds
