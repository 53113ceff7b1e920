"""The simulated cell's port commands (sim/cell.py CellCommands), line by line, without the sockets."""

from __future__ import annotations

import json

import numpy as np
import pytest

from comp_daemon.sim.cell import CellCommands
from comp_daemon.sim.converter import ConverterConfig, ConverterFault, SimulatedConverter
from comp_daemon.sim.plant import RobotPlant
from comp_daemon.sim.rsi_controller import RsiControllerConfig, SimulatedRsiController
from comp_daemon.sim.scenario import load_scenario
from comp_daemon.sim.tracker import LaserTracker

SCENARIO = load_scenario("kr210-cell")


@pytest.fixture
def cell() -> CellCommands:
    plant = RobotPlant.from_scenario(SCENARIO, seed=3, payload_kg=0.0)
    tracker = LaserTracker(0.0, np.eye(4), seed=4)  # no noise, the base frame: measure == tcp
    controller = SimulatedRsiController(RsiControllerConfig(), plant)
    converters = {j: SimulatedConverter(ConverterConfig(joint=j), plant) for j in (1, 2)}
    return CellCommands(plant, tracker, controller, converters)


def _numbers(answer: str) -> list[float]:
    assert answer.startswith("OK "), answer
    return [float(v) for v in answer[3:].split()]


async def test_queries_answer_the_plant_and_the_tracker(cell: CellCommands) -> None:
    tcp = _numbers(await cell("tcp"))
    np.testing.assert_allclose(tcp, cell.plant.tcp_true_mm(), atol=1e-6)
    np.testing.assert_allclose(_numbers(await cell("MEASURE")), tcp, atol=1e-6)
    joints = await cell("joints")
    assert len(joints.split()[1].split(".")[1]) == 8  # angles to 1e-8 deg
    np.testing.assert_allclose(_numbers(joints), cell.plant.output_angles_deg(), atol=1e-8)
    status = json.loads((await cell("status"))[3:])
    assert set(status) == {"controller", "correction_deg", "output_deg", "converters"}
    assert status["converters"] == {"1": [], "2": []}


async def test_converter_commands_take_their_joint_and_arguments(cell: CellCommands) -> None:
    assert await cell("fault 2 bad_crc") == "OK"
    assert cell.converters[2].faults == {ConverterFault.BAD_CRC}
    assert await cell("clear 2") == "OK"
    assert cell.converters[2].faults == set()
    assert await cell("fault 3 bad_crc") == "ERR no grating on joint 3"
    assert await cell("fault 2") == "ERR bad arguments to fault"
    assert await cell("clear 2 bad_crc") == "ERR bad arguments to clear"
    assert (await cell("fault 2 melted")).startswith("ERR 'melted' is not a valid ConverterFault")
    assert (await cell("unplug two")).startswith("ERR invalid literal")
    assert await cell("unplug 1") == "OK" and not cell.converters[1].plugged


async def test_payload_and_refusals(cell: CellCommands) -> None:
    before = cell.plant.tcp_true_mm()
    assert await cell("payload 150") == "OK"
    assert not np.allclose(cell.plant.tcp_true_mm(), before)  # the payload bends the arm
    assert (await cell("payload heavy")).startswith("ERR could not convert")
    assert await cell("   ") == "ERR empty command"
    assert await cell("tcp now") == "ERR unknown command 'tcp now'"
    assert await cell("fault") == "ERR unknown command 'fault'"
    assert await cell("x" * 50) == f"ERR unknown command {'x' * 40!r}"
