"""POE calibration from measured positions (seed 002, spec A.2–A.3).

The parameters are the 12 POE errors of :mod:`comp_daemon.kinematics.poe` (``dl1..dl6`` mm,
``dtheta1..dtheta6`` rad) and, when the positions are measured in another frame (a tracker), the
six parameters of ``world_T_base``: ``base_x, base_y, base_z`` (mm) and the rotation vector
``base_rx, base_ry, base_rz`` (rad, applied on the left of the registered start frame). The
residual is ``p(A_k; x) − p_meas,k`` in mm.

Identifiability (spec A.2 product rule). Some columns are structurally dependent: ``dl1 ≡ dl2``
(both shift everything beyond q1 along joint 1's axis), ``dl5 ≡ dl6`` (q4 moves along its own axis),
``dtheta6`` is zero with the TCP on axis 6, and a fitted base frame absorbs ``dtheta1`` and ``dl2``.
:func:`poe_identifiability` offers the columns to
:func:`comp_daemon.estimation.identifiability.analyze_identifiability` in :data:`POE_PRIORITY` order
(frame parameters first, then the errors, the ones to fix when dependent last: ``dl5``, ``dl1``,
``dtheta6``), so the removed set is named the way the spec names it, each with the kept columns it
depends on. :func:`null_directions` adds the null-space vectors of the normalised columns (largest
four coefficients each), which is what a caller prints for "not identifiable".

Segment layout. Which segments carry ``dl1..dl6`` is a choice of the model (:class:`PoeModel`):
seed 002 names its own for the IRB 120 (Table 1 and spec A.2: 187 z, 103 z, 270 z, 70 z, 134 x,
168 x), so that ``dl1..dl6`` are that robot's link-length errors; any other robot has one segment
per joint point (:meth:`PoeModel.from_robot`). :func:`paper_layout` tells which a robot gets
(``"table1"`` when Table 1's chain is this robot's kinematics, else ``"robot"``) and
:func:`layout_twists` builds it; the paper's forms (``poe:paper``, a ballbar campaign's fit) use it.

The fit iterates the identifiable columns with the improved Levenberg–Marquardt method of
:mod:`comp_daemon.estimation.lm` (columns scaled); the removed parameters stay at zero. The standard
uncertainty of each fitted parameter is ``s·sqrt(diag((JᵀWJ)⁻¹))`` with ``s²`` the weighted residual
variance (or 1 when the weights are known inverse variances, ``weights_are_inverse_variance``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from comp_daemon.common.logs import get_logger
from comp_daemon.estimation.identifiability import IdentifiabilityReport, analyze_identifiability
from comp_daemon.estimation.lm import improved_lm
from comp_daemon.estimation.registration import rigid_registration
from comp_daemon.kinematics.poe import (
    N_POE_PARAMS,
    POE_PARAM_NAMES,
    PoeModel,
    irb120_table1,
    poe_chain,
    poe_error_jacobian,
)
from comp_daemon.kinematics.so3 import left_jacobian, rotvec_to_matrix, skew
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "BASE_NAMES",
    "LAYOUTS",
    "POE_PRIORITY",
    "NullDirection",
    "PoeFit",
    "fit_least_squares_subset",
    "fit_poe_positions",
    "layout_twists",
    "null_directions",
    "paper_layout",
    "poe_identifiability",
    "poe_world_jacobian",
    "poe_world_position_mm",
    "start_frame",
]

_log = get_logger(__name__)

PoeLayout = Literal["robot", "table1"]
#: the segment layouts, by the name an artifact stores: one segment per joint point, or seed 002's
#: Table 1 (the IRB 120)
LAYOUTS: dict[str, str] = {
    "robot": "one segment per joint point of the robot file",
    "table1": "seed 002's Table 1 (IRB 120: 187 z, 103 z, 270 z, 70 z, 134 x, 168 x)",
}
#: Table 1's chain must put the TCP within this of the robot file's at every test pose
_LAYOUT_TOL_MM = 1e-6


def layout_twists(robot: RobotDescription, layout: PoeLayout) -> PoeModel:
    """The POE chain of ``robot`` with the segment ``layout`` (module docstring)."""
    return irb120_table1(robot) if layout == "table1" else PoeModel.from_robot(robot)


def paper_layout(robot: RobotDescription) -> PoeLayout:
    """``"table1"`` when seed 002's Table 1 chain is ``robot``'s kinematics (the IRB 120: the TCP
    within 1e-6 mm of the robot file's chain over poses spread across the axis ranges), else
    ``"robot"``."""
    try:
        table1 = irb120_table1(robot)
    except ValueError:
        return "robot"
    lim = robot.axis_limits_deg
    a = np.random.default_rng(0).uniform(lim[:, 0], lim[:, 1], (20, 6))
    same = np.abs(poe_chain(table1, a).tcp_mm - poe_chain(PoeModel.from_robot(robot), a).tcp_mm)
    return "table1" if float(same.max()) < _LAYOUT_TOL_MM else "robot"

BASE_NAMES: tuple[str, ...] = ("base_x", "base_y", "base_z", "base_rx", "base_ry", "base_rz")
# kept first … offered last (fixed first when dependent): spec A.2's order Δθ6, Δl1, Δl5, then Δθ1, Δl2
POE_PRIORITY: tuple[str, ...] = (
    "dl3",
    "dl4",
    "dtheta2",
    "dtheta3",
    "dtheta4",
    "dtheta5",
    "dl6",
    "dl2",
    "dtheta1",
    "dl5",
    "dl1",
    "dtheta6",
)


@dataclass(frozen=True, slots=True)
class NullDirection:
    """A combination of normalised columns the data do not see: ``Σ coefficient·column/‖column‖ ≈ 0``.

    ``singular_value`` is ``‖J·v‖`` relative to the largest singular value of the normalised columns.
    """

    names: tuple[str, ...]
    coefficients: tuple[float, ...]
    singular_value: float  # relative to the largest

    def describe(self) -> str:
        terms = " ".join(f"{c:+.3f}·{n}" for n, c in zip(self.names, self.coefficients, strict=True))
        return f"not identifiable: {terms} (relative singular value {self.singular_value:.1e})"


def null_directions(
    report: IdentifiabilityReport, jac: NDArray[np.float64], *, top: int = 4
) -> tuple[NullDirection, ...]:
    """One null-space vector per removed parameter of ``report``, ``top`` largest coefficients each.

    A removed parameter r that depends on kept ones (``column_r = Σ c_k·column_k``) gives the
    direction ``e_r − Σ c_k·e_k``; a zero column is its own direction. Coefficients are those of the
    normalised columns (so mm and rad compare), the vector scaled to unit length.
    """
    names = report.names
    a = np.asarray(jac, dtype=float).reshape(-1, len(names))
    norms = np.linalg.norm(a, axis=0)
    index = {n: i for i, n in enumerate(names)}
    sv = report.singular_values
    out = []
    for removed in report.removed:
        v = np.zeros(len(names))
        v[index[removed.name]] = 1.0
        for dep, c in zip(removed.depends_on, removed.coefficients, strict=True):
            v[index[dep]] = -c
        v_scaled = v * np.where(norms > 0, norms, 1.0)
        v_scaled /= np.linalg.norm(v_scaled)
        order = np.argsort(-np.abs(v_scaled), kind="stable")[:top]
        order = order[np.abs(v_scaled[order]) > 1e-9]
        if removed.reason == "zero":
            rel = float(norms[index[removed.name]] / max(norms.max(), 1e-300))
        else:
            seen = float(np.linalg.norm(a @ (v_scaled / np.where(norms > 0, norms, 1.0))))
            rel = seen / float(sv[0]) if sv.size and sv[0] > 0 else 0.0
        out.append(
            NullDirection(tuple(names[i] for i in order), tuple(float(v_scaled[i]) for i in order), rel)
        )
    return tuple(out)


def poe_identifiability(
    jac: NDArray[np.float64],
    names: Sequence[str],
    frame_names: Sequence[str] = (),
    rtol: float = 1e-7,
) -> IdentifiabilityReport:
    """Which of ``names`` (POE errors plus any frame/pivot names) the stacked ``jac`` identifies.

    Frame parameters (``frame_names``) are offered first, then :data:`POE_PRIORITY`; the parameters
    removed are the ones the spec's product rule fixes.
    """
    priority = [*frame_names, *POE_PRIORITY]
    priority += [n for n in names if n not in priority]
    return analyze_identifiability(
        jac, list(names), priority=[n for n in priority if n in names], rtol=rtol, rank_rtol=rtol
    )


def poe_world_position_mm(
    model: PoeModel,
    a_deg: NDArray[np.float64],
    x: NDArray[np.float64],
    world_T_base: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """(n, 3) TCP in the world frame for POE errors ``x`` (12,) and the frame ``world_T_base``."""
    p = poe_chain(model, a_deg, x).tcp_mm
    if world_T_base is None:
        return p
    return p @ world_T_base[:3, :3].T + world_T_base[:3, 3]


def start_frame(start: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """The frame ``Rot(b_r)·start`` shifted by ``b_t`` (``b`` the six base parameters)."""
    out = np.eye(4)
    rot = rotvec_to_matrix(b[3:])
    out[:3, :3] = rot @ start[:3, :3]
    out[:3, 3] = rot @ start[:3, 3] + b[:3]
    return out


def poe_world_jacobian(
    model: PoeModel,
    a_deg: NDArray[np.float64],
    theta: NDArray[np.float64],
    start_T_base: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """World TCP (n, 3) and its Jacobian (n, 3, 12 [+6]) w.r.t. ``theta`` = (x [, base params]).

    With ``start_T_base`` the world frame is ``Rot(b_r)·start_T_base`` shifted by ``b_t``; the
    rotation's derivative is exact (SO(3) left Jacobian).
    """
    ch = poe_chain(model, a_deg, theta[:N_POE_PARAMS])
    jac_x = poe_error_jacobian(model, a_deg, ch=ch)
    if start_T_base is None:
        return ch.tcp_mm, jac_x
    world = start_frame(start_T_base, theta[N_POE_PARAMS:])
    p = ch.tcp_mm @ world[:3, :3].T + world[:3, 3]
    n = p.shape[0]
    jac = np.empty((n, 3, N_POE_PARAMS + 6))
    jac[:, :, :N_POE_PARAMS] = world[:3, :3] @ jac_x
    jac[:, :, N_POE_PARAMS : N_POE_PARAMS + 3] = np.eye(3)
    b = theta[N_POE_PARAMS:]
    # world point = R(b_r)·q + b_t with q the start-frame point; d/d b_r = −[R q]× J_l(b_r)
    rq = p - b[:3]
    jac[:, :, N_POE_PARAMS + 3 :] = -skew(rq) @ left_jacobian(b[3:])
    return p, jac


@dataclass(frozen=True, slots=True)
class PoeFit:
    """A POE calibration: full error vector (removed entries zero), frame, report, residuals."""

    names: tuple[str, ...]  # POE_PARAM_NAMES (+ BASE_NAMES when the frame was fitted)
    theta: NDArray[np.float64]  # values of ``names``
    std: NDArray[np.float64]  # standard uncertainty of each (NaN for removed ones)
    cov: NDArray[np.float64]  # covariance of ``theta`` (rows and columns of removed ones zero: fixed)
    world_T_base: NDArray[np.float64] | None
    report: IdentifiabilityReport
    null_space: tuple[NullDirection, ...]
    rms_before_mm: float
    rms_after_mm: float
    iterations: int
    reason: str

    @property
    def x(self) -> NDArray[np.float64]:
        """The 12 POE errors."""
        return self.theta[:N_POE_PARAMS]

    def value(self, name: str) -> float:
        return float(self.theta[self.names.index(name)])


def fit_least_squares_subset(
    fn: Callable[[NDArray[np.float64]], tuple[NDArray[np.float64], NDArray[np.float64]]],
    theta0: NDArray[np.float64],
    keep: NDArray[np.intp],
    *,
    inverse_variance: bool,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], int, str, NDArray[np.float64]]:
    """LM on the ``keep`` columns of ``fn(theta) -> (residual, jacobian)``.

    Returns (theta, std, cov, iterations, reason, residual); std is NaN and cov zero for the fixed.
    """

    def full(u: NDArray[np.float64]) -> NDArray[np.float64]:
        th = theta0.copy()
        th[keep] = u
        return th

    res = improved_lm(
        lambda u: fn(full(u))[0],
        lambda u: fn(full(u))[1][:, keep],
        theta0[keep],
        x_scale="jac",
        phi=1e-12,
        max_iter=100,
    )
    theta = full(res.x)
    r, jac = fn(theta)
    jk = jac[:, keep]
    dof = max(r.size - keep.size, 1)
    s2 = 1.0 if inverse_variance else float(r @ r) / dof
    std = np.full(theta.size, np.nan)
    cov = np.zeros((theta.size, theta.size))
    try:
        cov[np.ix_(keep, keep)] = np.linalg.inv(jk.T @ jk) * s2
        std[keep] = np.sqrt(np.clip(np.diag(cov)[keep], 0.0, None))
    except np.linalg.LinAlgError:
        pass
    return theta, std, cov, res.iterations, res.reason, r


def fit_poe_positions(
    model: PoeModel,
    a_deg: NDArray[np.float64],
    p_meas_mm: NDArray[np.float64],
    *,
    fit_base: bool = False,
    weights: NDArray[np.float64] | None = None,
    weights_are_inverse_variance: bool = False,
    rtol: float = 1e-7,
) -> PoeFit:
    """Identify the POE errors (and, with ``fit_base``, the frame) from measured TCP positions.

    ``a_deg`` (n, 6) axis values, ``p_meas_mm`` (n, 3). ``weights`` (n,) multiply each point's squared
    residual (e.g. ``1/u²`` from :mod:`comp_daemon.estimation.uncertainty`). With ``fit_base`` the start
    frame is the rigid registration of the nominal TCPs onto the measured ones.
    """
    a = np.atleast_2d(np.asarray(a_deg, dtype=float))
    p_meas = np.atleast_2d(np.asarray(p_meas_mm, dtype=float))
    if p_meas.shape != (a.shape[0], 3):
        raise ValueError(f"positions must be (n, 3) with n = {a.shape[0]}, got {p_meas.shape}")
    sw = np.ones(a.shape[0]) if weights is None else np.sqrt(np.asarray(weights, dtype=float))
    p_nom = poe_chain(model, a).tcp_mm
    start = rigid_registration(p_nom, p_meas) if fit_base else None
    names = POE_PARAM_NAMES + (BASE_NAMES if fit_base else ())
    theta0 = np.zeros(len(names))

    def fn(theta: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        p, jac = poe_world_jacobian(model, a, theta, start)
        r = ((p - p_meas) * sw[:, None]).reshape(-1)
        return r, (jac * sw[:, None, None]).reshape(-1, len(names))

    r0, jac0 = fn(theta0)
    report = poe_identifiability(jac0, names, BASE_NAMES if fit_base else (), rtol)
    null = null_directions(report, jac0)
    keep = report.identifiable_index
    theta, std, cov, its, reason, r = fit_least_squares_subset(
        fn, theta0, keep, inverse_variance=weights_are_inverse_variance
    )
    rms0 = float(np.sqrt(np.mean(np.sum((r0.reshape(-1, 3) / sw[:, None]) ** 2, axis=1))))
    rms1 = float(np.sqrt(np.mean(np.sum((r.reshape(-1, 3) / sw[:, None]) ** 2, axis=1))))
    _log.info("poe_fit", points=a.shape[0], kept=report.n_identifiable, rms_before_mm=rms0, rms_after_mm=rms1)
    return PoeFit(
        names=names,
        theta=theta,
        std=std,
        cov=cov,
        world_T_base=None if start is None else start_frame(start, theta[N_POE_PARAMS:]),
        report=report,
        null_space=null,
        rms_before_mm=rms0,
        rms_after_mm=rms1,
        iterations=its,
        reason=reason,
    )
