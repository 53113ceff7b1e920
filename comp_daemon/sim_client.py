"""The handle on the simulated cell: start it as a child process, read what it reports, stop it.

The cell itself (hidden robot, simulated KR C4, grating converters on pseudo-terminals, laser
tracker) is :mod:`comp_daemon.sim.cell`; this module starts it by module name
(``python -m comp_daemon.sim.cell …``) and imports nothing of the simulator, so the daemon
(``comp-daemon run --sim``) and the trial can bring a cell up while only the child loads the
simulator. It sits in a layer of its own, below :mod:`comp_daemon.sim` (whose child prints the
start-up line defined here) and outside it (the daemon, the trial and the commands import it, never
the simulator). The child prints one JSON line on stdout once it is up (:class:`SimCellInfo`), then
serves line ports on 127.0.0.1 (:func:`line_command`):

- motion (the controller's command port): ``move A1 … A6``, ``rsi_on``, ``rsi_off``, ``status``
  (:meth:`SimCellProcess.controller_status`: the RSI state and the stops with their causes);
- cell: ``measure``, ``tcp``, ``joints``, ``fault J KIND``, ``clear J``, ``unplug J``,
  ``replug J``, ``payload KG``, ``status``.

The scenario presets are the TOML files packaged in ``comp_daemon/sim/scenarios/``:
:func:`preset_scenarios` lists them and :func:`check_scenario` refuses a name that is neither a
preset nor a readable file, both without loading the simulator.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import signal
import sys
from dataclasses import asdict, dataclass
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "CELL_MODULE",
    "SimCellInfo",
    "SimCellProcess",
    "check_scenario",
    "floats",
    "line_command",
    "preset_scenarios",
]

#: The module the child runs (``python -m``).
CELL_MODULE = "comp_daemon.sim.cell"


@cache
def preset_scenarios() -> tuple[str, ...]:
    """Names of the packaged scenario presets (``comp_daemon/sim/scenarios/NAME.toml``), sorted."""
    folder = resources.files("comp_daemon").joinpath("sim/scenarios")
    return tuple(sorted(p.name.removesuffix(".toml") for p in folder.iterdir() if p.name.endswith(".toml")))


def check_scenario(name_or_path: str) -> None:
    """Raise ValueError unless ``name_or_path`` is a preset or a readable file (the child parses it)."""
    if name_or_path in preset_scenarios() or Path(name_or_path).is_file():
        return
    raise ValueError(
        f"scenario '{name_or_path}': neither a preset ({', '.join(preset_scenarios())}) nor a readable file"
    )


@dataclass(frozen=True, slots=True)
class SimCellInfo:
    """What the child reported when it came up."""

    pid: int
    motion_host: str
    motion_port: int
    cell_host: str
    cell_port: int
    rsi_local_port: int
    gratings: dict[int, str]  # joint (1-based) -> serial port path (symlink)
    radius_mm: float
    zero_deg: float
    resolution_nm: float
    bits: int
    home_deg: tuple[float, ...]
    cycle_ms: int

    def to_json(self) -> str:
        """The child's ready line (one line of JSON)."""
        doc = asdict(self)
        doc["gratings"] = {str(j): path for j, path in self.gratings.items()}
        return json.dumps(doc)

    @classmethod
    def from_json(cls, line: str | bytes) -> SimCellInfo:
        """Parse the child's ready line."""
        doc = json.loads(line)
        return cls(
            pid=int(doc["pid"]),
            motion_host=str(doc["motion_host"]),
            motion_port=int(doc["motion_port"]),
            cell_host=str(doc["cell_host"]),
            cell_port=int(doc["cell_port"]),
            rsi_local_port=int(doc["rsi_local_port"]),
            gratings={int(k): str(v) for k, v in doc["gratings"].items()},
            radius_mm=float(doc["radius_mm"]),
            zero_deg=float(doc["zero_deg"]),
            resolution_nm=float(doc["resolution_nm"]),
            bits=int(doc["bits"]),
            home_deg=tuple(float(v) for v in doc["home_deg"]),
            cycle_ms=int(doc["cycle_ms"]),
        )


class SimCellProcess:
    """Starts, talks to and stops the child; use from an event loop (the daemon's, the trial's)."""

    def __init__(
        self,
        *,
        rsi_port: int,
        link_dir: Path,
        scenario: str = "kr210-cell",
        seed: int = 0,
        cycle_ms: int = 12,
        servo_lag_cycles: int = 1,
        timeout_count: int = 10,
        sen_type: str = "ImFree",
        rearm_after_s: float | None = None,
        start_timeout_s: float = 30.0,
    ) -> None:
        """``rearm_after_s``: the simulated controller restarts RSI this long after a stop (None: never)."""
        self.argv = [
            sys.executable,
            "-m",
            CELL_MODULE,
            "--scenario",
            scenario,
            "--seed",
            str(seed),
            "--rsi-port",
            str(rsi_port),
            "--cycle-ms",
            str(cycle_ms),
            "--servo-lag-cycles",
            str(servo_lag_cycles),
            "--timeout-count",
            str(timeout_count),
            "--sen-type",
            sen_type,
            "--link-dir",
            str(link_dir),
            "--exit-with-parent",
        ]
        if rearm_after_s is not None:
            self.argv += ["--rearm-after-s", repr(float(rearm_after_s))]
        self.start_timeout_s = start_timeout_s
        self.proc: asyncio.subprocess.Process | None = None
        self.info: SimCellInfo | None = None

    async def start(self) -> SimCellInfo:
        self.proc = await asyncio.create_subprocess_exec(
            *self.argv, stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE
        )
        assert self.proc.stdout is not None
        try:
            async with asyncio.timeout(self.start_timeout_s):
                line = await self.proc.stdout.readline()
        except TimeoutError:
            await self.stop()
            raise RuntimeError(f"the simulated cell did not start within {self.start_timeout_s} s") from None
        if not line:
            code = await self.proc.wait()
            raise RuntimeError(f"the simulated cell exited with code {code} before it was ready")
        self.info = SimCellInfo.from_json(line)
        return self.info

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.returncode is None

    async def command(self, line: str, *, timeout_s: float = 10.0) -> str:
        """One command on the cell port; returns the text after ``OK`` or raises RuntimeError."""
        if self.info is None:
            raise RuntimeError("the simulated cell is not running")
        return await line_command(self.info.cell_host, self.info.cell_port, line, timeout_s=timeout_s)

    async def controller_status(self, *, timeout_s: float = 5.0) -> dict[str, Any]:
        """The simulated controller's ``status`` (state, stop cause, the stops of its sessions…)."""
        if self.info is None:
            raise RuntimeError("the simulated cell is not running")
        answer = await line_command(
            self.info.motion_host, self.info.motion_port, "status", timeout_s=timeout_s
        )
        doc: dict[str, Any] = json.loads(answer)
        return doc

    async def rsi_on(self) -> None:
        """``RSI_ON`` in the robot program: the controller starts sending telegrams."""
        if self.info is None:
            raise RuntimeError("the simulated cell is not running")
        await line_command(self.info.motion_host, self.info.motion_port, "rsi_on")

    async def stop(self, timeout_s: float = 5.0) -> int | None:
        proc = self.proc
        if proc is None:
            return None
        if proc.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)
            try:
                async with asyncio.timeout(timeout_s):
                    await proc.wait()
            except TimeoutError:
                with contextlib.suppress(ProcessLookupError):
                    proc.kill()
                await proc.wait()
        if proc.stdin is not None:
            proc.stdin.close()
        return proc.returncode


async def line_command(host: str, port: int, line: str, *, timeout_s: float = 10.0) -> str:
    """Send one line on a fresh connection and return the answer after ``OK`` (``ERR`` raises)."""
    async with asyncio.timeout(timeout_s):
        reader, writer = await asyncio.open_connection(host, port)
        try:
            writer.write(line.encode() + b"\n")
            await writer.drain()
            answer = (await reader.readline()).decode("utf-8", "replace").strip()
        finally:
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()
    if answer == "OK" or answer.startswith("OK "):
        return answer[3:]
    raise RuntimeError(answer.removeprefix("ERR ").strip() or "no answer")


def floats(text: str) -> NDArray[np.float64]:
    """The numbers of an answer such as ``measure``'s ``x y z``."""
    return np.array([float(v) for v in text.split()], dtype=float)
