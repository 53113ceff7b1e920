"""Simulated grating converter on a real pty, checked with an independent bit-by-bit BiSS decoder."""

from __future__ import annotations

import asyncio
import math
import os
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
import serial
import serial_asyncio_fast

from comp_daemon.sim.converter import ConverterConfig, ConverterFault, SimulatedConverter

RADIUS_MM = 350.0
ZERO_DEG = -190.0


def independent_decode(hex16: str, bits: int) -> tuple[int, int, int, bool]:
    """Position, nE, nW and CRC verdict by long division over a bit list (x^6 + x + 1, init 0, inverted)."""
    stream = [int(b) for ch in hex16 for b in format(int(ch, 16), "04b")]
    assert len(stream) == 64
    data = stream[: bits + 2]
    crc_sent = stream[bits + 2 : bits + 8]
    register = [0] * 6
    for bit in data:  # shift-register form: feedback = incoming bit XOR register MSB
        feedback = bit ^ register[0]
        register = [*register[1:], 0]
        if feedback:
            register[4] ^= 1  # x^1
            register[5] ^= 1  # x^0
    crc_ok = [1 - b for b in crc_sent] == register
    return int("".join(map(str, stream[:bits])), 2), stream[bits], stream[bits + 1], crc_ok


def expected_count(angle_deg: float) -> int:
    return round(math.radians(angle_deg - ZERO_DEG) * RADIUS_MM / 50e-6)


class Angles:
    def __init__(self) -> None:
        self.deg = 0.0

    def output_angle_deg(self, joint: int) -> float:
        assert joint == 2
        return self.deg


class Port:
    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer

    async def ask(self, request: str, timeout_s: float = 1.0) -> str:
        self.writer.write(request.encode() + b"\r")
        return await self.line(timeout_s)

    async def line(self, timeout_s: float = 1.0) -> str:
        raw = await asyncio.wait_for(self.reader.readuntil(b"\r"), timeout_s)
        return raw[:-1].decode("ascii", "replace")

    async def close(self) -> None:
        self.writer.close()
        try:
            await self.writer.wait_closed()
        except serial.SerialException:
            pass


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[tuple[SimulatedConverter, Angles, Port]]:
    angles = Angles()
    link = str(tmp_path / "usb-Sim_BiSS_Converter_J2-if00")
    conv = SimulatedConverter(ConverterConfig(2, RADIUS_MM, ZERO_DEG, link_path=link), angles)
    conv.start()
    reader, writer = await serial_asyncio_fast.open_serial_connection(url=link, baudrate=115200)
    port = Port(reader, writer)
    yield conv, angles, port
    await port.close()
    conv.close()


async def test_stable_name_identification_and_configuration(
    rig: tuple[SimulatedConverter, Angles, Port],
) -> None:
    conv, _, port = rig
    assert conv.port.endswith("usb-Sim_BiSS_Converter_J2-if00")
    assert os.path.realpath(conv.port).startswith("/dev/pts/")
    assert await port.ask("v") == "E201,1.07-sim"
    assert await port.ask("s") == "SIM-J2"
    assert await port.ask("B32") == "OK" and conv.bits == 32
    assert await port.ask("B26") == "OK" and conv.bits == 26
    assert await port.ask("B16") == "ERR"
    assert await port.ask("hello") == "ERR"


@pytest.mark.parametrize("bits", [26, 32])
async def test_frames_carry_the_true_angle_with_a_valid_crc(
    rig: tuple[SimulatedConverter, Angles, Port], bits: int
) -> None:
    _, angles, port = rig
    assert await port.ask(f"B{bits}") == "OK"
    for angle in (-185.0, -90.0, -0.00001, 0.0, 0.00731, 45.5, 123.456789, 185.0):
        angles.deg = angle
        frame = await port.ask("4")
        assert len(frame) == 16
        position, n_e, n_w, crc_ok = independent_decode(frame, bits)
        assert (position, n_e, n_w, crc_ok) == (expected_count(angle), 1, 1, True)
        assert await port.ask("?") == str(expected_count(angle))


async def test_injected_faults(rig: tuple[SimulatedConverter, Angles, Port]) -> None:
    conv, angles, port = rig
    angles.deg = 10.0
    conv.inject(ConverterFault.BAD_CRC)
    position, n_e, n_w, crc_ok = independent_decode(await port.ask("4"), 26)
    assert (position, n_e, n_w, crc_ok) == (expected_count(10.0), 1, 1, False)
    assert await port.ask("?") == "ERR"
    conv.clear()
    conv.inject(ConverterFault.ERROR_BIT, ConverterFault.WARNING_BIT)
    assert independent_decode(await port.ask("4"), 26)[1:] == (0, 0, True)
    assert await port.ask("?") == "ERR"
    conv.clear(ConverterFault.ERROR_BIT)
    assert independent_decode(await port.ask("4"), 26)[1:] == (1, 0, True)
    conv.clear()
    conv.inject(ConverterFault.GARBLE)
    garbage = await port.ask("4")
    assert len(garbage) != 16 or not all(c in "0123456789ABCDEF" for c in garbage)
    conv.clear()
    conv.inject(ConverterFault.SILENT)
    with pytest.raises(TimeoutError):
        await port.ask("4", timeout_s=0.1)
    conv.clear()
    assert independent_decode(await port.ask("4"), 26)[3]


async def test_off_the_scale_sets_the_error_bit(rig: tuple[SimulatedConverter, Angles, Port]) -> None:
    _, angles, port = rig
    angles.deg = ZERO_DEG - 1.0  # before count 0
    assert independent_decode(await port.ask("4"), 26)[1] == 0
    assert await port.ask("?") == "ERR"


async def test_streaming_mode(rig: tuple[SimulatedConverter, Angles, Port]) -> None:
    _, angles, port = rig
    angles.deg = 33.0
    assert await port.ask("1") == "OK"
    frames = [await port.line() for _ in range(5)]
    assert all(independent_decode(f, 26) == (expected_count(33.0), 1, 1, True) for f in frames)
    port.writer.write(b"0\r")
    while (await port.line()) != "OK":  # frames already in flight, then the acknowledgement
        pass
    with pytest.raises(TimeoutError):
        await port.line(timeout_s=0.05)


async def test_unplug_removes_the_device_and_replug_restores_it(
    rig: tuple[SimulatedConverter, Angles, Port],
) -> None:
    conv, angles, port = rig
    link = conv.port
    conv.unplug()
    assert not os.path.lexists(link) and not conv.plugged
    with pytest.raises((serial.SerialException, asyncio.IncompleteReadError, TimeoutError)):
        await port.ask("4", timeout_s=0.5)
    await port.close()
    conv.replug()
    assert os.path.realpath(link).startswith("/dev/pts/")
    reader, writer = await serial_asyncio_fast.open_serial_connection(url=link, baudrate=115200)
    port.reader, port.writer = reader, writer
    angles.deg = -12.5
    assert independent_decode(await port.ask("4"), 26) == (expected_count(-12.5), 1, 1, True)
