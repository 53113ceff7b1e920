"""Simulated BiSS-C-to-USB converters on pseudo-terminals (the line protocol of :mod:`comp_daemon.rt.biss`).

Each :class:`SimulatedConverter` owns a pty pair (``os.openpty``, raw mode) and answers the
converter line protocol on the master side; the daemon opens the slave side as its serial port,
by the slave's name or by a stable symlink (``link_path``, like ``/dev/serial/by-id/…``).

Position: the joint's true output angle from an :class:`OutputAngleSource` (the plant: after
backlash, compliance, transmission error) as a count of ``resolution_nm`` along an arc of
``radius_mm``: ``count = round(radians(sign·(angle_deg − zero_deg))·radius_mm·1e6 / resolution_nm)``.
``zero_deg`` is the angle at count 0, so the joint's range must map into ``[0, 2^bits)``; a count
outside it is reported with the error bit (nE = 0), as a scale reads invalid off its end. This is
the inverse of :class:`comp_daemon.rt.encoder_reader.LinearGratingCalibration` with the same numbers.

Fault injection (:class:`ConverterFault`, any combination): ``BAD_CRC`` corrupts the CRC6,
``ERROR_BIT``/``WARNING_BIT`` clear nE/nW, ``SILENT`` answers nothing, ``GARBLE`` answers junk.
:meth:`SimulatedConverter.unplug` closes the pty and removes the symlink (the daemon's port fails);
:meth:`SimulatedConverter.replug` makes a new pty and points the symlink at it.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import math
import os
import tty
from dataclasses import dataclass
from typing import Protocol

from comp_daemon.rt.biss import (
    RESOLUTION_NM,
    SUPPORTED_BITS,
    BissProtocolError,
    LineReader,
    RequestKind,
    encode_frame,
    parse_request,
)

__all__ = ["ConverterConfig", "ConverterFault", "OutputAngleSource", "SimulatedConverter"]


class OutputAngleSource(Protocol):
    """Where a converter reads its joint: the true output-side angle (deg) of joint 1..6."""

    def output_angle_deg(self, joint: int) -> float: ...


class ConverterFault(enum.StrEnum):
    BAD_CRC = "bad_crc"
    ERROR_BIT = "error_bit"
    WARNING_BIT = "warning_bit"
    SILENT = "silent"
    GARBLE = "garble"


@dataclass(frozen=True, slots=True)
class ConverterConfig:
    joint: int  # 1..6
    radius_mm: float = 400.0
    zero_deg: float = -200.0  # joint angle at count 0
    sign: float = 1.0  # -1 when the count grows against the axis direction
    resolution_nm: float = RESOLUTION_NM
    bits: int = 26  # until the host sends B26/B32
    firmware: str = "1.07-sim"
    serial_number: str = ""  # default: SIM-J<joint>
    link_path: str | None = None  # stable symlink to the pty slave
    stream_period_ms: float = 2.0  # own rate of the streaming mode ('1')

    def __post_init__(self) -> None:
        if not 1 <= self.joint <= 6:
            raise ValueError(f"joint must be 1..6, got {self.joint}")
        if not (math.isfinite(self.radius_mm) and self.radius_mm > 0):
            raise ValueError(f"radius_mm must be positive, got {self.radius_mm}")
        if self.bits not in SUPPORTED_BITS:
            raise ValueError(f"bits must be one of {SUPPORTED_BITS}, got {self.bits}")
        if self.sign not in (1.0, -1.0):
            raise ValueError(f"sign must be +1 or -1, got {self.sign}")


class SimulatedConverter:
    """One converter on a pty, served from the running event loop. See the module docstring."""

    def __init__(self, config: ConverterConfig, source: OutputAngleSource) -> None:
        self.config = config
        self.source = source
        self.faults: set[ConverterFault] = set()
        self.bits = config.bits
        self.serial_number = config.serial_number or f"SIM-J{config.joint}"
        self.requests = 0
        self.replies = 0
        self.dropped_replies = 0
        self._master: int | None = None
        self._slave: int | None = None
        self._slave_name: str | None = None
        self._lines = LineReader()
        self._stream_task: asyncio.Task[None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    # lifecycle -------------------------------------------------------------------------------------

    @property
    def plugged(self) -> bool:
        return self._master is not None

    @property
    def port(self) -> str:
        """The path the daemon should open: the symlink if configured, else the pty slave."""
        if self.config.link_path is not None:
            return self.config.link_path
        if self._slave_name is None:
            raise RuntimeError("converter is not plugged in")
        return self._slave_name

    @property
    def slave_name(self) -> str | None:
        return self._slave_name

    def start(self) -> None:
        """Create the pty (and symlink) and serve it from the running loop."""
        if self._master is not None:
            return
        self._loop = asyncio.get_running_loop()
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no CR/NL translation until the host configures its side
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self._slave_name = os.ttyname(slave)
        self._lines.clear()
        self.bits = self.config.bits
        link = self.config.link_path
        if link is not None:
            tmp = f"{link}.tmp{os.getpid()}"
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            os.symlink(self._slave_name, tmp)
            os.replace(tmp, link)  # atomic: the daemon never sees a half-made link
        self._loop.add_reader(master, self._on_readable)

    def unplug(self) -> None:
        """The device disappears: stop serving, remove the symlink, close both pty ends."""
        self._stop_stream()
        master, slave = self._master, self._slave
        self._master = self._slave = None
        self._slave_name = None
        link = self.config.link_path
        if link is not None:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(link)
        if master is not None:
            if self._loop is not None:
                self._loop.remove_reader(master)
            os.close(master)
        if slave is not None:
            os.close(slave)

    def replug(self) -> None:
        """The device comes back (on a new pty; the symlink follows)."""
        self.unplug()
        self.start()

    def close(self) -> None:
        self.unplug()

    # faults ----------------------------------------------------------------------------------------

    def inject(self, *faults: ConverterFault) -> None:
        self.faults.update(faults)

    def clear(self, *faults: ConverterFault) -> None:
        """Clear the given faults, or all of them."""
        if faults:
            self.faults.difference_update(faults)
        else:
            self.faults.clear()

    # position --------------------------------------------------------------------------------------

    def count_for_angle(self, angle_deg: float) -> int:
        cfg = self.config
        arc_mm = math.radians(cfg.sign * (angle_deg - cfg.zero_deg)) * cfg.radius_mm
        return round(arc_mm * 1e6 / cfg.resolution_nm)

    def frame(self) -> str:
        """The frame for the joint's current true angle, with the injected faults."""
        count = self.count_for_angle(self.source.output_angle_deg(self.config.joint))
        in_range = 0 <= count < (1 << self.bits)
        return encode_frame(
            count if in_range else 0,
            self.bits,
            error_ok=in_range and ConverterFault.ERROR_BIT not in self.faults,
            warning_ok=ConverterFault.WARNING_BIT not in self.faults,
            crc_xor=0x15 if ConverterFault.BAD_CRC in self.faults else 0,
        )

    # protocol --------------------------------------------------------------------------------------

    def _on_readable(self) -> None:
        master = self._master
        if master is None:
            return
        try:
            data = os.read(master, 1024)
        except BlockingIOError:
            return
        except OSError:  # EIO: no slave open — cannot happen while we hold our own slave fd
            return
        self._lines.feed(data)
        while True:
            try:
                line = self._lines.next_line()
            except BissProtocolError:
                self._reply("ERR")
                continue
            if line is None:
                return
            self._handle(line)

    def _handle(self, line: str) -> None:
        self.requests += 1
        request = parse_request(line)
        kind = request.kind
        if kind is RequestKind.FRAME:
            self._reply(self.frame())
        elif kind is RequestKind.COUNT:
            count = self.count_for_angle(self.source.output_angle_deg(self.config.joint))
            ok = (
                0 <= count < (1 << self.bits)
                and ConverterFault.BAD_CRC not in self.faults
                and ConverterFault.ERROR_BIT not in self.faults
            )
            self._reply(str(count) if ok else "ERR")
        elif kind is RequestKind.IDENT:
            self._reply(f"E201,{self.config.firmware}")
        elif kind is RequestKind.SERIAL:
            self._reply(self.serial_number)
        elif kind is RequestKind.BIT_LENGTH:
            assert request.bits is not None
            self.bits = request.bits
            self._reply("OK")
        elif kind is RequestKind.STREAM_ON:
            self._reply("OK")
            self._start_stream()
        elif kind is RequestKind.STREAM_OFF:
            self._stop_stream()
            self._reply("OK")
        else:
            self._reply("ERR")

    def _reply(self, text: str) -> None:
        if ConverterFault.SILENT in self.faults:
            return
        if ConverterFault.GARBLE in self.faults:
            text = "#\x7f?g@rbl3"
        master = self._master
        if master is None:
            return
        try:
            os.write(master, text.encode("ascii") + b"\r")
            self.replies += 1
        except (BlockingIOError, OSError):
            self.dropped_replies += 1  # the host does not read; a real converter would drop too

    def _start_stream(self) -> None:
        if self._stream_task is None and self._loop is not None:
            self._stream_task = self._loop.create_task(
                self._stream(), name=f"converter-j{self.config.joint}-stream"
            )

    def _stop_stream(self) -> None:
        task, self._stream_task = self._stream_task, None
        if task is not None:
            task.cancel()

    async def _stream(self) -> None:
        loop = asyncio.get_running_loop()
        period = self.config.stream_period_ms / 1000.0
        deadline = loop.time()
        while self._master is not None:
            self._reply(self.frame())
            deadline += period
            await asyncio.sleep(max(0.0, deadline - loop.time()))
