"""Moth-flame optimiser (MFO), seed 002's improved MFO and the whale optimiser, for IK and identification.

All three search a box ``[lb, ub]`` with a population of N agents; the objective takes the whole
population at once, ``(N, d) → (N,)`` (one batched forward kinematics per iteration). One seeded
generator supplies every draw. Iterations are counted K = 1 … K_max.

**MFO** (Mirjalili 2015; seed 002 eqs 13–14). The moths M start uniform in the box. Each iteration:
clip M to the box, evaluate, and merge into the flames — the best N of (previous flames ∪ M), sorted
by fitness (elitist). Flame number ``N_f = round(N − K·(N−1)/K_max)``; moth i (1-based) follows flame
``j = min(i, N_f)``. Spiral: ``M_i ← D·e^{bt}·cos(2πt) + F_j`` with ``D = |F_j − M_i|`` per dimension,
``b = 1`` and ``t ~ U[−1, 1]`` per dimension as the paper states (``t_mode="reference"``: the reference
code's ``t ~ U[r, 1]``, ``r = −1 − K/K_max``).

**Improved MFO** (eqs 15–18 and 33 reconstructed in spec A.7 as the whale optimiser's encircling and
prey search with the sorted flames as prey). ``S_i`` is the flame moth i follows (row ``min(i, N_f)``
of the sorted flames), ``A = 2 − 2K/K_max``, ``T = 2A·T0 − A`` with ``T0 ~ U[0, 1]`` per moth and
dimension, ``D = |S_i − M_i|``, and per moth ``p ~ U[0, 1]``::

    p < 0.5, |T| < 1 :  M(i,j) ← S(i,j) − T·D(i,j)                          (encircle own flame)
    p < 0.5, |T| ≥ 1 :  M(i,j) ← M(r,j) − T·|M(r,j) − M(i,j)|, r a random moth (search)
    p ≥ 0.5          :  M(i,j) ← D(i,j)·e^{bt}·cos(2πt) + S(i,j)              (spiral)

**WOA** (Mirjalili & Lewis 2016), the comparison of the paper: leader X* = best so far,
``a = 2 − 2K/K_max``, per whale ``A = 2a·r1 − a``, ``C = 2·r2``, ``l ~ U[−1, 1]`` and ``p``: ``p < 0.5`` and
``|A| < 1``: ``X ← X* − A·|C·X* − X|``; ``p < 0.5``, ``|A| ≥ 1``: the same about a random whale;
``p ≥ 0.5``: ``X ← |X* − X|·e^{bl}·cos(2πl) + X*``.

Objectives: :func:`ballbar_objective` (``H(x) = sqrt(mean((L_t − L_a)²))`` in mm, spec eq. 32) and
:func:`ik_objective` (``‖p − p_d‖ + w_R·‖R − R_d‖_F``, w_R = 100 mm, spec eqs 19–21);
:func:`solve_ik_mfo` polishes the MFO answer by least squares and checks it by forward kinematics.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.optimize
from numpy.typing import ArrayLike, NDArray

from comp_daemon.common.logs import get_logger
from comp_daemon.kinematics.poe import N_POE_PARAMS, PoeModel, poe_chain

__all__ = [
    "DEFAULT_BOUNDS",
    "IkMfoResult",
    "MfoResult",
    "Variant",
    "at_bound",
    "ballbar_objective",
    "ik_objective",
    "optimise",
    "solve_ik_mfo",
]

_log = get_logger(__name__)

Objective = Callable[[NDArray[np.float64]], NDArray[np.float64]]
Variant = Literal["mfo", "imfo", "woa"]
# spec A.4: Δl ∈ [−1, 1] mm, Δθ ∈ [−0.01, 0.01] rad, Δo ∈ [−2, 2] mm
DEFAULT_BOUNDS: dict[str, float] = {"dl": 1.0, "dtheta": 0.01, "pivot": 2.0}


@dataclass(frozen=True, slots=True)
class MfoResult:
    """Best point and value; per iteration the best value, the flame number N_f and A (2 → 0)."""

    x: NDArray[np.float64]
    fun: float
    variant: str
    iterations: int
    evaluations: int
    reached_at: int | None  # first iteration whose best value was below ``target`` (None: never)
    time_s: float
    best_history: NDArray[np.float64]
    flame_numbers: NDArray[np.intp]
    a_values: NDArray[np.float64]


#: the variants :func:`optimise` runs, and the schedules of the plain MFO's spiral parameter t
_VARIANTS: tuple[Variant, ...] = ("mfo", "imfo", "woa")
_T_MODES = ("paper", "reference")


def _flame_number(n: int, k: int, k_max: int) -> int:
    return round(n - k * (n - 1) / k_max)


def _spiral(
    d: NDArray[np.float64], centre: NDArray[np.float64], t: NDArray[np.float64], b: float
) -> NDArray[np.float64]:
    return d * np.exp(b * t) * np.cos(2.0 * np.pi * t) + centre


def _merge_flames(
    flames: NDArray[np.float64],
    flame_fit: NDArray[np.float64],
    moths: NDArray[np.float64],
    fit: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The elitist flames: the best N of (previous flames ∪ moths), N the number of moths, sorted by
    fitness (ties keep the earlier, a flame before a moth), and their fitness."""
    pool = np.vstack([flames, moths])
    pool_fit = np.concatenate([flame_fit, fit])
    order = np.argsort(pool_fit, kind="stable")[: moths.shape[0]]
    return pool[order], pool_fit[order]


def optimise(
    objective: Objective,
    lb: NDArray[np.float64],
    ub: NDArray[np.float64],
    *,
    variant: Variant = "imfo",
    n_agents: int = 500,
    max_iter: int = 1000,
    seed: int = 0,
    b: float = 1.0,
    t_mode: Literal["paper", "reference"] = "paper",
    target: float | None = None,
    callback: Callable[[int, NDArray[np.float64]], None] | None = None,
) -> MfoResult:
    """Minimise ``objective`` over the box with MFO, the improved MFO or WOA (module docstring).

    Stops after ``max_iter`` iterations or once the best value is below ``target``. ``callback(K, M)``
    sees the clipped population before each evaluation.
    """
    lo, hi = np.asarray(lb, dtype=float), np.asarray(ub, dtype=float)
    if lo.shape != hi.shape or lo.ndim != 1 or np.any(lo >= hi):
        raise ValueError("bounds must be two vectors of the same length with lb < ub")
    if variant not in _VARIANTS:
        raise ValueError(f"unknown variant {variant!r} ({', '.join(_VARIANTS)})")
    if t_mode not in _T_MODES:
        raise ValueError(f"unknown t_mode {t_mode!r} ({', '.join(_T_MODES)})")
    rng = np.random.default_rng(seed)
    t_start = time.perf_counter()
    n, dim = n_agents, lo.size
    moths = rng.uniform(lo, hi, (n, dim))
    flames = np.empty((0, dim))
    flame_fit = np.empty(0)
    best_hist, nf_hist, a_hist = [], [], []
    reached: int | None = None
    evaluations = 0
    k = 0
    for k in range(1, max_iter + 1):
        moths = np.clip(moths, lo, hi)
        if callback is not None:
            callback(k, moths)
        fit = np.asarray(objective(moths), dtype=float)
        evaluations += n
        flames, flame_fit = _merge_flames(flames, flame_fit, moths, fit)
        best_hist.append(float(flame_fit[0]))
        nf = _flame_number(n, k, max_iter)
        a = 2.0 - 2.0 * k / max_iter
        nf_hist.append(nf)
        a_hist.append(a)
        if target is not None and flame_fit[0] < target:
            reached = k
            break
        follow = flames[np.minimum(np.arange(n), nf - 1)]
        if variant == "mfo":
            moths = _mfo_step(moths, follow, k / max_iter, b, t_mode, rng)
        elif variant == "imfo":
            moths = _improved_step(moths, follow, a, b, rng)
        else:
            moths = _woa_step(moths, flames[0], a, b, rng)
    elapsed = time.perf_counter() - t_start
    _log.info(
        "mfo_done",
        variant=variant,
        iterations=k,
        best=float(flame_fit[0]),
        reached_at=reached,
        time_s=elapsed,
    )
    return MfoResult(
        x=flames[0].copy(),
        fun=float(flame_fit[0]),
        variant=variant,
        iterations=k,
        evaluations=evaluations,
        reached_at=reached,
        time_s=elapsed,
        best_history=np.array(best_hist),
        flame_numbers=np.array(nf_hist, dtype=np.intp),
        a_values=np.array(a_hist),
    )


def _mfo_step(
    moths: NDArray[np.float64],
    follow: NDArray[np.float64],
    progress: float,
    b: float,
    t_mode: str,
    rng: np.random.Generator,
) -> NDArray[np.float64]:
    """The plain MFO's spiral about each moth's flame; ``progress`` = K/K_max sets the reference t."""
    n, dim = moths.shape
    if t_mode == "paper":
        t = rng.uniform(-1.0, 1.0, (n, dim))
    else:
        r = -1.0 - progress
        t = (1.0 - r) * rng.random((n, dim)) + r
    return _spiral(np.abs(follow - moths), follow, t, b)


def _improved_step(
    moths: NDArray[np.float64], follow: NDArray[np.float64], a: float, b: float, rng: np.random.Generator
) -> NDArray[np.float64]:
    n, dim = moths.shape
    t_coef = 2.0 * a * rng.random((n, dim)) - a
    d = np.abs(follow - moths)
    p = rng.random((n, 1))
    r = rng.integers(0, n, n)
    other = moths[r]
    encircle = follow - t_coef * d
    search = other - t_coef * np.abs(other - moths)
    t = rng.uniform(-1.0, 1.0, (n, dim))
    spiral = _spiral(d, follow, t, b)
    return np.where(p < 0.5, np.where(np.abs(t_coef) < 1.0, encircle, search), spiral)


def _woa_step(
    whales: NDArray[np.float64], leader: NDArray[np.float64], a: float, b: float, rng: np.random.Generator
) -> NDArray[np.float64]:
    n, _ = whales.shape
    a_coef = 2.0 * a * rng.random((n, 1)) - a
    c_coef = 2.0 * rng.random((n, 1))
    p = rng.random((n, 1))
    ell = rng.uniform(-1.0, 1.0, (n, 1))
    other = whales[rng.integers(0, n, n)]
    about_leader = leader - a_coef * np.abs(c_coef * leader - whales)
    about_other = other - a_coef * np.abs(c_coef * other - whales)
    spiral = _spiral(np.abs(leader - whales), leader, ell, b)
    return np.where(p < 0.5, np.where(np.abs(a_coef) < 1.0, about_leader, about_other), spiral)


def at_bound(
    x: NDArray[np.float64], lb: NDArray[np.float64], ub: NDArray[np.float64], frac: float = 0.01
) -> NDArray[np.bool_]:
    """Which entries of ``x`` ended within ``frac`` of the box width of a bound (an unreliable value)."""
    width = np.asarray(ub) - np.asarray(lb)
    return np.asarray((x - lb <= frac * width) | (ub - x <= frac * width))


# ---- objectives -------------------------------------------------------------------------------


def ballbar_objective(
    model: PoeModel,
    a_deg: NDArray[np.float64],
    bar_mm: NDArray[np.float64],
    pivot_mm: ArrayLike,
    free: NDArray[np.intp],
    fixed: NDArray[np.float64] | None = None,
    weights: NDArray[np.float64] | None = None,
) -> Objective:
    """``H`` (mm) of a population over the ``free`` entries of the 15 ballbar parameters (others ``fixed``).

    With ``weights`` (n,) the mean is weighted (normalised to mean 1).
    """
    a = np.asarray(a_deg, dtype=float)
    f = a.shape[0]
    base = np.zeros(N_POE_PARAMS + 3) if fixed is None else np.asarray(fixed, dtype=float)
    w = np.ones(f) if weights is None else np.asarray(weights, dtype=float) / np.mean(weights)
    pivot = np.asarray(pivot_mm, dtype=float)
    measured = np.asarray(bar_mm, dtype=float)

    def objective(pop: NDArray[np.float64]) -> NDArray[np.float64]:
        n = pop.shape[0]
        theta = np.tile(base, (n, 1))
        theta[:, free] = pop
        x = np.repeat(theta[:, :N_POE_PARAMS], f, axis=0)
        p = poe_chain(model, np.tile(a, (n, 1)), x).tcp_mm.reshape(n, f, 3)
        length = np.linalg.norm(p - (pivot + theta[:, None, N_POE_PARAMS:]), axis=2)
        return np.asarray(np.sqrt(np.mean(w * (length - measured) ** 2, axis=1)))

    return objective


def ik_objective(
    model: PoeModel,
    target_p_mm: NDArray[np.float64],
    target_R: NDArray[np.float64],
    x: NDArray[np.float64] | None = None,
    w_r_mm: float = 100.0,
) -> Objective:
    """``R_t(A) = ‖p(A) − p_d‖ + w_R·‖R(A) − R_d‖_F`` (mm) of a population of axis values (deg)."""

    def objective(pop: NDArray[np.float64]) -> NDArray[np.float64]:
        pose = poe_chain(model, pop, x)
        pos = np.linalg.norm(pose.tcp_mm - target_p_mm, axis=1)
        rot = np.linalg.norm(pose.base_T_flange[:, :3, :3] - target_R, axis=(1, 2))
        return np.asarray(pos + w_r_mm * rot)

    return objective


@dataclass(frozen=True, slots=True)
class IkMfoResult:
    a_deg: NDArray[np.float64]  # (6,) after polishing
    ok: bool  # FK check: position within ``tol_mm`` and orientation within 1e-6
    position_error_mm: float
    orientation_error: float  # ‖R − R_d‖_F
    search: MfoResult  # the MFO run before polishing


def solve_ik_mfo(
    model: PoeModel,
    axis_limits_deg: NDArray[np.float64],
    target_p_mm: NDArray[np.float64],
    target_R: NDArray[np.float64],
    *,
    x: NDArray[np.float64] | None = None,
    variant: Variant = "imfo",
    n_agents: int = 500,
    max_iter: int = 200,
    seed: int = 0,
    target: float | None = None,
    tol_mm: float = 1e-6,
) -> IkMfoResult:
    """IK of one pose by MFO over the joint box, polished by least squares, checked by FK."""
    lim = np.asarray(axis_limits_deg, dtype=float)
    search = optimise(
        ik_objective(model, target_p_mm, target_R, x),
        lim[:, 0],
        lim[:, 1],
        variant=variant,
        n_agents=n_agents,
        max_iter=max_iter,
        seed=seed,
        target=target,
    )

    def residual(a: NDArray[np.float64]) -> NDArray[np.float64]:
        pose = poe_chain(model, a, x)
        return np.concatenate(
            [pose.tcp_mm[0] - target_p_mm, 100.0 * (pose.base_T_flange[0, :3, :3] - target_R).ravel()]
        )

    polished = scipy.optimize.least_squares(
        residual, search.x, bounds=(lim[:, 0], lim[:, 1]), xtol=1e-15, ftol=1e-15, gtol=1e-15
    )
    pose = poe_chain(model, polished.x, x)
    pos_err = float(np.linalg.norm(pose.tcp_mm[0] - target_p_mm))
    rot_err = float(np.linalg.norm(pose.base_T_flange[0, :3, :3] - target_R))
    return IkMfoResult(polished.x, pos_err <= tol_mm and rot_err <= 1e-6, pos_err, rot_err, search)
