"""Calibration from cross-bar position constraints (seed 003, spec Part B).

A cross-bar is two bars of known length L crossing at their midpoints at a right angle; the robot
seats a probe ball in its four sockets A, B, C, D (A–C and B–D are the bars). Per placement the
constraints are ``|AC| = |BD| = L`` and ``AC ⊥ BD``. They are invariant under a rigid motion of the
whole point set, so no base-to-measurement transform is needed — and θ1, d1 (a rotation about and a
shift along z0) cannot be identified.

Rows (spec B.2) with ``P_X = f(q_X; x̂)`` and ``J_X = ∂P_X/∂x`` (the MDH identification Jacobian of
:func:`comp_daemon.kinematics.forward.identification_jacobian`)::

    distance:          (dᵀ(J_A − J_C)/D)·Δx = L − D,          d = P_A − P_C, D = ‖d‖  (same for B, D)
    perpendicularity:  (e1ᵀ(J_D − J_B) + e2ᵀ(J_C − J_A))·Δx = −e1ᵀe2,  e1 = P_C − P_A, e2 = P_D − P_B

The perpendicularity right-hand side is ``−e1ᵀe2`` (the paper prints ``+``; first-order expansion
gives the minus, and Gauss–Newton diverges with the printed sign). Each perpendicularity row and
its right-hand side are divided by ``√2·L`` (``weighted=True``, the default): its noise is about
``√2·L`` times a distance row's. The unweighted paper form is available for comparison.

Identifiability (B.3): the columns are the 24 MDH parameters (θ, d, a, α per joint; β instead of d
at a parallel pair) and, optionally, the tool. :func:`comparison_identifiability` names zero and
dependent columns (:func:`comp_daemon.estimation.identifiability.analyze_identifiability`, MDH
priority). With the probe on axis 6, rank 18; off axis, 21 (the paper's count for the MH6).

Iteration (B.4): solve the weighted rows on the identifiable columns; if any ``|Δx_j| > 3·e_j``
(``e`` = 2 mm for d and a, 0.5° for θ, α, β) drop the placement with the largest normalised residual
and solve again (refused once fewer rows than twice the unknowns remain); otherwise apply the step,
relinearise and repeat until ``max|Δx| < 1e-9``, the weighted RMS changes by less than 1e-12
(relative) or 30 iterations.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from comp_daemon.common.logs import get_logger
from comp_daemon.estimation.identifiability import (
    IdentifiabilityReport,
    analyze_identifiability,
    mdh_priority,
    parallel_joints,
)
from comp_daemon.kinematics.forward import chain, identification_jacobian
from comp_daemon.kinematics.inverse import solve_ik, solve_ik_axes
from comp_daemon.kinematics.params import N_PARAMS, PARAM_NAMES, KinematicParams, axes_deg_to_q_rad
from comp_daemon.kinematics.so3 import rotvec_to_matrix

__all__ = [
    "CrossbarFit",
    "CrossbarPlan",
    "CrossbarRefusedError",
    "absorb_probe",
    "bar_errors_mm",
    "calibrate_crossbar",
    "check_plan",
    "constraint_rows",
    "constraint_values",
    "crossbar_columns",
    "crossbar_identifiability",
    "plan_crossbar",
    "preset_errors_b5",
    "row_shortage",
    "seat_probe",
]

_log = get_logger(__name__)

SOCKETS = ("A", "B", "C", "D")
MIN_A6_SPAN_DEG = 30.0
#: constraint rows of one placement: |AC| = L, |BD| = L, AC ⊥ BD (B.2)
ROWS_PER_PLACEMENT = 3
#: rows the identification wants per unknown (B.3)
ROWS_PER_UNKNOWN = 2


class CrossbarRefusedError(ValueError):
    """A cross-bar campaign or calibration that cannot be used; the message says why."""


def absorb_probe(params: KinematicParams) -> KinematicParams:
    """The same TCP with the probe folded into link 6: ``a6 += tool_x``, ``d6 += tool_z·cos α6``.

    Needs ``tool_y = 0`` and ``sin α6 = 0`` (the MH6's α6 = 180°), so that the TCP is the origin of
    frame 6; then α6 (and θ6 when a6 = 0) have zero columns, as in the spec's rank table.
    """
    tx, ty, tz = params.tool_xyz_mm
    if abs(ty) > 1e-12 or abs(np.sin(params.alpha_rad[5])) > 1e-12 or abs(params.beta_rad[5]) > 1e-12:
        raise ValueError("absorb_probe needs tool_y = 0, sin(alpha6) = 0 and beta6 = 0")
    a = params.a_mm.copy()
    d = params.d_mm.copy()
    a[5] += tx
    d[5] += tz * np.cos(params.alpha_rad[5])
    return replace(params, a_mm=a, d_mm=d, tool_xyz_mm=np.zeros(3))


def crossbar_columns(params: KinematicParams, tool: bool = False) -> tuple[str, ...]:
    """The 24 MDH columns (θ, d, a, α; β for d at a parallel pair) [+ the tool], in PARAM_NAMES order."""
    parallel = parallel_joints(params)
    wanted = {"tool_x", "tool_y", "tool_z"} if tool else set()
    for j in range(1, 7):
        wanted |= {f"theta{j}", f"beta{j}" if parallel[j - 1] else f"d{j}", f"a{j}", f"alpha{j}"}
    return tuple(n for n in PARAM_NAMES if n in wanted)


def preset_errors_b5() -> NDArray[np.float64]:
    """The spec's B.5 preset errors as a 39-vector (``KinematicParams.apply`` layout)."""
    dx = np.zeros(N_PARAMS)
    table = dx[:30].reshape(6, 5)
    table[:, 0] = np.deg2rad([0.3, -0.4, 0.35, -0.3, 0.4, 0.3])
    table[:, 1] = [1.0, 0.0, -1.5, 1.2, -1.0, 0.8]
    table[:, 2] = [1.2, -1.5, 1.0, -0.8, 0.9, 0.6]
    table[:, 3] = np.deg2rad([0.2, -0.3, 0.25, -0.2, 0.3, 0.2])
    table[1, 4] = np.deg2rad(0.3)
    return dx


# ---- geometry -------------------------------------------------------------------------------


def _positions_and_jac(
    params: KinematicParams, a_deg: NDArray[np.float64], sign: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(p, 4, 3) socket positions and (p, 4, 3, 39) Jacobians for readings ``a_deg`` (p, 4, 6)."""
    p = a_deg.shape[0]
    q = axes_deg_to_q_rad(a_deg.reshape(-1, 6), sign)
    ch = chain(params, q)
    jac = identification_jacobian(params, q, ch)
    return ch.tcp_mm.reshape(p, 4, 3), jac.reshape(p, 4, 3, N_PARAMS)


def constraint_values(
    params: KinematicParams, a_deg: NDArray[np.float64], sign: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(p, 3): |AC|, |BD| (mm) and (C − A)·(D − B) (mm²) of each placement."""
    pos, _ = _positions_and_jac(params, a_deg, sign)
    e1 = pos[:, 2] - pos[:, 0]
    e2 = pos[:, 3] - pos[:, 1]
    return np.stack(
        [np.linalg.norm(e1, axis=1), np.linalg.norm(e2, axis=1), np.einsum("pi,pi->p", e1, e2)], axis=1
    )


def bar_errors_mm(
    params: KinematicParams,
    a_deg: NDArray[np.float64],
    sign: NDArray[np.float64],
    bar_l_mm: NDArray[np.float64],
) -> NDArray[np.float64]:
    """(p, 2) bar length errors |AC| − L, |BD| − L of each placement, mm."""
    vals = constraint_values(params, a_deg, sign)
    return vals[:, :2] - np.asarray(bar_l_mm, dtype=float)[:, None]


def constraint_rows(
    params: KinematicParams,
    a_deg: NDArray[np.float64],
    sign: NDArray[np.float64],
    bar_l_mm: NDArray[np.float64],
    *,
    weighted: bool = True,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Rows (p, 3, 39) and right-hand sides (p, 3) of B.2: distance AC, distance BD, perpendicularity."""
    pos, jac = _positions_and_jac(params, a_deg, sign)
    length = np.asarray(bar_l_mm, dtype=float)
    rows = np.empty((pos.shape[0], 3, N_PARAMS))
    rhs = np.empty((pos.shape[0], 3))
    for k, (i, j) in enumerate(((0, 2), (1, 3))):
        d = pos[:, i] - pos[:, j]
        dist = np.linalg.norm(d, axis=1)
        rows[:, k] = np.einsum("pi,pin->pn", d, jac[:, i] - jac[:, j]) / dist[:, None]
        rhs[:, k] = length - dist
    e1 = pos[:, 2] - pos[:, 0]
    e2 = pos[:, 3] - pos[:, 1]
    rows[:, 2] = np.einsum("pi,pin->pn", e1, jac[:, 3] - jac[:, 1]) + np.einsum(
        "pi,pin->pn", e2, jac[:, 2] - jac[:, 0]
    )
    rhs[:, 2] = -np.einsum("pi,pi->p", e1, e2)
    if weighted:
        w = np.sqrt(2.0) * length
        rows[:, 2] /= w[:, None]
        rhs[:, 2] /= w
    return rows, rhs


def crossbar_identifiability(
    params: KinematicParams,
    a_deg: NDArray[np.float64],
    sign: NDArray[np.float64],
    bar_l_mm: NDArray[np.float64],
    *,
    tool: bool = False,
    rtol: float = 1e-8,
) -> IdentifiabilityReport:
    """Zero and dependent columns of the constraint rows among :func:`crossbar_columns`, by name."""
    rows, _ = constraint_rows(params, a_deg, sign, bar_l_mm)
    names = crossbar_columns(params, tool=tool)
    return analyze_identifiability(
        rows.reshape(-1, N_PARAMS),
        PARAM_NAMES,
        candidates=names,
        priority=mdh_priority(params),
        rtol=rtol,
        rank_rtol=rtol,
    )


# ---- planning and seating -------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class CrossbarPlan:
    """Socket centres (p, 4, 3) in the base frame, the flange orientation per socket (p, 4, 3, 3)."""

    sockets_mm: NDArray[np.float64]
    flange_R: NDArray[np.float64]
    bar_l_mm: NDArray[np.float64]  # (p,)

    def subset(self, index: NDArray[np.intp] | NDArray[np.bool_]) -> CrossbarPlan:
        """The placements selected by ``index`` (indices or a mask)."""
        return CrossbarPlan(self.sockets_mm[index], self.flange_R[index], self.bar_l_mm[index])


def plan_crossbar(
    n_placements: int,
    rng: np.random.Generator,
    *,
    bar_l_mm: float = 400.0,
    centre_box_mm: tuple[tuple[float, float], ...] = ((500.0, 900.0), (-400.0, 400.0), (-300.0, 200.0)),
    tilt_deg: float = 30.0,
    approach_deg: float = 30.0,
) -> CrossbarPlan:
    """Placements as in spec B.5: centres in a box, cross tilted up to ``tilt_deg`` with random yaw;
    the probe (flange z) within ``approach_deg`` of straight down, random rotation about it (A6)."""
    box = np.asarray(centre_box_mm, dtype=float)
    centre = rng.uniform(box[:, 0], box[:, 1], (n_placements, 3))
    yaw = rng.uniform(-np.pi, np.pi, n_placements)
    tilt_axis = rng.uniform(-np.pi, np.pi, n_placements)
    tilt = np.deg2rad(rng.uniform(0.0, tilt_deg, n_placements))
    sockets = np.empty((n_placements, 4, 3))
    flange_r = np.empty((n_placements, 4, 3, 3))
    half = bar_l_mm / 2.0
    for k in range(n_placements):
        r_cross = rotvec_to_matrix(tilt[k] * np.array([np.cos(tilt_axis[k]), np.sin(tilt_axis[k]), 0.0]))
        r_cross = r_cross @ rotvec_to_matrix(np.array([0.0, 0.0, yaw[k]]))
        u, v = r_cross[:, 0], r_cross[:, 1]
        sockets[k] = centre[k] + half * np.stack([u, v, -u, -v])
        for s in range(4):
            az = rng.uniform(-np.pi, np.pi)
            ang = np.deg2rad(rng.uniform(0.0, approach_deg))
            z = rotvec_to_matrix(ang * np.array([np.cos(az), np.sin(az), 0.0])) @ np.array([0.0, 0.0, -1.0])
            spin = rng.uniform(-np.pi, np.pi)
            ref = np.array([1.0, 0.0, 0.0]) - z[0] * z
            x = ref / np.linalg.norm(ref)
            x = rotvec_to_matrix(spin * z) @ x
            flange_r[k, s] = np.column_stack([x, np.cross(z, x), z])
    return CrossbarPlan(sockets_mm=sockets, flange_R=flange_r, bar_l_mm=np.full(n_placements, bar_l_mm))


def seat_probe(
    params: KinematicParams,
    sign: NDArray[np.float64],
    axis_limits_deg: NDArray[np.float64],
    plan: CrossbarPlan,
    *,
    noise_sigma_mm: float = 0.0,
    rng: np.random.Generator | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Axis values (p, 4, 6) that seat the probe of the robot ``params`` in each socket; ok (p,).

    With ``noise_sigma_mm`` each seated position is the socket centre plus N(0, σ²) per axis (seating
    and teach error). The IK starts from the probe-down pose turned towards the socket.
    """
    p = plan.sockets_mm.shape[0]
    target = plan.sockets_mm.reshape(-1, 3).copy()
    if noise_sigma_mm > 0.0:
        gen = rng if rng is not None else np.random.default_rng()
        target += gen.normal(0.0, noise_sigma_mm, target.shape)
    rot = plan.flange_R.reshape(-1, 3, 3)
    seed = np.zeros((target.shape[0], 6))
    seed[:, 0] = np.rad2deg(np.arctan2(target[:, 1], target[:, 0]))
    seed[:, 4] = -90.0
    down = rot[:, :, 0]  # flange x; A6 ≈ its angle about the probe
    seed[:, 5] = np.rad2deg(np.arctan2(down[:, 1], -down[:, 0])) - seed[:, 0]
    a_deg, res = solve_ik_axes(params, sign, axis_limits_deg, target, rot, seed)
    # polish to rounding so that noise-free readings satisfy the constraints exactly
    limits_q = np.sort(np.deg2rad(axis_limits_deg) * sign[:, None], axis=1)
    res = solve_ik(params, limits_q, target, rot, np.deg2rad(a_deg) * sign, tol_mm=1e-11, tol_rad=1e-13)
    a_out: NDArray[np.float64] = (np.rad2deg(res.q_rad) * sign).reshape(p, 4, 6)
    ok: NDArray[np.bool_] = np.asarray((res.position_error_mm < 1e-8).reshape(p, 4).all(axis=1))
    return a_out, ok


def row_shortage(placements: int, unknowns: int) -> str | None:
    """Why ``placements`` are too few to identify ``unknowns`` (:data:`ROWS_PER_PLACEMENT` rows each,
    :data:`ROWS_PER_UNKNOWN` wanted per unknown); None when they are enough."""
    rows, need = ROWS_PER_PLACEMENT * placements, ROWS_PER_UNKNOWN * unknowns
    if rows >= need:
        return None
    return f"{placements} placements give {rows} rows; {unknowns} unknowns need {need}"


def check_plan(a_deg: NDArray[np.float64], n_unknowns: int = 21) -> None:
    """Refuse a campaign whose A6 spans less than 30° or that has too few placements (B.3, data forms)."""
    a = np.asarray(a_deg, dtype=float)
    span = float(np.ptp(a[..., 5]))
    if span < MIN_A6_SPAN_DEG:
        raise CrossbarRefusedError(
            f"A6 spans {span:.1f}° (< {MIN_A6_SPAN_DEG:.0f}°): θ6 and joint 5 cannot be told apart; vary A6"
        )
    short = row_shortage(a.shape[0], n_unknowns)
    if short is not None:
        raise CrossbarRefusedError(short)


# ---- iterative solution ---------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class CrossbarFit:
    """The calibrated parameters and how the iteration went."""

    params: KinematicParams
    dx: NDArray[np.float64]  # (39,) added to the start parameters
    report: IdentifiabilityReport
    step_max: tuple[float, ...]  # max |Δx| of each accepted step
    rms: tuple[float, ...]  # weighted RMS of the right-hand sides before each step
    dropped: tuple[int, ...]  # placements rejected (indices into the campaign)
    reason: str  # step | rms | max_iter
    weighted: bool = True
    not_identified: tuple[str, ...] = field(default=())

    @property
    def iterations(self) -> int:
        return len(self.step_max)


def _step_bounds(names: tuple[str, ...], length_mm: float, angle_deg: float) -> NDArray[np.float64]:
    """The error bound e_j of each parameter: ``length_mm`` for d, a and the tool, ``angle_deg`` else."""
    is_length = [n.rstrip("0123456789") in ("d", "a") or n.startswith("tool") for n in names]
    return np.where(is_length, length_mm, np.deg2rad(angle_deg))


def calibrate_crossbar(
    params: KinematicParams,
    a_deg: NDArray[np.float64],
    sign: NDArray[np.float64],
    bar_l_mm: NDArray[np.float64],
    *,
    weighted: bool = True,
    tool: bool = False,
    bound_mm: float = 2.0,
    bound_deg: float = 0.5,
    max_iter: int = 30,
) -> CrossbarFit:
    """Identify the MDH errors from cross-bar readings ``a_deg`` (p, 4, 6), sockets in A, B, C, D order."""
    a = np.asarray(a_deg, dtype=float)
    lengths = np.asarray(bar_l_mm, dtype=float)
    report = crossbar_identifiability(params, a, sign, lengths, tool=tool)
    cols = report.identifiable_index
    names = report.identifiable
    bounds = 3.0 * _step_bounds(names, bound_mm, bound_deg)
    active = np.arange(a.shape[0])
    dropped: list[int] = []
    dx = np.zeros(N_PARAMS)
    steps: list[float] = []
    rms_hist: list[float] = []
    reason = "max_iter"
    current = params
    while len(steps) < max_iter:
        rows, rhs = constraint_rows(current, a[active], sign, lengths[active], weighted=weighted)
        g = rows[:, :, cols]
        rms = float(np.sqrt(np.mean(rhs**2)))
        if rms_hist and abs(rms_hist[-1] - rms) <= 1e-12 * max(rms_hist[-1], 1e-300):
            reason = "rms"
            break
        step, *_ = np.linalg.lstsq(g.reshape(-1, cols.size), rhs.reshape(-1), rcond=1e-12)
        if np.any(np.abs(step) > bounds):
            resid = (np.einsum("prn,n->pr", g, step) - rhs) / max(rms, 1e-300)
            worst = int(np.argmax(np.linalg.norm(resid, axis=1)))
            dropped.append(int(active[worst]))
            active = np.delete(active, worst)
            _log.info(
                "crossbar_step_rejected",
                placement=dropped[-1],
                step_over_bound=float(np.max(np.abs(step) / bounds)),
            )
            short = row_shortage(active.size, cols.size)
            if short is not None:
                raise CrossbarRefusedError(f"after rejecting placements {dropped}, {short}")
            continue
        rms_hist.append(rms)
        dx[cols] += step
        current = params.apply(dx)
        steps.append(float(np.abs(step).max()))
        if steps[-1] < 1e-9:
            reason = "step"
            break
    _log.info("crossbar_fit", iterations=len(steps), reason=reason, dropped=dropped)
    not_identified = report.removed_names()
    return CrossbarFit(
        params=current,
        dx=dx,
        report=report,
        step_max=tuple(steps),
        rms=tuple(rms_hist),
        dropped=tuple(dropped),
        reason=reason,
        weighted=weighted,
        not_identified=not_identified,
    )
