"""Seed 000's joint correction: rough steps, then a PD, sent as RSI ``#RELATIVE`` axis steps.

Conventions
-----------
- Angles are controller axis values in deg (``A1..A6`` as in ``AIPos`` and ``AK``); a joint is
  addressed by its 0-based index ``j`` (``A1`` is ``j = 0``).
- One call of :func:`joint_step` is one RSI cycle (12 ms with ``#IPO``, 4 ms with ``#IPO_FAST``).
  Gains are per cycle, not per second: the PD below is the discrete form the robot sees.
- ``error_deg = target_deg - measured_deg``: the target is the compensated joint angle, the
  measured one comes from the joint's grating (counts mapped by :mod:`comp_daemon.rt.grating_cal`).
- The output is a *step* (``AK`` with ``RSI_ON(#RELATIVE)``): the controller adds it to the joint
  every cycle, so the sum of all steps (``total_deg``) is the correction currently applied.

The law (seed 000, §2.3 and §3)
-------------------------------
- Rough correction: while ``|error| >= rough_threshold_deg`` the step is
  ``sign(error) * rough_step_deg`` (±0.002°/cycle by default).
- Fine correction once ``|error| < rough_threshold_deg`` (0.007°): a PD without integral term,
  ``step = kp * error - kd * (measured_k - measured_{k-1})`` (kP = 0.05, kD = 0.65). Because the
  robot integrates relative steps, the loop has zero steady-state error without an integral term.
  The D term acts on the measurement, not on the error: a new target or the switch from rough to
  fine does not kick the output, and with a fixed target the two forms are identical.
- Rough mode is re-entered only if ``|error| >= rough_reenter_deg`` (hysteresis), so noise near
  0.007° does not chatter between the modes.

Fresh readings only. The robot integrates every step, so a step computed from a reading that
has already been acted on is a step taken blind: when the grating reading is older than one cycle
(the converter is polled on its own schedule, and a busy machine delays polls in bursts) the
proportional part would be added again and again for the same error, and the derivative of two
readings several cycles apart would brake several times too hard. :func:`joint_step` therefore
takes the reading's own time stamp: a cycle without a new reading sends no step, and the velocity
of the D term is the difference of two readings divided by the cycles between them (``cycle_s``;
at least one, so readings that arrive close together never inflate it). With a fresh reading every
cycle this is exactly the law above.

Why this matters: the D path alone is the recursion ``u_k = -kd·u_(k-1-delay)`` (the joint's
per-cycle motion is the step sent ``delay`` cycles earlier), stable only while the effective ``kd``
stays below 1. A derivative taken over n cycles of motion as if it were one multiplies ``kd`` by n,
so with kD = 0.65 a reading that is only two cycles old is enough for a sustained oscillation.

On the 12 ms loop the D term sees the joint's per-cycle motion, i.e. the steps sent one to three
cycles earlier (servo lag of 1–2 cycles plus the reading's age). It therefore brakes the approach:
at the switch from rough to fine the joint still moves ~0.002°/cycle, and ``-kd * 0.002`` reverses
the step before the in-flight rough steps overshoot. With kP = 0.05, kD = 0.65 the closed loop on an
integrator with 0–10 cycles of pure delay has its slowest pole at z ≈ 0.97 (≈ 33 cycles) and stays
stable; the tests show the step responses.

Hunting guard (an addition to seed 000, which names "one PD for all poses" as its limit): with
kD = 0.65 and two or more cycles of servo lag the oscillatory poles sit at |z| ≈ 0.88–0.92, lightly
damped; a joint nonlinearity with more than unit gain over a small band (the simulated cell's play,
inside which the output moves twice as far as the motor; a slipping or springy joint can act alike)
then sustains a limit cycle about the band's width once something kicks it (a burst of late
readings, a disturbance): ±0.013° on the simulated cell. The guard counts sign changes of the error
outside ``±hunt_band_deg`` in fine mode; after ``hunt_crossings`` of them the joint's D gain is
halved (down to ``kd_min_scale`` of kD), which damps the mode (kD ≤ 0.5 gives |z| ≤ 0.85 at three
cycles of lag) and ends the limit cycle. The scale is reset for every new target and reported
(``kd_reduced``).

Limits: every step is clamped to ``±max_step_deg`` (per cycle) and the total to
``±max_total_deg`` (the analogue of the controller's ``AXISCORR``); a clamp is reported in the
result (``step_clamped``, ``total_limited``) so that :mod:`comp_daemon.rt.safety` can act on it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

__all__ = [
    "JointLoopSettings",
    "JointLoopState",
    "JointStep",
    "LoopMode",
    "hold_step",
    "joint_step",
]


class LoopMode(StrEnum):
    """Which of seed 000's two correction processes a joint is in."""

    ROUGH = "rough"
    FINE = "fine"


@dataclass(frozen=True, slots=True)
class JointLoopSettings:
    """Gains and limits of one joint's loop (per RSI cycle; angles in deg)."""

    kp: float = 0.05
    kd: float = 0.65
    rough_step_deg: float = 0.002
    rough_threshold_deg: float = 0.007
    rough_reenter_deg: float = 0.014
    max_step_deg: float = 0.002
    max_total_deg: float = 0.25
    cycle_s: float = 0.012
    hunt_band_deg: float = 0.002
    hunt_crossings: int = 4
    kd_min_scale: float = 0.125

    def __post_init__(self) -> None:
        for name in ("kp", "kd"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        for name in (
            "rough_step_deg",
            "rough_threshold_deg",
            "rough_reenter_deg",
            "max_step_deg",
            "max_total_deg",
            "cycle_s",
            "hunt_band_deg",
            "hunt_crossings",
            "kd_min_scale",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        if self.rough_reenter_deg < self.rough_threshold_deg:
            raise ValueError(
                f"rough_reenter_deg ({self.rough_reenter_deg}) must be >= rough_threshold_deg "
                f"({self.rough_threshold_deg})"
            )
        if self.rough_step_deg > self.max_step_deg:
            raise ValueError(
                f"rough_step_deg ({self.rough_step_deg}) must not exceed max_step_deg ({self.max_step_deg})"
            )
        if self.kd_min_scale > 1.0:
            raise ValueError(f"kd_min_scale must be <= 1, got {self.kd_min_scale}")
        if self.max_step_deg > self.max_total_deg:
            raise ValueError(
                f"max_step_deg ({self.max_step_deg}) must not exceed max_total_deg ({self.max_total_deg})"
            )


@dataclass(frozen=True, slots=True)
class JointLoopState:
    """What one joint's loop remembers between cycles.

    ``total_deg`` is the sum of the steps sent since the RSI session started (the correction the
    robot applies now). ``prev_measured_deg`` / ``prev_reading_t_s`` are the last reading acted on
    and its time stamp; NaN when there is none (after a gap the D term is zero for one step: no
    derivative across a gap). ``kd_scale``, ``last_sign`` and ``crossings`` belong to the hunting
    guard (module docstring); :meth:`for_new_target` resets them.
    """

    def for_new_target(self) -> JointLoopState:
        """The same joint with the hunting guard reset (the total correction is kept)."""
        return JointLoopState(self.mode, self.total_deg, self.prev_measured_deg, self.prev_reading_t_s)

    mode: LoopMode = LoopMode.ROUGH
    total_deg: float = 0.0
    prev_measured_deg: float = math.nan
    prev_reading_t_s: float = math.nan
    kd_scale: float = 1.0
    last_sign: int = 0
    crossings: int = 0


@dataclass(frozen=True, slots=True)
class JointStep:
    """One cycle's result for one joint."""

    state: JointLoopState
    step_deg: float
    error_deg: float
    step_clamped: bool = False
    total_limited: bool = False
    fresh: bool = True
    kd_reduced: bool = False


def joint_step(
    settings: JointLoopSettings,
    state: JointLoopState,
    target_deg: float,
    measured_deg: float,
    reading_t_s: float,
) -> JointStep:
    """One cycle of seed 000's correction for one joint: the relative step to send as ``AK``.

    ``reading_t_s`` is when the grating reading was taken (any monotonic clock, s). A reading
    that was already used (same time stamp) gives no step (``fresh`` False).
    """
    error = target_deg - measured_deg
    if reading_t_s == state.prev_reading_t_s:
        return JointStep(state, 0.0, error, fresh=False)
    magnitude = abs(error)
    mode = state.mode
    if mode is LoopMode.ROUGH and magnitude < settings.rough_threshold_deg:
        mode = LoopMode.FINE
    elif mode is LoopMode.FINE and magnitude >= settings.rough_reenter_deg:
        mode = LoopMode.ROUGH

    kd_scale, last_sign, crossings, kd_reduced = state.kd_scale, state.last_sign, state.crossings, False
    if mode is LoopMode.ROUGH:
        raw = settings.rough_step_deg if error > 0.0 else -settings.rough_step_deg
    else:
        prev = state.prev_measured_deg
        if math.isnan(prev) or math.isnan(state.prev_reading_t_s):
            velocity = 0.0
        else:
            # never over one cycle: the D path alone is u_k = -kd·u_(k-1-delay), stable only while
            # the effective kd stays below 1, so two readings close together must not inflate it
            cycles = max(1.0, (reading_t_s - state.prev_reading_t_s) / settings.cycle_s)
            velocity = (measured_deg - prev) / cycles  # deg per cycle
        sign = 0 if magnitude <= settings.hunt_band_deg else (1 if error > 0.0 else -1)
        if sign != 0:
            if last_sign != 0 and sign != last_sign:
                crossings += 1
                if crossings >= settings.hunt_crossings:
                    kd_scale = max(settings.kd_min_scale, 0.5 * kd_scale)
                    crossings, kd_reduced = 0, True
            last_sign = sign
        raw = settings.kp * error - settings.kd * kd_scale * velocity

    step = raw
    step_clamped = False
    if step > settings.max_step_deg:
        step, step_clamped = settings.max_step_deg, True
    elif step < -settings.max_step_deg:
        step, step_clamped = -settings.max_step_deg, True

    total_limited = False
    total = state.total_deg + step
    if total > settings.max_total_deg:
        step = max(0.0, settings.max_total_deg - state.total_deg)
        total, total_limited = state.total_deg + step, True
    elif total < -settings.max_total_deg:
        step = min(0.0, -settings.max_total_deg - state.total_deg)
        total, total_limited = state.total_deg + step, True

    new_state = JointLoopState(mode, total, measured_deg, reading_t_s, kd_scale, last_sign, crossings)
    return JointStep(new_state, step, error, step_clamped, total_limited, True, kd_reduced)


def hold_step(state: JointLoopState, measured_deg: float | None, reading_t_s: float | None) -> JointStep:
    """A cycle without correction: step 0, the total kept, the reading remembered for the D term.

    Used whenever the loop must not act (disabled, waiting for arrival, frozen by a fault). The
    next active cycle starts in rough mode unless the error is already small, and its D term uses
    this reading, so resuming is bumpless.
    """
    guard = (state.kd_scale, state.last_sign, state.crossings)
    if measured_deg is None or reading_t_s is None:
        gap = JointLoopState(LoopMode.ROUGH, state.total_deg, math.nan, math.nan, *guard)
        return JointStep(gap, 0.0, math.nan)
    new = JointLoopState(LoopMode.ROUGH, state.total_deg, measured_deg, reading_t_s, *guard)
    return JointStep(new, 0.0, math.nan)
