"""Compensation: commanded axis values whose *predicted* actual TCP is the wanted one.

Targets are given in the robot base frame (mm; optional orientation as rotation matrices) and
mapped into the model's measurement frame by its ``registration``. Two methods:

One place decides what a compensated target is, for the ``compensate`` command, the HTTP API and
the daemon's executor alike: :func:`compensate`.

1. *Nominal solution*: the axis values the controller would use without compensation — the nominal
   robot's inverse kinematics of the target in the robot base frame, inside the axis limits, from
   the seed (the nominal program's axis values give themselves back) (:func:`nominal_solution`).
2. *Compensated solution*, model + inverse kinematics, iterated, starting from the nominal solution
   (so it stays on its branch): the IK of the target on the model's kinematic parameters
   (``ik_params``); then repeat: predict the actual TCP of the current command with the model, move
   the IK target by the remaining error (``target_ik ← target_ik + (wanted − predicted)``) and solve
   the IK again from the current command, until the predicted TCP is within ``tol_mm`` of the wanted
   one. This is a fixed-point iteration that contracts with the ratio of the model's error slope
   to the Jacobian's (per mille for a robot), so a handful of iterations reach rounding level.
   A target with an orientation keeps the orientation its nominal solution has on the model's
   chain: the tracker data are positions only, and a rotation of the flange with the opposite
   rotation of the tool vector puts the TCP on the same point, so a model knows nothing about the
   tool's orientation that would justify turning the wrist; compensation moves the TCP. Without an
   orientation the wrist is free and each IK step is the smallest from the nominal solution.
3. The axis changes are measured against the nominal solution
   (:attr:`CompensationResult.da_deg`).

Two joint mappings (``mapping``; the daemon's ``[compensation] mapping``):

- ``"six-axis"`` (default): step 2 above, every axis from the inverse kinematics on the model's
  chain.
- ``"three-axis"`` (called ``"seed000"`` before, a name still read with a warning:
  :data:`RENAMED_MAPPINGS`): seed 000's closed loop (§2.2) — the wrist (joints 4–6) stays at the nominal
  solution and only joints 1–3 move: starting from the nominal solution, the model's predicted
  error ``ΔP`` (predicted − wanted) is mapped to joints 1–3 by :func:`joint_mapping` and the joint
  targets become ``θ − Δθ``, repeated from the new command until the predicted TCP is within
  ``tol_mm`` of the wanted one. The first step is the paper's feed-forward (:func:`feed_forward`);
  the further steps take out its second-order remainder (micrometres for a calibrated robot),
  so both mappings put the predicted TCP on the target and differ only in how the axes get there.
  The tool's orientation is not held: it turns with joints 1–3 by the correction (hundredths of a
  degree).

Limits (:class:`CompensationLimits`; the daemon's ``[compensation]`` settings). A target is refused
with :class:`CompensationRefused`, whose message names the target, the axis, the size and the
reason, rather than compensated when

- the TCP lies inside the robot's own base (:func:`base_refusals`);
- its orientation is held and the nominal wrist is within ``wrist_singularity_deg`` of the wrist
  singularity (axes 4 and 6 in line; |A5| on a KUKA wrist): to hold the orientation, A4 and A6
  turn against each other by the forearm's rotation over sin(A5) — an arm correction of 0.07° (a
  KR 210 with 0.3 mm, 0.01° errors) costs them 0.3–0.4° at 10°, 0.6–0.8° at 5° and 6–9° at 0.5°,
  and at 0° the solution is not even unique. Default 5°, below which the wrist turns more than ten
  times the correction;
- an axis would change by more than ``max_axis_change_deg`` from the nominal solution (default
  0.5°: a calibrated robot's compensation is hundredths to tenths of a degree, and 0.5° is also the
  joint loop's default correction budget, ``controller.max_total_deg``);
- a compensated axis value leaves the axis limits (the six-axis inverse kinematics keeps inside
  them; seed 000's mapping does not look);
- the compensated axis values leave the nominal configuration: the arm's branch (shoulder, elbow)
  or the wrist's (flip) (:func:`configuration`);
- the model records the axis ranges of the poses it was fitted on (Chebyshev of order 1 or more:
  its Chebyshev ranges; kriging: its sampling points) and an axis of the nominal or compensated
  values lies more than ``hull_margin_deg`` beyond them (the Chebyshev model would only hold its
  edge value there, the kriging prediction fall back to its mean) (:func:`sampling_range_deg`).
  Default 25°: seed 000's target points, drawn in the same Cartesian box and A/B/C ranges as the
  sampling points, lie up to 22° beyond the sampled wrist ranges (A4, A6) and up to 5° beyond the
  arm's; a target in another part of the workspace is refused. Nominal, kinematic, compliance and
  order-0 Chebyshev models are global: there is no region to check (``region_deg`` None).

:func:`joint_mapping` — the joint mapping of seed 000 (§2.2): the estimated Cartesian error ``ΔP``
(predicted actual − wanted, mm) of a command is mapped to corrections of joints 1–3 by least
squares on the position Jacobian of those joints, ``Δθ = (J₁₂₃ᵀJ₁₂₃)⁻¹J₁₂₃ᵀ ΔP``, and the modified
joint targets are ``θ − Δθ`` (the feed-forward of the closed loop, whose gratings sit on joints 1–3).
:func:`feed_forward` applies it to commands whose nominal TCP is the wanted one.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
from numpy.typing import NDArray

from comp_daemon.estimation.registration import transform_points
from comp_daemon.kinematics.forward import chain, position_jacobian_mm
from comp_daemon.kinematics.inverse import require_reachable, solve_ik
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad, q_rad_to_axes_deg
from comp_daemon.models.base import ErrorModel, as_axes
from comp_daemon.models.chebyshev import ChebyshevModel
from comp_daemon.models.kriging import KrigingModel
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "DEFAULT_LIMITS",
    "MAPPINGS",
    "RENAMED_MAPPINGS",
    "CompensationLimits",
    "CompensationRefused",
    "CompensationResult",
    "FeedForward",
    "JointMapping",
    "Refusal",
    "axis_limits_q_rad",
    "base_refusals",
    "compensate",
    "configuration",
    "feed_forward",
    "joint_mapping",
    "nominal_solution",
    "nominal_targets",
    "region_refusals",
    "renamed_mapping_note",
    "sampling_range_deg",
    "wrist_angle_deg",
    "wrist_refusals",
]

MAPPED_JOINTS = (1, 2, 3)

#: How a compensated target becomes axis values (module docstring, *joint mappings*).
JointMapping = Literal["six-axis", "three-axis"]
MAPPINGS: tuple[str, ...] = get_args(JointMapping)
#: former names of the mappings, read as the new one with a warning that names it
RENAMED_MAPPINGS: dict[str, JointMapping] = {"seed000": "three-axis"}


def renamed_mapping_note(old: str) -> str:
    """The words that tell a user of a former mapping name (:data:`RENAMED_MAPPINGS`) its new one."""
    return (
        f"the joint mapping {old!r} is now called {RENAMED_MAPPINGS[old]!r} (what it does: joints 1-3 "
        f"take the correction, the wrist stays at the nominal solution); {old!r} is read as "
        f"{RENAMED_MAPPINGS[old]!r} for now: write {RENAMED_MAPPINGS[old]!r}"
    )


def axis_limits_q_rad(robot: RobotDescription) -> NDArray[np.float64]:
    """(6, 2) joint limits in q (rad, DH sign): the axis limits with each joint's sign applied."""
    return np.sort(axes_deg_to_q_rad(robot.axis_limits_deg, robot.sign[:, None]), axis=1)


@dataclass(frozen=True, slots=True)
class CompensationLimits:
    """What a compensated target may do; see the module docstring (*Limits*).

    ``max_axis_change_deg``: largest change of any axis from the nominal solution (deg).
    ``wrist_singularity_deg``: targets whose axes 4 and 6 are closer than this to being in line
    (|A5| on a KUKA wrist) are refused when the orientation is held (deg).
    ``hull_margin_deg``: how far beyond the sampled range of an axis the model may be used (deg).
    """

    max_axis_change_deg: float = 0.5
    wrist_singularity_deg: float = 5.0
    hull_margin_deg: float = 25.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.max_axis_change_deg) and self.max_axis_change_deg > 0.0):
            raise ValueError(f"max_axis_change_deg must be > 0, got {self.max_axis_change_deg}")
        if not (math.isfinite(self.wrist_singularity_deg) and 0.0 <= self.wrist_singularity_deg < 90.0):
            raise ValueError(f"wrist_singularity_deg must be in [0, 90), got {self.wrist_singularity_deg}")
        if not (math.isfinite(self.hull_margin_deg) and self.hull_margin_deg >= 0.0):
            raise ValueError(f"hull_margin_deg must be >= 0, got {self.hull_margin_deg}")


DEFAULT_LIMITS = CompensationLimits()


@dataclass(frozen=True, slots=True)
class Refusal:
    """Why one target is not compensated: ``axis`` (1-based; None when no axis is at fault) and
    ``value_deg`` (its value or change; nan without an axis)."""

    index: int  # 0-based position of the target in the call
    axis: int | None
    value_deg: float
    reason: str  # names the axis, the size and the reason


class CompensationRefused(ValueError):
    """Targets whose compensation is refused (wrist singularity, too large a change, another
    configuration, outside the model's validity region); ``refusals`` has one entry per target.

    The message is the reason itself when the call had one target, else ``target <i>: <reason>``
    for the first five (1-based ``i``); callers that number targets otherwise use ``refusals``.
    """

    def __init__(self, refusals: Sequence[Refusal], n_targets: int) -> None:
        self.refusals = tuple(sorted(refusals, key=lambda r: r.index))
        if n_targets == 1 and len(self.refusals) == 1:
            super().__init__(self.refusals[0].reason)
            return
        shown = "; ".join(f"target {r.index + 1}: {r.reason}" for r in self.refusals[:5])
        more = f"; and {len(self.refusals) - 5} more" if len(self.refusals) > 5 else ""
        super().__init__(f"{shown}{more}")


@dataclass(frozen=True, slots=True)
class CompensationResult:
    a_deg: NDArray[np.float64]  # (n, 6) compensated commands
    a_uncompensated_deg: NDArray[np.float64]  # (n, 6) the nominal solution the controller would use
    wanted_mm: NDArray[np.float64]  # (n, 3) in the measurement frame
    predicted_mm: NDArray[np.float64]  # (n, 3) the model's prediction at a_deg
    residual_mm: NDArray[np.float64]  # (n,) |predicted − wanted|
    iterations: int
    converged: bool
    region_deg: NDArray[np.float64] | None = None  # (6, 2) sampled axis ranges checked; None: unknown

    @property
    def da_deg(self) -> NDArray[np.float64]:
        """(n, 6) compensated minus nominal axis values (deg)."""
        return self.a_deg - self.a_uncompensated_deg


def nominal_targets(
    model: ErrorModel, a_deg: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Wanted TCP positions (n, 3) and orientations (n, 3, 3), robot base frame, of nominal commands."""
    params = KinematicParams.from_robot(model.robot)
    ch = chain(params, axes_deg_to_q_rad(as_axes(a_deg), params.sign))
    return ch.tcp_mm, ch.world_T_frame[:, 6, :3, :3]


def _target_positions(target_p_base_mm: NDArray[np.float64]) -> NDArray[np.float64]:
    """The (n, 3) target positions (one may be given as (3,)); another shape is a ValueError."""
    target = np.atleast_2d(np.asarray(target_p_base_mm, dtype=float))
    if target.ndim != 2 or target.shape[1] != 3:
        raise ValueError(f"target positions must have shape (n, 3), got {np.shape(target_p_base_mm)}")
    return target


def nominal_solution(
    robot: RobotDescription,
    target_p_base_mm: NDArray[np.float64],
    target_R_base: NDArray[np.float64] | None = None,
    a_seed_deg: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """(n, 6) axis values (deg) the controller reaches the targets with: the nominal robot's inverse
    kinematics, in the robot base frame, inside the axis limits, from ``a_seed_deg`` (default the
    middle of every axis range). Raises :class:`UnreachableTargetError` naming unreachable targets."""
    target = _target_positions(target_p_base_mm)
    n = target.shape[0]
    rot = None if target_R_base is None else np.asarray(target_R_base, dtype=float).reshape(n, 3, 3)
    if a_seed_deg is None:
        a_seed = np.broadcast_to(robot.axis_limits_deg.mean(axis=1), (n, 6))
    else:
        a_seed = np.broadcast_to(np.asarray(a_seed_deg, dtype=float), (n, 6))
    params = KinematicParams.from_robot(robot)
    res = solve_ik(
        params,
        axis_limits_q_rad(robot),
        target,
        rot,
        axes_deg_to_q_rad(a_seed, params.sign),
        tol_mm=1e-10,
        tol_rad=1e-12,
    )
    return q_rad_to_axes_deg(require_reachable(res, "target"), params.sign)


def base_refusals(robot: RobotDescription, target_p_base_mm: NDArray[np.float64]) -> list[Refusal]:
    """Targets inside the robot's own base: nearer to axis 1 than the shoulder (the first link's
    offset ``a1``) and below it (``d1``), robot base frame. The inverse kinematics may well fold the
    arm there (the base origin of a KR 210 has a solution inside the axis limits), but the TCP would
    be inside the robot's column."""
    p = np.atleast_2d(np.asarray(target_p_base_mm, dtype=float))
    params = KinematicParams.from_robot(robot)
    radius_mm, shoulder_mm = float(params.a_mm[0]), float(params.d_mm[0])
    r = np.hypot(p[:, 0], p[:, 1])
    inside = (r < radius_mm) & (p[:, 2] < shoulder_mm)
    return [
        Refusal(
            int(i),
            None,
            math.nan,
            f"the TCP ({p[i, 0]:.1f}, {p[i, 1]:.1f}, {p[i, 2]:.1f}) mm is inside the robot's base: "
            f"{r[i]:.1f} mm from axis 1 (the shoulder is {radius_mm:g} mm out) and below the shoulder "
            f"({shoulder_mm:g} mm)",
        )
        for i in np.flatnonzero(inside)
    ]


def wrist_angle_deg(params: KinematicParams, a_deg: NDArray[np.float64]) -> NDArray[np.float64]:
    """(n,) how far axes 4 and 6 are from being in line (deg, ≥ 0): |A5| on a KUKA wrist."""
    a = as_axes(a_deg)
    z = chain(params, axes_deg_to_q_rad(a, params.sign)).world_T_frame[:, 3:6, :3, 2]  # axes 4, 5, 6
    cos = np.clip(np.einsum("ni,ni->n", z[:, 0], z[:, 2]), -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))
    return np.minimum(angle, 180.0 - angle)


def configuration(params: KinematicParams, a_deg: NDArray[np.float64]) -> NDArray[np.float64]:
    """(n, 2) signs of the arm and wrist configuration (branch) of axis values.

    Arm: the sign of the determinant of the wrist point's Jacobian over joints 1–3 (it changes at
    the shoulder and the elbow singularity, between the branches of the arm). Wrist: the sign of
    the angle from axis 4 to axis 6 about axis 5 (it changes at the wrist singularity, the flip).
    """
    a = as_axes(a_deg)
    frames = chain(params, axes_deg_to_q_rad(a, params.sign)).world_T_frame
    wrist_point = frames[:, 4, :3, 3]
    z = frames[:, :3, :3, 2]
    jac = np.cross(z, wrist_point[:, None, :] - frames[:, :3, :3, 3])  # (n, 3 joints, 3)
    arm = np.sign(np.linalg.det(jac))
    axes = frames[:, 3:6, :3, 2]
    wrist = np.sign(np.einsum("ni,ni->n", np.cross(axes[:, 0], axes[:, 2]), axes[:, 1]))
    return np.stack([arm, wrist], axis=1)


def sampling_range_deg(model: ErrorModel) -> NDArray[np.float64] | None:
    """(6, 2) axis ranges of the poses the model was fitted on, or None when there is no such region
    to keep to: nominal, kinematic and compliance models are global, and so is an order-0 Chebyshev
    model (constant, geometric error terms only)."""
    if isinstance(model, ChebyshevModel):
        return np.array(model.range_deg, dtype=float) if model.order > 0 else None
    if isinstance(model, KrigingModel):
        a = model.sample_a_deg
        return np.stack([a.min(axis=0), a.max(axis=0)], axis=1)
    return None


def wrist_refusals(
    robot: RobotDescription, a_deg: NDArray[np.float64], limits: CompensationLimits
) -> list[Refusal]:
    """One refusal per axis-value row (n, 6) whose wrist is within ``limits.wrist_singularity_deg``
    of the singularity, judged on the nominal geometry."""
    angle = wrist_angle_deg(KinematicParams.from_robot(robot), a_deg)
    return [
        Refusal(
            int(i),
            5,
            float(a_deg[i, 4]),
            f"near wrist singularity: A5 = {_deg(a_deg[i, 4], 1)}° "
            f"(axes 4 and 6 less than {limits.wrist_singularity_deg:g}° from in line)",
        )
        for i in np.flatnonzero(angle < limits.wrist_singularity_deg)
    ]


def region_refusals(
    region_deg: NDArray[np.float64], a_deg: NDArray[np.float64], margin_deg: float
) -> list[Refusal]:
    """One refusal per target with an axis more than ``margin_deg`` outside ``region_deg`` (6, 2)."""
    a = as_axes(a_deg)
    beyond = np.maximum(region_deg[:, 0] - a, a - region_deg[:, 1])  # (n, 6) > 0 outside
    out = []
    for i in np.flatnonzero(np.any(beyond > margin_deg, axis=1)):
        j = int(np.argmax(beyond[i]))
        lo, hi = region_deg[j]
        out.append(
            Refusal(
                int(i),
                j + 1,
                float(a[i, j]),
                f"outside the model's validity region: A{j + 1} = {_deg(a[i, j], 2)}° is "
                f"{beyond[i, j]:.2f}° beyond the sampled range [{_deg(lo, 2)}°, {_deg(hi, 2)}°] "
                f"(margin {margin_deg:g}°)",
            )
        )
    return out


def _change_refusals(
    robot: RobotDescription,
    a_nominal_deg: NDArray[np.float64],
    a_deg: NDArray[np.float64],
    limits: CompensationLimits,
) -> list[Refusal]:
    da = a_deg - a_nominal_deg
    worst = np.argmax(np.abs(da), axis=1)
    params = KinematicParams.from_robot(robot)
    changed = np.any(configuration(params, a_nominal_deg) != configuration(params, a_deg), axis=1)
    lo, hi = robot.axis_limits_deg[:, 0], robot.axis_limits_deg[:, 1]
    outside = (a_deg < lo) | (a_deg > hi)
    out = []
    for i in range(a_deg.shape[0]):
        j = int(worst[i])
        size = float(da[i, j])
        if outside[i].any():
            k = int(np.argmax(outside[i]))
            out.append(
                Refusal(
                    i,
                    k + 1,
                    float(a_deg[i, k]),
                    f"the compensated A{k + 1} = {a_deg[i, k]:.4f}° is outside the axis limits "
                    f"[{lo[k]:g}°, {hi[k]:g}°]",
                )
            )
            continue
        if changed[i]:
            reason = (
                f"the compensated axis values leave the nominal arm or wrist configuration "
                f"(A{j + 1} changes by {size:+.3f}°)"
            )
        elif abs(size) > limits.max_axis_change_deg:
            reason = f"A{j + 1} would change by {size:+.3f}° (limit {limits.max_axis_change_deg:g}° per axis)"
        else:
            continue
        out.append(Refusal(i, j + 1, size, reason))
    return out


def _deg(value: float, digits: int) -> str:
    """``value`` with ``digits`` decimals, without a minus sign on a rounded zero."""
    text = f"{float(value):.{digits}f}"
    return text[1:] if text.startswith("-") and float(text) == 0.0 else text


def compensate(
    model: ErrorModel,
    target_p_base_mm: NDArray[np.float64],
    target_R_base: NDArray[np.float64] | None = None,
    *,
    a_seed_deg: NDArray[np.float64] | None = None,
    dir: NDArray[np.float64] | None = None,
    payload_kg: NDArray[np.float64] | float | None = None,
    temp_c: NDArray[np.float64] | None = None,
    tol_mm: float = 1e-8,
    max_iter: int = 30,
    limits: CompensationLimits = DEFAULT_LIMITS,
    mapping: JointMapping = "six-axis",
) -> CompensationResult:
    """Commands (deg) whose predicted TCP equals the wanted ``target_p_base_mm`` (n, 3), base frame.

    ``a_seed_deg`` (n, 6) or (6,): where the nominal inverse kinematics starts (the nominal
    program's axis values, or the robot's current ones); default the middle of every axis range.
    The compensated commands start from the nominal solution, are found by ``mapping`` (module
    docstring: ``"six-axis"`` or ``"three-axis"``) and are checked against ``limits``.
    Raises :class:`UnreachableTargetError` naming unreachable targets and
    :class:`CompensationRefused` naming refused ones (every refused target of the call).
    """
    target = _target_positions(target_p_base_mm)
    if mapping in RENAMED_MAPPINGS:
        raise ValueError(f"mapping {mapping!r} is now called {RENAMED_MAPPINGS[mapping]!r}")
    if mapping not in MAPPINGS:
        raise ValueError(f"mapping must be one of {', '.join(MAPPINGS)}, got {mapping!r}")
    n = target.shape[0]
    robot = model.robot
    rot_base = None if target_R_base is None else np.asarray(target_R_base, dtype=float).reshape(n, 3, 3)
    inside = base_refusals(robot, target)
    if inside:
        raise CompensationRefused(inside, n)
    a_nominal = nominal_solution(robot, target, rot_base, a_seed_deg)
    region = sampling_range_deg(model)
    refused = wrist_refusals(robot, a_nominal, limits) if rot_base is not None else []
    if region is not None:
        refused += region_refusals(region, a_nominal, limits.hull_margin_deg)
    if refused:
        raise CompensationRefused(_first_per_target(refused), n)

    reg = model.registration
    wanted = transform_points(reg, target)
    params: KinematicParams = model.ik_params()
    if mapping == "three-axis":
        a_final, predicted, iterations, converged = _joint_mapping_iteration(
            model, params, a_nominal, wanted, dir, payload_kg, temp_c, tol_mm, max_iter
        )
    else:
        a_final, predicted, iterations, converged = _six_axis_iteration(
            model, params, a_nominal, wanted, rot_base is not None, dir, payload_kg, temp_c, tol_mm, max_iter
        )
    refused = _change_refusals(robot, a_nominal, a_final, limits)
    if region is not None:
        refused += region_refusals(region, a_final, limits.hull_margin_deg)
    if refused:
        raise CompensationRefused(_first_per_target(refused), n)
    residual = np.linalg.norm(predicted - wanted, axis=1)
    return CompensationResult(
        a_deg=a_final,
        a_uncompensated_deg=a_nominal,
        wanted_mm=wanted,
        predicted_mm=predicted,
        residual_mm=residual,
        iterations=iterations,
        converged=converged or bool(np.all(residual <= tol_mm)),
        region_deg=region,
    )


_Iteration = tuple[NDArray[np.float64], NDArray[np.float64], int, bool]


def _six_axis_iteration(
    model: ErrorModel,
    params: KinematicParams,
    a_nominal: NDArray[np.float64],
    wanted: NDArray[np.float64],
    hold_orientation: bool,
    dir: NDArray[np.float64] | None,
    payload_kg: NDArray[np.float64] | float | None,
    temp_c: NDArray[np.float64] | None,
    tol_mm: float,
    max_iter: int,
) -> _Iteration:
    """Model + six-axis inverse kinematics, iterated (module docstring, step 2): the commands, the
    predicted TCP there, the iterations and whether they converged."""
    q_nominal = axes_deg_to_q_rad(a_nominal, params.sign)
    rot = None  # the orientation the nominal solution has on the model's chain, held
    if hold_orientation:
        rot = chain(params, q_nominal).world_T_frame[:, 6, :3, :3]
    limits_q = axis_limits_q_rad(model.robot)
    ik_tol = min(tol_mm, 1e-9) / 10.0

    def solve(p_ik: NDArray[np.float64], seed: NDArray[np.float64], what: str) -> NDArray[np.float64]:
        res = solve_ik(params, limits_q, p_ik, rot, seed, tol_mm=ik_tol, tol_rad=1e-12)
        return require_reachable(res, what)

    q = solve(wanted, q_nominal, "compensated target")
    p_ik = wanted.copy()
    converged = False
    iterations = 0
    predicted = model.predict_tcp_mm(q_rad_to_axes_deg(q, params.sign), dir, payload_kg, temp_c)
    for iterations in range(1, max_iter + 1):  # noqa: B007
        err = wanted - predicted
        if float(np.max(np.linalg.norm(err, axis=1), initial=0.0)) <= tol_mm:
            converged = True
            break
        p_ik = p_ik + err
        q = solve(p_ik, q, "compensated target")
        predicted = model.predict_tcp_mm(q_rad_to_axes_deg(q, params.sign), dir, payload_kg, temp_c)
    return q_rad_to_axes_deg(q, params.sign), predicted, iterations, converged


def _joint_mapping_iteration(
    model: ErrorModel,
    params: KinematicParams,
    a_nominal: NDArray[np.float64],
    wanted: NDArray[np.float64],
    dir: NDArray[np.float64] | None,
    payload_kg: NDArray[np.float64] | float | None,
    temp_c: NDArray[np.float64] | None,
    tol_mm: float,
    max_iter: int,
) -> _Iteration:
    """Seed 000's mapping (module docstring): joints 1–3 corrected by :func:`joint_mapping` from the
    nominal solution, repeated on the predicted error; joints 4–6 stay at the nominal solution."""
    a = a_nominal.copy()
    predicted = model.predict_tcp_mm(a, dir, payload_kg, temp_c)
    converged = False
    iterations = 0
    for iterations in range(1, max_iter + 1):  # noqa: B007
        err = predicted - wanted
        if float(np.max(np.linalg.norm(err, axis=1), initial=0.0)) <= tol_mm:
            converged = True
            break
        a = a + joint_mapping(params, a, err)
        predicted = model.predict_tcp_mm(a, dir, payload_kg, temp_c)
    return a, predicted, iterations, converged


def _first_per_target(refusals: list[Refusal]) -> list[Refusal]:
    seen: dict[int, Refusal] = {}
    for r in refusals:
        seen.setdefault(r.index, r)
    return list(seen.values())


def joint_mapping(
    params: KinematicParams, a_deg: NDArray[np.float64], error_mm: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(n, 6) axis corrections (deg, controller convention) of seed 000's joint mapping.

    ``error_mm`` (n, 3) is the estimated TCP error (actual − wanted) at the commands ``a_deg``; the
    corrections are zero on joints 4–6 and ``−Δθ`` on joints 1–3 with ``Δθ`` the least-squares
    solution of ``J₁₂₃·Δθ = ΔP`` (position Jacobian of joints 1–3 at ``a_deg``). Near a singularity
    of ``J₁₂₃`` (the TCP close to axis 1, a stretched arm) the corrections grow without bound; callers
    that move a robot limit them.
    """
    a = as_axes(a_deg)
    err = np.asarray(error_mm, dtype=float).reshape(a.shape[0], 3)
    q = axes_deg_to_q_rad(a, params.sign)
    jac = position_jacobian_mm(params, q)[:, :, : len(MAPPED_JOINTS)]  # (n, 3, 3)
    jtj = np.swapaxes(jac, 1, 2) @ jac
    jte = np.einsum("nij,ni->nj", jac, err)
    dtheta = np.linalg.solve(jtj, jte[..., None])[..., 0]  # (n, 3) rad, DH sign
    out = np.zeros_like(a)
    out[:, : len(MAPPED_JOINTS)] = -q_rad_to_axes_deg(dtheta, params.sign[: len(MAPPED_JOINTS)])
    return out


@dataclass(frozen=True, slots=True)
class FeedForward:
    a_deg: NDArray[np.float64]  # (n, 6) modified joint targets (joints 1–3 corrected)
    correction_deg: NDArray[np.float64]  # (n, 6) added to the nominal commands
    estimated_error_mm: NDArray[np.float64]  # (n, 3) the model's error at the nominal commands


def feed_forward(
    model: ErrorModel,
    a_nominal_deg: NDArray[np.float64],
    *,
    dir: NDArray[np.float64] | None = None,
    payload_kg: NDArray[np.float64] | float | None = None,
    temp_c: NDArray[np.float64] | None = None,
) -> FeedForward:
    """Seed 000 step (4): estimated error of nominal commands, mapped onto joints 1–3."""
    a = as_axes(a_nominal_deg)
    wanted_base, _ = nominal_targets(model, a)
    wanted = transform_points(model.registration, wanted_base)
    error = model.predict_tcp_mm(a, dir, payload_kg, temp_c) - wanted
    corr = joint_mapping(model.ik_params(), a, error)
    return FeedForward(a_deg=a + corr, correction_deg=corr, estimated_error_mm=error)
