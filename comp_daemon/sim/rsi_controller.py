"""A simulated KUKA robot controller speaking RSI over UDP (the exchange of :mod:`comp_daemon.rt.rsi_codec`).

The controller is the UDP client. Its interpolation cycle (``cycle_ms``: 12 with ``#IPO``, 4 with
``#IPO_FAST``) runs on an absolute schedule (``loop.call_at(t0 + k·cycle)``; a late wake-up skips
whole cycles and counts an ``overrun`` instead of drifting). In cycle k it

1. judges the reply to telegram k−1: it must have arrived (before this cycle started), parse, carry
   the configured ``sen_type`` and echo IPOC k−1; otherwise the reply is *late* (``Delay`` + 1) and,
   with ``holdon``, the last valid ``AK`` is used again (the ETHERNET object holds its outputs;
   without ``holdon`` they fall to zero). When the late count reaches ``timeout_count`` RSI stops.
2. applies ``AK``: in ``relative`` mode (``RSI_ON(#RELATIVE)``) it is a step added to the total
   correction, in ``absolute`` mode the total itself. The total is clipped per axis to
   ``axiscorr_min_deg``..``axiscorr_max_deg`` (AXISCORR); if it then exceeds
   ``axiscorrmon_max_deg`` in magnitude (AXISCORRMON) RSI stops. ``Stop=1`` stops RSI as well.
3. passes the total to the servo through a ``servo_lag_cycles`` delay line: the ``AK`` of the reply to
   telegram j first shows in the ``AIPos`` of telegram j + 1 + ``servo_lag_cycles``.
4. advances the plant by the elapsed cycles, then sends telegram k: ``IPOC = ipoc_start + k·cycle_ms``,
   ``AIPos`` (actual axes incl. corrections), ``ASPos`` (setpoint without corrections), ``Delay`` and,
   if a ``pose_fn`` is given, ``RIst``/``RSol``.

A stop (Timeout, Stop=1, AXISCORRMON) ends the telegrams, halts the plant's motion where it is (a
pending :meth:`move_to` raises :class:`RobotStoppedError`) and keeps the correction (no jump);
:meth:`rsi_off` ends the telegrams only; :meth:`rsi_on` starts a new RSI session. Each stop is
kept (:class:`RsiStop`: when, :class:`StopCause`, the message, telegrams and late replies of the
session). With ``rearm_after_s`` the controller re-arms RSI as an operator does on the line
(acknowledge the message, re-select and start the program): ``rearm_after_s`` after a stop that was
not ``RSI_OFF`` or the controller's shutdown, the next cycle starts a new session (``rsi_on``). On
the wire that is what a restart looks like: telegrams cease, then come again with ``Delay`` 0 and
an ``IPOC`` that has kept counting (the controller's clock ran on meanwhile).
Motion: :meth:`move_to` starts a PTP move in the plant and waits for arrival; :meth:`serve_commands`
offers the same over a line-based TCP port.

The plant is any :class:`JointStateSource` (``comp_daemon.sim.plant`` provides the physical one).
Units: axis values and corrections in degrees (A1..A6), times in seconds on the loop clock.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import json
import socket
import time
from collections import deque
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from comp_daemon.common.logs import get_logger
from comp_daemon.rt.rsi_codec import RsiProtocolError, SenReply, build_rob, parse_sen

__all__ = [
    "JointStateSource",
    "RobotStoppedError",
    "RsiControllerConfig",
    "RsiControllerStats",
    "RsiState",
    "RsiStop",
    "SimulatedRsiController",
    "StopCause",
    "serve_lines",
]

log = get_logger(__name__)

Axes = NDArray[np.float64]
_SHUTDOWN = "controller shut down"
PoseFn = Callable[[Axes], Sequence[float]]


class JointStateSource(Protocol):
    """The robot plant as the controller sees it. Arrays are shape (6,), degrees, A1..A6."""

    def advance(self, dt_s: float) -> None:
        """Advance the plant (motion, servo, thermal state…) by ``dt_s`` seconds."""

    def axis_setpoint_deg(self) -> Axes:
        """The interpolator's setpoint without RSI corrections (``ASPos``)."""
        ...

    def axis_actual_deg(self) -> Axes:
        """The measured (motor-side) axis values including applied corrections (``AIPos``)."""
        ...

    def apply_correction(self, correction_deg: Axes) -> None:
        """Set the total RSI correction in effect at the servo from now on (absolute, not a step)."""

    def start_move(self, target_axes_deg: Axes) -> None:
        """Start a PTP move (trapezoid velocity profile) of the setpoint to ``target_axes_deg``."""

    def in_motion(self) -> bool:
        """True while a move started by :meth:`start_move` has not arrived."""
        ...

    def halt(self) -> None:
        """Stop the current move where it is (the robot stops on an RSI error)."""


class RsiState(enum.StrEnum):
    OFF = "off"  # before the first RSI_ON
    RUNNING = "running"
    STOPPED = "stopped"


class StopCause(enum.StrEnum):
    """Why RSI stopped, as the controller's message window says it."""

    LATE_REPLIES = "late_replies"  # ETHERNET Timeout: the late-reply count reached its limit
    SENSOR_STOP = "sensor_stop"  # Stop=1 in a reply (the sensor asked for the stop)
    AXISCORRMON = "axiscorrmon"  # the total correction exceeded its monitored maximum
    INTERNAL_ERROR = "internal_error"  # the controller's own cycle failed
    RSI_OFF = "rsi_off"  # RSI_OFF in the robot program
    SHUTDOWN = "shutdown"  # the controller itself shut down


#: stops after which an operator restarts the program (not RSI_OFF, not the controller's shutdown)
_REARMABLE = frozenset(
    {StopCause.LATE_REPLIES, StopCause.SENSOR_STOP, StopCause.AXISCORRMON, StopCause.INTERNAL_ERROR}
)


@dataclass(frozen=True, slots=True)
class RsiStop:
    """One end of an RSI session: ``time`` in UNIX seconds; ``telegrams`` and ``late`` of the session."""

    session: int
    time: float
    ipoc: int
    cause: StopCause
    reason: str
    telegrams: int
    late: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "session": self.session,
            "time": round(self.time, 3),
            "ipoc": self.ipoc,
            "cause": str(self.cause),
            "reason": self.reason,
            "telegrams": self.telegrams,
            "late": self.late,
        }


class RobotStoppedError(RuntimeError):
    """A motion ended because the robot stopped (RSI error or stop request)."""


def _six(values: Sequence[float] | float, name: str) -> tuple[float, ...]:
    arr = np.broadcast_to(np.asarray(values, dtype=float), (6,))
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {values!r}")
    return tuple(float(v) for v in arr)


@dataclass(frozen=True)
class RsiControllerConfig:
    server_host: str = "127.0.0.1"
    server_port: int = 49152
    local_host: str = "127.0.0.1"  # address the telegrams are sent from
    local_port: int = 0
    cycle_ms: int = 12  # 12 (#IPO) or 4 (#IPO_FAST)
    timeout_count: int = 10  # ETHERNET Timeout: late replies before RSI stops
    holdon: bool = True  # ETHERNET HOLDON: hold the last AK while a reply is late
    mode: Literal["relative", "absolute"] = "relative"
    servo_lag_cycles: int = 1
    axiscorr_min_deg: tuple[float, ...] = (-5.0,) * 6
    axiscorr_max_deg: tuple[float, ...] = (5.0,) * 6
    axiscorrmon_max_deg: tuple[float, ...] | None = None  # None: no AXISCORRMON object
    sen_type: str = "ImFree"
    rob_type: str = "KUKA"
    ipoc_start: int = 1_000_000
    decimals: int = 4
    rearm_after_s: float | None = None  # restart RSI this long after a stop (None: stay stopped)

    def __post_init__(self) -> None:
        if self.cycle_ms not in (4, 12):
            raise ValueError(f"cycle_ms must be 4 (#IPO_FAST) or 12 (#IPO), got {self.cycle_ms}")
        if self.timeout_count < 1:
            raise ValueError(f"timeout_count must be at least 1, got {self.timeout_count}")
        if self.rearm_after_s is not None and not (0.0 <= self.rearm_after_s < float("inf")):
            raise ValueError(f"rearm_after_s must be a finite time >= 0 s, got {self.rearm_after_s}")
        if self.mode not in ("relative", "absolute"):
            raise ValueError(f"mode must be 'relative' or 'absolute', got {self.mode!r}")
        if not 0 <= self.servo_lag_cycles <= 10:
            raise ValueError(f"servo_lag_cycles must be 0..10, got {self.servo_lag_cycles}")
        lo = _six(self.axiscorr_min_deg, "axiscorr_min_deg")
        hi = _six(self.axiscorr_max_deg, "axiscorr_max_deg")
        if any(a > 0 or b < 0 for a, b in zip(lo, hi, strict=True)):
            raise ValueError("need axiscorr_min_deg <= 0 <= axiscorr_max_deg per axis")
        object.__setattr__(self, "axiscorr_min_deg", lo)
        object.__setattr__(self, "axiscorr_max_deg", hi)
        if self.axiscorrmon_max_deg is not None:
            mon = _six(self.axiscorrmon_max_deg, "axiscorrmon_max_deg")
            if any(m <= 0 for m in mon):
                raise ValueError("axiscorrmon_max_deg must be positive per axis")
            object.__setattr__(self, "axiscorrmon_max_deg", mon)


@dataclass
class RsiControllerStats:
    telegrams_sent: int = 0
    replies_ok: int = 0
    late: int = 0  # late or missing replies in the current RSI session (the Delay value)
    late_total: int = 0
    garbled: int = 0  # replies that did not parse or had the wrong Type
    mismatched: int = 0  # replies for another IPOC, or a second reply to the same one
    axiscorr_limited: int = 0  # cycles in which AXISCORR clipped the total
    overruns: int = 0  # wake-ups more than a cycle late (cycles skipped)
    send_errors: int = 0
    sessions: int = 0
    rearms: int = 0  # sessions started by the re-arm (rearm_after_s), not by rsi_on
    history: deque[str] = field(default_factory=lambda: deque(maxlen=32))
    stops: deque[RsiStop] = field(default_factory=lambda: deque(maxlen=32))


class _ControllerProtocol(asyncio.DatagramProtocol):
    def __init__(self, owner: SimulatedRsiController) -> None:
        self.owner = owner

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        self.owner._on_reply(data)

    def error_received(self, exc: Exception) -> None:
        self.owner.stats.send_errors += 1


class SimulatedRsiController:
    """The simulated KR C4 RSI side; see the module docstring."""

    def __init__(
        self,
        config: RsiControllerConfig,
        source: JointStateSource,
        *,
        pose_fn: PoseFn | None = None,
        clock: Callable[[], float] | None = None,
    ) -> None:
        """``clock`` (seconds) times the re-arm; by default the event loop's clock."""
        self.config = config
        self.source = source
        self.pose_fn = pose_fn
        self.clock = clock
        self.state = RsiState.OFF
        self.stop_reason: str | None = None
        self.stop_cause: StopCause | None = None
        self.rearm_at: float | None = None  # when the re-arm is due (``clock`` seconds), or None
        self._session_telegrams = 0  # telegrams_sent when the session started
        self.stats = RsiControllerStats()
        self.total_correction_deg = np.zeros(6)
        self._lo = np.asarray(config.axiscorr_min_deg)
        self._hi = np.asarray(config.axiscorr_max_deg)
        self._mon = None if config.axiscorrmon_max_deg is None else np.asarray(config.axiscorrmon_max_deg)
        self._last_ak = np.zeros(6)
        self._pending_ipoc: int | None = None
        self._reply: SenReply | None = None
        self._servo: deque[Axes] = deque(maxlen=config.servo_lag_cycles + 1)
        self._transport: asyncio.DatagramTransport | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._t0 = 0.0
        self._k = 0  # index of the next cycle
        self._last_k = 0
        self._move: asyncio.Future[None] | None = None
        self._servers: list[asyncio.Server] = []

    # lifecycle -------------------------------------------------------------------------------------

    @property
    def cycle_s(self) -> float:
        return self.config.cycle_ms / 1000.0

    @property
    def local_address(self) -> tuple[str, int]:
        if self._transport is None:
            raise RuntimeError("controller not started")
        host, port = self._transport.get_extra_info("sockname")[:2]
        return str(host), int(port)

    @property
    def ipoc(self) -> int:
        """IPOC of the latest cycle."""
        return self.config.ipoc_start + self._last_k * self.config.cycle_ms

    async def start(self, *, rsi_on: bool = True) -> None:
        """Open the UDP socket, start the interpolation cycle and (by default) RSI."""
        if self._transport is not None:
            return
        loop = asyncio.get_running_loop()
        self._loop = loop
        cfg = self.config
        transport, _ = await loop.create_datagram_endpoint(
            lambda: _ControllerProtocol(self),
            local_addr=(cfg.local_host, cfg.local_port),
            remote_addr=(cfg.server_host, cfg.server_port),  # connected: only the server's replies arrive
            family=socket.AF_INET,
        )
        self._transport = transport
        self.source.apply_correction(self.total_correction_deg.copy())
        self._t0 = loop.time()
        self._k = self._last_k = 0
        if rsi_on:
            self.rsi_on()
        self._timer = loop.call_at(self._t0, self._tick)

    async def close(self) -> None:
        """Stop RSI and the cycle, close the UDP socket and the command ports."""
        if self.state is RsiState.RUNNING:
            self._stop(_SHUTDOWN, StopCause.SHUTDOWN)
        self.rearm_at = None
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        for server in self._servers:
            server.close()
            await server.wait_closed()
        self._servers.clear()
        if self._transport is not None:
            self._transport.close()
            self._transport = None
        if self._move is not None and not self._move.done():
            self._move.set_exception(RobotStoppedError(_SHUTDOWN))
            self._move.exception()  # retrieved here if nobody awaits it
        self._move = None

    def rsi_on(self) -> None:
        """``RSI_ON``: start a session (late count 0, AK held 0, correction kept)."""
        if self.state is RsiState.RUNNING:
            return
        self.state = RsiState.RUNNING
        self.stop_reason = None
        self.stop_cause = None
        self.rearm_at = None
        self.stats.late = 0
        self.stats.sessions += 1
        self._session_telegrams = self.stats.telegrams_sent
        self._last_ak = np.zeros(6)
        self._pending_ipoc = None
        self._reply = None

    def rsi_off(self) -> None:
        """``RSI_OFF`` from the robot program."""
        self.rearm_at = None
        if self.state is RsiState.RUNNING:
            self._stop("RSI_OFF", StopCause.RSI_OFF)

    def now(self) -> float:
        """The re-arm clock (seconds): ``clock`` if given, else the event loop's."""
        if self.clock is not None:
            return self.clock()
        return self._loop.time() if self._loop is not None else time.monotonic()

    # motion ----------------------------------------------------------------------------------------

    async def move_to(self, axes_deg: Sequence[float]) -> None:
        """PTP move of the plant to ``axes_deg``; returns on arrival, raises RobotStoppedError on a stop."""
        if self._loop is None or self._timer is None:
            raise RuntimeError("controller not started")
        target = np.asarray(axes_deg, dtype=float)
        if target.shape != (6,) or not np.all(np.isfinite(target)):
            raise ValueError(f"move target must be 6 finite axis values (deg), got {axes_deg!r}")
        if self._move is not None and not self._move.done():
            raise RuntimeError("a motion is in progress")
        self._move = self._loop.create_future()
        self.source.start_move(target)
        await self._move

    # cycle -----------------------------------------------------------------------------------------

    def _tick(self) -> None:
        loop = self._loop
        assert loop is not None
        cycle = self.cycle_s
        k = self._k
        behind = int((loop.time() - (self._t0 + k * cycle)) / cycle)
        if behind >= 1:
            self.stats.overruns += 1
            k += behind
        steps = max(1, k - self._last_k) if k > 0 else 1
        self._last_k = k
        self._k = k + 1
        self._timer = loop.call_at(self._t0 + self._k * cycle, self._tick)
        try:
            self._cycle(k, steps)
        except Exception:  # a plant bug must not kill the interpolation cycle silently
            log.exception("rsi controller: cycle failed", cycle=k)
            self._stop("internal error in the controller cycle", StopCause.INTERNAL_ERROR)

    def _cycle(self, k: int, steps: int) -> None:
        if self.state is RsiState.STOPPED and self.rearm_at is not None and self.now() >= self.rearm_at:
            log.info(
                "rsi controller: RSI re-armed", after_s=self.config.rearm_after_s, cause=str(self.stop_cause)
            )
            self.stats.rearms += 1
            self.rsi_on()
        if self.state is RsiState.RUNNING and self._pending_ipoc is not None:
            self._judge_reply()
        for _ in range(min(steps, self.config.servo_lag_cycles + 1)):
            self._servo.append(self.total_correction_deg.copy())
        self.source.apply_correction(self._servo[0])
        self.source.advance(steps * self.cycle_s)
        move = self._move
        if move is not None and not move.done() and not self.source.in_motion():
            move.set_result(None)
        if self.state is RsiState.RUNNING:
            self._send(self.config.ipoc_start + k * self.config.cycle_ms)

    def _judge_reply(self) -> None:
        cfg = self.config
        stats = self.stats
        reply, self._reply = self._reply, None
        self._pending_ipoc = None
        if reply is None:
            stats.late += 1
            stats.late_total += 1
            ak = self._last_ak if cfg.holdon else np.zeros(6)
            if stats.late >= cfg.timeout_count:
                self._apply(ak)
                if self.state is RsiState.RUNNING:
                    self._stop(
                        f"Timeout: {stats.late} late replies (limit {cfg.timeout_count})",
                        StopCause.LATE_REPLIES,
                    )
                return
        else:
            stats.replies_ok += 1
            if reply.stop:
                self._stop("Stop=1 from the sensor", StopCause.SENSOR_STOP)
                return
            ak = np.asarray(reply.ak_deg, dtype=float)
            self._last_ak = ak
        self._apply(ak)

    def _apply(self, ak: Axes) -> None:
        requested = self.total_correction_deg + ak if self.config.mode == "relative" else ak.copy()
        total = np.clip(requested, self._lo, self._hi)
        if not np.array_equal(total, requested):
            self.stats.axiscorr_limited += 1
        self.total_correction_deg = total
        mon = self._mon
        if mon is not None and np.any(np.abs(total) > mon):
            axes = ", ".join(f"A{i + 1}={total[i]:+.6f}" for i in np.flatnonzero(np.abs(total) > mon))
            self._stop(f"AXISCORRMON: total correction beyond its maximum ({axes})", StopCause.AXISCORRMON)

    def _send(self, ipoc: int) -> None:
        transport = self._transport
        if transport is None:
            return
        actual: list[float] = np.asarray(self.source.axis_actual_deg(), dtype=float).tolist()
        setpoint: list[float] = np.asarray(self.source.axis_setpoint_deg(), dtype=float).tolist()
        rist = rsol = None
        if self.pose_fn is not None:
            rist, rsol = self.pose_fn(np.asarray(actual)), self.pose_fn(np.asarray(setpoint))
        cfg = self.config
        datagram = build_rob(
            ipoc, actual, setpoint, rist, rsol, self.stats.late, rob_type=cfg.rob_type, decimals=cfg.decimals
        )
        transport.sendto(datagram)
        self.stats.telegrams_sent += 1
        self._pending_ipoc = ipoc
        self._reply = None

    def _on_reply(self, data: bytes) -> None:
        stats = self.stats
        try:
            reply = parse_sen(data)
        except RsiProtocolError as exc:
            stats.garbled += 1
            stats.history.append(f"garbled reply: {exc.reason}")
            return
        if reply.sen_type != self.config.sen_type:
            stats.garbled += 1
            stats.history.append(f"reply Type {reply.sen_type!r}, expected {self.config.sen_type!r}")
            return
        if self._pending_ipoc is None or reply.ipoc != self._pending_ipoc or self._reply is not None:
            stats.mismatched += 1
            return
        self._reply = reply

    def _stop(self, reason: str, cause: StopCause) -> None:
        stats = self.stats
        self.state = RsiState.STOPPED
        self.stop_reason = reason
        self.stop_cause = cause
        self._pending_ipoc = None
        self._reply = None
        stats.history.append(f"RSI stopped at IPOC {self.ipoc}: {reason}")
        stats.stops.append(
            RsiStop(
                session=stats.sessions,
                time=time.time(),
                ipoc=self.ipoc,
                cause=cause,
                reason=reason,
                telegrams=stats.telegrams_sent - self._session_telegrams,
                late=stats.late,
            )
        )
        after = self.config.rearm_after_s
        self.rearm_at = self.now() + after if after is not None and cause in _REARMABLE else None
        if cause is StopCause.RSI_OFF:  # a program statement: the motion goes on without RSI
            log.info("rsi controller: RSI_OFF", ipoc=self.ipoc)
            return
        report = log.info if cause is StopCause.SHUTDOWN else log.warning
        report("rsi controller: RSI stopped", ipoc=self.ipoc, reason=reason)
        self.source.halt()
        move = self._move
        if move is not None and not move.done():
            move.set_exception(RobotStoppedError(reason))

    # status and command port -----------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        s = self.stats
        rearm_in = None if self.rearm_at is None else max(0.0, self.rearm_at - self.now())
        return {
            "state": str(self.state),
            "stop_reason": self.stop_reason,
            "stop_cause": None if self.stop_cause is None else str(self.stop_cause),
            "sessions": s.sessions,
            "rearms": s.rearms,
            "rearm_after_s": self.config.rearm_after_s,
            "rearm_in_s": None if rearm_in is None else round(rearm_in, 3),
            "stops": [stop.to_dict() for stop in s.stops],
            "ipoc": self.ipoc,
            "cycle_ms": self.config.cycle_ms,
            "moving": self._move is not None and not self._move.done(),
            "axis_actual_deg": [round(float(v), 6) for v in self.source.axis_actual_deg()],
            "axis_setpoint_deg": [round(float(v), 6) for v in self.source.axis_setpoint_deg()],
            "total_correction_deg": [round(float(v), 6) for v in self.total_correction_deg],
            "telegrams_sent": s.telegrams_sent,
            "replies_ok": s.replies_ok,
            "late": s.late,
            "late_total": s.late_total,
            "garbled": s.garbled,
            "mismatched": s.mismatched,
            "axiscorr_limited": s.axiscorr_limited,
            "overruns": s.overruns,
        }

    async def serve_commands(self, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        """Line-based TCP command port; returns its (host, port).

        Commands (one per line, answers ``OK …`` or ``ERR <reason>``): ``move A1 A2 A3 A4 A5 A6``
        (answers on arrival), ``rsi_on``, ``rsi_off``, ``status`` (``OK <json>``).
        """
        server = await asyncio.start_server(self._serve_client, host, port)
        self._servers.append(server)
        sockname = server.sockets[0].getsockname()
        return str(sockname[0]), int(sockname[1])

    async def _serve_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await serve_lines(reader, writer, self._command)

    async def _command(self, line: str) -> str:
        words = line.split()
        if not words:
            return "ERR empty command"
        name, args = words[0].lower(), words[1:]
        try:
            if name == "move":
                if len(args) != 6:
                    return f"ERR move needs 6 axis values (deg), got {len(args)}"
                await self.move_to([float(a) for a in args])
                return "OK arrived"
            if name == "rsi_on" and not args:
                self.rsi_on()
                return "OK"
            if name == "rsi_off" and not args:
                self.rsi_off()
                return "OK"
            if name == "status" and not args:
                return "OK " + json.dumps(self.status())
        except (ValueError, RuntimeError) as exc:
            return f"ERR {exc}"
        return f"ERR unknown command {line[:40]!r}"


async def serve_lines(
    reader: asyncio.StreamReader, writer: asyncio.StreamWriter, handle: Callable[[str], Awaitable[str]]
) -> None:
    """Serve one client of a line port: each line in, ``await handle(line)`` out, until it hangs up."""
    try:
        while line := await reader.readline():
            answer = await handle(line.decode("utf-8", "replace").strip())
            writer.write(answer.encode() + b"\n")
            await writer.drain()
    except (ConnectionError, asyncio.IncompleteReadError):
        pass
    finally:
        writer.close()
        with contextlib.suppress(ConnectionError):
            await writer.wait_closed()
