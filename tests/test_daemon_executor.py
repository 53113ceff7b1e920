"""Target execution through the loop runtime and the SQLite store: order, lifecycle, failures.

The robot here is a small joint model driven cycle by cycle (telegrams handed straight to the
runtime's handler, a stepped clock): what is tested is the executor's sequencing, not the wire.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pytest

from comp_daemon.data.target import Target
from comp_daemon.rt.controller import JointLoopSettings
from comp_daemon.rt.encoder_reader import EncoderFault, EncoderReading
from comp_daemon.rt.encoder_reader import FaultKind as EncoderFaultKind
from comp_daemon.rt.executor import (
    CompensatedTarget,
    CompensationError,
    MotionError,
    TargetExecutor,
    TargetOutcome,
)
from comp_daemon.rt.grating_cal import GratingCalibration, JointGratingMap
from comp_daemon.rt.loop import LoopRuntime
from comp_daemon.rt.rsi_codec import RobTelegram
from comp_daemon.rt.safety import SafetySettings, SafetyState
from comp_daemon.service.store import Store, StoreFullError

CYCLE_NS = 12_000_000
SLOPE = 7.16e-6  # deg per count (50 nm on a 400 mm arc)
JOINTS = (1, 2, 3)
OFFSETS = (0.011, -0.008, 0.02)  # where each joint really sits relative to the motor (backlash …)
HOME = (0.0, -90.0, 90.0, 0.0, 30.0, 0.0)


class Clock:
    def __init__(self) -> None:
        self.ns = 10_000_000_000

    def __call__(self) -> int:
        return self.ns


class Robot:
    """Setpoint ramps to the commanded axes; corrections show one cycle late; joints carry offsets."""

    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self.setpoint = list(HOME)
        self.goal = list(HOME)
        self.correction = [0.0] * 6
        self.pending: list[tuple[float, ...]] = []
        self.moves: list[tuple[float, ...]] = []
        self.refuse: set[tuple[float, ...]] = set()
        self.ipoc = 5_000_000

    def angle(self, joint: int) -> float:
        return self.setpoint[joint - 1] + self.correction[joint - 1] + OFFSETS[joint - 1]

    def telegram(self) -> RobTelegram:
        for a in range(6):
            d = self.goal[a] - self.setpoint[a]
            self.setpoint[a] += max(-0.4, min(0.4, d))
        if len(self.pending) > 1:
            ak = self.pending.pop(0)
            self.correction = [c + s for c, s in zip(self.correction, ak, strict=True)]
        self.ipoc += 12
        actual = tuple(s + c for s, c in zip(self.setpoint, self.correction, strict=True))
        return RobTelegram(self.ipoc, aipos_deg=actual, aspos_deg=tuple(self.setpoint), delay=0)


class Grating:
    def __init__(self, robot: Robot, joint: int) -> None:
        self.robot = robot
        self.joint = joint
        self.broken = False

    def reading(self, now_ns: int | None = None) -> EncoderReading | EncoderFault:
        if self.broken:
            return EncoderFault(self.joint, EncoderFaultKind.CRC, "CRC6 mismatch", None)
        angle = self.robot.angle(self.joint)
        t = self.robot.clock.ns
        return EncoderReading(self.joint, angle, round(angle / SLOPE), t, 0, False)


class Motion:
    def __init__(self, robot: Robot) -> None:
        self.robot = robot

    async def move_to(self, axes_deg: Sequence[float]) -> None:
        axes = tuple(axes_deg)
        if axes in self.robot.refuse:
            raise MotionError("A2 outside its software limit")
        self.robot.moves.append(axes)
        self.robot.goal = list(axes)


def calibration() -> GratingCalibration:
    maps = tuple(JointGratingMap(j, 400.0, 50.0, SLOPE, 0.0, 10, 60.0, 0.0, 0.0) for j in JOINTS)
    return GratingCalibration(1, "2026-11-21T00:00:00Z", maps)


def compensate(target: Target) -> CompensatedTarget:
    assert target.axes_deg is not None
    axes = list(target.axes_deg)
    if target.pose_id == "unreachable":
        raise CompensationError("target outside the workspace")
    commanded = tuple(a + 0.003 for a in axes)  # the "model": a small feed-forward correction
    return CompensatedTarget(commanded, tuple(commanded[j - 1] for j in JOINTS), model_id=1)


class FullDisk:
    """The store's queue with a disk that can be made full: every write is then refused as the
    store refuses it on ENOSPC (:class:`StoreFullError`), before anything is changed."""

    def __init__(self, store: Store) -> None:
        self.store = store
        self.full = False
        self.full_at: str | None = None  # the disk fills just before a move to this state is written
        self.refused = 0

    def _check(self) -> None:
        if self.full:
            self.refused += 1
            raise StoreFullError(self.store.path, 0)

    def claim_next_target(self) -> Any:
        self._check()
        return self.store.claim_next_target()

    def advance_target(self, target_id: int, state: str, **kwargs: Any) -> Any:
        self.full = self.full or state == self.full_at
        self._check()
        return self.store.advance_target(target_id, state, **kwargs)


class Cell:
    def __init__(self, tmp_path: Path) -> None:
        self.clock = Clock()
        self.robot = Robot(self.clock)
        self.gratings = {j: Grating(self.robot, j) for j in JOINTS}
        self.runtime = LoopRuntime(
            self.gratings,
            calibration=calibration(),
            safety=SafetySettings(),
            loop=JointLoopSettings(),
            clock_ns=self.clock,
        )
        self.store = Store(tmp_path / "store.sqlite3")
        self.log: list[tuple[int, str]] = []
        self.store.add_listener(
            lambda ev: self.log.append((ev.target_id, ev.kind)) if ev.target_id is not None else None
        )
        self.ready_reason: str | None = None
        self.outcomes: list[TargetOutcome] = []
        self.disk = FullDisk(self.store)
        self.executor = TargetExecutor(
            self.disk,
            compensate,
            Motion(self.robot),
            self.runtime,
            joints=[j - 1 for j in JOINTS],
            readiness=self.readiness,
            recheck_s=0.01,
            motion_fault_grace_s=0.01,  # real seconds; the stepped clock here runs much faster
            on_outcome=self.outcomes.append,
        )

    def readiness(self) -> str | None:
        if self.ready_reason is not None:
            return self.ready_reason
        reasons = self.runtime.readiness_reasons()
        return "; ".join(reasons) if reasons else None

    async def cycles(self, n: int) -> None:
        for _ in range(n):
            self.clock.ns += CYCLE_NS
            reply = self.runtime.handle(self.robot.telegram())
            self.robot.pending.append(reply.ak_deg)
            self.runtime.tick()
            # a little real time per cycle, so worker threads (store, compensation) get their turn
            await asyncio.sleep(0.0002)

    async def until(self, cond: Any, limit: int = 20000) -> None:
        for _ in range(limit):
            if cond():
                return
            await self.cycles(1)
            if self.executor_task.done():
                self.executor_task.result()
        raise AssertionError("condition not reached")

    def start(self) -> None:
        self.executor_task = asyncio.get_running_loop().create_task(self.executor.run())

    async def stop(self) -> None:
        self.executor.stop_claiming()
        await self.cycles(3)
        await asyncio.wait_for(self.executor_task, 5.0)
        self.store.close()


def submit(store: Store, key: str, requests: list[dict[str, Any]]) -> list[int]:
    _, targets, _ = store.submit_batch(key, key, requests)
    return [t.id for t in targets]


def axes(i: int) -> list[float]:
    return [5.0 * i, -85.0 + i, 92.0 - i, 1.0, 30.0 + i, 2.0]


def record(i: int, pose_id: str | None = None) -> dict[str, Any]:
    """A queued target's request as the service stores it."""
    return Target(axes_deg=tuple(axes(i)), pose_id=pose_id).to_record()


async def test_targets_run_one_at_a_time_in_queue_order(tmp_path: Path) -> None:
    cell = Cell(tmp_path)
    await cell.cycles(5)
    ids_a = submit(cell.store, "batch-a", [record(i) for i in range(3)])
    ids_b = submit(cell.store, "batch-b", [record(i) for i in (3, 4)])
    cell.start()
    await cell.until(lambda: len(cell.outcomes) == 5)
    order = ids_a + ids_b
    assert [o.target_id for o in cell.outcomes] == order
    assert all(o.state == "done" for o in cell.outcomes)
    # every target went through the whole lifecycle, and the next began only after the last was done
    kinds = [(t, k) for t, k in cell.log]
    expected = [(t, f"target.{s}") for t in order for s in ("compensating", "moving", "settling", "done")]
    assert kinds == expected
    assert cell.robot.moves == [compensate(Target.from_record(record(i))).commanded_deg for i in range(5)]
    for tid in order:
        rec = cell.store.get_target(tid)
        assert rec.state == "done"
        assert rec.commanded_axes_deg is not None
        assert rec.final_joint_errors_deg is not None
        assert set(rec.final_joint_errors_deg) == {"A1", "A2", "A3"}
        assert all(v is not None and abs(v) <= 0.001 for v in rec.final_joint_errors_deg.values())
    # the loop took the offsets out: the joints sit at the commanded angles
    last = compensate(Target.from_record(record(4))).commanded_deg
    for j in JOINTS:
        assert cell.robot.angle(j) == pytest.approx(last[j - 1], abs=0.001)
    assert cell.runtime.core.state is SafetyState.IDLE
    await cell.stop()


async def test_failures_are_recorded_and_the_queue_goes_on(tmp_path: Path) -> None:
    cell = Cell(tmp_path)
    await cell.cycles(5)
    refused = compensate(Target.from_record(record(2))).commanded_deg
    cell.robot.refuse.add(refused)
    ids = submit(
        cell.store,
        "b",
        [
            record(1, pose_id="unreachable"),
            record(2),
            record(3),
            record(4),
        ],
    )
    cell.start()
    await cell.until(lambda: cell.executor.current_target_id == ids[3] and cell.executor.phase == "settling")
    cell.gratings[2].broken = True  # CRC errors while settling: freeze, target failed
    await cell.until(lambda: len(cell.outcomes) == 4)
    states = [(o.target_id, o.state) for o in cell.outcomes]
    assert states == [(ids[0], "failed"), (ids[1], "failed"), (ids[2], "done"), (ids[3], "failed")]
    assert "compensation: target outside the workspace" in (cell.outcomes[0].reason or "")
    assert "motion: A2 outside its software limit" in (cell.outcomes[1].reason or "")
    reason = cell.outcomes[3].reason or ""
    assert reason.startswith("feedback_fault: A2: crc: CRC6 mismatch") and "(freeze)" in reason
    errors = cell.store.get_target(ids[3]).final_joint_errors_deg
    assert errors is not None and set(errors) == {"A1", "A2", "A3"}
    assert cell.runtime.core.state is SafetyState.FAULT and not cell.runtime.core.stop
    await cell.stop()


async def test_a_queued_request_that_is_not_a_target_fails_by_name_and_is_never_driven(
    tmp_path: Path,
) -> None:
    cell = Cell(tmp_path)
    await cell.cycles(5)
    ids = submit(cell.store, "b", [{"a1": 1.0, "a2": 2.0}, record(1)])
    cell.start()
    await cell.until(lambda: len(cell.outcomes) == 2)
    assert [(o.target_id, o.state) for o in cell.outcomes] == [(ids[0], "failed"), (ids[1], "done")]
    reason = cell.outcomes[0].reason or ""
    assert reason.startswith("the queued request is not a target: a3, a4, a5, a6 missing"), reason
    assert cell.robot.moves == [compensate(Target.from_record(record(1))).commanded_deg]
    await cell.stop()


async def test_nothing_is_claimed_while_not_ready(tmp_path: Path) -> None:
    cell = Cell(tmp_path)
    cell.ready_reason = "no active model"
    (tid,) = submit(cell.store, "b", [record(1)])
    cell.start()
    await cell.cycles(50)
    await asyncio.sleep(0.05)
    assert cell.store.get_target(tid).state == "queued"
    assert cell.executor.blocked_reason == "no active model"
    cell.ready_reason = None
    cell.executor.wake()
    await cell.until(lambda: len(cell.outcomes) == 1)
    assert cell.outcomes[0].state == "done"
    await cell.stop()


async def test_shutdown_mid_target_marks_it_interrupted(tmp_path: Path) -> None:
    cell = Cell(tmp_path)
    await cell.cycles(5)
    ids = submit(cell.store, "b", [record(1), record(2)])
    cell.start()
    await cell.until(lambda: cell.executor.phase == "settling")
    cell.executor.stop_claiming()
    cell.runtime.shutdown()
    await cell.cycles(3)
    await asyncio.wait_for(cell.executor_task, 5.0)
    assert [o.state for o in cell.outcomes] == ["interrupted"]
    rec = cell.store.get_target(ids[0])
    assert rec.state == "interrupted" and rec.reason is not None and rec.reason.startswith("shutdown")
    assert cell.store.get_target(ids[1]).state == "queued"  # never started, still in the queue
    reply = cell.runtime.handle(cell.robot.telegram())
    assert reply.ak_deg == (0.0,) * 6 and reply.stop
    assert not math.isnan(cell.runtime.core.total_correction_deg[0])
    cell.store.close()


async def test_a_full_disk_fails_the_target_safely_and_the_executor_goes_on(tmp_path: Path) -> None:
    cell = Cell(tmp_path)
    await cell.cycles(5)
    ids = submit(cell.store, "b", [record(i) for i in (1, 2, 3)])
    cell.start()
    # 1. the disk fills while the first target settles: its final state cannot be written
    cell.disk.full_at = "done"
    await cell.until(lambda: len(cell.outcomes) == 1)
    assert cell.outcomes[0].state == "done"
    assert cell.store.get_target(ids[0]).state == "settling"  # not yet recorded ...
    assert [u[:2] for u in cell.executor.unsaved] == [(ids[0], "done")]  # ... but kept
    # nothing more is claimed while the disk is full, and the executor keeps running
    await cell.until(lambda: cell.disk.refused >= 3 and cell.executor.blocked_reason is not None)
    assert not cell.executor_task.done()
    assert cell.store.get_target(ids[1]).state == "queued"
    assert cell.executor.blocked_reason is not None and "disk full" in cell.executor.blocked_reason
    assert str(cell.store.path) in cell.executor.blocked_reason
    assert cell.runtime.core.state is SafetyState.IDLE and cell.runtime.core.target_id is None
    # 2. space again: the kept state is written first, then the queue goes on
    cell.disk.full, cell.disk.full_at = False, None
    cell.executor.wake()
    await cell.until(lambda: len(cell.outcomes) == 2)
    assert cell.store.get_target(ids[0]).state == "done"
    assert cell.store.get_target(ids[0]).final_joint_errors_deg is not None
    assert cell.executor.unsaved == []
    assert cell.outcomes[1].target_id == ids[1] and cell.outcomes[1].state == "done"
    # 3. full again when the next target's move is to be recorded: it is failed, never commanded
    moves = len(cell.robot.moves)
    cell.disk.full_at = "moving"
    await cell.until(lambda: len(cell.outcomes) == 3)
    assert cell.outcomes[2].state == "failed"
    assert "the store could not record the target: disk full" in (cell.outcomes[2].reason or "")
    assert len(cell.robot.moves) == moves  # the robot was not commanded
    assert cell.runtime.core.target_id is None
    cell.disk.full, cell.disk.full_at = False, None
    cell.executor.wake()
    await cell.until(lambda: cell.store.get_target(ids[2]).state == "failed")
    assert not cell.executor_task.done()
    await cell.stop()
