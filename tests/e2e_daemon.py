"""``comp-daemon run`` as a real process for the end-to-end tests (not a test module itself).

A :class:`DaemonProcess` writes a configuration with one token per role, free TCP/UDP ports and a
data folder under the test's temporary directory, starts ``python -m comp_daemon run --config …``
(``--sim`` by default), and offers what a client on the line has: HTTP on 127.0.0.1 with a bearer
token, signals, the process's exit code and its log. The process's descendants (the simulated
cell, the job pool's workers) are found through ``/proc`` so that a test can check that none
outlives the daemon, and end them by pid if one does.

Units: times in seconds.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import httpx
import numpy as np

TOKENS = {
    "viewer": "e2e-viewer-token-0123456789abcdef",
    "operator": "e2e-mes-operator-token-0123456789",
    "engineer": "e2e-engineer-token-0123456789abcd",
}


def free_port(kind: socket.SocketKind = socket.SOCK_STREAM) -> int:
    """A port the kernel just handed out on 127.0.0.1 (free now; the daemon binds it a moment later)."""
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def config_text(
    data_dir: Path,
    http_port: int,
    rsi_port: int,
    extra: str = "",
    http_extra: str = "",
    *,
    stale_after_ms: float = 400.0,
) -> str:
    """A configuration for the simulated cell: tokens for the three roles, a loaded-machine margin.

    ``extra`` is appended as tables of its own; ``http_extra`` goes into the ``[http]`` table.
    ``stale_after_ms``: when a grating reading counts as stale (400 ms: a loaded 2-core test machine
    leaves the simulated cell unscheduled for 150 ms and more now and then, and its gratings answer
    late meanwhile; staleness itself is test_rt_encoder_reader.py's test).
    """
    tokens = "".join(
        f'[[auth.tokens]]\nname = "{name}"\nrole = "{role}"\ntoken = "{TOKENS[role]}"\n'
        for name, role in (("screen", "viewer"), ("mes", "operator"), ("calibration", "engineer"))
    )
    return f"""
[http]
host = "127.0.0.1"
port = {http_port}
sse_keepalive_s = 1.0
{http_extra}
[store]
data_dir = "{data_dir}"
synchronous = "normal"
[rsi]
listen_host = "127.0.0.1"
listen_port = {rsi_port}
# a loaded test machine may answer late now and then; the late-reply stop is the controller's own test
timeout_count = 1000
[encoders]
stale_after_ms = {stale_after_ms:g}
[jobs]
workers = 1
[log]
level = "INFO"
format = "json"
{extra}
{tokens}"""


def descendants(pid: int) -> list[int]:
    """Every live descendant of ``pid`` (children first), read from ``/proc``."""
    parents: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        parents.setdefault(ppid, []).append(int(entry.name))
    out: list[int] = []
    todo = [pid]
    while todo:
        for child in parents.get(todo.pop(), []):
            out.append(child)
            todo.append(child)
    return out


def alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        return ""


def describe(pids: Sequence[int]) -> str:
    """The live ones among ``pids`` with their command lines (for failure messages)."""
    return "; ".join(f"{pid}: {cmdline(pid)}" for pid in pids if alive(pid)) or "none alive"


def wait_until(
    cond: Callable[[], Any], timeout_s: float, what: str | Callable[[], str], *, every_s: float = 0.05
) -> Any:
    """Poll ``cond`` until it returns something truthy; fail naming ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = cond()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(
                f"timed out after {timeout_s} s waiting for {what if isinstance(what, str) else what()}"
            )
        time.sleep(every_s)


class DaemonProcess:
    """One daemon process on a data folder that outlives it (a restart uses the same folder)."""

    def __init__(
        self, root: Path, *, sim: bool = True, extra_config: str = "", http_config: str = ""
    ) -> None:
        self.root = root
        self.data_dir = root / "data"
        self.http_port = free_port(socket.SOCK_STREAM)
        self.rsi_port = free_port(socket.SOCK_DGRAM)
        self.config_path = root / "config.toml"
        self.config_path.write_text(
            config_text(self.data_dir, self.http_port, self.rsi_port, extra_config, http_config),
            encoding="utf-8",
        )
        self.sim = sim
        self.proc: subprocess.Popen[bytes] | None = None
        self.runs = 0
        self.log_path = root / "daemon-0.log"
        self.base_url = f"http://127.0.0.1:{self.http_port}"
        self._started_children: list[int] = []

    # ------------------------------------------------------------------------------ process

    def start(
        self,
        *args: str,
        env: Mapping[str, str] | None = None,
        preexec_fn: Callable[[], None] | None = None,
    ) -> None:
        """Start the daemon; ``env`` adds variables, ``preexec_fn`` runs in the child before exec."""
        assert self.proc is None or self.proc.poll() is not None, "already running"
        self.runs += 1
        self.log_path = self.root / f"daemon-{self.runs}.log"
        argv = [sys.executable, "-m", "comp_daemon", "run", "--config", str(self.config_path)]
        if self.sim:
            argv.append("--sim")
        environ = {k: v for k, v in os.environ.items() if not k.startswith("COMP_DAEMON_")}
        environ.update(env or {})
        with self.log_path.open("wb") as log:
            self.proc = subprocess.Popen(
                argv + list(args), stdout=log, stderr=subprocess.STDOUT, env=environ, preexec_fn=preexec_fn
            )

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def log_text(self) -> str:
        return self.log_path.read_text(encoding="utf-8", errors="replace")

    def tail(self, n: int = 4000) -> str:
        return self.log_text()[-n:]

    def wait_http(self, timeout_s: float = 60.0) -> None:
        """Until ``/health`` answers (the store is recovered, the loop and HTTP run)."""

        def up() -> bool:
            assert self.proc is not None
            if self.proc.poll() is not None:
                raise AssertionError(f"the daemon exited with {self.proc.returncode}:\n{self.tail()}")
            try:
                return httpx.get(f"{self.base_url}/health", timeout=2.0).status_code == 200
            except httpx.TransportError:
                return False

        wait_until(up, timeout_s, "GET /health", every_s=0.1)

    def ready(self) -> dict[str, Any]:
        r = httpx.get(f"{self.base_url}/ready", timeout=5.0)
        doc: dict[str, Any] = r.json()
        assert (r.status_code == 200) == bool(doc.get("ready")), (r.status_code, doc)
        return doc

    def wait_ready(self, timeout_s: float = 60.0, *, allow: Sequence[str] = ()) -> dict[str, Any]:
        """Until ``/ready`` reports no reason other than those starting with one of ``allow``."""

        def ok() -> dict[str, Any] | None:
            assert self.proc is not None
            if self.proc.poll() is not None:
                raise AssertionError(f"the daemon exited with {self.proc.returncode}:\n{self.tail()}")
            doc = self.ready()
            left = [r for r in doc.get("reasons", []) if not any(r.startswith(a) for a in allow)]
            return None if left else doc

        try:
            result: dict[str, Any] = wait_until(ok, timeout_s, "/ready", every_s=0.1)
        except AssertionError:
            raise AssertionError(f"not ready: {self.ready()}\n{self.tail()}") from None
        return result

    def children(self) -> list[int]:
        return descendants(self.pid) if self.proc is not None and self.proc.poll() is None else []

    def sigterm(self, timeout_s: float = 30.0) -> int:
        assert self.proc is not None
        self._started_children = self.children()
        self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"no exit within {timeout_s} s of SIGTERM:\n{self.tail()}") from None

    def kill9(self) -> list[int]:
        """SIGKILL the daemon; returns the pids of its descendants at that moment."""
        assert self.proc is not None
        self._started_children = self.children()
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=10)
        return list(self._started_children)

    def end_orphans(self) -> None:
        """SIGKILL, by pid, whatever the last daemon process left running when it ended."""
        for pid in self._started_children:
            if alive(pid):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)

    def cleanup(self) -> None:
        """End the daemon and anything it left behind (by pid), whatever the test did."""
        if self.proc is not None and self.proc.poll() is None:
            self._started_children = self.children()
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.end_orphans()

    # ------------------------------------------------------------------------------ HTTP

    @contextlib.contextmanager
    def client(self, role: str | None = "viewer", timeout_s: float = 10.0) -> Iterator[httpx.Client]:
        headers = {} if role is None else {"Authorization": f"Bearer {TOKENS[role]}"}
        with httpx.Client(base_url=self.base_url, headers=headers, timeout=timeout_s) as c:
            yield c


def sample_campaign(path: Path, n: int = 60, seed: int = 1) -> Path:
    """A measurement campaign of the simulated cell, written by ``comp-daemon sim sample``."""
    subprocess.run(
        [
            sys.executable,
            "-m",
            "comp_daemon",
            "sim",
            "sample",
            "--n",
            str(n),
            "--out",
            str(path),
            "--seed",
            str(seed),
        ],
        check=True,
        capture_output=True,
        timeout=120,
    )
    return path


def upload_campaign(client: httpx.Client, path: Path, name: str | None = None) -> dict[str, Any]:
    """Upload a campaign CSV as the engineer; returns the stored data set's document (201 asserted)."""
    params = None if name is None else {"name": name}
    r = client.post(
        "/api/datasets", params=params, content=path.read_bytes(), headers={"Content-Type": "text/csv"}
    )
    assert r.status_code == 201, r.text
    doc: dict[str, Any] = r.json()
    return doc


def fit_and_activate(client: httpx.Client, dataset_id: int, model: str = "kinematic") -> dict[str, Any]:
    """Start a fit as the engineer, follow the job to done, activate its model; returns the job."""
    r = client.post("/api/fits", json={"dataset_id": dataset_id, "model": model})
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]

    def finished() -> dict[str, Any] | None:
        doc: dict[str, Any] = client.get(f"/api/jobs/{job_id}").json()
        return doc if doc["state"] in ("done", "failed", "cancelled") else None

    job: dict[str, Any] = wait_until(finished, 60, f"fit job {job_id}", every_s=0.1)
    assert job["state"] == "done", job
    models = [m for m in client.get("/api/models").json() if m["job_id"] == job_id]
    assert len(models) == 1, models
    r = client.post(f"/api/models/{models[0]['id']}/activate")
    assert r.status_code == 200, r.text
    return job


@contextlib.asynccontextmanager
async def in_process_cell(
    root: Path, *, seed: int, stale_after_ms: float = 400.0, **sim: Any
) -> AsyncIterator[Any]:
    """The assembled daemon with its simulated cell (kr210-cell), in this process and event loop:
    started, RSI running, the gratings calibrated on three poses around home, the nominal model
    active, ready. ``sim``: further :class:`~comp_daemon.daemon.app.SimOptions` (``rearm_after_s``).
    Stopped at the end (exit code 0 asserted)."""
    import asyncio

    from comp_daemon.daemon.app import Daemon, SimOptions
    from comp_daemon.models.artifact import model_document
    from comp_daemon.models.nominal import NominalModel
    from comp_daemon.service.config import load_settings
    from comp_daemon.service.store import ModelDraft

    async def until(cond: Callable[[], Any], timeout_s: float) -> None:
        async with asyncio.timeout(timeout_s):
            while not cond():
                await asyncio.sleep(0.01)

    def activate_nominal(daemon: Daemon) -> None:
        assert daemon.store is not None
        doc = model_document(NominalModel(daemon.robot), data_sha256="0" * 64, frame="base")
        daemon.store.activate_model(
            daemon.store.add_model(ModelDraft("nominal", None, doc, {}, None)).id, by="test"
        )

    cfg = root / "config.toml"
    cfg.write_text(config_text(root / "data", 0, 0, stale_after_ms=stale_after_ms), encoding="utf-8")
    daemon = Daemon(load_settings(cfg), sim=SimOptions(scenario="kr210-cell", seed=seed, **sim))
    run = asyncio.create_task(daemon.run())
    try:
        async with asyncio.timeout(60):
            await daemon.started.wait()
        await until(lambda: daemon.realtime.runtime is not None and daemon.realtime.runtime.rsi_alive(), 10)
        assert daemon.sim_info is not None
        home = np.array(daemon.sim_info.home_deg)
        poses = [
            tuple(home + np.r_[d * np.array([1.0, (-1.0) ** k, 0.5]), 0, 0, 0])
            for k, d in enumerate((-12.0, 0.0, 12.0))
        ]
        await daemon.gratings.calibrate(poses, settle_cycles=15, sample_cycles=8)
        await asyncio.to_thread(activate_nominal, daemon)
        await until(lambda: not daemon.view.readiness_reasons(), 10)
        yield daemon
    finally:
        daemon.request_stop("tests over")
        code = await asyncio.wait_for(run, 30)
        assert code == 0


def target_rows(targets: Sequence[dict[str, Any]]) -> str:
    return "\n".join(f"{t['id']:>4} {t['state']:<12} {t.get('reason') or ''}" for t in targets)
