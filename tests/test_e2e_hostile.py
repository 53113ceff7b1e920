"""End to end: an idle-connection flood against ``comp-daemon run --sim`` in a process with few descriptors.

The daemon runs with ``RLIMIT_NOFILE`` 256, ``[http] max_connections`` 64, a 2 s header timeout,
``$NOTIFY_SOCKET`` on a datagram socket this test reads and ``$WATCHDOG_USEC`` 2 s (a ping every
second). A flooder thread keeps opening half-sent requests (no token, headers never finished) many
times over the descriptor limit, and while it does: fresh authenticated requests are answered, a
batch of targets completes ``done``, and the watchdog pings keep coming at their interval. When the
flood stops, every connection still open is closed by the daemon within the header timeout. The
data folder and the database the daemon made under umask 022 are private (0700 / 0600).

Times in seconds.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import resource
import selectors
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from e2e_daemon import TOKENS, DaemonProcess, target_rows, wait_until

from comp_daemon.models.artifact import model_document
from comp_daemon.models.nominal import NominalModel
from comp_daemon.robot.description import load_robot
from comp_daemon.service.config import load_settings
from comp_daemon.service.store import ModelDraft, Store
from comp_daemon.sim.scenario import load_scenario

pytestmark = pytest.mark.slow

NOFILE = 256
MAX_CONNECTIONS = 64
HEADER_TIMEOUT_S = 2.0
WATCHDOG_USEC = 2_000_000  # systemd's WatchdogSec=2: a gap of 2 s without a ping is a restart
PING_INTERVAL_S = WATCHDOG_USEC / 2e6  # the daemon pings at half of it
FINISHED = ("done", "failed", "cancelled", "interrupted")
HALF_REQUEST = b"GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: "


def _few_descriptors_umask_022() -> None:
    resource.setrlimit(resource.RLIMIT_NOFILE, (NOFILE, NOFILE))
    os.umask(0o022)


class NotifyListener:
    """The service manager's end of ``$NOTIFY_SOCKET``: every datagram with its arrival time."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.2)
        self.messages: list[tuple[float, str]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="notify", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            self.messages.append((time.monotonic(), data.decode("utf-8", "replace")))

    def pings(self) -> list[float]:
        return [t for t, m in list(self.messages) if "WATCHDOG=1" in m.splitlines()]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.sock.close()


class Flood:
    """Half-sent requests opened at ``rate_per_s`` while at most ``hold`` are open on this side.

    A connection the daemon closes (evicted to make room, or answered 408) is noticed through an
    epoll selector and replaced; ``stop_opening`` ends the flood and leaves the open ones waiting.
    """

    def __init__(self, port: int, hold: int = 600, rate_per_s: float = 150.0) -> None:
        self.port, self.hold, self.rate_per_s = port, hold, rate_per_s
        self.sel = selectors.DefaultSelector()
        self.opened = 0
        self.connect_failures = 0
        self.closed_by_server = 0
        self.answered_408 = 0
        self.peak_open = 0
        self.opening = threading.Event()
        self.opening.set()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="flood", daemon=True)
        self._thread.start()

    def open_count(self) -> int:
        with self._lock:
            return len(self.sel.get_map())

    def _open_one(self) -> None:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.settimeout(0.5)
        try:
            s.connect(("127.0.0.1", self.port))
            s.sendall(HALF_REQUEST)
        except OSError:
            self.connect_failures += 1
            s.close()
            return
        s.setblocking(False)
        with self._lock:
            self.sel.register(s, selectors.EVENT_READ)
        self.opened += 1

    def _reap(self, timeout_s: float) -> None:
        for key, _ in self.sel.select(timeout_s):
            sock: socket.socket = key.fileobj  # type: ignore[assignment]
            try:
                data = sock.recv(4096)
            except BlockingIOError:
                continue
            except OSError:
                data = b""
            if data.startswith(b"HTTP/1.1 408"):
                self.answered_408 += 1
            with self._lock:
                self.sel.unregister(sock)
            sock.close()
            self.closed_by_server += 1

    def _run(self) -> None:
        next_at = time.monotonic()
        while not self._stop.is_set():
            if self.opening.is_set() and self.open_count() < self.hold and time.monotonic() >= next_at:
                self._open_one()
                self.peak_open = max(self.peak_open, self.open_count())
                next_at += 1.0 / self.rate_per_s
                next_at = max(next_at, time.monotonic() - 0.1)
                self._reap(0)
            else:
                self._reap(0.005)

    def stop_opening(self) -> None:
        self.opening.clear()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        with self._lock:
            for key in list(self.sel.get_map().values()):
                key.fileobj.close()  # type: ignore[union-attr]
            self.sel.close()


@pytest.fixture
def daemon(tmp_path: Path) -> Iterator[DaemonProcess]:
    d = DaemonProcess(
        tmp_path,
        http_config=f"max_connections = {MAX_CONNECTIONS}\nheader_timeout_s = {HEADER_TIMEOUT_S}\n",
    )
    try:
        yield d
    finally:
        d.cleanup()


def activate_nominal_model(d: DaemonProcess) -> None:
    """An active nominal model in the daemon's store before it starts (the targets need one)."""
    settings = load_settings(d.config_path)
    doc = model_document(NominalModel(load_robot(settings.robot.name)), data_sha256="0" * 64, frame="base")
    with Store(settings.store.db_path) as store:
        store.activate_model(store.add_model(ModelDraft("nominal", None, doc, {}, None)).id, by="test")


def batch_body(n: int) -> dict[str, Any]:
    home = [float(v) for v in load_scenario("kr210-cell").campaign.home_deg]
    targets = []
    for k in range(n):
        axes = list(home)
        axes[0] += 5.0 * (k + 1) * (-1) ** k
        axes[1] += 2.0 * (k + 1)
        targets.append({f"a{i + 1}": round(v, 4) for i, v in enumerate(axes)})
    return {"targets": targets}


def fresh_get(d: DaemonProcess, path: str, role: str = "viewer") -> tuple[httpx.Response, float]:
    """One request on a connection of its own (no pool: a kept-alive idle one may be evicted)."""
    t0 = time.monotonic()
    r = httpx.get(f"{d.base_url}{path}", headers={"Authorization": f"Bearer {TOKENS[role]}"}, timeout=10.0)
    return r, time.monotonic() - t0


def guard_counts(log: str) -> list[dict[str, Any]]:
    out = []
    for line in log.splitlines():
        if line.startswith("{") and "closed by the guard" in line:
            with contextlib.suppress(json.JSONDecodeError):
                out.append(json.loads(line))
    return out


def test_idle_connection_flood_leaves_requests_targets_and_watchdog_running(
    daemon: DaemonProcess, tmp_path: Path
) -> None:
    notify = NotifyListener(tmp_path / "notify.sock")
    try:
        _run_flood(daemon, notify)
    finally:
        notify.close()


def _run_flood(daemon: DaemonProcess, notify: NotifyListener) -> None:
    activate_nominal_model(daemon)
    daemon.start(
        "--calibrate-gratings",
        env={"NOTIFY_SOCKET": str(notify.path), "WATCHDOG_USEC": str(WATCHDOG_USEC)},
        preexec_fn=_few_descriptors_umask_022,
    )
    daemon.wait_http()
    daemon.wait_ready(60)
    wait_until(lambda: len(notify.pings()) >= 2, 10, "watchdog pings before the flood")
    assert any("READY=1" in m for _, m in notify.messages), notify.messages

    flood = Flood(daemon.http_port)
    try:
        t_flood = time.monotonic()
        wait_until(lambda: flood.opened >= 2 * NOFILE, 30, lambda: f"the flood to open ({flood.opened})")

        # a fresh authenticated request is answered while the flood runs
        latencies: list[float] = []
        fds: list[int] = []  # the daemon's open descriptors, sampled
        for _ in range(3):
            r, dt = fresh_get(daemon, "/api/status")
            assert r.status_code == 200, r.text
            latencies.append(dt)

        # a batch of targets runs to done
        r = httpx.post(
            f"{daemon.base_url}/api/batches",
            json=batch_body(3),
            headers={"Authorization": f"Bearer {TOKENS['operator']}", "Idempotency-Key": "flood-1"},
            timeout=10.0,
        )
        assert r.status_code == 201, r.text
        batch_id = r.json()["id"]

        def batch_finished() -> list[dict[str, Any]] | None:
            resp, dt = fresh_get(daemon, f"/api/batches/{batch_id}")
            assert resp.status_code == 200, resp.text
            latencies.append(dt)
            fds.append(len(os.listdir(f"/proc/{daemon.pid}/fd")))
            targets: list[dict[str, Any]] = resp.json()["targets"]
            return targets if all(t["state"] in FINISHED for t in targets) else None

        try:
            targets = wait_until(batch_finished, 45, "the batch to finish", every_s=0.5)
        except AssertionError:
            raise AssertionError(f"flood opened {flood.opened}\n{daemon.tail()}") from None
        assert all(t["state"] == "done" for t in targets), target_rows(targets)
        # a bit more flood after the targets, so the watchdog window is at least 10 s
        while time.monotonic() - t_flood < 10.0:
            time.sleep(0.2)
        t_flood_end = time.monotonic()
        opened_during_flood = flood.opened

        # the flood stops; whatever is still open is closed by the daemon within the header timeout
        flood.stop_opening()
        still_open = flood.open_count()
        wait_until(
            lambda: flood.open_count() == 0,
            HEADER_TIMEOUT_S + 3.0,
            lambda: f"the daemon to close {flood.open_count()} of {still_open} half-sent requests",
        )
    finally:
        flood.close()

    # watchdog: a ping at least every WatchdogSec throughout the flood (and none stopped)
    pings = [
        t for t in notify.pings() if t_flood - 2 * PING_INTERVAL_S <= t <= t_flood_end + 2 * PING_INTERVAL_S
    ]
    gaps = [b - a for a, b in itertools.pairwise(pings)]
    assert pings and pings[0] <= t_flood + PING_INTERVAL_S and pings[-1] >= t_flood_end, (pings, t_flood)
    assert max(gaps) < WATCHDOG_USEC / 1e6, gaps
    assert max(latencies) < 2.0, latencies

    assert opened_during_flood >= 4 * NOFILE, opened_during_flood
    assert flood.closed_by_server == flood.opened, (flood.closed_by_server, flood.opened)
    assert flood.answered_408 > 0, flood.answered_408
    log = daemon.tail(10**7)
    assert "out of system resource" not in log and "Too many open files" not in log
    guards = guard_counts(log)
    assert guards, "the guard logged no count"
    # the cap held: connections were evicted, and the descriptors stayed well under the limit
    # (the guard's max_open counts, at an accept, the connections it just closed as well)
    assert guards[-1]["evicted"] > 0, guards[-1]
    assert max(fds) < NOFILE - 32, fds
    assert fresh_get(daemon, "/health")[0].status_code == 200

    # made under umask 022: the data folder is 0700, the database and the daemon's files 0600
    assert daemon.data_dir.stat().st_mode & 0o777 == 0o700
    modes = {
        str(p.relative_to(daemon.data_dir)): p.stat().st_mode & 0o777 for p in daemon.data_dir.rglob("*")
    }
    assert all(m & 0o077 == 0 for m in modes.values()), modes
    code = daemon.sigterm()
    assert code == 0, daemon.tail()
    print(
        f"flood: opened {opened_during_flood} half-sent requests (peak {flood.peak_open} open on the "
        f"client side), {flood.answered_408} answered 408, slowest request {max(latencies):.3f} s, "
        f"watchdog gaps {min(gaps):.2f}..{max(gaps):.2f} s over {len(pings)} pings, daemon fds max "
        f"{max(fds)}, "
        f"guard {guards[-1]}"
    )
