"""The link between the daemon and its real-time process: framed messages over a Unix socket pair.

What goes over it (both ends import these from here, so they unpickle under the same names):

- daemon → child: requests (``("req", n, name, args)``, answered by ``("reply", n, ok, value)``) —
  ``"rsi"`` with :class:`RtStart`, then ``"loop"`` with :class:`LoopStart`, ``"samples"``,
  ``"close_rsi"``, ``"stop"``; and commands to the loop (``("cmd", seq, name, args)``, one of
  :data:`COMMANDS`, no reply: the next report says which was applied);
- child → daemon: ``("state", StateReport)``, ``("event", safety event)``, ``("log", logger
  name, level, text)``.

A frame is a 4-byte big-endian length and a pickled Python object (protocol 5). Pickle is used
because both ends are this package, started by each other over a private ``socketpair`` that no
other process can reach: the messages are the package's own frozen dataclasses (the loop's core
state, encoder readings, safety events), and pickle carries them without a second schema.

:class:`FrameDecoder` is the protocol without I/O (bytes in, messages out); :class:`LinkProtocol` is
the thin asyncio adapter both ends use. ``send`` never blocks: it queues the frame on the transport.
"""

from __future__ import annotations

import asyncio
import logging
import pickle
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, TypeVar, cast

from comp_daemon.rt.controller import JointLoopSettings
from comp_daemon.rt.encoder_reader import (
    EncoderFault,
    EncoderReaderConfig,
    EncoderReading,
    LinearGratingCalibration,
)
from comp_daemon.rt.encoder_reader import FaultKind as EncoderFaultKind
from comp_daemon.rt.grating_cal import GratingCalibration
from comp_daemon.rt.loop import FeedbackSource, LoopView
from comp_daemon.rt.rsi_server import RsiServerConfig
from comp_daemon.rt.safety import Fault, SafetySettings

__all__ = [
    "COMMANDS",
    "MAX_FRAME_BYTES",
    "RSI_COUNTERS",
    "FrameDecoder",
    "LinkError",
    "LinkProtocol",
    "LoopStart",
    "RtProcessError",
    "RtStart",
    "StateReport",
    "encode_frame",
]

MAX_FRAME_BYTES = 64 * 1024 * 1024  # a grating calibration or a latency batch is far smaller
_HEADER = struct.Struct(">I")

V = TypeVar("V", bound=LoopView)

#: the RSI endpoint's counters a state report carries, in this order
RSI_COUNTERS = (
    "received",
    "answered",
    "garbled",
    "foreign",
    "superseded",
    "handler_errors",
    "late",
    "ipoc_skipped",
    "send_errors",
    "controller_delay",
    "stale",
    "other_sender",
    "sessions",
    "session_sender",
)
#: the loop's commands the daemon may send (methods of LoopRuntime)
COMMANDS = frozenset({"arm", "release", "reset", "fault", "shutdown", "set_calibration"})


class RtProcessError(RuntimeError):
    """The real-time process failed, refused a request or has gone."""


@dataclass(frozen=True, slots=True)
class RtStart:
    """The first request: where to run, and the RSI endpoint to open."""

    rsi: RsiServerConfig
    cpu: int | None = None
    priority: int = 0
    cpu_wakeup_latency_us: int | None = None
    push_period_s: float = 0.025
    tick_s: float = 0.05
    grace_cycles: int = 3  # replies with Stop = 1 before the child closes the endpoint on its own
    log_level: int = logging.INFO


@dataclass(frozen=True, slots=True)
class LoopStart:
    """The second request: the grating readers and the loop (once the ports are known)."""

    readers: tuple[tuple[EncoderReaderConfig, LinearGratingCalibration], ...]
    calibration: GratingCalibration | None
    safety: SafetySettings
    loop: JointLoopSettings
    sen_type: str = "ImFree"
    rsi_alive_s: float = 0.5

    def build(self, cls: type[V], sources: Mapping[int, FeedbackSource], clock_ns: Callable[[], int]) -> V:
        """The loop (``LoopRuntime``, in the child) or its view (``RemoteRuntime``, in the daemon)."""
        return cls(
            sources,
            calibration=self.calibration,
            safety=self.safety,
            loop=self.loop,
            sen_type=self.sen_type,
            clock_ns=clock_ns,
            rsi_alive_s=self.rsi_alive_s,
        )


@dataclass(frozen=True, slots=True)
class StateReport:
    """The child's state as of ``now_ns``; the sample and fault fields hold what is new since the last."""

    applied: int  # sequence number of the last command applied
    now_ns: int
    core: Any  # LoopCore
    telegrams: int
    last_ipoc: int | None
    last_actual_deg: tuple[float, ...] | None
    last_setpoint_deg: tuple[float, ...] | None
    last_angles_deg: tuple[float | None, ...]
    last_stop: bool
    last_ak_deg: tuple[float, ...]
    replies_after_shutdown: int
    last_rx_ns: int | None
    readings: tuple[EncoderReading | EncoderFault, ...]
    reader_counts: tuple[tuple[int, dict[EncoderFaultKind, int], int], ...]  # joint, faults, warnings
    rsi_counters: tuple[int | str | None, ...]  # in the order of RSI_COUNTERS
    latency_ns: bytes  # new samples, array('q')
    jitter_ns: bytes
    trace: tuple[Any, ...]  # new rows of LoopRuntime.trace
    faults: tuple[Fault, ...]  # new entries of LoopRuntime.fault_log
    calibration_version: int | None


class LinkError(RuntimeError):
    """A frame that cannot be read (too long, or not a pickled message)."""


def encode_frame(message: Any) -> bytes:
    payload = pickle.dumps(message, protocol=5)
    if len(payload) > MAX_FRAME_BYTES:
        raise LinkError(f"message of {len(payload)} bytes exceeds the frame limit of {MAX_FRAME_BYTES}")
    return _HEADER.pack(len(payload)) + payload


class FrameDecoder:
    """Bytes from the stream in, whole messages out (any split of the stream into chunks)."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[Any]:
        buf = self._buf
        buf += data
        out: list[Any] = []
        pos = 0
        while len(buf) - pos >= _HEADER.size:
            (n,) = _HEADER.unpack_from(buf, pos)
            if n > MAX_FRAME_BYTES:
                raise LinkError(f"frame of {n} bytes announced; the limit is {MAX_FRAME_BYTES}")
            end = pos + _HEADER.size + n
            if len(buf) < end:
                break
            try:
                out.append(pickle.loads(memoryview(buf)[pos + _HEADER.size : end]))
            except Exception as exc:
                raise LinkError(f"unreadable frame of {n} bytes: {exc}") from exc
            pos = end
        del buf[:pos]
        return out


class LinkProtocol(asyncio.Protocol):
    """Delivers each message to ``on_message``; ``on_lost`` once when the other end has gone."""

    def __init__(
        self,
        on_message: Callable[[Any], None],
        on_lost: Callable[[Exception | None], None],
    ) -> None:
        self.on_message = on_message
        self.on_lost = on_lost
        self.transport: asyncio.Transport | None = None
        self._decoder = FrameDecoder()
        self.closed = asyncio.Event()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.Transport, transport)

    def data_received(self, data: bytes) -> None:
        try:
            messages = self._decoder.feed(data)
        except LinkError as exc:
            if self.transport is not None:
                self.transport.abort()  # connection_lost follows with the error
            self._lost(exc)
            return
        for message in messages:
            self.on_message(message)

    def connection_lost(self, exc: Exception | None) -> None:
        self.transport = None
        self._lost(exc)

    def _lost(self, exc: Exception | None) -> None:
        if not self.closed.is_set():
            self.closed.set()
            self.on_lost(exc)

    @property
    def connected(self) -> bool:
        return self.transport is not None and not self.transport.is_closing()

    def send(self, message: Any) -> bool:
        """Queue one message; False when the link is down (the message is dropped)."""
        transport = self.transport
        if transport is None or transport.is_closing():
            return False
        transport.write(encode_frame(message))
        return True

    def buffered_bytes(self) -> int:
        transport = self.transport
        return 0 if transport is None else transport.get_write_buffer_size()

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()
