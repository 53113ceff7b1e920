"""Ballbar calibration of the POE error model (seed 002, spec A.4–A.6).

A ballbar measures the centre-to-centre length between a fixed pivot ball and a ball on the flange
(the TCP). The model (spec A.4, reconstructed) is::

    L_t,k(x, Δo) = ‖ p(A_k; Δl, Δθ) − (o + Δo) ‖

with ``p`` the POE TCP of :mod:`comp_daemon.kinematics.poe`, ``o`` the nominal pivot in the robot
base frame and 15 unknowns: the 12 POE errors and the pivot offset ``dXo, dYo, dZo`` (mm).

What a ballbar cannot see. Lengths are invariant under every motion of the TCP set *together with*
the pivot: a rotation of everything about z0 makes Δθ1 indistinguishable from the pivot (ΔY_o =
X_o·Δθ1 to first order), a shift along z0 makes Δl1 + Δl2 indistinguishable from ΔZ_o. Added to the
POE dependencies (Δl1 ≡ Δl2, Δl5 ≡ Δl6, Δθ6 zero with the TCP on axis 6) and, with the tool held
vertical, the parallel axes 2, 3, 5 (Δθ3 = Δθ5's effect plus a forearm shift), a single-orientation
campaign identifies 9 (vertical tool) or 10 (tilted) of the 15; one orientation per arc with an
off-axis TCP reaches 11 (10 with the TCP on axis 6, as in the IRB 120 preset). Pairs that are
identifiable but barely told apart are named by the campaign fit (near-dependent pairs) and, on
request, the weaker of each held at zero (:func:`weaker_of_pairs`).
:func:`ballbar_identifiability` names the removed parameters in the spec's canonical order (pivot
kept, then Δθ1 and Δl2 fixed) and the null directions; the fit keeps them at zero and reports them
as "not identifiable" instead of returning arbitrary values.

Arcs (spec A.5): :func:`arc_through_points` is the circle through three points (bisector planes and
the points' plane), sampled every 5° from P1 through P2 to P3. :func:`default_arcs` is the spec's
plan (A.6): arc 1 at elevation 10° from azimuth −90° to 90°, arcs 2 and 3 the vertical great circles
in the x–z and y–z planes from elevation 10° over the top (37 + 33 + 33 points).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from comp_daemon.common.logs import get_logger
from comp_daemon.estimation.identifiability import IdentifiabilityReport
from comp_daemon.kinematics.inverse import solve_ik_axes
from comp_daemon.kinematics.params import KinematicParams
from comp_daemon.kinematics.poe import N_POE_PARAMS, POE_PARAM_NAMES, PoeModel, poe_chain, poe_error_jacobian
from comp_daemon.models.covariance import near_dependent_pairs
from comp_daemon.models.poe.calibration import (
    NullDirection,
    fit_least_squares_subset,
    null_directions,
    poe_identifiability,
)

__all__ = [
    "BALLBAR_PARAM_NAMES",
    "PAPER_PIVOT_MM",
    "PAPER_RADIUS_MM",
    "PIVOT_NAMES",
    "RIDGE_SCALES",
    "Arc",
    "BallbarFit",
    "arc_through_points",
    "ballbar_identifiability",
    "ballbar_jacobian",
    "ballbar_lengths_mm",
    "default_arcs",
    "error_variogram",
    "fit_ballbar",
    "pair_variogram",
    "plan_ballbar_axes",
    "sphere_point_mm",
    "to_canonical",
    "weaker_of_pairs",
]

_log = get_logger(__name__)

PIVOT_NAMES: tuple[str, ...] = ("dXo", "dYo", "dZo")
BALLBAR_PARAM_NAMES: tuple[str, ...] = POE_PARAM_NAMES + PIVOT_NAMES
N_BALLBAR_PARAMS = len(BALLBAR_PARAM_NAMES)
PAPER_PIVOT_MM = (350.0, 0.0, 394.0)
PAPER_RADIUS_MM = 100.0


# ---- arcs (A.5) -----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Arc:
    """Circle through three points: centre, radius, in-plane basis (u towards P1), sweep Φ to P3."""

    centre_mm: NDArray[np.float64]
    radius_mm: float
    u: NDArray[np.float64]
    v: NDArray[np.float64]
    normal: NDArray[np.float64]
    sweep_rad: float

    def angle_rad(self, p_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        """Angle φ(P) ∈ [0, 2π) of points (n, 3) from P1, counter-clockwise about the normal."""
        d = np.atleast_2d(p_mm) - self.centre_mm
        return np.mod(np.arctan2(d @ self.v, d @ self.u), 2.0 * np.pi)

    def sample(self, step_deg: float = 5.0) -> NDArray[np.float64]:
        """(m, 3) points from P1 to P3, ``m = round(Φ/step) + 1``, equally spaced."""
        m = round(self.sweep_rad / float(np.deg2rad(step_deg))) + 1
        t = np.linspace(0.0, 1.0, max(m, 2)) * self.sweep_rad
        return self.centre_mm + self.radius_mm * (np.cos(t)[:, None] * self.u + np.sin(t)[:, None] * self.v)


def arc_through_points(p1: NDArray[np.float64], p2: NDArray[np.float64], p3: NDArray[np.float64]) -> Arc:
    """The arc from ``p1`` through ``p2`` to ``p3`` (spec A.5); collinear points are refused."""
    p1, p2, p3 = (np.asarray(p, dtype=float) for p in (p1, p2, p3))
    n = np.cross(p2 - p1, p3 - p1)
    if np.linalg.norm(n) < 1e-9 * np.linalg.norm(p2 - p1) * np.linalg.norm(p3 - p1):
        raise ValueError("the three points are collinear: no circle passes through them")
    a = np.vstack([p2 - p1, p3 - p2, n])
    b = np.array([(p2 @ p2 - p1 @ p1) / 2.0, (p3 @ p3 - p2 @ p2) / 2.0, n @ p1])
    centre = np.linalg.solve(a, b)
    radius = float(np.linalg.norm(p1 - centre))
    u = (p1 - centre) / radius
    n_hat = n / np.linalg.norm(n)
    v = np.cross(n_hat, u)
    arc = Arc(centre, radius, u, v, n_hat, 0.0)
    sweep = float(arc.angle_rad(p3)[0])
    return Arc(centre, radius, u, v, n_hat, sweep)


def sphere_point_mm(
    azimuth_deg: float,
    elevation_deg: float,
    pivot_mm: ArrayLike = PAPER_PIVOT_MM,
    radius_mm: float = 100.0,
) -> NDArray[np.float64]:
    """Point on the ballbar sphere about the pivot at azimuth φ and elevation ψ (deg)."""
    az, el = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
    return np.asarray(pivot_mm, dtype=float) + radius_mm * np.array(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]
    )


def default_arcs(pivot_mm: ArrayLike = PAPER_PIVOT_MM, radius_mm: float = PAPER_RADIUS_MM) -> tuple[Arc, ...]:
    """The spec's three arcs (A.6): ψ = 10° from φ −90° to 90°; x–z and y–z great circles over the top."""
    pts = [
        ((-90.0, 10.0), (0.0, 10.0), (90.0, 10.0)),
        ((180.0, 10.0), (0.0, 90.0), (0.0, 10.0)),
        ((-90.0, 10.0), (0.0, 90.0), (90.0, 10.0)),
    ]
    return tuple(
        arc_through_points(*(sphere_point_mm(az, el, pivot_mm, radius_mm) for az, el in triple))
        for triple in pts
    )


def plan_ballbar_axes(
    params: KinematicParams,
    sign: NDArray[np.float64],
    axis_limits_deg: NDArray[np.float64],
    arcs: Sequence[Arc],
    flange_R: Sequence[NDArray[np.float64]],
    seed_a_deg: NDArray[np.float64],
    step_deg: float = 5.0,
) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Axis values (n, 6) that put the TCP on the arcs' points at a fixed flange orientation per arc.

    Numerical IK of the nominal model, each point seeded by the previous answer on its arc. Returns
    the axis values and the arc index (1-based) of each point. An unreachable point is refused.
    """
    a_all, arc_id = [], []
    for k, (arc, rot) in enumerate(zip(arcs, flange_R, strict=True)):
        pts = arc.sample(step_deg)
        seed = np.asarray(seed_a_deg, dtype=float)
        for p in pts:
            a_deg, res = solve_ik_axes(params, sign, axis_limits_deg, p[None], rot[None], seed[None])
            if not bool(res.ok[0]):
                raise ValueError(f"arc {k + 1}: point {p.round(3)} not reachable at the given orientation")
            seed = a_deg[0]
            a_all.append(a_deg[0])
            arc_id.append(k + 1)
    return np.array(a_all), np.array(arc_id, dtype=np.intp)


# ---- variogram of the error field (A.6) -------------------------------------------------------


def _error_field(model: PoeModel, a_deg: NDArray[np.float64], x: NDArray[np.float64]) -> NDArray[np.float64]:
    """ΔP(A) = p(A; x) − p(A; 0), mm."""
    return poe_chain(model, a_deg, x).tcp_mm - poe_chain(model, a_deg).tcp_mm


def error_variogram(
    model: PoeModel,
    x: NDArray[np.float64],
    base_a_deg: NDArray[np.float64],
    lags_deg: Sequence[float],
    rng: np.random.Generator,
) -> NDArray[np.float64]:
    """γ(h) in mm² at exact joint-space lags h (deg): ``mean ‖ΔP(A + h·u) − ΔP(A)‖² / 2`` over the
    base poses, u a random unit direction in the six joints (one draw per pose and lag)."""
    base = np.asarray(base_a_deg, dtype=float)
    d0 = _error_field(model, base, x)
    out = []
    for h in lags_deg:
        u = rng.normal(size=base.shape)
        u /= np.linalg.norm(u, axis=1)[:, None]
        diff = _error_field(model, base + h * u, x) - d0
        out.append(0.5 * float(np.mean(np.sum(diff**2, axis=1))))
    return np.array(out)


def pair_variogram(
    model: PoeModel,
    x: NDArray[np.float64],
    a_deg: NDArray[np.float64],
    lags_deg: Sequence[float],
    width_deg: float = 5.0,
) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """The binned semivariogram of spec eqs 22–24 over all pairs of ``a_deg``: γ(h) (mm², NaN for an
    empty bin) and the pair count N(h), pairs with ``|h_ij − h| < width/2``."""
    a = np.asarray(a_deg, dtype=float)
    d = _error_field(model, a, x)
    i, j = np.triu_indices(a.shape[0], 1)
    h_ij = np.linalg.norm(a[i] - a[j], axis=1)
    g_ij = 0.5 * np.sum((d[i] - d[j]) ** 2, axis=1)
    gamma, count = [], []
    for h in lags_deg:
        sel = np.abs(h_ij - h) < width_deg / 2
        count.append(int(sel.sum()))
        gamma.append(float(g_ij[sel].mean()) if sel.any() else float("nan"))
    return np.array(gamma), np.array(count, dtype=np.intp)


# ---- model ------------------------------------------------------------------------------------


def ballbar_lengths_mm(
    model: PoeModel, a_deg: NDArray[np.float64], theta: NDArray[np.float64], pivot_mm: ArrayLike
) -> NDArray[np.float64]:
    """(n,) predicted centre-to-centre lengths for ``theta`` = (12 POE errors, dXo, dYo, dZo)."""
    th = np.asarray(theta, dtype=float)
    p = poe_chain(model, a_deg, th[..., :N_POE_PARAMS]).tcp_mm
    return np.asarray(np.linalg.norm(p - (np.asarray(pivot_mm) + th[..., N_POE_PARAMS:]), axis=-1))


def ballbar_jacobian(
    model: PoeModel, a_deg: NDArray[np.float64], theta: NDArray[np.float64], pivot_mm: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Lengths (n,) and their Jacobian (n, 15) w.r.t. ``theta``."""
    ch = poe_chain(model, a_deg, theta[:N_POE_PARAMS])
    jp = poe_error_jacobian(model, a_deg, ch=ch)
    d = ch.tcp_mm - (np.asarray(pivot_mm, dtype=float) + theta[N_POE_PARAMS:])
    length = np.linalg.norm(d, axis=1)
    unit = d / length[:, None]
    jac = np.empty((length.size, N_BALLBAR_PARAMS))
    jac[:, :N_POE_PARAMS] = np.einsum("ni,nij->nj", unit, jp)
    jac[:, N_POE_PARAMS:] = -unit
    return length, jac


def ballbar_identifiability(
    model: PoeModel,
    a_deg: NDArray[np.float64],
    pivot_mm: ArrayLike,
    theta: NDArray[np.float64] | None = None,
    rtol: float = 1e-7,
) -> tuple[IdentifiabilityReport, tuple[NullDirection, ...]]:
    """Rank, removed parameters (pivot kept; Δθ1 and Δl2 fixed first) and null directions."""
    th = np.zeros(N_BALLBAR_PARAMS) if theta is None else theta
    _, jac = ballbar_jacobian(model, a_deg, th, pivot_mm)
    report = poe_identifiability(jac, BALLBAR_PARAM_NAMES, PIVOT_NAMES, rtol)
    return report, null_directions(report, jac)


@dataclass(frozen=True, slots=True)
class BallbarFit:
    """A ballbar calibration. Removed parameters are zero in ``theta`` and listed in ``null_space``."""

    theta: NDArray[np.float64]  # (15,) BALLBAR_PARAM_NAMES
    std: NDArray[np.float64]  # standard uncertainty (NaN for the not identifiable)
    cov: NDArray[np.float64]  # (15, 15) covariance; rows/columns of the not identifiable zero
    report: IdentifiabilityReport
    null_space: tuple[NullDirection, ...]
    h_before_mm: float  # RMS length error (unweighted) at the start
    h_after_mm: float
    iterations: int
    reason: str
    # near-dependent pairs resolved by holding one member at zero (fit_ballbar's fix_near_dependent)
    fixed_pairs: tuple[dict[str, Any], ...] = ()

    @property
    def fitted_index(self) -> NDArray[np.intp]:
        """The identifiable parameters the fit moved: without those of :attr:`fixed_pairs`."""
        return _without(self.report.identifiable_index, {p["fixed"] for p in self.fixed_pairs})

    @property
    def rank(self) -> int:
        return self.report.rank_svd

    @property
    def nullity(self) -> int:
        return N_BALLBAR_PARAMS - self.report.rank_svd

    def not_identifiable(self) -> tuple[str, ...]:
        return self.report.removed_names()

    def summary(self) -> str:
        lines = [f"ballbar fit: rank {self.rank} of {N_BALLBAR_PARAMS} (nullity {self.nullity})"]
        lines.append(
            f"H {self.h_before_mm:.6g} mm -> {self.h_after_mm:.3g} mm ({self.iterations} iterations)"
        )
        for i in self.report.identifiable_index:
            lines.append(f"  {BALLBAR_PARAM_NAMES[i]} = {self.theta[i]:+.6g} ± {self.std[i]:.2g}")
        lines += ["  " + d.describe() for d in self.null_space]
        return "\n".join(lines)


def fit_ballbar(
    model: PoeModel,
    a_deg: NDArray[np.float64],
    bar_mm: NDArray[np.float64],
    pivot_mm: ArrayLike,
    *,
    weights: NDArray[np.float64] | None = None,
    weights_are_inverse_variance: bool = False,
    theta0: NDArray[np.float64] | None = None,
    rtol: float = 1e-7,
    fixed: Sequence[str] = (),
    fix_near_dependent: bool = False,
    ridge: bool = False,
) -> BallbarFit:
    """Identify POE errors and pivot offset from measured lengths ``bar_mm`` (n,), improved LM.

    ``weights`` (n,) multiply the squared residuals (e.g. ``1/u²``); ``theta0`` warm-starts (the
    nested uncertainty loop); ``fixed`` names parameters held at zero besides the not identifiable
    ones. Only the identifiable columns move. ``fix_near_dependent``: the near-dependent pairs of
    the fit are resolved by holding one of each at zero and fitting again
    (:func:`weaker_of_pairs`); :attr:`BallbarFit.fixed_pairs` names them. ``ridge``: each POE error
    is also pulled toward zero by a row ``error / scale`` (mm), :data:`RIDGE_SCALES`.
    """
    a = np.atleast_2d(np.asarray(a_deg, dtype=float))
    measured = np.asarray(bar_mm, dtype=float)
    sw = np.ones(measured.size) if weights is None else np.sqrt(np.asarray(weights, dtype=float))
    start = np.zeros(N_BALLBAR_PARAMS) if theta0 is None else np.asarray(theta0, dtype=float).copy()

    def fn(theta: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        length, jac = ballbar_jacobian(model, a, theta, pivot_mm)
        if not ridge:
            return (length - measured) * sw, jac * sw[:, None]
        w = np.concatenate([1.0 / _RIDGE, np.zeros(len(PIVOT_NAMES))])
        return (
            np.concatenate([(length - measured) * sw, w * theta]),
            np.vstack([jac * sw[:, None], np.diag(w)]),
        )

    report, null = ballbar_identifiability(model, a, pivot_mm, np.zeros(N_BALLBAR_PARAMS), rtol)
    keep = _without(report.identifiable_index, fixed)
    start[np.setdiff1d(np.arange(N_BALLBAR_PARAMS), keep)] = 0.0
    h0 = float(np.sqrt(np.mean((ballbar_lengths_mm(model, a, start, pivot_mm) - measured) ** 2)))
    theta, std, cov, its, reason, _ = fit_least_squares_subset(
        fn, start, keep, inverse_variance=weights_are_inverse_variance
    )
    fixed_pairs: tuple[dict[str, Any], ...] = ()
    if fix_near_dependent:
        _, jac = fn(theta)
        fixed_pairs = weaker_of_pairs(keep, cov, np.linalg.norm(jac, axis=0))
        if fixed_pairs:
            held = {p["fixed"] for p in fixed_pairs}
            keep = _without(keep, held)
            start[[BALLBAR_PARAM_NAMES.index(n) for n in held]] = 0.0
            theta, std, cov, more, reason, _ = fit_least_squares_subset(
                fn, start, keep, inverse_variance=weights_are_inverse_variance
            )
            its += more
    h1 = float(np.sqrt(np.mean((ballbar_lengths_mm(model, a, theta, pivot_mm) - measured) ** 2)))
    _log.info("ballbar_fit", points=measured.size, rank=report.rank_svd, h_before_mm=h0, h_after_mm=h1)
    return BallbarFit(
        theta=theta,
        std=std,
        cov=cov,
        report=report,
        null_space=null,
        h_before_mm=h0,
        h_after_mm=h1,
        iterations=its,
        reason=reason,
        fixed_pairs=fixed_pairs,
    )


#: the ridge option's scales: a POE error of this size costs as much as 1 mm of length residual on one
#: reading (Δl mm, Δθ deg); the pivot offset is not pulled
RIDGE_SCALES: tuple[float, float] = (5.0, 2.0)
_RIDGE = np.array([RIDGE_SCALES[0]] * 6 + [np.radians(RIDGE_SCALES[1])] * 6)


def _without(index: NDArray[np.intp], names: Sequence[str] | set[str]) -> NDArray[np.intp]:
    return np.array([k for k in index if BALLBAR_PARAM_NAMES[k] not in names], dtype=np.intp)


def weaker_of_pairs(
    keep: NDArray[np.intp], cov: NDArray[np.float64], column_norms: NDArray[np.float64]
) -> tuple[dict[str, Any], ...]:
    """Which parameter of each near-dependent pair of a fit to hold at zero (one pass, strongest pair
    first, each parameter at most once): ``({"pair", "correlation", "condition", "fixed"}, …)``.

    The one held is the *weaker* of the pair: the one the lengths determine less, i.e. with the larger
    variance in units of its own column (``cov_kk·|J_k|²``, the variance of the fit on unit columns).
    A pivot offset is never the one held: where the ball was set down is an unknown of the set-up, of
    millimetres, while the robot's errors are small; the robot's member of such a pair is held instead.
    """
    names = [BALLBAR_PARAM_NAMES[k] for k in keep]
    pairs = near_dependent_pairs(names, cov[np.ix_(keep, keep)])
    scaled = np.diag(cov) * column_norms**2
    held: list[str] = []
    out = []
    for pair in pairs:
        members = [n for n in pair["pair"] if n not in PIVOT_NAMES]
        if not members or any(n in held for n in pair["pair"]):
            continue
        weaker = max(members, key=lambda n: scaled[BALLBAR_PARAM_NAMES.index(n)])
        held.append(weaker)
        out.append({**pair, "fixed": weaker})
    return tuple(out)


def to_canonical(theta: NDArray[np.float64], pivot_mm: ArrayLike) -> NDArray[np.float64]:
    """The ballbar-equivalent parameter vector with Δθ1 = Δl1 = Δl2 = Δl5 = 0 (exact, not linearised).

    Every ballbar length is unchanged: Δθ1 turns all TCPs about z0, which equals turning the pivot
    by −Δθ1; Δl1 + Δl2 shift all TCPs along z0, which equals shifting the pivot down; Δl5 moves the
    same points as Δl6. A fit on the canonical set is compared with a truth mapped by this function.
    """
    th = np.array(theta, dtype=float, copy=True)
    i = {n: k for k, n in enumerate(BALLBAR_PARAM_NAMES)}
    d1, shift = th[i["dtheta1"]], th[i["dl1"]] + th[i["dl2"]]
    pivot = np.asarray(pivot_mm, dtype=float)
    c, s_ = np.cos(-d1), np.sin(-d1)
    true_pivot = pivot + th[N_POE_PARAMS:]
    turned = np.array(
        [c * true_pivot[0] - s_ * true_pivot[1], s_ * true_pivot[0] + c * true_pivot[1], true_pivot[2]]
    )
    turned[2] -= shift
    th[N_POE_PARAMS:] = turned - pivot
    th[i["dl6"]] += th[i["dl5"]]
    for name in ("dtheta1", "dl1", "dl2", "dl5"):
        th[i[name]] = 0.0
    return th
