"""The simulated robot plant: a hidden robot that moves, settles, plays in its gears and bends under load.

Time advances only through :meth:`RobotPlant.step` (``dt_s`` seconds; no wall clock inside the
physics). Axis values are in the controller's convention (deg, KUKA A1..A6). Per axis:

* **Interpolator** (``axis_setpoint_deg``, RSI's ASPos): synchronised point-to-point motion with a
  trapezoid velocity profile. All axes share one normalised profile s(t) ∈ [0, 1], limited by the
  axis that needs longest for its velocity and acceleration limits, so they start and arrive
  together (KUKA's synchronous PTP). Targets given while moving are queued.
* **Command** = setpoint + the total RSI correction (:meth:`apply_correction` sets the total, as
  the controller's servo interface does; :meth:`add_correction` adds a relative step).
* **Motor** (``axis_actual_deg``, RSI's AIPos, what the motor encoder reports): follows the command
  through a first-order servo lag (``servo_time_constant_s``); the exact update for a command
  held over the step never overshoots, so an axis arrives from the side it moved from.
* **Approach direction** (:meth:`approach_dir`): sign of the axis' last motor motion (+1 at start).
* **Play** (backlash, half-width ``|h|``): a play operator ``b ← clip(b − Δmotor, −|h|, |h|)`` with
  the output at ``motor + b``: inside the play the output stands still while the motor turns, and
  after a motion longer than the play the output trails the motor, ``b = −|h|·dir``. In the twin's
  terms (:mod:`comp_daemon.models.effects`, docs/diagnosis-output.md: the axis sits at ``A + h·dir``) this is
  ``h = −|h|``: a play always lags. A short reversal leaves the output in between.
* **Repeatability**: every motion draws a fresh joint offset (σ ``joint_repeatability_deg``) that
  the output keeps until the next motion.
* **Output** (:meth:`output_angle_deg`, what a grating on the joint reads): the effect model at the
  motor value + offset with the play as backlash, i.e. after ratio error, play, transmission error
  and gravity deflection (payload included) — see :func:`~comp_daemon.models.effects.twin_state`.
* **TCP** (:meth:`tcp_true_mm`): the hidden kinematics (nominal + geometric errors, in the robot
  base frame) at the output angles, with thermal growth at the cell's temperature at this time.
* **Time effects**: a drift of the TCP (``v·t + w·t²``, t the plant time in h) and a step of a
  joint's zero from a moment on (re-mastering, a collision), the catalogue's ``drift`` and
  ``step`` evaluated at :attr:`clock_h`. Nothing the plant reports names them.

:class:`RobotPlant` is the ``JointStateSource`` of :mod:`comp_daemon.sim.rsi_controller`
(``advance``, ``axis_setpoint_deg``, ``axis_actual_deg``, ``apply_correction``, ``start_move``,
``in_motion``, ``halt``) and the ``OutputAngleSource`` of :mod:`comp_daemon.sim.converter`
(``output_angle_deg``).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.params import KinematicParams
from comp_daemon.models.effects import EffectParams, MassModel, TwinState, twin_state
from comp_daemon.robot.description import RobotDescription
from comp_daemon.sim.scenario import CellSettings, MotionSettings, Scenario

__all__ = [
    "RobotPlant",
    "TrapezoidProfile",
]

_MOVE_EPS_DEG = 1e-12


@dataclass(frozen=True, slots=True)
class TrapezoidProfile:
    """Synchronised PTP from ``start_deg`` to ``target_deg``: a trapezoid in the path parameter s."""

    start_deg: NDArray[np.float64]
    target_deg: NDArray[np.float64]
    accel_s: float  # s'' during acceleration (1/s²)
    speed_s: float  # peak s' (1/s)
    t_acc_s: float
    duration_s: float

    @classmethod
    def plan(
        cls,
        start_deg: NDArray[np.float64],
        target_deg: NDArray[np.float64],
        v_max_deg_s: NDArray[np.float64],
        a_max_deg_s2: NDArray[np.float64],
    ) -> TrapezoidProfile:
        start = np.array(start_deg, dtype=float)
        target = np.array(target_deg, dtype=float)
        dist = np.abs(target - start)
        moving = dist > 0.0
        if not moving.any():
            return cls(start, target, 0.0, 0.0, 0.0, 0.0)
        speed = float(np.min(v_max_deg_s[moving] / dist[moving]))
        accel = float(np.min(a_max_deg_s2[moving] / dist[moving]))
        if speed * speed / accel < 1.0:  # reaches cruise speed
            t_acc = speed / accel
            duration = 1.0 / speed + t_acc
        else:  # triangular
            t_acc = math.sqrt(1.0 / accel)
            speed = accel * t_acc
            duration = 2.0 * t_acc
        return cls(start, target, accel, speed, t_acc, duration)

    def s(self, t_s: float) -> float:
        """Path parameter at time ``t_s`` after the start (0 before, 1 after the motion)."""
        if self.duration_s == 0.0 or t_s >= self.duration_s:
            return 1.0
        if t_s <= 0.0:
            return 0.0
        if t_s < self.t_acc_s:
            return 0.5 * self.accel_s * t_s * t_s
        if t_s <= self.duration_s - self.t_acc_s:
            return 0.5 * self.accel_s * self.t_acc_s**2 + self.speed_s * (t_s - self.t_acc_s)
        rest = self.duration_s - t_s
        return 1.0 - 0.5 * self.accel_s * rest * rest

    def position_deg(self, t_s: float) -> NDArray[np.float64]:
        return self.start_deg + self.s(t_s) * (self.target_deg - self.start_deg)


class RobotPlant:
    """A hidden robot with every effect of docs/diagnosis-output.md, moved in explicit time steps.

    Build one from a scenario with :meth:`from_scenario`, or from parts (tests: nominal parameters
    and :class:`EffectParams` zeros give a plant that is the nominal forward kinematics).
    """

    def __init__(
        self,
        robot: RobotDescription,
        true_params: KinematicParams,
        effects: EffectParams,
        motion: MotionSettings,
        *,
        cell: CellSettings | None = None,
        joint_repeatability_deg: NDArray[np.float64] | None = None,
        start_axes_deg: NDArray[np.float64] | None = None,
        payload_kg: float = 0.0,
        seed: int = 0,
    ) -> None:
        self.robot = robot
        self.true_params = true_params
        self.effects = effects
        self.motion = motion
        self.cell = cell if cell is not None else CellSettings()
        self._mass = MassModel.from_robot(robot)
        self._sigma = (
            np.zeros(6)
            if joint_repeatability_deg is None
            else np.asarray(joint_repeatability_deg, dtype=float)
        )
        self._rng = np.random.default_rng(seed)
        self._limits = robot.axis_limits_deg
        start = np.zeros(6) if start_axes_deg is None else np.array(start_axes_deg, dtype=float)
        self._check_axes(start, "start_axes_deg")
        self._time_s = 0.0
        self._setpoint = start.copy()
        self._correction = np.zeros(6)
        self._motor = start.copy()
        self._last_dir = np.ones(6)
        self._play = -np.abs(effects.backlash_deg) * self._last_dir
        self._offset = np.zeros(6)
        self._payload_kg = float(payload_kg)
        self._profile: TrapezoidProfile | None = None
        self._profile_t0 = 0.0
        self._queue: deque[NDArray[np.float64]] = deque()
        self._state: TwinState | None = None

    @classmethod
    def from_scenario(
        cls,
        scenario: Scenario,
        *,
        seed: int = 0,
        start_axes_deg: NDArray[np.float64] | None = None,
        payload_kg: float = 0.0,
    ) -> RobotPlant:
        """The scenario's hidden robot; ``seed`` drives the repeatability noise only."""
        return cls(
            scenario.robot,
            scenario.true_params(),
            scenario.effects,
            scenario.motion,
            cell=scenario.cell,
            joint_repeatability_deg=scenario.noise.joint_repeatability_deg,
            start_axes_deg=scenario.campaign.home_deg if start_axes_deg is None else start_axes_deg,
            payload_kg=payload_kg,
            seed=seed,
        )

    # ---- inputs ------------------------------------------------------------------------------
    def _check_axes(self, axes: NDArray[np.float64], what: str) -> None:
        if axes.shape != (6,) or not np.all(np.isfinite(axes)):
            raise ValueError(f"{what}: expected six finite axis values (deg), got {axes!r}")
        low = axes < self._limits[:, 0]
        high = axes > self._limits[:, 1]
        if low.any() or high.any():
            j = int(np.flatnonzero(low | high)[0])
            raise ValueError(
                f"{what}: A{j + 1} = {axes[j]:.4f} deg is outside the limits "
                f"[{self._limits[j, 0]:g}, {self._limits[j, 1]:g}] of {self.robot.name}"
            )

    def move_to(self, axes_deg: NDArray[np.float64]) -> None:
        """Queue a PTP motion to ``axes_deg`` (6,); it starts when the previous one has ended."""
        target = np.array(axes_deg, dtype=float).reshape(-1)
        self._check_axes(target, "move_to")
        self._queue.append(target)
        if self._profile is None:
            self._start_next()

    def _start_next(self) -> None:
        target = self._queue.popleft()
        self._profile = TrapezoidProfile.plan(
            self._setpoint, target, self.motion.v_max_deg_s, self.motion.a_max_deg_s2
        )
        self._profile_t0 = self._time_s
        self._offset = self._rng.standard_normal(6) * self._sigma
        self._state = None

    def start_move(self, target_axes_deg: NDArray[np.float64]) -> None:
        """The controller's name for :meth:`move_to`."""
        self.move_to(target_axes_deg)

    def halt(self) -> None:
        """Stop the interpolator where it is and drop queued motions (a robot stop)."""
        self._profile = None
        self._queue.clear()

    @staticmethod
    def _six(values: NDArray[np.float64], what: str) -> NDArray[np.float64]:
        out = np.array(values, dtype=float).reshape(-1)
        if out.shape != (6,) or not np.all(np.isfinite(out)):
            raise ValueError(f"{what}: expected six finite values (deg), got {values!r}")
        return out

    def apply_correction(self, correction_deg: NDArray[np.float64]) -> None:
        """Set the total RSI correction (deg per axis) added to the setpoint; the motor follows it."""
        self._correction = self._six(correction_deg, "apply_correction")

    def add_correction(self, ak_deg: NDArray[np.float64]) -> None:
        """Add a relative RSI correction step (``RSI_ON(#RELATIVE)``'s AK) to the total."""
        self._correction = self._correction + self._six(ak_deg, "add_correction")

    def set_payload(self, payload_kg: float) -> None:
        if not (payload_kg >= 0.0 and math.isfinite(payload_kg)):
            raise ValueError(f"payload_kg: must be a finite number >= 0, got {payload_kg!r}")
        self._payload_kg = float(payload_kg)
        self._state = None

    def advance(self, dt_s: float) -> None:
        """The controller's name for :meth:`step`."""
        self.step(dt_s)

    def step(self, dt_s: float) -> None:
        """Advance the plant by ``dt_s`` seconds."""
        if not (dt_s >= 0.0 and math.isfinite(dt_s)):
            raise ValueError(f"step: dt_s must be a finite number >= 0, got {dt_s!r}")
        t = self._time_s + dt_s
        if self._profile is not None:
            self._setpoint = self._profile.position_deg(t - self._profile_t0)
            if t - self._profile_t0 >= self._profile.duration_s:
                self._setpoint = self._profile.target_deg.copy()
                self._profile = None
        self._time_s = t
        if self._profile is None and self._queue:
            self._start_next()
        command = self._setpoint + self._correction
        tau = self.motion.servo_time_constant_s
        motor = command + (self._motor - command) * math.exp(-dt_s / tau)
        delta = motor - self._motor
        moved = np.abs(delta) > _MOVE_EPS_DEG
        self._last_dir = np.where(moved, np.sign(delta), self._last_dir)
        h = np.abs(self.effects.backlash_deg)
        self._play = np.clip(self._play - delta, -h, h)
        self._motor = motor
        self._state = None

    # ---- state -------------------------------------------------------------------------------
    @property
    def time_s(self) -> float:
        return self._time_s

    @property
    def payload_kg(self) -> float:
        return self._payload_kg

    def in_motion(self) -> bool:
        """True while the interpolator has a motion running or queued (the setpoint still moves)."""
        return self._profile is not None or bool(self._queue)

    @property
    def settled(self) -> bool:
        """No motion left and every motor within ``settle_tol_deg`` of its command."""
        if self.in_motion():
            return False
        lag = np.abs(self._setpoint + self._correction - self._motor)
        return bool(lag.max() < self.motion.settle_tol_deg)

    def run_until_settled(self, dt_s: float = 0.012, max_s: float = 600.0) -> float:
        """Step until :attr:`settled`; returns the time spent (s)."""
        t0 = self._time_s
        while not self.settled:
            if self._time_s - t0 > max_s:
                raise RuntimeError(f"plant did not settle within {max_s} s")
            self.step(dt_s)
        return self._time_s - t0

    @property
    def clock_h(self) -> float:
        """Plant time in hours: the clock of the time effects (drift, step)."""
        return self._time_s / 3600.0

    def temperature_c(self) -> float:
        return float(self.cell.temperature_c(self._time_s))

    def axis_setpoint_deg(self) -> NDArray[np.float64]:
        """Interpolator setpoint without RSI corrections (RSI's ASPos)."""
        return self._setpoint.copy()

    def axis_actual_deg(self) -> NDArray[np.float64]:
        """Motor-side axis values, corrections included, with servo lag (RSI's AIPos)."""
        return self._motor.copy()

    def correction_deg(self) -> NDArray[np.float64]:
        """Sum of the RSI corrections applied so far."""
        return self._correction.copy()

    def approach_dir(self) -> NDArray[np.int8]:
        """(6,) sign of each axis' last motion (the data set's dir1..dir6)."""
        return self._last_dir.astype(np.int8)

    def _twin(self) -> TwinState:
        if self._state is None:
            h = np.abs(self.effects.backlash_deg)
            frac = np.divide(self._play, h, out=np.zeros(6), where=h > 0.0)
            self._state = twin_state(
                self._mass,
                self.true_params,
                self.effects,
                (self._motor + self._offset)[None, :],
                frac[None, :],
                self._payload_kg,
                np.array([self.temperature_c()]),
                clock=np.array([self.clock_h]),
            )
        return self._state

    def output_angles_deg(self) -> NDArray[np.float64]:
        """(6,) true output angle of every joint, controller convention (deg)."""
        st = self._twin()
        deflection = np.rad2deg(self.effects.compliance_rad_per_nm * st.tau_nm[0])
        return st.a_eff_deg[0] + self.true_params.sign * deflection

    def output_angle_deg(self, joint: int) -> float:
        """True output angle of ``joint`` (1..6): what a grating on that joint reads, in deg."""
        if not 1 <= joint <= 6:
            raise ValueError(f"joint {joint}: joints are numbered 1..6")
        return float(self.output_angles_deg()[joint - 1])

    def tcp_true_mm(self) -> NDArray[np.float64]:
        """(3,) true TCP in the robot base frame (mm)."""
        return self._twin().tcp_mm[0].copy()

    def flange_rotation_true(self) -> NDArray[np.float64]:
        """(3, 3) true orientation of the flange frame in the robot base frame."""
        return self._twin().chain.world_T_frame[0, 6, :3, :3].copy()

    def points_true_mm(self, flange_xyz_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        """(k, 3) true positions (robot base frame, mm) of points fixed to the flange at ``flange_xyz_mm``
        (k, 3, flange frame): further reflectors beside the TCP."""
        flange = self._twin().chain.world_T_frame[0, 6]
        return np.asarray(flange_xyz_mm, dtype=float) @ flange[:3, :3].T + flange[:3, 3]
