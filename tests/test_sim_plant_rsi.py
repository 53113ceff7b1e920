"""The physical plant inside the simulated RSI controller, over real loopback UDP."""

from __future__ import annotations

import asyncio
import socket
from typing import Any

import numpy as np

from comp_daemon.rt.rsi_codec import RobTelegram, SenReply, build_sen, parse_rob
from comp_daemon.sim.plant import RobotPlant
from comp_daemon.sim.rsi_controller import RsiControllerConfig, SimulatedRsiController
from comp_daemon.sim.scenario import load_scenario

STEP_DEG = 0.002  # seed 000's rough correction per cycle


class Corrector(asyncio.DatagramProtocol):
    """A daemon stand-in: answers every telegram with a relative AK of +STEP_DEG on A1 while armed."""

    def __init__(self) -> None:
        self.telegrams: list[RobTelegram] = []
        self.armed = False
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        t = parse_rob(data)
        self.telegrams.append(t)
        ak = (STEP_DEG if self.armed else 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        assert self.transport is not None
        self.transport.sendto(build_sen(SenReply(t.ipoc, ak)), addr)


async def test_plant_moves_and_follows_rsi_corrections() -> None:
    scenario = load_scenario("kr210-cell")
    plant = RobotPlant.from_scenario(scenario, seed=1)
    loop = asyncio.get_running_loop()
    server = Corrector()
    transport, _ = await loop.create_datagram_endpoint(
        lambda: server, local_addr=("127.0.0.1", 0), family=socket.AF_INET
    )
    port = transport.get_extra_info("sockname")[1]
    controller = SimulatedRsiController(RsiControllerConfig(server_port=port, timeout_count=100), plant)
    try:
        await controller.start()
        target = scenario.campaign.home_deg + np.array([2.0, -1.0, 1.0, 0.0, 0.5, 0.0])
        await asyncio.wait_for(controller.move_to(target), timeout=10.0)
        np.testing.assert_array_equal(plant.axis_setpoint_deg(), target)
        grating_before = plant.output_angle_deg(1)
        server.armed = True
        n0 = len(server.telegrams)
        for _ in range(500):
            if len(server.telegrams) >= n0 + 30:
                break
            await asyncio.sleep(0.012)
        server.armed = False
        await asyncio.sleep(0.1)
        total = plant.correction_deg()[0]
        # the corrections reached the plant: A1's command, AIPos and its true output angle moved by them
        assert total > 20 * STEP_DEG
        last = server.telegrams[-1]
        assert last.aipos_deg is not None and last.aspos_deg is not None
        assert abs(last.aspos_deg[0] - target[0]) < 1e-3  # ASPos stays without corrections
        assert last.aipos_deg[0] - last.aspos_deg[0] > 15 * STEP_DEG
        assert plant.output_angle_deg(1) - grating_before > 15 * STEP_DEG
    finally:
        await controller.close()
        transport.close()
