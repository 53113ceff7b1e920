"""Encoder reader over real pseudo-terminals, against the simulated converter."""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import pytest

from comp_daemon.rt.encoder_reader import (
    EncoderFault,
    EncoderReader,
    EncoderReaderConfig,
    EncoderReading,
    FaultKind,
    LinearGratingCalibration,
)
from comp_daemon.sim.converter import ConverterConfig, ConverterFault, SimulatedConverter

RADIUS_MM = 400.0
ZERO_DEG = -200.0
HALF_COUNT_DEG = 0.5 * math.degrees(50e-6 / RADIUS_MM)


class Angles:
    """In-test joint source: fixed output angles that the test sets."""

    def __init__(self) -> None:
        self.deg = {1: 12.345, 2: -47.5, 3: 101.0}

    def output_angle_deg(self, joint: int) -> float:
        return self.deg[joint]


async def until(cond: Callable[[], bool], timeout_s: float = 3.0) -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    while not cond():
        if loop.time() > end:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.004)


Rig = tuple[SimulatedConverter, EncoderReader, Angles]


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[Callable[..., Rig]]:
    made: list[tuple[SimulatedConverter, EncoderReader]] = []

    def make(joint: int = 1, *, bits: int = 26, start_converter: bool = True, **reader_cfg: float) -> Rig:
        angles = Angles()
        link = str(tmp_path / f"usb-BiSS_sim_J{joint}")
        conv = SimulatedConverter(ConverterConfig(joint, RADIUS_MM, ZERO_DEG, link_path=link), angles)
        if start_converter:
            conv.start()
        settings = {
            "poll_ms": 5.0,
            "reply_timeout_ms": 4.0,
            "stale_after_ms": 60.0,
            "backoff_initial_ms": 10.0,
        }
        settings.update(reader_cfg)
        config = EncoderReaderConfig(link, joint, bits=bits, backoff_max_ms=80.0, **settings)  # type: ignore[arg-type]
        reader = EncoderReader(config, LinearGratingCalibration(RADIUS_MM, ZERO_DEG))
        reader.start()
        made.append((conv, reader))
        return conv, reader, angles

    yield make
    for conv, reader in made:
        await reader.stop()
        conv.close()


def is_reading(r: EncoderReader) -> bool:
    return isinstance(r.reading(), EncoderReading)


def fault_kind(r: EncoderReader) -> FaultKind | None:
    value = r.reading()
    return value.kind if isinstance(value, EncoderFault) else None


async def test_reading_is_the_true_angle_within_half_a_count(rig: Callable[..., Rig]) -> None:
    conv, reader, angles = rig(1)
    await until(lambda: is_reading(reader))
    value = reader.reading()
    assert isinstance(value, EncoderReading)
    assert value.joint == 1 and not value.warning
    assert value.count == conv.count_for_angle(12.345)
    assert abs(value.angle_deg - 12.345) <= HALF_COUNT_DEG
    assert reader.firmware == "1.07-sim" and reader.serial_number == "SIM-J1"
    angles.deg[1] = -3.25
    await until(lambda: abs(getattr(reader.reading(), "angle_deg", 99.0) + 3.25) <= HALF_COUNT_DEG)
    bad = (FaultKind.CRC, FaultKind.ERROR_BIT, FaultKind.GARBLED, FaultKind.GONE)
    assert all(reader.fault_counts[k] == 0 for k in bad)


async def test_32_bit_positions(rig: Callable[..., Rig]) -> None:
    conv, reader, _ = rig(2, bits=32)
    await until(lambda: is_reading(reader))
    assert conv.bits == 32
    assert abs(reader.reading().angle_deg + 47.5) <= HALF_COUNT_DEG  # type: ignore[union-attr]


@pytest.mark.parametrize(
    ("fault", "kind"),
    [
        (ConverterFault.BAD_CRC, FaultKind.CRC),
        (ConverterFault.ERROR_BIT, FaultKind.ERROR_BIT),
        (ConverterFault.GARBLE, FaultKind.GARBLED),
    ],
)
async def test_bad_frames_are_faults_at_once_and_recover(
    rig: Callable[..., Rig], fault: ConverterFault, kind: FaultKind
) -> None:
    conv, reader, _ = rig(1)
    await until(lambda: is_reading(reader))
    conv.inject(fault)
    await until(lambda: fault_kind(reader) is kind)
    assert reader.fault_counts[kind] >= 1
    conv.clear()
    await until(lambda: is_reading(reader))


async def test_warning_bit_keeps_reading_valid_but_flagged(rig: Callable[..., Rig]) -> None:
    conv, reader, _ = rig(1)
    conv.inject(ConverterFault.WARNING_BIT)
    await until(lambda: is_reading(reader))
    value = reader.reading()
    assert isinstance(value, EncoderReading) and value.warning
    assert reader.warnings >= 1


async def test_silence_makes_the_reading_stale(rig: Callable[..., Rig]) -> None:
    conv, reader, _ = rig(1)
    await until(lambda: is_reading(reader))
    conv.inject(ConverterFault.SILENT)
    await until(lambda: fault_kind(reader) is FaultKind.SILENT)
    value = reader.reading()
    assert isinstance(value, EncoderFault) and value.last_good_age_ns is not None
    assert value.last_good_age_ns > 60e6
    assert reader.fault_counts[FaultKind.SILENT] >= 1
    conv.clear()
    await until(lambda: is_reading(reader))


async def test_age_alone_makes_a_reading_stale(rig: Callable[..., Rig]) -> None:
    _, reader, _ = rig(1, poll_ms=12.0, reply_timeout_ms=8.0)
    await until(lambda: is_reading(reader))
    value = reader.reading()
    assert isinstance(value, EncoderReading)
    assert isinstance(reader.reading(value.t_ns + 60_000_000), EncoderReading)
    late = reader.reading(value.t_ns + 60_000_001)
    assert isinstance(late, EncoderFault) and late.kind is FaultKind.STALE


async def test_unplug_and_replug_recovered(rig: Callable[..., Rig]) -> None:
    conv, reader, _ = rig(1)
    await until(lambda: is_reading(reader))
    conv.unplug()
    await until(lambda: fault_kind(reader) is FaultKind.GONE)
    assert not Path(conv.port).exists()
    assert reader.fault_counts[FaultKind.GONE] == 1
    conv.start()  # replugged: a new pty behind the same name
    await until(lambda: is_reading(reader))
    assert reader.connects == 2


async def test_device_absent_at_start_then_appears(rig: Callable[..., Rig]) -> None:
    conv, reader, _ = rig(3, start_converter=False)
    await asyncio.sleep(0.05)
    gone = reader.reading()
    assert isinstance(gone, EncoderFault) and gone.kind is FaultKind.GONE and "does not exist" in gone.detail
    conv.replug()
    await until(lambda: is_reading(reader))
    assert abs(reader.reading().angle_deg - 101.0) <= HALF_COUNT_DEG  # type: ignore[union-attr]


def test_config_and_calibration_reject_bad_values() -> None:
    with pytest.raises(ValueError, match="joint"):
        EncoderReaderConfig("/dev/null", 7)
    with pytest.raises(ValueError, match="reply_timeout_ms"):
        EncoderReaderConfig("/dev/null", 1, poll_ms=4.0, reply_timeout_ms=8.0)
    with pytest.raises(ValueError, match="radius_mm"):
        LinearGratingCalibration(0.0)
    cal = LinearGratingCalibration(RADIUS_MM, ZERO_DEG, sign=-1.0)
    assert cal.angle_deg(0) == ZERO_DEG
    assert math.isclose(cal.angle_deg(1_000_000), ZERO_DEG - math.degrees(50.0 / RADIUS_MM))


def test_poll_schedule_follows_the_telegram_forecast() -> None:
    reader = EncoderReader(
        EncoderReaderConfig("/dev/null", 1, poll_ms=12.0, reply_timeout_ms=8.0, poll_lead_ms=3.0),
        LinearGratingCalibration(RADIUS_MM),
    )
    ms = 1_000_000
    # no forecast: the reader's own absolute schedule; a passed deadline is an overrun, not a burst
    assert reader.next_poll_ns(100 * ms, 95 * ms) == 100 * ms
    assert reader.next_poll_ns(100 * ms, 104 * ms) == 104 * ms and reader.overruns == 1
    forecast: list[int | None] = [120 * ms]
    reader.next_telegram_ns = lambda: forecast[0]
    assert reader.next_poll_ns(100 * ms, 95 * ms) == 117 * ms  # 3 ms before the telegram
    assert reader.next_poll_ns(100 * ms, 118 * ms) == 129 * ms  # too late for this one: the next
    forecast[0] = 10_000 * ms  # nonsense: keep the own schedule
    assert reader.next_poll_ns(100 * ms, 95 * ms) == 100 * ms
    forecast[0] = None  # telegrams stopped
    assert reader.next_poll_ns(100 * ms, 95 * ms) == 100 * ms
    with pytest.raises(ValueError, match="poll_lead_ms"):
        EncoderReaderConfig("/dev/null", 1, poll_ms=4.0, reply_timeout_ms=4.0, poll_lead_ms=4.0)


async def test_polls_land_just_before_each_telegram(rig: Callable[..., Rig]) -> None:
    """Readings are taken in the lead window before each (forecast) telegram, never across it."""
    period = 12_000_000
    base = time.perf_counter_ns()
    _conv, reader, _ = rig(1, poll_ms=12.0, reply_timeout_ms=8.0, poll_lead_ms=3.0)

    def forecast() -> int:
        now = time.perf_counter_ns()
        return base + (-(-(now - base) // period)) * period

    reader.next_telegram_ns = forecast
    await until(lambda: is_reading(reader))
    stamps: set[int] = set()
    # 50 telegram periods give some 50 readings; on a loaded machine (polls answered too late to
    # count) look longer, up to 5 s, until 25 have been seen
    start = time.monotonic()
    while (now := time.monotonic()) < start + 0.6 or (len(stamps) < 25 and now < start + 5.0):
        r = reader.reading()
        if isinstance(r, EncoderReading):
            stamps.add(r.t_ns)
        await asyncio.sleep(0.001)
    phases_ms = sorted(((t - base) % period) / 1e6 for t in stamps)
    assert len(phases_ms) >= 25, phases_ms
    before = [p for p in phases_ms if 9.0 <= p <= 11.9]  # lead window: 3 ms before the telegram
    assert len(before) >= 0.8 * len(phases_ms), phases_ms
