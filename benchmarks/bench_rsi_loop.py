"""The daemon's RSI reply latency under load, seen from the controller's side of the wire.

Run: ``python -m benchmarks.bench_rsi_loop [--cycles 50000 | --duration-s 3600] [--cycle-ms 12
--cycle-ms 4] [--http-rate 20] [--json OUT]`` (about 10 min at 12 ms and 3.5 min at 4 ms for 50 000
cycles; ``--duration-s`` measures that long per cycle time instead).

Each run measures the daemon beside a **baseline**: a bare asyncio UDP echo (``echo_main``: a
minimal ``DatagramProtocol`` answering every telegram with one fixed valid ``<Sen>`` reply, only
the IPOC copied in) in a process of its own on the daemon's real-time CPU at the same
``SCHED_FIFO`` priority. The relay hands it a copy of every telegram from the same simulated
controller half a cycle after the daemon's (so the two never queue behind each other on their
CPU) and timestamps its reply the same way, under the same load. What the echo takes is what the
platform, the interpreter and asyncio cost; the difference is the daemon's own.

Set-up, per cycle time (all on 127.0.0.1, each a separate process):

- the simulated cell (``python -m comp_daemon.sim.cell``): robot plant, simulated KR C4
  sending ``<Rob>`` telegrams every ``cycle_ms`` on its absolute schedule, three grating converters
  on pseudo-terminals, the motion command port; at ``SCHED_FIFO`` ``--controller-priority`` (10,
  below the daemon's) on ``--controller-cpu`` (the first CPU, away from the daemon's real-time
  CPU, which is the last). The KR C4 is a real-time controller on hardware of its own: at normal
  priority on two shared cores the fit workers made the simulated one overrun its own 4 ms cycle
  and send telegrams in bursts, and at ``SCHED_FIFO`` 10 on any CPU its plant physics lengthened
  the tail of the replies at 12 ms (docs/benchmarks.md);
- a relay between the controller and the daemon, in its own process, which timestamps every
  datagram (``SCHED_FIFO`` 30 where permitted: it stands in for the controller's wire, and at
  normal priority its own hold-ups queued two telegrams at the daemon): the telegram just before
  it is forwarded (``time.time_ns``, CLOCK_REALTIME) and the
  daemon's reply on arrival by the kernel (``SO_TIMESTAMPNS``, CLOCK_REALTIME, so the relay's own
  scheduling does not count against the daemon). Reply latency = reply received − telegram sent:
  the daemon's receive path, event-loop delay, handler and send, plus loopback both ways;
- ``comp-daemon run --config … --motion …`` as in production (grating readers on the
  pseudo-terminals, ``--calibrate-gratings``, the HTTP service, the job pool), with the loop
  correcting real targets. Its ``[realtime]`` section comes from ``--rt-priority`` (20) and
  ``--cpu-wakeup-latency-us`` (0), as in ``config.example.toml``.

Load while the ``--cycles`` cycles are measured: the MES queue kept fed (batches of 10 targets
around the home pose, so the loop is armed and correcting most of the time); fits one after the
other in the job pool (Chebyshev with the order chosen by cross-validation, and kinematic + ratio
+ backlash, on a ``--campaign-rows`` campaign); HTTP requests at ``--http-rate`` per second over
status, queue, models, jobs, metrics, event log and a data set download, plus one dashboard-like
event stream (a bounded loop: it stops with the measurement and never exceeds 1.5 × the planned
count). Late: a reply that took longer than one cycle, or none at all.

Printed: the machine, per cycle time the latency p50/p99/p99.9/max, late and missing replies of
the daemon and of the echo baseline, the daemon's own view (handler latency percentiles, late
count), the simulated controller's late count, what the load achieved (fits done, targets
done/failed, HTTP requests and their latency); the histogram of the reply latency on the wire; and
the worst 20 replies and the 20 longest stretches of telegrams left without one (after a stall the
endpoint answers only the newest), each with what was going on when it came: a sampler reads every 50 ms the
real-time process's ``/proc`` state (running or sleeping, the CPU it ran on, its voluntary and
involuntary context switches since the last sample), the number of runnable tasks on the machine,
and the load's own state (which fit was running, which HTTP request was in flight); and, from the
real-time process's own per-cycle trace (``COMP_DAEMON_RT_TRACE``, :mod:`comp_daemon.rt.cycle_trace`,
joined by IPOC), what held that reply: the wait from the kernel's receive time to the callback, the
time in the callback, and since the previous reply the process's CPU time (the collector's share),
its wait for its CPU, context switches and page faults, with the cause in words; the causes of all
late and unanswered telegrams are counted (``late_causes``).
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import datetime as dt
import json
import multiprocessing as mp
import os
import re
import select
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from benchmarks.machine import machine_info, machine_line
from comp_daemon.rt import cycle_trace
from comp_daemon.rt.rsi_codec import SenReply, build_sen
from comp_daemon.rt.scheduling import apply_scheduling, resolve_cpu

SO_TIMESTAMPNS = 35  # Linux: <asm-generic/socket.h>; SCM_TIMESTAMPNS has the same value
_IPOC = re.compile(rb"<IPOC>\s*(\d+)\s*</IPOC>")
TOKEN = "bench-engineer-token-0123456789abcdef"


# ------------------------------------------------------------------------------------ the relay


def _recv_stamped(sock: socket.socket) -> tuple[bytes, tuple[str, int], int]:
    data, anc, _flags, addr = sock.recvmsg(65536, socket.CMSG_SPACE(16))
    t_ns = time.time_ns()
    for level, kind, payload in anc:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(payload) >= 16:
            sec, nsec = struct.unpack("qq", payload[:16])
            t_ns = sec * 1_000_000_000 + nsec
    return data, addr, t_ns


# ------------------------------------------------------------------------------------ the baseline


class _Echo(asyncio.DatagramProtocol):
    """Answers every telegram at once with the same valid ``<Sen>`` reply (its IPOC copied in)."""

    def __init__(self, sen_type: str) -> None:
        head, _, tail = build_sen(SenReply(1, (0.0,) * 6, False, sen_type)).partition(b"<IPOC>1</IPOC>")
        self.head, self.tail = head + b"<IPOC>", b"</IPOC>" + tail
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        m = _IPOC.search(data)
        if m is not None and self.transport is not None:
            self.transport.sendto(self.head + m.group(1) + self.tail, addr)


def echo_main(port: int, cpu: int | None, priority: int, sen_type: str, ready: Any) -> None:
    """The baseline: a bare asyncio UDP echo, pinned and scheduled as the daemon's real-time process."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    apply_scheduling(cpu, priority, who="the echo baseline")

    async def serve() -> None:
        loop = asyncio.get_running_loop()
        await loop.create_datagram_endpoint(lambda: _Echo(sen_type), local_addr=("127.0.0.1", port))
        ready.set()
        await asyncio.Event().wait()  # until terminated

    asyncio.run(serve())


# ------------------------------------------------------------------------------------ the relay


def relay_main(
    listen_port: int,
    daemon_port: int,
    echo_port: int,
    cycle_ms: int,
    out_path: str,
    cycles: int,
    recording: Any,
    finished: Any,
    ready: Any,
) -> None:
    """Forward controller ↔ daemon, and a copy of each telegram to the echo half a cycle later;
    while ``recording`` is set, log the first ``cycles`` telegrams of each."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # the relay stands in for the controller's wire, a real-time system: where permitted it runs
    # SCHED_FIFO above the daemon, so its own hold-ups do not queue two telegrams at the daemon
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(30))
    ctrl = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ctrl.bind(("127.0.0.1", listen_port))
    ctrl.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    up = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    up.bind(("127.0.0.1", 0))
    up.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    side = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    side.bind(("127.0.0.1", 0))
    side.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    daemon = ("127.0.0.1", daemon_port)
    echo = ("127.0.0.1", echo_port)
    half_cycle_ns = cycle_ms * 500_000
    daemon_log, echo_log = _RelayLog(cycles), _RelayLog(cycles)
    copies: collections.deque[tuple[int, bytes]] = collections.deque()  # (due, monotonic ns), telegram
    controller: tuple[str, int] | None = None
    poller = select.poll()
    for sock in (ctrl, up, side):
        poller.register(sock, select.POLLIN)
    ready.set()
    done_at: float | None = None
    while True:
        if done_at is not None and time.monotonic() > done_at:
            break
        while copies and copies[0][0] <= time.monotonic_ns():
            data = copies.popleft()[1]
            t_tx = time.time_ns()
            side.sendto(data, echo)
            echo_log.sent(data, 0, t_tx, recording.is_set())
        wait_ms = 100 if not copies else max(0, -(-(copies[0][0] - time.monotonic_ns()) // 1_000_000))
        for fd, _ in poller.poll(wait_ms):
            if fd == ctrl.fileno():
                data, addr, t_rx = _recv_stamped(ctrl)
                controller = addr
                t_tx = time.time_ns()
                up.sendto(data, daemon)
                copies.append((time.monotonic_ns() + half_cycle_ns, data))
                if daemon_log.sent(data, t_rx, t_tx, recording.is_set()) and daemon_log.n == cycles:
                    done_at = time.monotonic() + 0.5 + cycle_ms / 1000.0  # the last replies
            elif fd == up.fileno():
                data, _addr, t_rx = _recv_stamped(up)
                if controller is not None:
                    ctrl.sendto(data, controller)
                daemon_log.replied(data, t_rx)
            else:
                data, _addr, t_rx = _recv_stamped(side)
                echo_log.replied(data, t_rx)
    record: dict[str, Any] = daemon_log.arrays() | {f"echo_{k}": v for k, v in echo_log.arrays().items()}
    np.savez(out_path, **record)
    finished.set()
    # go on forwarding until terminated, so the cell and the daemon can stop cleanly
    while True:
        for fd, _ in poller.poll(100):
            if fd == ctrl.fileno():
                data, controller, _ = _recv_stamped(ctrl)
                up.sendto(data, daemon)
            elif fd == up.fileno():
                data, _addr, _ = _recv_stamped(up)
                if controller is not None:
                    ctrl.sendto(data, controller)
            else:
                _recv_stamped(side)


class _RelayLog:
    """The first ``cycles`` telegrams sent to one peer while recording: when, and when answered."""

    def __init__(self, cycles: int) -> None:
        self.cycles = cycles
        self.ipoc = np.zeros(cycles, dtype=np.int64)
        self.t_arrive = np.zeros(cycles, dtype=np.int64)  # telegram at the relay (kernel)
        self.t_sent = np.zeros(cycles, dtype=np.int64)  # telegram forwarded to the peer
        self.t_reply = np.zeros(cycles, dtype=np.int64)  # reply at the relay (kernel); 0 = none
        self.index: dict[int, int] = {}
        self.n = 0

    def sent(self, data: bytes, t_rx: int, t_tx: int, recording: bool) -> bool:
        m = _IPOC.search(data)
        if m is None or not recording or self.n >= self.cycles:
            return False
        k, n = int(m.group(1)), self.n
        self.ipoc[n], self.t_arrive[n], self.t_sent[n] = k, t_rx, t_tx
        self.index[k] = n
        self.n += 1
        return True

    def replied(self, data: bytes, t_rx: int) -> None:
        m = _IPOC.search(data)
        if m is not None:
            i = self.index.pop(int(m.group(1)), None)
            if i is not None:
                self.t_reply[i] = t_rx

    def arrays(self) -> dict[str, np.ndarray]:
        n = self.n
        return {
            "ipoc": self.ipoc[:n],
            "t_arrive": self.t_arrive[:n],
            "t_sent": self.t_sent[:n],
            "t_reply": self.t_reply[:n],
        }


# ------------------------------------------------------------------------------------ processes


def _free_port(kind: socket.SocketKind) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _line(port: int, text: str, timeout_s: float = 10.0) -> str:
    with socket.create_connection(("127.0.0.1", port), timeout=timeout_s) as s:
        s.sendall(text.encode() + b"\n")
        answer = s.makefile().readline().strip()
    if not answer.startswith("OK"):
        raise RuntimeError(f"{text!r}: {answer}")
    return answer[3:]


def _config(
    root: Path, cell: dict[str, Any], cycle_ms: int, http_port: int, rsi_port: int, opts: Options
) -> Path:
    joints = "".join(
        f'[[encoders.joints]]\njoint = {j}\nport = "{path}"\nradius_mm = {cell["radius_mm"]}\n'
        f"resolution_nm = {cell['resolution_nm']}\nbits = {cell['bits']}\n"
        for j, path in sorted(cell["gratings"].items(), key=lambda kv: int(kv[0]))
    )
    cfg = root / "config.toml"
    cfg.write_text(
        f"""
[http]
host = "127.0.0.1"
port = {http_port}
[store]
data_dir = "{root / "data"}"
[rsi]
listen_host = "127.0.0.1"
listen_port = {rsi_port}
controller_allow = ["127.0.0.1"]
cycle_ms = {cycle_ms}
[realtime]
priority = {opts.rt_priority}
cpu_wakeup_latency_us = {opts.cpu_wakeup_latency_us}
[encoders]
poll_period_ms = {float(cycle_ms)}
[jobs]
workers = 1
max_pending = 4
[log]
level = "INFO"
[[auth.tokens]]
name = "bench"
role = "engineer"
token = "{TOKEN}"
{joints}""",
        encoding="utf-8",
    )
    return cfg


@contextlib.contextmanager
def _cell(
    root: Path, cycle_ms: int, rsi_port: int, priority: int, cpu: int | None
) -> Iterator[tuple[subprocess.Popen[bytes], dict[str, Any]]]:
    argv = [
        sys.executable, "-m", "comp_daemon.sim.cell", "--rsi-port", str(rsi_port),
        "--cycle-ms", str(cycle_ms), "--timeout-count", "1000000000", "--link-dir", str(root / "cell"),
        "--exit-with-parent",
    ]  # fmt: skip
    with (root / "cell.log").open("wb") as log:
        proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log)
    try:
        if cpu is not None:
            os.sched_setaffinity(proc.pid, {cpu})
        if priority > 0:
            os.sched_setscheduler(proc.pid, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as exc:
        print(f"simulated controller: scheduling not applied ({exc})", file=sys.stderr)
    try:
        assert proc.stdout is not None
        info: dict[str, Any] = json.loads(proc.stdout.readline())
        yield proc, info
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        for pipe in (proc.stdin, proc.stdout):
            if pipe is not None:
                pipe.close()


def _wait(cond: Any, timeout_s: float, what: str, every_s: float = 0.2) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with contextlib.suppress(httpx.TransportError):
            value = cond()
            if value:
                return value
        time.sleep(every_s)
    raise RuntimeError(f"timed out waiting for {what}")


# ------------------------------------------------------------------------------------ the load


@dataclass(frozen=True)
class Options:
    """One measurement: cycles per cycle time and which load runs beside it."""

    cycles: int = 50_000
    http_rate: float = 20.0  # requests per second; 0: no HTTP load (and no event stream)
    fits: bool = True
    targets: bool = True
    campaign_rows: int = 1000
    rt_priority: int = 20  # [realtime] priority: SCHED_FIFO priority of the real-time process (0: normal)
    cpu_wakeup_latency_us: int = 0  # [realtime] cpu_wakeup_latency_us (-1: no PM QoS request)
    controller_priority: int = 10  # SCHED_FIFO priority of the simulated cell (0: normal scheduling)
    controller_cpu: int | None = None  # pin the simulated cell to this CPU (None: not pinned)
    floor_cpu: int | None = None  # run cyclictest on this CPU during the measurement
    keep: bool = False


class Load:
    """Fits, targets and HTTP requests against the daemon until :meth:`stop`; counts what it did."""

    def __init__(self, base_url: str, dataset_id: int, home: list[float], opts: Options, duration_s: float):
        self.base_url = base_url
        self.dataset_id = dataset_id
        self.home = home
        self.http_rate = opts.http_rate
        self.max_requests = int(1.5 * opts.http_rate * duration_s) + 100
        self.stop_event = threading.Event()
        self.fits_done = 0
        self.fits_started = 0
        self.batches = 0
        self.requests = 0
        self.request_errors: Counter[str] = Counter()
        self.request_ms: list[float] = []
        self.sse_events = 0
        self.fit_running: str | None = None  # the kind of the fit in progress
        self.in_flight: str | None = None  # the HTTP request in flight
        self.threads = []
        if opts.fits:
            self.threads.append(threading.Thread(target=self._fits, name="fits", daemon=True))
        if opts.targets:
            self.threads.append(threading.Thread(target=self._targets, name="targets", daemon=True))
        if opts.http_rate > 0:
            self.threads.append(threading.Thread(target=self._http, name="http", daemon=True))
            self.threads.append(threading.Thread(target=self._sse, name="sse", daemon=True))

    def _client(self, timeout_s: float = 30.0) -> httpx.Client:
        return httpx.Client(
            base_url=self.base_url, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=timeout_s
        )

    def start(self) -> None:
        for t in self.threads:
            t.start()

    def stop(self) -> None:
        self.stop_event.set()
        for t in self.threads:
            t.join(timeout=30)

    def _fits(self) -> None:
        kinds = [{"model": "chebyshev"}, {"model": "kinematic+ratio+backlash"}]
        with self._client() as c:
            while not self.stop_event.is_set():
                body = {"dataset_id": self.dataset_id, **kinds[self.fits_started % len(kinds)]}
                r = c.post("/api/fits", json=body)
                if r.status_code != 202:
                    self.stop_event.wait(1.0)
                    continue
                self.fits_started += 1
                self.fit_running = str(body["model"])
                job = r.json()["id"]
                while not self.stop_event.wait(0.5):
                    if c.get(f"/api/jobs/{job}").json()["state"] in ("done", "failed", "cancelled"):
                        self.fits_done += 1
                        break
                self.fit_running = None

    def _targets(self) -> None:
        rng = np.random.default_rng(7)
        with self._client() as c:
            while not self.stop_event.is_set():
                queued = c.get("/api/targets", params={"state": "queued", "limit": 50}).json()
                if len(queued) < 4:
                    targets = []
                    for _ in range(10):
                        a = np.array(self.home)
                        a[:3] += rng.uniform(-10.0, 10.0, 3)
                        targets.append({f"a{i + 1}": round(float(v), 4) for i, v in enumerate(a)})
                    self.batches += 1
                    c.post(
                        "/api/batches",
                        json={"targets": targets},
                        headers={"Idempotency-Key": f"bench-{self.batches}"},
                    )
                self.stop_event.wait(1.0)

    def _http(self) -> None:
        paths = [
            "/api/status", "/api/targets?limit=100", "/metrics", "/api/models", "/api/jobs", "/ready",
            "/api/events/log?limit=200", "/api/status", "/api/targets?newest_first=true&limit=20",
            f"/api/datasets/{self.dataset_id}/content",
        ]  # fmt: skip
        period = 1.0 / self.http_rate
        next_t = time.monotonic()
        with self._client() as c:
            while not self.stop_event.is_set() and self.requests < self.max_requests:
                path = paths[self.requests % len(paths)]
                self.in_flight = path
                t0 = time.perf_counter()
                try:
                    r = c.get(path)
                    if r.status_code >= 500 and not (path == "/ready" and r.status_code == 503):
                        self.request_errors[f"{r.status_code} {path}"] += 1  # 503 is /ready's "no"
                except httpx.HTTPError as exc:
                    self.request_errors[f"{type(exc).__name__} {path}"] += 1
                self.in_flight = None
                self.request_ms.append((time.perf_counter() - t0) * 1e3)
                self.requests += 1
                next_t += period
                self.stop_event.wait(max(0.0, next_t - time.monotonic()))

    def _sse(self) -> None:
        with self._client(timeout_s=60.0) as c, c.stream("GET", "/api/events") as r:
            for line in r.iter_lines():
                if line.startswith("event:"):
                    self.sse_events += 1
                if self.stop_event.is_set():
                    break


# ------------------------------------------------------------------------------------ what was going on


def _proc_sample(pid: int) -> tuple[str, int, int, int] | None:
    """The process's state letter, last CPU, voluntary and involuntary context switches."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    fields = stat[stat.rindex(")") + 2 :].split()  # after "pid (comm) "
    switches = dict(line.split(":\t") for line in status.splitlines() if "ctxt_switches" in line)
    return (
        fields[0],
        int(fields[36]),  # processor (field 39 of stat)
        int(switches.get("voluntary_ctxt_switches", 0)),
        int(switches.get("nonvoluntary_ctxt_switches", 0)),
    )


class Sampler:
    """Every ``period_s``: the real-time process's /proc state, runnable tasks, the load's state."""

    def __init__(self, rt_pid: int | None, load: Load, period_s: float = 0.05) -> None:
        self.rt_pid = rt_pid
        self.load = load
        self.period_s = period_s
        self.rows: list[tuple[int, str, int, int, int, int, str | None, str | None]] = []
        self.stop_event = threading.Event()
        self.thread = threading.Thread(target=self._run, name="sampler", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        self.stop_event.set()
        self.thread.join(timeout=10)

    def _run(self) -> None:
        while not self.stop_event.wait(self.period_s):
            proc = None if self.rt_pid is None else _proc_sample(self.rt_pid)
            state, cpu, vol, invol = proc if proc is not None else ("?", -1, 0, 0)
            try:
                runnable = int(Path("/proc/loadavg").read_text().split()[3].split("/")[0])
            except (OSError, ValueError, IndexError):
                runnable = -1
            load = self.load
            self.rows.append(
                (time.time_ns(), state, cpu, vol, invol, runnable, load.fit_running, load.in_flight)
            )

    def around(self, t_ns: int) -> str:
        """What was going on at ``t_ns`` (CLOCK_REALTIME): the first sample after it, with the context
        switches since the sample before."""
        rows = self.rows
        times = [r[0] for r in rows]
        i = int(np.searchsorted(times, t_ns))
        if not rows or i >= len(rows):
            return "no sample"
        t, state, cpu, vol, invol, runnable, fit, http = rows[i]
        dvol = dinv = 0
        if i > 0:
            dvol, dinv = vol - rows[i - 1][3], invol - rows[i - 1][4]
        return (
            f"rt process {state} on CPU {cpu}, +{dvol} voluntary / +{dinv} involuntary switches in "
            f"{(t - rows[i - 1][0]) / 1e6 if i > 0 else 0:.0f} ms; {runnable} runnable tasks; "
            f"fit: {fit or 'none'}; HTTP: {http or 'none'}"
        )


class RtTrace:
    """The real-time process's own per-cycle trace (:mod:`comp_daemon.rt.cycle_trace`), looked up by
    IPOC: for a reply, what held it up between the kernel and the receive callback."""

    def __init__(self, table: dict[str, np.ndarray], cycle_ms: int) -> None:
        order = np.argsort(table["ipoc"], kind="stable")
        self.t = {k: v[order] for k, v in table.items()}
        self.cycle_ns = cycle_ms * 1_000_000

    @classmethod
    def load(cls, path: Path, cycle_ms: int) -> RtTrace | None:
        if not path.exists():
            return None
        with np.load(path) as z:
            return cls({k: z[k] for k in z.files}, cycle_ms)

    def row(self, ipoc: int) -> dict[str, int] | None:
        """The row of the reply that answered ``ipoc``, or that superseded it (the next answered)."""
        i = int(np.searchsorted(self.t["ipoc"], ipoc))
        if i >= self.t["ipoc"].size:
            return None
        return {k: int(v[i]) for k, v in self.t.items()}

    def cause(self, r: dict[str, int]) -> str:
        """The largest share of the wait from the kernel's arrival to the callback, in words."""
        wait = r["entry_ns"] - r["kernel_first_ns"]
        if wait < self.cycle_ns / 4:
            return "in the callback" if r["sent_ns"] - r["entry_ns"] > self.cycle_ns / 4 else "not held up"
        shares = {
            "the collector": r["gc_ns"],
            "busy in other callbacks": r["cpu_ns"] - r["gc_ns"],
            "runnable, its CPU taken": r["run_delay_ns"],
        }
        what, ns = max(shares.items(), key=lambda kv: kv[1])
        if ns >= wait / 2:
            return what
        return "asleep: the datagram reached the kernel, not the socket, or the machine was held"

    def describe(self, r: dict[str, int] | None) -> str:
        if r is None:
            return "not in the trace"
        ms = 1e-6
        wait, inside = r["entry_ns"] - r["kernel_first_ns"], r["sent_ns"] - r["entry_ns"]
        return (
            f"[rt: answered IPOC {r['ipoc']}, {r['taken']} taken; kernel → callback "
            f"{wait * ms:.2f} ms, callback {inside * ms:.2f} ms; "
            f"since the last reply: CPU {r['cpu_ns'] * ms:.2f} ms (collector {r['gc_ns'] * ms:.2f} ms, "
            f"gen {r['gc_gen']}), waited runnable {r['run_delay_ns'] * ms:.2f} ms, "
            f"{r['involuntary']} involuntary / {r['voluntary']} voluntary switches, "
            f"{r['faults']} page faults → {self.cause(r)}]"
        )

    def causes(self, ipocs: np.ndarray) -> dict[str, int]:
        """How many of these telegrams (late or unanswered) each cause held up."""
        out: Counter[str] = Counter()
        for k in ipocs:
            r = self.row(int(k))
            out["not in the trace" if r is None else self.cause(r)] += 1
        return dict(out.most_common())


#: upper bounds (ms) of the wire-latency histogram; the last bucket is open
HISTOGRAM_MS = (0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 24.0)


def _histogram(ms: np.ndarray, missing: int) -> dict[str, int]:
    edges = np.array(HISTOGRAM_MS)
    counts = np.bincount(np.searchsorted(edges, ms, side="left"), minlength=edges.size + 1)
    out = {f"<= {b:g} ms": int(n) for b, n in zip(edges, counts[:-1], strict=True)}
    out[f"> {edges[-1]:g} ms"] = int(counts[-1])
    out["no reply"] = missing
    return out


@dataclass
class _Wire:
    """The relay's record of the daemon's telegrams, with what was going on around each."""

    ipoc: np.ndarray
    sent: np.ndarray
    reply: np.ndarray
    sampler: Sampler | None
    trace: RtTrace | None

    def _about(self, i: int) -> dict[str, Any]:
        t0 = int(self.sent[0])
        return {
            "ipoc": int(self.ipoc[i]),
            "at_s": round((int(self.sent[i]) - t0) / 1e9, 3),
            "context": self.sampler.around(int(self.sent[i])) if self.sampler is not None else "",
            "rt": self.trace.describe(self.trace.row(int(self.ipoc[i]))) if self.trace is not None else "",
        }

    def worst(self, n: int = 20) -> list[dict[str, Any]]:
        """The ``n`` slowest replies that came, oldest first within equal latency."""
        lat = np.where(self.reply > 0, (self.reply - self.sent) / 1e6, -np.inf)
        order = [i for i in np.argsort(-lat, kind="stable")[:n] if np.isfinite(lat[i])]
        return [self._about(int(i)) | {"latency_ms": round(float(lat[i]), 3)} for i in order]

    def unanswered(self, n: int = 20) -> list[dict[str, Any]]:
        """The ``n`` longest stretches of consecutive telegrams without a reply (the endpoint answers
        the newest after a stall, so a wait of more than a cycle shows here, not as a late reply)."""
        missing = np.flatnonzero(self.reply == 0)
        if missing.size == 0:
            return []
        stretches = np.split(missing, np.flatnonzero(np.diff(missing) != 1) + 1)
        stretches.sort(key=len, reverse=True)
        return [self._about(int(run[0])) | {"telegrams": int(run.size)} for run in stretches[:n]]


# ------------------------------------------------------------------------------------ one run


def _pct(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) if values.size else float("nan")


_BUCKET = re.compile(r'^comp_daemon_loop_reply_latency_seconds_bucket\{le="([^"]+)"\} ([0-9.e+]+)$', re.M)


def _reply_histogram(metrics_text: str) -> dict[float, float]:
    """The daemon's reply-latency histogram (receive callback → sent): upper bound in s → count."""
    return {float(le): float(n) for le, n in _BUCKET.findall(metrics_text)}


def _window(before: dict[float, float], after: dict[float, float]) -> dict[str, Any]:
    """The histogram of the measured window: share of replies within each bound, and the bounds
    that hold p50 and p99 (the daemon's own time per reply, from its metrics)."""
    bounds = sorted(after)
    counts = np.array([after[b] - before.get(b, 0.0) for b in bounds])
    if not bounds or counts[-1] <= 0:
        return {}
    share = [float(f) for f in counts / counts[-1]]
    pairs = list(zip(bounds, share, strict=True))
    within = {f"{b * 1e6:g}us" if b < 1 else f"{b:g}s": round(f, 5) for b, f in pairs if b != float("inf")}
    p50 = next(b for b, f in pairs if f >= 0.5)
    p99 = next(b for b, f in pairs if f >= 0.99)
    return {
        "replies": int(counts[-1]),
        "within": within,
        "p50_at_most_ms": p50 * 1e3,
        "p99_at_most_ms": p99 * 1e3,
    }


def _latency(ms: np.ndarray) -> dict[str, float]:
    return {
        "p50": _pct(ms, 50),
        "p99": _pct(ms, 99),
        "p99.9": _pct(ms, 99.9),
        "max": float(ms.max()) if ms.size else float("nan"),
    }


def _steal_s() -> float:
    """CPU time the hypervisor gave to others (``steal`` of ``/proc/stat``, all CPUs), in s."""
    try:
        fields = Path("/proc/stat").read_text().splitlines()[0].split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("nan")


def _floor_start(cpu: int | None) -> subprocess.Popen[str] | None:
    """``cyclictest`` (Debian's rt-tests) on ``cpu`` at SCHED_FIFO 21 with a 1 ms period: how late
    the platform itself wakes the highest-priority thread while the load runs."""
    if cpu is None:
        return None
    exe = shutil.which("cyclictest")
    if exe is None:
        print(
            "--floor-cpu: cyclictest not found (apt-get install rt-tests); no floor measured", file=sys.stderr
        )
        return None
    argv = [exe, "-m", "-q", "-a", str(cpu), "-p", "21", "-i", "1000", "-h", "100000"]
    return subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)


def _floor_stop(proc: subprocess.Popen[str] | None, cycle_ms: int) -> dict[str, Any] | None:
    if proc is None:
        return None
    proc.send_signal(signal.SIGINT)  # cyclictest prints its histogram (µs → count) on SIGINT
    text, _ = proc.communicate(timeout=30)
    counts: dict[int, int] = {}
    for line in text.splitlines():
        parts = line.split()
        if len(parts) >= 2 and not line.startswith("#") and parts[0].isdigit():
            counts[int(parts[0])] = counts.get(int(parts[0]), 0) + int(parts[1])
    m = re.search(r"# Max Latencies:\s*(\d+)", text)
    if not counts:
        return None
    us = np.array(sorted(counts))
    n = np.array([counts[u] for u in us])
    cum = np.cumsum(n) / n.sum()
    pct = {
        f"p{q:g}_us": int(us[min(int(np.searchsorted(cum, q / 100)), us.size - 1)])
        for q in (50, 99, 99.9, 99.99)
    }
    return {
        "wakeups": int(n.sum()),
        **pct,
        "max_us": int(m.group(1)) if m else int(us[n > 0].max()),
        "over_1ms": int(n[us > 1000].sum()),
        f"over_{cycle_ms}ms": int(n[us > cycle_ms * 1000].sum()),
    }


def run(cycle_ms: int, opts: Options) -> dict[str, Any]:
    cycles = opts.cycles
    root = Path(tempfile.mkdtemp(prefix=f"bench-rsi-{cycle_ms}ms-"))
    relay_port, daemon_rsi, echo_port, http_port = (
        _free_port(socket.SOCK_DGRAM),
        _free_port(socket.SOCK_DGRAM),
        _free_port(socket.SOCK_DGRAM),
        _free_port(socket.SOCK_STREAM),
    )
    ctx = mp.get_context("spawn")
    recording, finished, relay_ready, echo_ready = ctx.Event(), ctx.Event(), ctx.Event(), ctx.Event()
    out = root / "relay.npz"
    trace_path = root / "rt-trace.npz"
    # the echo where the daemon's real-time process runs ([realtime] cpu = "auto"), at its priority
    echo_cpu = resolve_cpu("auto")
    echo = ctx.Process(
        target=echo_main, args=(echo_port, echo_cpu, opts.rt_priority, "ImFree", echo_ready), daemon=True
    )
    echo.start()
    echo_ready.wait(30)
    relay = ctx.Process(
        target=relay_main,
        args=(
            relay_port,
            daemon_rsi,
            echo_port,
            cycle_ms,
            str(out),
            cycles,
            recording,
            finished,
            relay_ready,
        ),
        daemon=True,
    )
    relay.start()
    relay_ready.wait(30)
    campaign = root / "campaign.csv"
    sample = ["sim", "sample", "--n", str(opts.campaign_rows), "--out", str(campaign), "--seed", "11"]
    subprocess.run([sys.executable, "-m", "comp_daemon", *sample], check=True, capture_output=True)
    load: Load | None = None
    sampler: Sampler | None = None
    daemon: subprocess.Popen[bytes] | None = None
    result: dict[str, Any] = {"cycle_ms": cycle_ms, "options": asdict(opts)}
    try:
        cell_at = (opts.controller_priority, opts.controller_cpu)
        with _cell(root, cycle_ms, relay_port, *cell_at) as (_cell_proc, cell):
            cfg = _config(root, cell, cycle_ms, http_port, daemon_rsi, opts)
            env = os.environ | {
                cycle_trace.ENV_PATH: str(trace_path),
                cycle_trace.ENV_CYCLES: str(cycles + 200_000),  # + calibration and the first fit
            }
            with (root / "daemon.log").open("wb") as log:
                daemon = subprocess.Popen(
                    [sys.executable, "-m", "comp_daemon", "run", "--config", str(cfg),
                     "--motion", f"127.0.0.1:{cell['motion_port']}", "--calibrate-gratings"],
                    stdout=log, stderr=subprocess.STDOUT, env=env,
                )  # fmt: skip
            base = f"http://127.0.0.1:{http_port}"
            _wait(lambda: httpx.get(f"{base}/health").status_code == 200, 60, "the daemon's HTTP service")
            _line(cell["motion_port"], "rsi_on")  # RSI_ON in the robot program

            def calibrated() -> bool:
                reasons = httpx.get(f"{base}/ready").json().get("reasons", [])
                return reasons == ["no model is active"]

            _wait(calibrated, 120, "the grating calibration")
            headers = {"Authorization": f"Bearer {TOKEN}"}
            with httpx.Client(base_url=base, headers=headers, timeout=60) as c:
                r = c.post(
                    "/api/datasets", content=campaign.read_bytes(), headers={"Content-Type": "text/csv"}
                )
                r.raise_for_status()
                dataset_id = r.json()["id"]
                job = c.post("/api/fits", json={"dataset_id": dataset_id, "model": "kinematic"}).json()["id"]
                _wait(lambda: c.get(f"/api/jobs/{job}").json()["state"] == "done", 120, "the first fit")
                model = next(m["id"] for m in c.get("/api/models").json() if m["job_id"] == job)
                c.post(f"/api/models/{model}/activate").raise_for_status()
                _wait(lambda: httpx.get(f"{base}/ready").status_code == 200, 30, "readiness")

                load = Load(base, dataset_id, cell["home_deg"], opts, cycles * cycle_ms / 1000.0)
                load.start()
                word = c.get("/api/status").json()["daemon"]["loop"].get("realtime") or ""
                pid = re.search(r"pid (\d+)", word)
                sampler = Sampler(int(pid.group(1)) if pid else None, load)
                sampler.start()
                time.sleep(3.0)  # the first fit and batch under way
                ctrl0 = json.loads(_line(cell["motion_port"], "status"))
                status0 = c.get("/api/status").json()["daemon"]["loop"]
                hist0 = _reply_histogram(c.get("/metrics").text)
                load_start = os.getloadavg()
                floor = _floor_start(opts.floor_cpu)
                steal0 = _steal_s()
                t0 = time.monotonic()
                recording.set()
                try:
                    while not finished.wait(5.0):
                        if daemon.poll() is not None:
                            raise RuntimeError(f"the daemon exited with {daemon.returncode}")
                        if time.monotonic() - t0 > cycles * cycle_ms / 1000.0 * 3 + 120:
                            raise RuntimeError("the measurement did not finish")
                finally:
                    wall_s = time.monotonic() - t0
                    steal_s = _steal_s() - steal0
                    platform = _floor_stop(floor, cycle_ms)
                sampler.stop()
                ctrl1 = json.loads(_line(cell["motion_port"], "status"))
                status1 = c.get("/api/status").json()["daemon"]["loop"]
                hist1 = _reply_histogram(c.get("/metrics").text)
                load.stop()
                finished_targets = {
                    s: c.get("/api/targets", params={"state": s, "limit": 500}).json()
                    for s in ("done", "failed")
                }
                states = {s: len(v) for s, v in finished_targets.items()}
                fail_reasons = Counter(str(t["reason"]).split(":")[0] for t in finished_targets["failed"])
            daemon.send_signal(signal.SIGTERM)
            code = daemon.wait(timeout=60)
    finally:
        if sampler is not None:
            sampler.stop()
        if load is not None:
            load.stop()
        if daemon is not None and daemon.poll() is None:
            daemon.kill()
            daemon.wait()
        relay.terminate()
        relay.join(10)
        echo.terminate()
        echo.join(10)

    rec = np.load(out)
    sent, reply, arrive = rec["t_sent"], rec["t_reply"], rec["t_arrive"]
    trace = RtTrace.load(trace_path, cycle_ms)
    late_mask = (reply == 0) | (reply - sent > cycle_ms * 1_000_000)
    wire = _Wire(rec["ipoc"], sent, reply, sampler, trace)
    answered = reply > 0
    # a telegram the relay forwarded less than half a cycle before the next one (the relay itself
    # was held up) arrives at the daemon with its successor queued behind it: only the newest is
    # answered, by design; counted apart from the daemon's own misses
    gap_next = np.diff(sent, append=np.iinfo(np.int64).max)
    burst = gap_next < cycle_ms * 1e6 / 2
    lat_ms = (reply[answered] - sent[answered]) / 1e6
    cycle = float(cycle_ms)
    relay_ms = (sent - arrive) / 1e6
    http_ms = np.array(load.request_ms if load else [], dtype=np.float64)
    echo_sent, echo_reply = rec["echo_t_sent"], rec["echo_t_reply"]
    echo_ms = (echo_reply[echo_reply > 0] - echo_sent[echo_reply > 0]) / 1e6
    result.update(
        date=dt.date.today().isoformat(),
        recorded=int(sent.size),
        wall_s=round(wall_s, 1),
        latency_ms=_latency(lat_ms),
        late=int(np.sum(lat_ms > cycle)) + int(np.sum(~answered)),
        missing=int(np.sum(~answered)),
        missing_in_relay_burst=int(np.sum(~answered & burst)),
        echo={
            "cpu": echo_cpu,
            "priority": opts.rt_priority,
            "recorded": int(echo_sent.size),
            "latency_ms": _latency(echo_ms),
            "late": int(np.sum(echo_ms > cycle)) + int(np.sum(echo_reply == 0)),
            "missing": int(np.sum(echo_reply == 0)),
            "over_1ms": int(np.sum(echo_ms > 1.0)),
        },
        over_1ms=int(np.sum(lat_ms > 1.0)),
        histogram=_histogram(lat_ms, int(np.sum(~answered))),
        worst=wire.worst(),
        unanswered=wire.unanswered(),
        late_causes=trace.causes(rec["ipoc"][late_mask]) if trace is not None else {},
        relay_forward_ms_p99=_pct(relay_ms, 99),
        steal_s=round(steal_s, 2),
        platform_floor=platform,
        daemon_view={
            "p50_ms": status1.get("latency_p50_ms"),
            "p99_ms": status1.get("latency_p99_ms"),
            "max_ms": status1.get("latency_max_ms"),
            "late": (status1.get("late_replies") or 0) - (status0.get("late_replies") or 0),
            "realtime": status1.get("realtime"),
            "in_callback": _window(hist0, hist1),
        },
        controller_late=ctrl1["late_total"] - ctrl0["late_total"],
        controller_overruns=ctrl1["overruns"] - ctrl0["overruns"],
        fits_done=load.fits_done if load else 0,
        targets=states,
        target_fail_reasons=dict(fail_reasons),
        batches=load.batches if load else 0,
        http_requests=load.requests if load else 0,
        http_errors=dict(load.request_errors) if load else {},
        http_ms={"p50": _pct(http_ms, 50), "p99": _pct(http_ms, 99)},
        sse_events=load.sse_events if load else 0,
        loadavg_start=[round(v, 2) for v in load_start],
        loadavg_end=[round(v, 2) for v in os.getloadavg()],
        daemon_exit=code,
    )
    if not opts.keep:
        shutil.rmtree(root, ignore_errors=True)
    else:
        result["folder"] = str(root)
    return result


def _ms(value: float | None) -> str:
    return "–" if value is None else f"{value:.3f} ms"


def _report(r: dict[str, Any]) -> str:
    lat, dv, echo = r["latency_ms"], r["daemon_view"], r["echo"]
    elat = echo["latency_ms"]
    return (
        f"{r['cycle_ms']:>2} ms  {r['recorded']} cycles in {r['wall_s']} s\n"
        f"   {'':<8} {'p50':>8} {'p99':>8} {'p99.9':>8} {'max':>8}  late   (reply latency, ms, relay side)\n"
        f"   {'daemon':<8} {lat['p50']:8.3f} {lat['p99']:8.3f} {lat['p99.9']:8.3f} {lat['max']:8.3f}  "
        f"{r['late']}\n"
        f"   {'echo':<8} {elat['p50']:8.3f} {elat['p99']:8.3f} {elat['p99.9']:8.3f} {elat['max']:8.3f}  "
        f"{echo['late']}   (bare asyncio echo, {echo['recorded']} telegrams, CPU {echo['cpu']}, "
        f"SCHED_FIFO {echo['priority']} where granted)\n"
        f"   daemon p99 / echo p99: {lat['p99'] / elat['p99']:.2f}; > 1 ms: daemon {r['over_1ms']}, "
        f"echo {echo['over_1ms']}\n"
        f"   late (> {r['cycle_ms']} ms or none): {r['late']} (no reply: {r['missing']}, of which "
        f"{r['missing_in_relay_burst']} right behind a relay hold-up); echo {echo['late']} "
        f"(no reply: {echo['missing']}); "
        f"simulated controller counted {r['controller_late']} late, {r['controller_overruns']} own overruns\n"
        f"   daemon's own view (callback → sent, last 65 536): p50 {_ms(dv['p50_ms'])}, "
        f"p99 {_ms(dv['p99_ms'])}, max since start {_ms(dv['max_ms'])}, late {dv['late']}\n"
        f"   daemon's own view in the measured window (metrics histogram): {_callback_text(dv)}\n"
        f"   real-time path: {dv.get('realtime')}\n"
        f"   load: {r['fits_done']} fits done, targets done {r['targets']['done']} / failed "
        f"{r['targets']['failed']} {r['target_fail_reasons'] or ''}, {r['http_requests']} HTTP requests "
        f"(p50 {r['http_ms']['p50']:.1f} ms, p99 {r['http_ms']['p99']:.1f} ms, "
        f"errors: {r['http_errors'] or 0}), "
        f"{r['sse_events']} SSE events; "
        f"relay forwarding p99 {r['relay_forward_ms_p99']:.3f} ms; load average {r['loadavg_start']} → "
        f"{r['loadavg_end']}; daemon exit {r['daemon_exit']}\n"
        f"   platform: {r['steal_s']} s of CPU time stolen by the hypervisor; {_floor_text(r)}\n"
        f"   reply latency on the wire (relay side): {_histogram_text(r['histogram'])}\n"
        f"   what held up the late and unanswered telegrams (the real-time process's trace): "
        f"{r['late_causes'] or 'no trace'}\n"
        f"   the worst {len(r['worst'])} replies:\n{_worst_text(r['worst'])}\n"
        f"   the longest {len(r['unanswered'])} stretches without a reply:\n"
        f"{_unanswered_text(r['unanswered'])}"
    )


def _unanswered_text(rows: list[dict[str, Any]]) -> str:
    return (
        "\n".join(
            f"     IPOC {w['ipoc']} at {w['at_s']:9.3f} s: {w['telegrams']} telegram(s) — {w['context']}"
            f"\n       {w['rt']}"
            for w in rows
        )
        or "     none"
    )


def _histogram_text(h: dict[str, int]) -> str:
    return ", ".join(f"{k}: {v}" for k, v in h.items() if v)


def _worst_text(rows: list[dict[str, Any]]) -> str:
    return "\n".join(
        f"     IPOC {w['ipoc']} at {w['at_s']:9.3f} s: {w['latency_ms']:.3f} ms — {w['context']}"
        f"\n       {w['rt']}"
        for w in rows
    )


def _callback_text(dv: dict[str, Any]) -> str:
    w = dv.get("in_callback") or {}
    if not w:
        return "–"
    shares = ", ".join(f"≤ {k}: {v:.2%}" for k, v in w["within"].items())
    p50, p99 = w["p50_at_most_ms"], w["p99_at_most_ms"]
    return f"{w['replies']} replies, p50 ≤ {p50:g} ms, p99 ≤ {p99:g} ms ({shares})"


def _floor_text(r: dict[str, Any]) -> str:
    f = r.get("platform_floor")
    if not f:
        return "no wake-up floor measured (--floor-cpu)"
    over = f"over_{r['cycle_ms']}ms"
    return (
        f"cyclictest ({f['wakeups']} wake-ups): p50 {f['p50_us']} µs, p99 {f['p99_us']} µs, "
        f"p99.9 {f['p99.9_us']} µs, p99.99 {f['p99.99_us']} µs, max {f['max_us']} µs; "
        f"> 1 ms: {f['over_1ms']}, > {r['cycle_ms']} ms: {f[over]}"
    )


def _controller_cpu(setting: str) -> int | None:
    if setting == "none":
        return None
    if setting != "auto":
        return int(setting)
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    return cpus[0] if len(cpus) > 1 else None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cycles", type=int, default=50_000, help="measured cycles per cycle time")
    parser.add_argument(
        "--duration-s",
        type=float,
        default=None,
        help="measure this long per cycle time instead of --cycles (e.g. 3600 for an hour)",
    )
    parser.add_argument(
        "--cycle-ms", type=int, action="append", choices=(12, 4), help="12 and/or 4 (default both)"
    )
    parser.add_argument("--http-rate", type=float, default=20.0, help="HTTP requests per second (0: none)")
    parser.add_argument("--no-fits", action="store_true", help="no fit jobs during the measurement")
    parser.add_argument("--no-targets", action="store_true", help="no targets during the measurement")
    parser.add_argument(
        "--rt-priority", type=int, default=20, help="[realtime] priority (SCHED_FIFO; 0: normal scheduling)"
    )
    parser.add_argument(
        "--cpu-wakeup-latency-us",
        type=int,
        default=0,
        help="[realtime] cpu_wakeup_latency_us (PM QoS; -1: no request)",
    )
    parser.add_argument(
        "--controller-priority",
        type=int,
        default=10,
        help="SCHED_FIFO priority of the simulated cell, below --rt-priority (0: normal scheduling)",
    )
    parser.add_argument(
        "--controller-cpu",
        default="auto",
        help="pin the simulated cell to this CPU ('auto': the first, when there are two or more; 'none')",
    )
    parser.add_argument(
        "--floor-cpu",
        type=int,
        default=None,
        help="also measure the platform's own wake-up latency there (cyclictest, SCHED_FIFO 21, 1 ms)",
    )
    parser.add_argument("--campaign-rows", type=int, default=1000, help="rows of the campaign the fits use")
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    parser.add_argument("--keep", action="store_true", help="keep the run folders (logs, relay record)")
    args = parser.parse_args(argv)
    if args.cycles < 100:
        parser.error("--cycles must be at least 100")
    if args.duration_s is not None and args.duration_s < 10:
        parser.error("--duration-s must be at least 10 s")
    print(f"machine: {machine_line()}", flush=True)
    results = []
    opts = Options(
        cycles=args.cycles,
        http_rate=args.http_rate,
        fits=not args.no_fits,
        targets=not args.no_targets,
        campaign_rows=args.campaign_rows,
        rt_priority=args.rt_priority,
        cpu_wakeup_latency_us=args.cpu_wakeup_latency_us,
        controller_priority=args.controller_priority,
        controller_cpu=_controller_cpu(args.controller_cpu),
        floor_cpu=args.floor_cpu,
        keep=args.keep,
    )
    print(f"options: {asdict(opts)}, duration per cycle time: {args.duration_s or 'by --cycles'}", flush=True)
    for cycle_ms in args.cycle_ms or [12, 4]:
        if args.duration_s is not None:
            opts = replace(opts, cycles=int(args.duration_s * 1000 / cycle_ms))
        r = run(cycle_ms, opts)
        print(_report(r), flush=True)
        results.append(r)
    if args.json is not None:
        args.json.write_text(json.dumps({"machine": machine_info(), "results": results}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
