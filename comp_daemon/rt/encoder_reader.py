"""The daemon's reader of one grating converter on its serial port (pyserial-asyncio-fast).

One :class:`EncoderReader` per converter runs one asyncio task: open the port, configure it
(``0`` streaming off, ``B26``/``B32``, ``v`` identification, ``s`` serial number), then poll a raw
frame (``4``) every ``poll_ms`` on an absolute schedule, check CRC6 and nE/nW itself
(:mod:`comp_daemon.rt.biss`) and keep the latest good reading with its receive time. When the port
fails or vanishes the reader closes it and tries again with exponential back-off
(``backoff_initial_ms`` doubling up to ``backoff_max_ms``) until the device is back.

Polling phase: with :attr:`EncoderReader.next_telegram_ns` set (the daemon gives it the loop
runtime's forecast of the next RSI telegram), each poll is timed ``poll_lead_ms`` before the
telegram is due. The serial exchange is then over before the telegram arrives, so the two never
compete for the real-time loop, and the reading the controller uses is ``poll_lead_ms`` old at
most, every cycle alike. Without a forecast (no telegrams) the reader keeps its own schedule.

Units: times are integer nanoseconds from an injectable clock (``time.perf_counter_ns`` by default),
settings are named with their unit; angles are degrees in controller axis values (A1..A6), counts
are scale counts (50 nm). Counts become angles through a pluggable :class:`Calibration`
(anything with ``angle_deg(count) -> float``, e.g. ``comp_daemon.rt.grating_cal.JointGratingMap``);
:class:`LinearGratingCalibration` is the nominal map ``count·resolution/radius + zero``.

:meth:`EncoderReader.reading` never returns a bad value: it returns an :class:`EncoderReading`, or an
:class:`EncoderFault` saying why not (device gone, the latest frame had a bad CRC / error bit / was
garbage, nothing read yet, or the latest good reading is older than ``stale_after_ms`` — ``silent``
when the converter stopped answering, ``stale`` otherwise). A warning bit (nW = 0) keeps the reading
valid and sets its ``warning`` flag. ``fault_counts`` counts fault events per kind (one per poll).
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import serial_asyncio_fast

from comp_daemon.common.logs import get_logger
from comp_daemon.rt.biss import (
    REQ_FRAME,
    REQ_IDENT,
    REQ_SERIAL,
    REQ_STREAM_OFF,
    RESOLUTION_NM,
    SUPPORTED_BITS,
    BissProtocolError,
    LineReader,
    parse_frame_reply,
    parse_ident_reply,
    parse_ok_reply,
    request_bit_length,
)

__all__ = [
    "Calibration",
    "EncoderFault",
    "EncoderReader",
    "EncoderReaderConfig",
    "EncoderReading",
    "FaultKind",
    "LinearGratingCalibration",
]

log = get_logger(__name__)

Clock = Callable[[], int]


class Calibration(Protocol):
    """Counts → joint angle (deg, controller axis values)."""

    def angle_deg(self, count: int) -> float: ...


@dataclass(frozen=True, slots=True)
class LinearGratingCalibration:
    """Nominal map: ``angle_deg = degrees(count·resolution_nm·1e-6 / radius_mm)·sign + zero_deg``."""

    radius_mm: float
    zero_deg: float = 0.0
    resolution_nm: float = RESOLUTION_NM
    sign: float = 1.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.radius_mm) and self.radius_mm > 0):
            raise ValueError(f"radius_mm must be positive, got {self.radius_mm}")
        if not (math.isfinite(self.resolution_nm) and self.resolution_nm > 0):
            raise ValueError(f"resolution_nm must be positive, got {self.resolution_nm}")
        if self.sign not in (1.0, -1.0):
            raise ValueError(f"sign must be +1 or -1, got {self.sign}")

    @property
    def slope_deg_per_count(self) -> float:
        return self.sign * math.degrees(self.resolution_nm * 1e-6 / self.radius_mm)

    def angle_deg(self, count: int) -> float:
        return count * self.slope_deg_per_count + self.zero_deg


class FaultKind(enum.StrEnum):
    NO_DATA = "no_data"  # connected, nothing read yet
    STALE = "stale"  # the latest good reading is older than stale_after_ms
    SILENT = "silent"  # stale because the converter stopped answering (a timed-out poll)
    CRC = "crc"  # the latest frame failed its CRC6
    ERROR_BIT = "error_bit"  # the latest frame had nE = 0
    GARBLED = "garbled"  # the latest reply was not a frame
    GONE = "gone"  # the port is closed or has vanished


@dataclass(frozen=True, slots=True)
class EncoderReading:
    joint: int
    angle_deg: float
    count: int
    t_ns: int  # clock time the frame arrived
    age_ns: int  # at the time of the query
    warning: bool  # nW = 0: position valid, scale needs attention


@dataclass(frozen=True, slots=True)
class EncoderFault:
    joint: int
    kind: FaultKind
    detail: str
    last_good_age_ns: int | None  # None: no good reading since (re)connecting


@dataclass(frozen=True, slots=True)
class EncoderReaderConfig:
    port: str  # device path, e.g. /dev/serial/by-id/… or a pty symlink
    joint: int  # 1..6 (A1..A6)
    bits: int = 26
    baudrate: int = 115200
    poll_ms: float = 12.0
    reply_timeout_ms: float = 8.0  # per request; must not exceed poll_ms
    poll_lead_ms: float = 3.0  # poll this long before the next telegram is due (with a forecast)
    stale_after_ms: float = 36.0
    init_timeout_ms: float = 200.0  # per configuration request after opening
    open_timeout_ms: float = 2000.0
    backoff_initial_ms: float = 50.0
    backoff_max_ms: float = 2000.0

    def __post_init__(self) -> None:
        if not 1 <= self.joint <= 6:
            raise ValueError(f"joint must be 1..6, got {self.joint}")
        if self.bits not in SUPPORTED_BITS:
            raise ValueError(f"bits must be one of {SUPPORTED_BITS}, got {self.bits}")
        for name in ("poll_ms", "reply_timeout_ms", "stale_after_ms", "init_timeout_ms", "open_timeout_ms"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if not 0 < self.poll_lead_ms < self.poll_ms:
            raise ValueError(
                f"poll_lead_ms must be in (0, poll_ms = {self.poll_ms}), got {self.poll_lead_ms}"
            )
        if self.reply_timeout_ms > self.poll_ms:
            raise ValueError(
                f"reply_timeout_ms ({self.reply_timeout_ms}) must not exceed poll_ms ({self.poll_ms})"
            )
        if not 0 < self.backoff_initial_ms <= self.backoff_max_ms:
            raise ValueError("need 0 < backoff_initial_ms <= backoff_max_ms")


class _PortGone(Exception):
    """The serial port failed, closed or vanished."""


class EncoderReader:
    """Polls one converter; see the module docstring. Use from one event loop."""

    def __init__(
        self, config: EncoderReaderConfig, calibration: Calibration, *, clock: Clock = time.perf_counter_ns
    ) -> None:
        self.config = config
        self.calibration = calibration
        self.clock = clock
        self.connected = False
        self.firmware: str | None = None
        self.serial_number: str | None = None
        self.fault_counts: dict[FaultKind, int] = dict.fromkeys(FaultKind, 0)
        self.polls = 0
        self.good = 0
        self.warnings = 0
        self.connects = 0
        self.overruns = 0
        self.last_error = "not started"
        self._good: tuple[int, int, float, bool] | None = None  # t_ns, count, angle_deg, warning
        self._latest_fault: FaultKind | None = None  # of the latest poll, None if it was good
        self._latest_detail = ""
        self._lines = LineReader()
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._task: asyncio.Task[None] | None = None
        self._stopping = False
        #: forecast of the next RSI telegram (ns of ``clock``), or None; see the module docstring
        self.next_telegram_ns: Callable[[], int | None] | None = None

    # public ----------------------------------------------------------------------------------------

    def start(self) -> asyncio.Task[None]:
        """Start the reader task (idempotent)."""
        if self._task is None or self._task.done():
            self._stopping = False
            self._task = asyncio.get_running_loop().create_task(
                self.run(), name=f"encoder-j{self.config.joint}"
            )
        return self._task

    async def stop(self) -> None:
        """Stop polling and close the port."""
        self._stopping = True
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        await self._close()

    def reading(self, now_ns: int | None = None) -> EncoderReading | EncoderFault:
        """The latest valid reading if it is fresh, else the fault that prevents one."""
        now = self.clock() if now_ns is None else now_ns
        joint = self.config.joint
        good = self._good
        age = None if good is None else now - good[0]
        if not self.connected:
            return EncoderFault(joint, FaultKind.GONE, self.last_error, age)
        latest = self._latest_fault
        if latest in (FaultKind.CRC, FaultKind.ERROR_BIT, FaultKind.GARBLED):
            return EncoderFault(joint, latest, self._latest_detail, age)
        if good is None or age is None:
            kind = FaultKind.SILENT if latest is FaultKind.SILENT else FaultKind.NO_DATA
            return EncoderFault(joint, kind, self._latest_detail or "no frame read yet", None)
        if age > self.config.stale_after_ms * 1e6:
            kind = FaultKind.SILENT if latest is FaultKind.SILENT else FaultKind.STALE
            return EncoderFault(joint, kind, f"latest good reading is {age / 1e6:.1f} ms old", age)
        t_ns, count, angle, warning = good
        return EncoderReading(joint, angle, count, t_ns, age, warning)

    # task ------------------------------------------------------------------------------------------

    async def run(self) -> None:
        """Connect, poll, reconnect with back-off — until cancelled."""
        cfg = self.config
        attempt = 0
        loop = asyncio.get_running_loop()
        while not self._stopping:
            try:
                await self._connect()
                attempt = 0
                await self._poll_forever(loop)
            except _PortGone as exc:
                self._mark_gone(str(exc))
            await self._close()
            if self._stopping:
                break
            attempt += 1
            delay_ms = min(cfg.backoff_max_ms, cfg.backoff_initial_ms * 2 ** min(attempt - 1, 30))
            await asyncio.sleep(delay_ms / 1000.0)

    async def _connect(self) -> None:
        cfg = self.config
        if not os.path.exists(cfg.port):
            raise _PortGone(f"{cfg.port} does not exist")
        try:
            async with asyncio.timeout(cfg.open_timeout_ms / 1000.0):
                self._reader, self._writer = await serial_asyncio_fast.open_serial_connection(
                    url=cfg.port, baudrate=cfg.baudrate
                )
        except (OSError, TimeoutError) as exc:
            raise _PortGone(f"cannot open {cfg.port}: {exc}") from None
        self._lines.clear()
        timeout_s = cfg.init_timeout_ms / 1000.0
        try:
            await self._request(
                REQ_STREAM_OFF, timeout_s
            )  # reply content ignored: the device may be streaming
            self._lines.clear()
            parse_ok_reply(await self._request(request_bit_length(cfg.bits), timeout_s))
            self.firmware = parse_ident_reply(await self._request(REQ_IDENT, timeout_s))
            self.serial_number = await self._request(REQ_SERIAL, timeout_s)
        except (TimeoutError, BissProtocolError) as exc:
            raise _PortGone(f"{cfg.port} did not configure: {exc!r}") from None
        self._good = None
        self._latest_fault = None
        self._latest_detail = ""
        self.connected = True
        self.connects += 1
        log.info(
            f"encoder j{cfg.joint}: {cfg.port} connected "
            f"(firmware {self.firmware}, serial {self.serial_number}, B{cfg.bits})"
        )

    async def _poll_forever(self, loop: asyncio.AbstractEventLoop) -> None:
        cfg = self.config
        timeout_s = cfg.reply_timeout_ms / 1000.0
        period_ns = int(cfg.poll_ms * 1e6)
        deadline_ns = self.clock()
        while True:
            self._poll_result(await self._poll(timeout_s))
            now_ns = self.clock()
            deadline_ns = self.next_poll_ns(deadline_ns + period_ns, now_ns)
            await asyncio.sleep((deadline_ns - now_ns) * 1e-9)

    def next_poll_ns(self, scheduled_ns: int, now_ns: int) -> int:
        """When to poll next: ``poll_lead_ms`` before the forecast telegram, else ``scheduled_ns``
        (or now, counted as an overrun, when that has passed: no burst to catch up)."""
        period_ns = int(self.config.poll_ms * 1e6)
        forecast = self.next_telegram_ns() if self.next_telegram_ns is not None else None
        if forecast is not None:
            t = forecast - int(self.config.poll_lead_ms * 1e6)
            while t <= now_ns:
                t += period_ns
            if t - now_ns <= 2 * period_ns:  # a sane forecast; anything else: our own schedule
                return t
        if scheduled_ns < now_ns:
            self.overruns += 1
            return now_ns
        return scheduled_ns

    async def _poll(self, timeout_s: float) -> str | FaultKind:
        self._lines.discard_pending()  # a reply still arriving after its request timed out belongs to none
        try:
            return await self._request(REQ_FRAME, timeout_s)
        except TimeoutError:
            return FaultKind.SILENT
        except BissProtocolError as exc:
            self._latest_detail = str(exc)
            return FaultKind.GARBLED

    def _poll_result(self, result: str | FaultKind) -> None:
        self.polls += 1
        now = self.clock()
        if isinstance(result, FaultKind):
            if result is FaultKind.SILENT:
                self._latest_detail = f"no reply within {self.config.reply_timeout_ms} ms"
            self._fault(result)
            return
        try:
            frame = parse_frame_reply(result, self.config.bits)
        except BissProtocolError as exc:
            self._latest_detail = str(exc)
            self._fault(FaultKind.GARBLED)
            return
        if not frame.crc_ok:
            self._latest_detail = f"CRC6 mismatch in frame {result}"
            self._fault(FaultKind.CRC)
            return
        if not frame.error_ok:
            self._latest_detail = f"error bit set (nE = 0) in frame {result}"
            self._fault(FaultKind.ERROR_BIT)
            return
        warning = not frame.warning_ok
        if warning:
            self.warnings += 1
        count = frame.position_count
        self._good = (now, count, self.calibration.angle_deg(count), warning)
        self._latest_fault = None
        self._latest_detail = ""
        self.good += 1

    def _fault(self, kind: FaultKind) -> None:
        self._latest_fault = kind
        self.fault_counts[kind] += 1

    async def _request(self, request: bytes, timeout_s: float) -> str:
        reader, writer = self._reader, self._writer
        if reader is None or writer is None or writer.transport.is_closing():
            raise _PortGone(f"{self.config.port} is closed")
        writer.write(request)
        lines = self._lines
        async with asyncio.timeout(timeout_s):
            while True:
                line = lines.next_line()
                if line is not None:
                    return line
                try:
                    data = await reader.read(256)
                except (OSError, ConnectionError) as exc:
                    raise _PortGone(f"{self.config.port} failed: {exc}") from None
                if not data:
                    raise _PortGone(f"{self.config.port} closed (end of file)")
                lines.feed(data)

    def _mark_gone(self, why: str) -> None:
        if self.connected:
            log.warning(f"encoder j{self.config.joint}: {why}")
            self.fault_counts[FaultKind.GONE] += 1
        self.connected = False
        self.last_error = why

    async def _close(self) -> None:
        writer, self._writer, self._reader = self._writer, None, None
        self.connected = False
        if writer is None:
            return
        writer.close()
        with contextlib.suppress(Exception):
            async with asyncio.timeout(1.0):
                await writer.wait_closed()
