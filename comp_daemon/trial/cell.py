"""The trial's cell: the simulated cell and the daemon as separate processes, and the trial's clients.

The trial brings the cell up as it stands on the line:

- the simulated cell (:mod:`comp_daemon.sim.cell`, the child ``comp-daemon run --sim`` starts too):
  the hidden robot behind a simulated KR C4 (RSI over UDP and a motion command port), one grating
  converter per grating joint on a pseudo-terminal, and the laser tracker (a line port);
- the daemon as ``comp-daemon run --config FILE --motion HOST:PORT``, a process of its own, with
  the converters' serial ports and the RSI port in its configuration, exactly as on the cell's PC.

The trial then uses only what a user of the cell has: the daemon's HTTP API with a bearer token,
the robot program's motion port (``move A1..A6`` for the moves the robot makes on its own, between
targets or without the daemon), ``rsi_on`` (the program's ``RSI_ON``), and the tracker
(``measure``). Tracker readings come in the tracker's frame; seed 000 sets the robot base frame up
in the tracker software before the experiment ("all the data were measured in the base coordinate
system of the robot"), which here is the scenario's stated tracker pose.

Units: mm (base frame), deg (axis values).
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import json
import os
import secrets
import signal
import socket
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from numpy.typing import NDArray

from comp_daemon.sim.scenario import Scenario
from comp_daemon.sim_client import SimCellInfo, SimCellProcess, floats, line_command

__all__ = ["CellError", "CellSettings", "TrialCell"]


class CellError(RuntimeError):
    """The cell or the daemon did something the trial cannot go on from; the message says what."""


@dataclass(frozen=True, slots=True)
class CellSettings:
    """How the daemon is configured for the trial (everything else: the configuration defaults).

    ``timeout_count`` (late replies per RSI session before the controller stops RSI) and
    ``stale_after_ms`` are more tolerant than a cell's usual settings: a trial of half an hour on a
    busy shared machine (a test suite beside it) collects a few hundred late replies, which would
    stop RSI part way; they are counted by the simulated controller and reported with the results.
    A grating reading counts as stale after 400 ms (the end-to-end tests' margin too): on a machine
    at load 8 a 150 ms limit left the grating calibration without a still stretch of readings.
    """

    cycle_ms: int = 12
    servo_lag_cycles: int = 1
    timeout_count: int = 100_000
    stale_after_ms: float = 400.0
    log_level: str = "INFO"


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _die_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    """Linux: SIGTERM to the daemon when the trial's process dies (no daemon left behind)."""
    with contextlib.suppress(Exception):
        ctypes.CDLL(None).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def _robot_name(scenario: Scenario) -> str:
    source = scenario.robot.source
    return source.removeprefix("preset:") if source.startswith("preset:") else source


class TrialCell:
    """Start with :meth:`start`, stop with :meth:`close` (or ``async with``)."""

    def __init__(
        self,
        scenario: Scenario,
        workdir: Path,
        *,
        seed: int = 0,
        payload_kg: float = 0.0,
        settings: CellSettings | None = None,
    ) -> None:
        self.scenario = scenario
        self.workdir = Path(workdir)
        self.seed = seed
        self.payload_kg = payload_kg
        self.settings = settings or CellSettings()
        self.token = secrets.token_urlsafe(24)
        self.sim: SimCellProcess | None = None
        self.info: SimCellInfo | None = None
        self.daemon: asyncio.subprocess.Process | None = None
        self.http: httpx.AsyncClient | None = None
        self.http_port: int | None = None
        self.daemon_log = self.workdir / "daemon.log"
        self.daemon_exit_code: int | None = None
        tracker_T_base = scenario.tracker_T_base()
        self._base_T_tracker = np.linalg.inv(tracker_T_base)

    # ------------------------------------------------------------------------------ lifecycle

    async def __aenter__(self) -> TrialCell:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def _config_text(self, info: SimCellInfo, http_port: int, rsi_port: int) -> str:
        st = self.settings
        data = self.workdir / "data"
        lines = [
            "# written by comp-daemon trial: the daemon as on the cell's PC, against the simulated cell",
            "[http]",
            'host = "127.0.0.1"',
            f"port = {http_port}",
            "[store]",
            f"data_dir = {json.dumps(str(data))}",
            'synchronous = "normal"',
            "[[auth.tokens]]",
            'name = "trial"',
            'role = "engineer"',
            f"token = {json.dumps(self.token)}",
            "[jobs]",
            "workers = 1",
            "[rsi]",
            'listen_host = "127.0.0.1"',
            f"listen_port = {rsi_port}",
            'controller_allow = ["127.0.0.1"]',
            f"cycle_ms = {st.cycle_ms}",
            f"timeout_count = {st.timeout_count}",
            "[encoders]",
            f"stale_after_ms = {st.stale_after_ms}",
        ]
        for joint, port in sorted(info.gratings.items()):
            lines += [
                "[[encoders.joints]]",
                f"joint = {joint}",
                f"port = {json.dumps(port)}",
                f"radius_mm = {info.radius_mm}",
                f"resolution_nm = {info.resolution_nm}",
                f"bits = {info.bits}",
            ]
        lines += [
            "[robot]",
            f"name = {json.dumps(_robot_name(self.scenario))}",
            "[log]",
            f'level = "{st.log_level}"',
            'format = "json"',
        ]
        return "\n".join(lines) + "\n"

    async def start(self, timeout_s: float = 60.0) -> None:
        """Simulated cell, then the daemon, then ``RSI_ON``; returns once the daemon answers HTTP."""
        self.workdir.mkdir(parents=True, exist_ok=True)
        st = self.settings
        rsi_port = _free_port(socket.SOCK_DGRAM)
        self.sim = SimCellProcess(
            rsi_port=rsi_port,
            link_dir=self.workdir / "cell",
            scenario=self.scenario.source.removeprefix("preset:"),
            seed=self.seed,
            cycle_ms=st.cycle_ms,
            servo_lag_cycles=st.servo_lag_cycles,
            timeout_count=st.timeout_count,
        )
        info = self.info = await self.sim.start()
        if self.payload_kg:
            await self.sim.command(f"payload {self.payload_kg}")
        self.http_port = _free_port(socket.SOCK_STREAM)
        config = self.workdir / "daemon.toml"
        config.write_text(self._config_text(info, self.http_port, rsi_port), encoding="utf-8")
        log = self.daemon_log.open("ab")
        try:
            self.daemon = await asyncio.create_subprocess_exec(
                sys.executable,
                "-m",
                "comp_daemon",
                "run",
                "--config",
                str(config),
                "--motion",
                f"{info.motion_host}:{info.motion_port}",
                stdin=asyncio.subprocess.DEVNULL,
                stdout=log,
                stderr=log,
                preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None,
            )
        finally:
            log.close()
        self.http = httpx.AsyncClient(
            base_url=f"http://127.0.0.1:{self.http_port}",
            headers={"Authorization": f"Bearer {self.token}"},
            timeout=30.0,
        )
        deadline = time.monotonic() + timeout_s
        while True:
            if self.daemon.returncode is not None:
                raise CellError(
                    f"the daemon exited with code {self.daemon.returncode}; see {self.daemon_log}"
                )
            with contextlib.suppress(httpx.TransportError):
                if (await self.http.get("/health")).status_code == 200:
                    break
            if time.monotonic() > deadline:
                raise CellError(f"the daemon did not answer within {timeout_s:.0f} s; see {self.daemon_log}")
            await asyncio.sleep(0.1)
        await self.sim.rsi_on()
        while not (await self.api("GET", "/api/status"))["daemon"]["loop"]["running"]:
            if time.monotonic() > deadline:
                raise CellError("no RSI telegrams reached the daemon")
            await asyncio.sleep(0.1)

    async def close(self) -> None:
        """SIGTERM to the daemon (it zeroes corrections and persists its state), then the cell."""
        if self.http is not None:
            await self.http.aclose()
            self.http = None
        proc = self.daemon
        if proc is not None and proc.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)
            try:
                async with asyncio.timeout(30.0):
                    await proc.wait()
            except TimeoutError:
                with contextlib.suppress(ProcessLookupError):
                    proc.kill()
                await proc.wait()
        if proc is not None:
            self.daemon_exit_code = proc.returncode
        if self.sim is not None:
            await self.sim.stop()

    # ------------------------------------------------------------------------------ the robot program

    async def move(self, axes_deg: Sequence[float] | NDArray[np.float64], timeout_s: float = 120.0) -> None:
        """A PTP move of the robot program (no daemon involved); returns on arrival."""
        assert self.info is not None
        line = "move " + " ".join(f"{float(v):.6f}" for v in axes_deg)
        try:
            await line_command(self.info.motion_host, self.info.motion_port, line, timeout_s=timeout_s)
        except RuntimeError as exc:
            raise CellError(f"the robot refused a move: {exc}") from None

    async def controller_status(self) -> dict[str, Any]:
        assert self.info is not None
        doc: dict[str, Any] = json.loads(
            await line_command(self.info.motion_host, self.info.motion_port, "status")
        )
        return doc

    # ------------------------------------------------------------------------------ the tracker

    async def measure_mm(self) -> NDArray[np.float64]:
        """One tracker reading of the TCP, in the robot base frame (mm)."""
        assert self.sim is not None
        p_tracker = floats(await self.sim.command("measure"))
        out: NDArray[np.float64] = self._base_T_tracker[:3, :3] @ p_tracker + self._base_T_tracker[:3, 3]
        return out

    # ------------------------------------------------------------------------------ the HTTP API

    async def api(self, method: str, path: str, **kwargs: Any) -> Any:
        """One API call; returns the JSON body, raises :class:`CellError` with the API's message."""
        assert self.http is not None
        r = await self.http.request(method, path, **kwargs)
        if r.status_code >= 400:
            try:
                message = r.json().get("message", r.text)
            except ValueError:
                message = r.text
            raise CellError(f"{method} {path}: {r.status_code} {message}")
        return None if r.status_code == 204 else r.json()

    def daemon_alive(self) -> bool:
        return self.daemon is not None and self.daemon.returncode is None

    @property
    def pid(self) -> int | None:
        return None if self.daemon is None else self.daemon.pid


def environment() -> dict[str, str]:
    """The machine the trial ran on (for the report)."""
    import platform

    return {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "machine": platform.machine(),
        "processor": platform.processor() or platform.machine(),
        "cpus": str(os.cpu_count()),
    }
