"""The safety state machine driven cycle by cycle against a small simulated joint set (pure, no I/O)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import pytest

from comp_daemon.rt.controller import JointLoopSettings
from comp_daemon.rt.safety import (
    FAULT_REACTIONS,
    Arrived,
    CycleInput,
    CycleResult,
    Faulted,
    FaultKind,
    FeedbackFault,
    LoopCore,
    Reaction,
    SafetySettings,
    SafetyState,
    SafetyTransitionError,
    Settled,
    arm,
    fault,
    new_core,
    on_cycle,
    on_tick,
    release,
    reset,
    shutdown,
)

CYCLE_S = 0.012
JOINTS = (0, 1, 2)
SAFETY = SafetySettings()
LOOP = JointLoopSettings()


@dataclass
class Cell:
    """Setpoint ramps to the commanded pose; each controlled joint sits at setpoint + offset + applied AK.

    AK answered to telegram k is applied at telegram k + 1 + lag.
    """

    offsets_deg: tuple[float, ...] = (0.012, -0.006, 0.03)
    lag: int = 1
    grating_sign: float = 1.0
    settings: SafetySettings = SAFETY
    loop: JointLoopSettings = LOOP
    core: LoopCore = field(default_factory=lambda: new_core(JOINTS))
    now: float = 0.0
    ipoc: int = 1000
    setpoint: list[float] = field(default_factory=lambda: [0.0, -90.0, 90.0, 0.0, 45.0, 0.0])
    goal: list[float] | None = None
    applied: list[float] = field(default_factory=lambda: [0.0] * 6)
    sent: list[tuple[float, ...]] = field(default_factory=list)
    results: list[CycleResult] = field(default_factory=list)
    speed_deg_per_cycle: float = 0.5
    override: dict[int, tuple[float, float] | FeedbackFault] = field(default_factory=dict)

    def angles(self) -> list[float]:
        return [self.setpoint[j] + self.offsets_deg[i] + self.applied[j] for i, j in enumerate(JOINTS)]

    def cycle(self) -> CycleResult:
        k = len(self.sent)
        if k - 1 - self.lag >= 0:
            for a in range(6):
                self.applied[a] += self.sent[k - 1 - self.lag][a]
        if self.goal is not None:
            for a in range(6):
                d = self.goal[a] - self.setpoint[a]
                self.setpoint[a] += max(-self.speed_deg_per_cycle, min(self.speed_deg_per_cycle, d))
        feedback: list[tuple[float, float] | FeedbackFault] = []
        for i, angle in enumerate(self.angles()):
            feedback.append(self.override.get(i, (self.grating_sign * angle, self.now)))
        actual = tuple(s + a for s, a in zip(self.setpoint, self.applied, strict=True))
        inp = CycleInput(self.now, self.ipoc, tuple(self.setpoint), actual, tuple(feedback))
        res = on_cycle(self.settings, self.loop, self.core, inp)
        self.core = res.core
        self.sent.append(res.output.ak_deg)
        self.results.append(res)
        self.now += CYCLE_S
        self.ipoc += 12
        return res

    def run(self, n: int) -> list[CycleResult]:
        return [self.cycle() for _ in range(n)]

    def arm(self, goal: list[float], target_id: str = "t1") -> None:
        self.goal = goal
        self.core = arm(self.core, target_id, goal, [goal[j] for j in JOINTS], self.now)

    def events(self) -> list[object]:
        return [e for r in self.results for e in r.events]


GOAL = [5.0, -85.0, 92.0, 1.0, 40.0, 3.0]


def test_target_goes_armed_correcting_settled_and_back_to_idle() -> None:
    cell = Cell()
    cell.run(5)
    assert cell.core.state is SafetyState.IDLE and all(ak == (0.0,) * 6 for ak in cell.sent)
    cell.arm(GOAL)
    assert cell.core.state is SafetyState.ARMED
    for _ in range(400):
        cell.cycle()
        if cell.core.state is SafetyState.SETTLED:
            break
    assert cell.core.state is SafetyState.SETTLED
    kinds = [type(e) for e in cell.events()]
    assert kinds == [Arrived, Settled]
    arrived = next(e for e in cell.events() if isinstance(e, Arrived))
    settled = next(e for e in cell.events() if isinstance(e, Settled))
    assert settled.target_id == "t1" and settled.at_s > arrived.at_s
    # no correction while the robot was moving
    i_arrived = round(arrived.at_s / CYCLE_S)
    assert all(ak == (0.0,) * 6 for ak in cell.sent[:i_arrived])
    assert max(abs(e) for e in settled.errors_deg) <= SAFETY.settle_tolerance_deg
    # the correction found is the joint offset (seed 000: backlash etc. taken out by the grating)
    for i, j in enumerate(JOINTS):
        assert settled.correction_deg[j] == pytest.approx(-cell.offsets_deg[i], abs=0.0015)
    # the true joint angles now match the loop target
    for i, j in enumerate(JOINTS):
        assert cell.angles()[i] == pytest.approx(GOAL[j], abs=SAFETY.settle_tolerance_deg)
    assert all(abs(v) <= LOOP.max_step_deg for ak in cell.sent for v in ak)
    # SETTLED keeps holding; release goes back to IDLE with the correction kept
    cell.run(10)
    assert cell.core.state is SafetyState.SETTLED
    total = cell.core.total_correction_deg
    cell.core = release(cell.core)
    res = cell.cycle()
    assert cell.core.state is SafetyState.IDLE and res.output.ak_deg == (0.0,) * 6
    assert cell.core.total_correction_deg == pytest.approx(total)


def settle(cell: Cell) -> None:
    cell.arm(GOAL)
    for _ in range(400):
        cell.cycle()
        if cell.core.state is SafetyState.SETTLED:
            return
    raise AssertionError("did not settle")


def until_correcting(cell: Cell, extra: int = 3) -> None:
    cell.arm(GOAL)
    for _ in range(400):
        cell.cycle()
        if cell.core.state is SafetyState.CORRECTING:
            cell.run(extra)
            return
    raise AssertionError("never started correcting")


def test_stale_feedback_freezes_without_a_jump_or_a_stop() -> None:
    cell = Cell()
    until_correcting(cell)
    total_before = cell.core.total_correction_deg
    cell.override[1] = FeedbackFault(FaultKind.FEEDBACK_STALE, "reading 40 ms old")
    res = cell.cycle()
    assert cell.core.state is SafetyState.FAULT
    assert res.output.ak_deg == (0.0,) * 6 and res.output.stop is False
    assert cell.core.fault is not None and cell.core.fault.kind is FaultKind.FEEDBACK_STALE
    assert "A2: reading 40 ms old" in cell.core.fault.detail
    (ev,) = res.events
    assert isinstance(ev, Faulted) and ev.target_id == "t1"
    assert cell.core.total_correction_deg == total_before  # held, not unwound
    for r in cell.run(20):
        assert r.output.ak_deg == (0.0,) * 6 and not r.output.stop
    # a freeze fault does not block the next target once feedback is back
    cell.override.clear()
    cell.arm([g + 1.0 for g in GOAL], "t2")
    assert cell.core.state is SafetyState.ARMED and cell.core.fault is None


def test_faulty_feedback_at_arrival_never_starts_correcting() -> None:
    cell = Cell()
    cell.override[0] = FeedbackFault(FaultKind.FEEDBACK_FAULT, "CRC mismatch")
    cell.arm(GOAL)
    cell.run(60)
    assert cell.core.state is SafetyState.FAULT
    assert cell.core.fault is not None and cell.core.fault.kind is FaultKind.FEEDBACK_FAULT
    assert all(ak == (0.0,) * 6 for ak in cell.sent)


def test_total_limit_stops_and_latches_until_an_operator_resets() -> None:
    cell = Cell(loop=JointLoopSettings(max_total_deg=0.02), offsets_deg=(0.0, 0.0, 0.05))
    until_correcting(cell, extra=0)
    for _ in range(100):
        res = cell.cycle()
        if cell.core.state is SafetyState.FAULT:
            break
    assert cell.core.fault is not None and cell.core.fault.kind is FaultKind.CORRECTION_LIMIT
    assert res.output.stop is True
    assert "A3 total -0.020000" in cell.core.fault.detail
    assert abs(cell.core.total_correction_deg[2]) == pytest.approx(0.02)
    for r in cell.run(5):
        assert r.output.stop and r.output.ak_deg == (0.0,) * 6
    with pytest.raises(SafetyTransitionError, match="operator must reset"):
        arm(cell.core, "t2", GOAL, GOAL[:3], cell.now)
    cell.core = reset(cell.core)
    assert cell.core.state is SafetyState.IDLE and not cell.cycle().output.stop


def test_an_inverted_grating_is_caught_as_divergence_and_stops() -> None:
    # measured = -angle: every correction makes the error grow
    cell = Cell(offsets_deg=(0.0, 0.0, 0.0), grating_sign=-1.0)
    cell.arm(GOAL)
    cell.run(200)
    assert cell.core.fault is not None
    assert cell.core.fault.kind is FaultKind.DIVERGING
    assert cell.core.stop
    assert max(abs(v) for v in cell.core.total_correction_deg) < SAFETY.divergence_margin_deg + 0.01


def test_shutdown_mid_target_zeroes_steps_sends_stop_and_reports_the_target() -> None:
    cell = Cell()
    until_correcting(cell, extra=2)
    assert any(v != 0.0 for v in cell.sent[-1])
    total = cell.core.total_correction_deg
    res = shutdown(cell.core, cell.now)
    cell.core = res.core
    assert res.output.ak_deg == (0.0,) * 6 and res.output.stop
    (ev,) = res.events
    assert isinstance(ev, Faulted) and ev.fault.kind is FaultKind.SHUTDOWN and ev.target_id == "t1"
    for r in cell.run(5):
        assert r.output.ak_deg == (0.0,) * 6 and r.output.stop
    assert cell.core.state is SafetyState.STOPPING
    assert cell.core.total_correction_deg == total
    with pytest.raises(SafetyTransitionError, match="shutting down"):
        arm(cell.core, "t2", GOAL, GOAL[:3], cell.now)


def test_shutdown_when_idle_reports_nothing() -> None:
    res = shutdown(new_core(JOINTS), 0.0)
    assert res.events == () and res.output.stop and res.core.state is SafetyState.STOPPING


def test_missing_model_freezes_and_does_not_downgrade_a_stop() -> None:
    cell = Cell()
    until_correcting(cell)
    res = fault(cell.core, FaultKind.MODEL_MISSING, "model 7 was deactivated", cell.now)
    assert res.core.state is SafetyState.FAULT and not res.output.stop
    assert isinstance(res.events[0], Faulted)
    stopped = shutdown(res.core, cell.now).core
    again = fault(stopped, FaultKind.FEEDBACK_STALE, "x", cell.now)
    assert again.core.state is SafetyState.STOPPING and again.output.stop


def test_telegrams_stopping_is_noticed_by_the_tick() -> None:
    cell = Cell()
    until_correcting(cell)
    assert on_tick(SAFETY, cell.core, cell.now + 0.1).core.state is SafetyState.CORRECTING
    res = on_tick(SAFETY, cell.core, cell.now + 1.0)
    assert res.core.fault is not None and res.core.fault.kind is FaultKind.RSI_LOST
    assert isinstance(res.events[0], Faulted)


def test_move_timeout_and_settle_timeout() -> None:
    cell = Cell(settings=SafetySettings(move_timeout_s=0.5), speed_deg_per_cycle=0.01)
    cell.arm(GOAL)
    cell.run(60)
    assert cell.core.fault is not None and cell.core.fault.kind is FaultKind.NOT_ARRIVED
    # a joint whose grating reading never updates gets no steps and cannot settle
    slow = Cell(settings=SafetySettings(settle_timeout_s=0.3, divergence_margin_deg=1.0))
    slow.arm(GOAL)
    slow.override[0] = (0.0, -1.0)
    slow.run(200)
    assert slow.core.fault is not None and slow.core.fault.kind is FaultKind.NOT_SETTLED


def test_robot_moving_away_while_correcting_freezes() -> None:
    cell = Cell()
    until_correcting(cell)
    cell.goal = [g + 2.0 for g in GOAL]
    cell.run(5)
    assert cell.core.fault is not None and cell.core.fault.kind is FaultKind.ROBOT_MOVED
    assert not cell.core.stop


@pytest.mark.parametrize("robot_keeps_corrections", [True, False])
def test_at_arrival_the_total_is_what_the_robot_applies(robot_keeps_corrections: bool) -> None:
    cell = Cell()
    settle(cell)
    sent = cell.core.total_correction_deg
    assert any(v != 0.0 for v in sent)
    cell.core = release(cell.core)
    cell.now += 2.0  # RSI was off for 2 s; a new session starts
    if not robot_keeps_corrections:
        cell.applied = [0.0] * 6
    cell.arm([g + 0.5 for g in GOAL], "t2")
    for _ in range(100):
        if any(isinstance(e, Arrived) and e.target_id == "t2" for e in cell.cycle().events):
            break
    assert cell.core.sessions == 2
    expected = sent if robot_keeps_corrections else (0.0,) * 6
    for j in JOINTS:
        # the step of the arrival cycle is on top of the synced total (steps still in flight: < 1e-4)
        assert cell.core.total_correction_deg[j] == pytest.approx(expected[j] + cell.sent[-1][j], abs=1e-4)


def test_arming_is_checked() -> None:
    core = new_core(JOINTS)
    with pytest.raises(ValueError, match="6 axis values"):
        arm(core, "t", GOAL[:5], GOAL[:3], 0.0)
    with pytest.raises(ValueError, match="needs 3 values"):
        arm(core, "t", GOAL, GOAL[:2], 0.0)
    with pytest.raises(ValueError, match="finite"):
        arm(core, "t", [math.nan, *GOAL[1:]], GOAL[:3], 0.0)
    armed = arm(core, "t", GOAL, GOAL[:3], 0.0)
    with pytest.raises(SafetyTransitionError, match="still active"):
        arm(armed, "u", GOAL, GOAL[:3], 0.0)
    with pytest.raises(ValueError, match="distinct"):
        new_core([0, 0])


def test_every_fault_kind_has_a_documented_reaction() -> None:
    assert set(FAULT_REACTIONS) == set(FaultKind)
    stops = {k for k, r in FAULT_REACTIONS.items() if r is Reaction.STOP}
    assert stops == {FaultKind.CORRECTION_LIMIT, FaultKind.DIVERGING, FaultKind.SHUTDOWN}
