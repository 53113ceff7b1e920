"""The loop's safety state machine and its per-cycle step (pure: no I/O, time passed in).

States (:class:`SafetyState`)::

    IDLE ──arm──▶ ARMED ──arrived + feedback fresh──▶ CORRECTING ──|e| ≤ tol for dwell──▶ SETTLED
      ▲             │                                     │                                 │
      └──release────┴──────────── fault ─────────────────▶ FAULT ◀──────── fault ───────────┘
                                                          │ reset (operator) / arm (freeze class)
    any ──shutdown──▶ STOPPING (terminal)

- IDLE: no target; ``AK`` = 0.
- ARMED: a target's commanded axis values are known; the robot is moving there. ``AK`` = 0. Arrival
  is read off the telegrams: the setpoint (``ASPos``, else ``AIPos`` minus our total correction)
  within ``arrival_tolerance_deg`` of the commanded values and still for ``standstill_cycles``.
- CORRECTING: seed 000's rough/PD correction (:mod:`comp_daemon.rt.controller`) on every joint with
  a grating, towards the loop target (the compensated joint angles).
- SETTLED: every controlled joint within ``settle_tolerance_deg`` for ``settle_dwell_s``; the PD keeps
  holding the joints until the executor releases the target.
- FAULT: ``AK`` = 0 (the correction already applied is held — never a jump back); the reason is kept
  in :attr:`LoopCore.fault`. A fault whose reaction is STOP also sends ``Stop = 1`` until an operator
  resets it.
- STOPPING: shutdown; ``AK`` = 0 and ``Stop = 1`` on every reply until the process exits.

Reactions (:data:`FAULT_REACTIONS`): faults that only mean "no trustworthy feedback" or "the target
cannot be finished" *freeze* (the robot is where its own program put it, plus a correction that was
valid when last computed — nothing grows, nothing needs stopping). Faults that mean "the loop itself
is wrong" *stop*: a total correction at its limit (a wrong grating calibration, swapped joints, an
inverted sign, a slipping scale) or an error that grows while correcting (divergence). Shutdown stops
the RSI program cleanly instead of letting the controller's late-reply ``Timeout`` do it.

Units: angles in deg (controller axis values), times in s from an injected monotonic clock.
Joints are 0-based indices into ``A1..A6``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from enum import StrEnum

from comp_daemon.rt.controller import (
    JointLoopSettings,
    JointLoopState,
    LoopMode,
    hold_step,
    joint_step,
)

__all__ = [
    "FAULT_REACTIONS",
    "Arrived",
    "CycleInput",
    "CycleOutput",
    "CycleResult",
    "Event",
    "Fault",
    "FaultKind",
    "Faulted",
    "FeedbackFault",
    "LoopCore",
    "Reaction",
    "Reading",
    "SafetySettings",
    "SafetyState",
    "SafetyTransitionError",
    "Settled",
    "arm",
    "fault",
    "new_core",
    "on_cycle",
    "on_tick",
    "release",
    "reset",
    "shutdown",
]

N_AXES = 6
ZERO_AK: tuple[float, ...] = (0.0,) * N_AXES


class SafetyState(StrEnum):
    IDLE = "idle"
    ARMED = "armed"
    CORRECTING = "correcting"
    SETTLED = "settled"
    FAULT = "fault"
    STOPPING = "stopping"


class FaultKind(StrEnum):
    FEEDBACK_STALE = "feedback_stale"
    FEEDBACK_FAULT = "feedback_fault"
    MODEL_MISSING = "model_missing"
    CORRECTION_LIMIT = "correction_limit"
    DIVERGING = "diverging"
    NOT_ARRIVED = "not_arrived"
    NOT_SETTLED = "not_settled"
    ROBOT_MOVED = "robot_moved"
    RSI_LOST = "rsi_lost"
    SHUTDOWN = "shutdown"


class Reaction(StrEnum):
    FREEZE = "freeze"
    STOP = "stop"


#: What each fault does besides zeroing the steps (see the module docstring and docs/daemon.md).
FAULT_REACTIONS: dict[FaultKind, Reaction] = {
    FaultKind.FEEDBACK_STALE: Reaction.FREEZE,
    FaultKind.FEEDBACK_FAULT: Reaction.FREEZE,
    FaultKind.MODEL_MISSING: Reaction.FREEZE,
    FaultKind.CORRECTION_LIMIT: Reaction.STOP,
    FaultKind.DIVERGING: Reaction.STOP,
    FaultKind.NOT_ARRIVED: Reaction.FREEZE,
    FaultKind.NOT_SETTLED: Reaction.FREEZE,
    FaultKind.ROBOT_MOVED: Reaction.FREEZE,
    FaultKind.RSI_LOST: Reaction.FREEZE,
    FaultKind.SHUTDOWN: Reaction.STOP,
}


class SafetyTransitionError(RuntimeError):
    """A command that the current state does not allow (e.g. arming while a stop fault is latched)."""


@dataclass(frozen=True, slots=True)
class SafetySettings:
    """Tolerances and time limits of the supervisor (deg, s, cycles)."""

    arrival_tolerance_deg: float = 0.002
    standstill_tolerance_deg: float = 0.0002
    standstill_cycles: int = 3
    settle_tolerance_deg: float = 0.001
    settle_dwell_s: float = 0.24
    move_timeout_s: float = 120.0
    settle_timeout_s: float = 10.0
    divergence_margin_deg: float = 0.02
    robot_moved_tolerance_deg: float = 0.01
    rsi_lost_after_s: float = 0.25
    session_gap_s: float = 0.5  # a telegram after a longer gap counts as a new RSI session

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")


@dataclass(frozen=True, slots=True)
class FeedbackFault:
    """A joint's feedback is not usable this cycle: ``stale`` or a ``fault`` (CRC, error bit, gone)."""

    kind: FaultKind
    detail: str


#: A grating reading: the joint angle (deg) and when it was taken (s, the cycle's clock).
Reading = tuple[float, float]
#: Per controlled joint: a reading, or why there is none.
Feedback = Reading | FeedbackFault


@dataclass(frozen=True, slots=True)
class Fault:
    kind: FaultKind
    reaction: Reaction
    detail: str
    at_s: float
    target_id: str | None = None


@dataclass(frozen=True, slots=True)
class LoopCore:
    """Everything the per-telegram step needs, replaced (never mutated) every cycle."""

    joints: tuple[int, ...]
    loops: tuple[JointLoopState, ...]
    state: SafetyState = SafetyState.IDLE
    fault: Fault | None = None
    target_id: str | None = None
    commanded_deg: tuple[float, ...] | None = None
    loop_target_deg: tuple[float, ...] | None = None
    armed_at_s: float = math.nan
    correcting_since_s: float = math.nan
    within_since_s: float = math.nan
    standstill_count: int = 0
    last_setpoint_deg: tuple[float, ...] | None = None
    best_abs_error_deg: tuple[float, ...] = ()
    errors_deg: tuple[float, ...] = ()
    last_telegram_s: float = math.nan
    cycles: int = 0
    step_clamps: int = 0
    sessions: int = 0

    @property
    def stop(self) -> bool:
        """True while ``Stop = 1`` must be sent."""
        if self.state is SafetyState.STOPPING:
            return True
        return (
            self.state is SafetyState.FAULT
            and self.fault is not None
            and self.fault.reaction is Reaction.STOP
        )

    @property
    def total_correction_deg(self) -> tuple[float, ...]:
        """The correction applied so far (sum of the steps sent), per axis A1..A6."""
        out = [0.0] * N_AXES
        for j, loop in zip(self.joints, self.loops, strict=True):
            out[j] = loop.total_deg
        return tuple(out)


@dataclass(frozen=True, slots=True)
class CycleInput:
    """One telegram's worth of inputs; ``feedback`` has one entry per controlled joint."""

    now_s: float
    ipoc: int
    setpoint_deg: tuple[float, ...] | None
    actual_deg: tuple[float, ...] | None
    feedback: tuple[Feedback, ...]


@dataclass(frozen=True, slots=True)
class CycleOutput:
    ak_deg: tuple[float, ...] = ZERO_AK
    stop: bool = False


@dataclass(frozen=True, slots=True)
class Arrived:
    target_id: str | None
    at_s: float


@dataclass(frozen=True, slots=True)
class Settled:
    target_id: str | None
    at_s: float
    errors_deg: tuple[float, ...]
    correction_deg: tuple[float, ...]
    settle_time_s: float
    kd_scale: tuple[float, ...] = ()  # per controlled joint: < 1 where the hunting guard cut kD


@dataclass(frozen=True, slots=True)
class Faulted:
    target_id: str | None
    fault: Fault
    errors_deg: tuple[float, ...]


Event = Arrived | Settled | Faulted


@dataclass(frozen=True, slots=True)
class CycleResult:
    core: LoopCore
    output: CycleOutput
    events: tuple[Event, ...] = field(default=())


def new_core(joints: Sequence[int]) -> LoopCore:
    """An IDLE core for the joints that have gratings (0-based indices, ascending)."""
    js = tuple(sorted(int(j) for j in joints))
    if len(set(js)) != len(js) or any(not 0 <= j < N_AXES for j in js):
        raise ValueError(f"joints must be distinct indices 0..5, got {list(joints)}")
    nan = (math.nan,) * len(js)
    return LoopCore(
        joints=js, loops=tuple(JointLoopState() for _ in js), errors_deg=nan, best_abs_error_deg=nan
    )


# --------------------------------------------------------------------------------------- commands


def arm(
    core: LoopCore,
    target_id: str,
    commanded_deg: Sequence[float],
    loop_target_deg: Sequence[float],
    now_s: float,
) -> LoopCore:
    """Take a target: the robot is about to move to ``commanded_deg`` (6 axis values); once there,
    the loop drives the controlled joints to ``loop_target_deg`` (one per controlled joint)."""
    if core.state is SafetyState.STOPPING:
        raise SafetyTransitionError("the loop is shutting down")
    if core.state in (SafetyState.ARMED, SafetyState.CORRECTING, SafetyState.SETTLED):
        raise SafetyTransitionError(f"target {core.target_id} is still active ({core.state})")
    if core.state is SafetyState.FAULT and core.fault is not None and core.fault.reaction is Reaction.STOP:
        raise SafetyTransitionError(
            f"a stop fault is latched ({core.fault.kind}: {core.fault.detail}); an operator must reset it"
        )
    commanded = tuple(float(v) for v in commanded_deg)
    loop_target = tuple(float(v) for v in loop_target_deg)
    if len(commanded) != N_AXES:
        raise ValueError(f"commanded_deg needs 6 axis values, got {len(commanded)}")
    if len(loop_target) != len(core.joints):
        raise ValueError(f"loop_target_deg needs {len(core.joints)} values, got {len(loop_target)}")
    if not all(math.isfinite(v) for v in commanded + loop_target):
        raise ValueError("commanded_deg and loop_target_deg must be finite")
    nan = (math.nan,) * len(core.joints)
    return replace(
        core,
        loops=tuple(loop.for_new_target() for loop in core.loops),
        state=SafetyState.ARMED,
        fault=None,
        target_id=target_id,
        commanded_deg=commanded,
        loop_target_deg=loop_target,
        armed_at_s=now_s,
        correcting_since_s=math.nan,
        within_since_s=math.nan,
        standstill_count=0,
        last_setpoint_deg=None,
        best_abs_error_deg=nan,
        errors_deg=nan,
    )


def release(core: LoopCore) -> LoopCore:
    """Let go of the current target (after it was reported): back to IDLE, the correction kept."""
    if core.state in (SafetyState.STOPPING, SafetyState.FAULT):
        return replace(core, target_id=None, commanded_deg=None, loop_target_deg=None)
    return replace(
        core, state=SafetyState.IDLE, target_id=None, commanded_deg=None, loop_target_deg=None, fault=None
    )


def reset(core: LoopCore) -> LoopCore:
    """Operator acknowledgement of a fault: FAULT → IDLE (nothing else changes state)."""
    if core.state is not SafetyState.FAULT:
        return core
    return replace(
        core, state=SafetyState.IDLE, fault=None, target_id=None, commanded_deg=None, loop_target_deg=None
    )


def fault(core: LoopCore, kind: FaultKind, detail: str, now_s: float) -> CycleResult:
    """Enter FAULT (or STOPPING for a shutdown) from outside the cycle, e.g. the model vanished."""
    if core.state is SafetyState.STOPPING or (core.state is SafetyState.FAULT and core.stop):
        return CycleResult(core, _idle_output(core))  # never downgrade a latched stop
    return _to_fault(core, kind, detail, now_s)


def shutdown(core: LoopCore, now_s: float) -> CycleResult:
    """Shutdown: steps zero, ``Stop = 1``; the active target (if any) is reported as faulted."""
    events: tuple[Event, ...] = ()
    if core.state in (SafetyState.ARMED, SafetyState.CORRECTING, SafetyState.SETTLED):
        f = Fault(FaultKind.SHUTDOWN, Reaction.STOP, "the daemon is shutting down", now_s, core.target_id)
        events = (Faulted(core.target_id, f, core.errors_deg),)
    new = replace(core, state=SafetyState.STOPPING)
    return CycleResult(new, CycleOutput(ZERO_AK, True), events)


def on_tick(settings: SafetySettings, core: LoopCore, now_s: float) -> CycleResult:
    """Timer check between telegrams: a loop that is waiting on telegrams that stopped coming."""
    if core.state not in (SafetyState.ARMED, SafetyState.CORRECTING, SafetyState.SETTLED):
        return CycleResult(core, _idle_output(core))
    last = core.last_telegram_s
    since = core.armed_at_s if math.isnan(last) else max(last, core.armed_at_s)
    if now_s - since > settings.rsi_lost_after_s:
        return _to_fault(core, FaultKind.RSI_LOST, f"no RSI telegram for {now_s - since:.3f} s", now_s)
    if core.state is SafetyState.ARMED and now_s - core.armed_at_s > settings.move_timeout_s:
        return _to_fault(
            core, FaultKind.NOT_ARRIVED, f"the robot did not arrive within {settings.move_timeout_s} s", now_s
        )
    return CycleResult(core, _idle_output(core))


# --------------------------------------------------------------------------------------- the cycle


def on_cycle(
    settings: SafetySettings, loop_settings: JointLoopSettings, core: LoopCore, inp: CycleInput
) -> CycleResult:
    """One RSI cycle: supervise, and in CORRECTING/SETTLED run the controller. O(joints)."""
    new_session = (
        math.isnan(core.last_telegram_s) or inp.now_s - core.last_telegram_s > settings.session_gap_s
    )
    core = replace(
        core, last_telegram_s=inp.now_s, cycles=core.cycles + 1, sessions=core.sessions + new_session
    )
    state = core.state

    if state is SafetyState.ARMED:
        return _armed(settings, loop_settings, core, inp)
    if state in (SafetyState.CORRECTING, SafetyState.SETTLED):
        return _correcting(settings, loop_settings, core, inp)
    return _hold(core, inp)


def _hold(core: LoopCore, inp: CycleInput) -> CycleResult:
    loops = []
    for s, fb in zip(core.loops, inp.feedback, strict=True):
        if isinstance(fb, FeedbackFault):
            loops.append(hold_step(s, None, None).state)
        else:
            loops.append(hold_step(s, fb[0], fb[1]).state)
    if core.loop_target_deg is not None:
        errors = tuple(
            math.nan if isinstance(fb, FeedbackFault) else t - fb[0]
            for t, fb in zip(core.loop_target_deg, inp.feedback, strict=True)
        )
        core = replace(core, loops=tuple(loops), errors_deg=errors)
    else:
        core = replace(core, loops=tuple(loops))
    return CycleResult(core, _idle_output(core))


def _idle_output(core: LoopCore) -> CycleOutput:
    return CycleOutput(ZERO_AK, core.stop)


def _setpoint(core: LoopCore, inp: CycleInput) -> tuple[float, ...] | None:
    if inp.setpoint_deg is not None:
        return inp.setpoint_deg
    if inp.actual_deg is None:
        return None
    total = core.total_correction_deg
    return tuple(a - t for a, t in zip(inp.actual_deg, total, strict=True))


def _feedback_fault(core: LoopCore, inp: CycleInput) -> tuple[FaultKind, str] | None:
    for j, fb in zip(core.joints, inp.feedback, strict=True):
        if isinstance(fb, FeedbackFault):
            return fb.kind, f"A{j + 1}: {fb.detail}"
    return None


def _armed(
    settings: SafetySettings, loop_settings: JointLoopSettings, core: LoopCore, inp: CycleInput
) -> CycleResult:
    held = _hold(core, inp)
    core = held.core
    assert core.commanded_deg is not None
    if inp.now_s - core.armed_at_s > settings.move_timeout_s:
        return _to_fault(
            core,
            FaultKind.NOT_ARRIVED,
            f"the robot did not arrive within {settings.move_timeout_s} s",
            inp.now_s,
        )
    sp = _setpoint(core, inp)
    if sp is None:
        return held
    at_target = max(abs(s - c) for s, c in zip(sp, core.commanded_deg, strict=True))
    prev = core.last_setpoint_deg
    still = prev is not None and max(abs(s - p) for s, p in zip(sp, prev, strict=True)) <= (
        settings.standstill_tolerance_deg
    )
    count = core.standstill_count + 1 if (still and at_target <= settings.arrival_tolerance_deg) else 0
    core = replace(core, last_setpoint_deg=sp, standstill_count=count)
    if count < settings.standstill_cycles:
        return CycleResult(core, _idle_output(core))
    # arrived: start correcting only with fresh feedback on every controlled joint
    bad = _feedback_fault(core, inp)
    if bad is not None:
        return _to_fault(core, bad[0], bad[1], inp.now_s)
    core = replace(core, state=SafetyState.CORRECTING, correcting_since_s=inp.now_s, loops=_synced(core, inp))
    arrived = Arrived(core.target_id, inp.now_s)
    # the hold above recorded this cycle's measurement, so the first D term is zero (bumpless)
    result = _correcting(settings, loop_settings, core, inp)
    return CycleResult(result.core, result.output, (arrived, *result.events))


def _synced(core: LoopCore, inp: CycleInput) -> tuple[JointLoopState, ...]:
    """The loops with their totals taken from the robot at standstill (``AIPos − ASPos``).

    The sum of the steps sent is what the robot applies only if it applied each exactly once and
    kept them; a late reply held over (HOLDON), a controller that clipped (AXISCORR) or a new RSI
    session that dropped or kept the corrections make the two differ. At arrival the servo has
    caught up, so the telegram tells the correction really in effect, and the total limit is
    checked against that.
    """
    if inp.actual_deg is None or inp.setpoint_deg is None:
        return core.loops
    return tuple(
        replace(loop, total_deg=inp.actual_deg[j] - inp.setpoint_deg[j])
        for j, loop in zip(core.joints, core.loops, strict=True)
    )


def _correcting(
    settings: SafetySettings, loop_settings: JointLoopSettings, core: LoopCore, inp: CycleInput
) -> CycleResult:
    """One cycle of the joint loops (CORRECTING, SETTLED): the guards, every joint's step, then the
    correction limit, divergence and the settling rule, in that order."""
    assert core.loop_target_deg is not None and core.commanded_deg is not None
    now = inp.now_s
    bad = _feedback_fault(core, inp)
    if bad is not None:
        return _to_fault(core, bad[0], bad[1], now)
    moved = _robot_moved(settings, core, inp)
    if moved is not None:
        return _to_fault(core, FaultKind.ROBOT_MOVED, moved, now)
    core, ak, limited, diverged = _joint_steps(settings, loop_settings, core, inp)
    if limited:
        # the step that reached the limit is still sent (it only brings the total up to the
        # limit); from the next cycle on the fault keeps every step at zero
        res_fault = _to_fault(
            core, FaultKind.CORRECTION_LIMIT, "correction limit reached: " + ", ".join(limited), now
        )
        return CycleResult(res_fault.core, CycleOutput(ak, True), res_fault.events)
    if diverged:
        return _to_fault(
            core, FaultKind.DIVERGING, "error grows while correcting: " + ", ".join(diverged), now
        )
    return _settling(settings, core, now, CycleOutput(ak, False))


def _robot_moved(settings: SafetySettings, core: LoopCore, inp: CycleInput) -> str | None:
    """Why the robot's setpoint has left the commanded pose (more than the tolerance); None if it has not."""
    assert core.commanded_deg is not None
    sp = _setpoint(core, inp)
    if sp is None:
        return None
    moved = max(abs(s - c) for s, c in zip(sp, core.commanded_deg, strict=True))
    if moved > settings.robot_moved_tolerance_deg:
        return f"the setpoint left the commanded pose by {moved:.4f} deg while correcting"
    return None


def _joint_steps(
    settings: SafetySettings, loop_settings: JointLoopSettings, core: LoopCore, inp: CycleInput
) -> tuple[LoopCore, tuple[float, ...], list[str], list[str]]:
    """Every loop joint's step on its reading: the core with the loops, errors, best errors and clamp
    count moved on, the AK correction of this cycle, and the joints that reached the correction
    limit or whose error grew beyond the best so far by more than the divergence margin."""
    assert core.loop_target_deg is not None
    ak = [0.0] * N_AXES
    loops: list[JointLoopState] = []
    errors: list[float] = []
    best: list[float] = []
    clamps = core.step_clamps
    limited: list[str] = []
    diverged: list[str] = []
    for i, j in enumerate(core.joints):
        reading = inp.feedback[i]
        assert not isinstance(reading, FeedbackFault)
        res = joint_step(loop_settings, core.loops[i], core.loop_target_deg[i], reading[0], reading[1])
        ak[j] = res.step_deg
        loops.append(res.state)
        err = res.error_deg
        errors.append(err)
        prev_best = core.best_abs_error_deg[i]
        b = abs(err) if math.isnan(prev_best) else min(prev_best, abs(err))
        best.append(b)
        clamps += res.step_clamped
        if res.total_limited:
            limited.append(f"A{j + 1} total {res.state.total_deg:+.6f} deg")
        if abs(err) > b + settings.divergence_margin_deg:
            diverged.append(f"A{j + 1} error {err:+.6f} deg (best {b:.6f})")
    core = replace(
        core, loops=tuple(loops), errors_deg=tuple(errors), best_abs_error_deg=tuple(best), step_clamps=clamps
    )
    return core, tuple(ak), limited, diverged


def _settling(settings: SafetySettings, core: LoopCore, now: float, output: CycleOutput) -> CycleResult:
    """The settling rule on the errors of this cycle: every joint within the settle tolerance for the
    dwell makes CORRECTING SETTLED (once); out of it, the dwell starts again, and a CORRECTING target
    not settled within the settle timeout is a fault."""
    worst = max(abs(e) for e in core.errors_deg) if core.errors_deg else 0.0
    events: tuple[Event, ...] = ()
    if worst <= settings.settle_tolerance_deg:
        since = now if math.isnan(core.within_since_s) else core.within_since_s
        core = replace(core, within_since_s=since)
        if core.state is SafetyState.CORRECTING and now - since >= settings.settle_dwell_s - 1e-9:
            core = replace(core, state=SafetyState.SETTLED)
            events = (
                Settled(
                    core.target_id,
                    now,
                    core.errors_deg,
                    core.total_correction_deg,
                    now - core.correcting_since_s,
                    tuple(loop.kd_scale for loop in core.loops),
                ),
            )
    else:
        core = replace(core, within_since_s=math.nan)
        if core.state is SafetyState.CORRECTING and now - core.correcting_since_s > settings.settle_timeout_s:
            return _to_fault(
                core,
                FaultKind.NOT_SETTLED,
                f"not within {settings.settle_tolerance_deg} deg after {settings.settle_timeout_s} s "
                f"(worst error {worst:.6f} deg)",
                now,
            )
    return CycleResult(core, output, events)


def _to_fault(core: LoopCore, kind: FaultKind, detail: str, now_s: float) -> CycleResult:
    reaction = FAULT_REACTIONS[kind]
    f = Fault(kind, reaction, detail, now_s, core.target_id)
    had_target = core.state in (SafetyState.ARMED, SafetyState.CORRECTING, SafetyState.SETTLED)
    loops = tuple(replace(s, mode=LoopMode.ROUGH, prev_measured_deg=math.nan) for s in core.loops)
    new = replace(core, state=SafetyState.FAULT, fault=f, loops=loops)
    events: tuple[Event, ...] = (Faulted(core.target_id, f, core.errors_deg),) if had_target else ()
    return CycleResult(new, CycleOutput(ZERO_AK, new.stop), events)
