"""Small bounded least-squares problems at the cost of their arithmetic: the trust-region reflective
method of ``scipy.optimize.least_squares`` without its per-call machinery.

The variogram fits (:mod:`comp_daemon.estimation.variogram`) solve thousands of problems of 2–3
parameters and about ten residuals each; ``least_squares`` spends most of such a call in its
function wrappers, argument checks and array-API dispatch, not in the method. :func:`trf_fit` is
the same method — ``method="trf"``, ``x_scale="jac"``, linear loss, exact trust-region solver
(one SVD per iteration), finite bounds, the default tolerances — step for step and operation for
operation (SciPy 1.17's ``trf_bounds``, ``select_step`` and the helpers of
``scipy.optimize._lsq.common`` they call), so it returns the same point and cost.
``tests/test_models_kriging_variogram.py`` compares the two on many variogram problems.

Even without that machinery a problem this small costs a few dozen NumPy calls per iteration on
3-element vectors. :func:`trf_fit_batch` runs the same method on many problems at once, one call
per operation for all of them; the points agree with :func:`trf_fit`'s to rounding.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

__all__ = ["trf_fit"]

FloatArray = NDArray[np.float64]
EPS = float(np.finfo(float).eps)
Reals = float | FloatArray  # one problem's value, or a row each


def _norm(x: FloatArray) -> float:
    return math.sqrt(float(np.dot(x, x)))  # numpy.linalg.norm of a real vector, to the bit


def _make_strictly_feasible(x: FloatArray, lb: FloatArray, ub: FloatArray, rstep: float) -> FloatArray:
    """``x`` moved off the bounds it sits on (within ``rstep``, or onto the next double with 0)."""
    x_new = x.copy()
    if rstep == 0:
        upper = x >= ub
        lower = (x <= lb) & ~upper
        x_new[lower] = np.nextafter(lb[lower], ub[lower])
        x_new[upper] = np.nextafter(ub[upper], lb[upper])
    else:
        lower_dist, upper_dist = x - lb, ub - x
        upper = upper_dist <= np.minimum(lower_dist, rstep * np.maximum(1, np.abs(ub)))
        lower = (lower_dist <= np.minimum(upper_dist, rstep * np.maximum(1, np.abs(lb)))) & ~upper
        x_new[lower] = lb[lower] + rstep * np.maximum(1, np.abs(lb[lower]))
        x_new[upper] = ub[upper] - rstep * np.maximum(1, np.abs(ub[upper]))
    tight = (x_new < lb) | (x_new > ub)
    x_new[tight] = 0.5 * (lb[tight] + ub[tight])
    return x_new


def _scaling(x: FloatArray, g: FloatArray, lb: FloatArray, ub: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Coleman–Li scaling vector and its derivative (bounds finite)."""
    v = np.ones_like(x)
    dv = np.zeros_like(x)
    mask = g < 0
    v[mask] = ub[mask] - x[mask]
    dv[mask] = -1
    mask = g > 0
    v[mask] = x[mask] - lb[mask]
    dv[mask] = 1
    return v, dv


def _step_to_bound(x: FloatArray, s: FloatArray, lb: FloatArray, ub: FloatArray) -> tuple[float, FloatArray]:
    non_zero = np.nonzero(s)
    s_nz = s[non_zero]
    steps = np.full_like(x, np.inf)
    with np.errstate(over="ignore"):
        steps[non_zero] = np.maximum((lb - x)[non_zero] / s_nz, (ub - x)[non_zero] / s_nz)
    min_step = float(np.min(steps))
    return min_step, np.equal(steps, min_step) * np.sign(s).astype(int)


def _quadratic(j: FloatArray, g: FloatArray, s: FloatArray, diag: FloatArray) -> float:
    js = j.dot(s)
    q = np.dot(js, js)
    q += np.dot(s * diag, s)
    return float(0.5 * q + np.dot(s, g))


def _quadratic_1d(
    j: FloatArray, g: FloatArray, s: FloatArray, diag: FloatArray, s0: FloatArray | None = None
) -> tuple[float, float, float]:
    v = j.dot(s)
    a = np.dot(v, v)
    a += np.dot(s * diag, s)
    a *= 0.5
    b = np.dot(g, s)
    c = 0.0
    if s0 is not None:
        u = j.dot(s0)
        b += np.dot(u, v)
        c = 0.5 * np.dot(u, u) + np.dot(g, s0)
        b += np.dot(s0 * diag, s)
        c += 0.5 * np.dot(s0 * diag, s0)
    return float(a), float(b), float(c)


def _minimize_1d(a: float, b: float, lb: float, ub: float, c: float = 0.0) -> tuple[float, float]:
    t = [lb, ub]
    if a != 0:
        extremum = -0.5 * b / a
        if lb < extremum < ub:
            t.append(extremum)
    ts = np.asarray(t)
    y = ts * (a * ts + b) + c
    k = int(np.argmin(y))
    return float(ts[k]), float(y[k])


def _intersect_trust_region(x: FloatArray, s: FloatArray, delta: float) -> tuple[float, float]:
    a = np.dot(s, s)
    if a == 0:
        raise ValueError("`s` is zero.")
    b = np.dot(x, s)
    c = np.dot(x, x) - delta**2
    if c > 0:
        raise ValueError("`x` is not within the trust region.")
    d = np.sqrt(b * b - a * c)
    q = -(b + math.copysign(d, b))
    t1, t2 = q / a, c / q
    return (float(t1), float(t2)) if t1 < t2 else (float(t2), float(t1))


def _solve_trust_region(
    n: int, m: int, uf: FloatArray, s: FloatArray, v: FloatArray, delta: float, initial_alpha: float
) -> tuple[FloatArray, float]:
    """More's method on one SVD (SciPy's ``solve_lsq_trust_region``, rtol 0.01, 10 iterations)."""

    def phi_and_derivative(alpha: float) -> tuple[float, float]:
        denom = s**2 + alpha
        p_norm = _norm(suf / denom)
        return p_norm - delta, float(-np.sum(suf**2 / denom**3) / p_norm)

    suf = s * uf
    full_rank = bool(s[-1] > EPS * m * s[0]) if m >= n else False
    if full_rank:
        p = -v.dot(uf / s)
        if _norm(p) <= delta:
            return p, 0.0
    alpha_upper = _norm(suf) / delta
    if full_rank:
        phi, phi_prime = phi_and_derivative(0.0)
        alpha_lower = -phi / phi_prime
    else:
        alpha_lower = 0.0
    if not full_rank and initial_alpha == 0:
        alpha = max(0.001 * alpha_upper, (alpha_lower * alpha_upper) ** 0.5)
    else:
        alpha = initial_alpha
    for _ in range(10):
        if alpha < alpha_lower or alpha > alpha_upper:
            alpha = max(0.001 * alpha_upper, (alpha_lower * alpha_upper) ** 0.5)
        phi, phi_prime = phi_and_derivative(alpha)
        if phi < 0:
            alpha_upper = alpha
        ratio = phi / phi_prime
        alpha_lower = max(alpha_lower, alpha - ratio)
        alpha -= (phi + delta) * ratio / delta
        if abs(phi) < 0.01 * delta:
            break
    p = -v.dot(suf / (s**2 + alpha))
    p *= delta / _norm(p)
    return p, alpha


def _select_step(
    x: FloatArray,
    j_h: FloatArray,
    diag_h: FloatArray,
    g_h: FloatArray,
    p: FloatArray,
    p_h: FloatArray,
    d: FloatArray,
    delta: float,
    lb: FloatArray,
    ub: FloatArray,
    theta: float,
) -> tuple[FloatArray, FloatArray, float]:
    """The best of the trust-region step (cut at the bound), its reflection and the gradient step."""
    xp = x + p
    if np.all((xp >= lb) & (xp <= ub)):
        return p, p_h, -_quadratic(j_h, g_h, p_h, diag_h)
    p_stride, hits = _step_to_bound(x, p, lb, ub)
    r_h = np.copy(p_h)
    r_h[hits.astype(bool)] *= -1
    r = d * r_h
    p *= p_stride
    p_h *= p_stride
    x_on_bound = x + p
    _, to_tr = _intersect_trust_region(p_h, r_h, delta)
    to_bound, _ = _step_to_bound(x_on_bound, r, lb, ub)
    r_stride = min(to_bound, to_tr)
    if r_stride > 0:
        r_stride_l = (1 - theta) * p_stride / r_stride
        r_stride_u = theta * to_bound if r_stride == to_bound else to_tr
    else:
        r_stride_l, r_stride_u = 0.0, -1.0
    if r_stride_l <= r_stride_u:
        a, b, c = _quadratic_1d(j_h, g_h, r_h, diag_h, s0=p_h)
        r_stride, r_value = _minimize_1d(a, b, r_stride_l, r_stride_u, c=c)
        r_h *= r_stride
        r_h += p_h
        r = r_h * d
    else:
        r_value = np.inf
    p *= theta
    p_h *= theta
    p_value = _quadratic(j_h, g_h, p_h, diag_h)
    ag_h = -g_h
    ag = d * ag_h
    to_tr = delta / _norm(ag_h)
    to_bound, _ = _step_to_bound(x, ag, lb, ub)
    ag_stride = theta * to_bound if to_bound < to_tr else to_tr
    a, b, _ = _quadratic_1d(j_h, g_h, ag_h, diag_h)
    ag_stride, ag_value = _minimize_1d(a, b, 0, ag_stride)
    ag_h *= ag_stride
    ag *= ag_stride
    if p_value < r_value and p_value < ag_value:
        return p, p_h, -p_value
    if r_value < p_value and r_value < ag_value:
        return r, r_h, -r_value
    return ag, ag_h, -ag_value


def _judge_step(
    actual: Reals,
    predicted: Reals,
    step_h_norm: Reals,
    step_norm: Reals,
    x_norm: Reals,
    delta: Reals,
    cost: Reals,
    ftol: float,
    xtol: float,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """A trial step judged by its actual against its predicted reduction (their ratio: 1 if both
    are 0, 0 if no reduction was predicted): the trust radius it leaves (a quarter of the step for a
    ratio below 0.25, twice the radius above 0.75 for a step near the border, else the radius) and
    whether the method has converged (``ftol`` on the cost, ``xtol`` on the step). Scalars for one
    problem, arrays for a row each."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(
            predicted > 0, actual / predicted, np.where((predicted == 0) & (actual == 0), 1.0, 0.0)
        )
    grow = (ratio > 0.75) & (step_h_norm > 0.95 * delta)
    radius = np.where(ratio < 0.25, 0.25 * step_h_norm, np.where(grow, 2.0 * delta, delta))
    converged = ((actual < ftol * cost) & (ratio > 0.25)) | (step_norm < xtol * (xtol + x_norm))
    return radius, converged


def _checked_bounds(x0: FloatArray, lb: FloatArray, ub: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The bounds, as float arrays of ``x0``'s shape: finite, lower below upper, ``x0`` within."""
    lb = np.broadcast_to(np.asarray(lb, dtype=float), x0.shape)
    ub = np.broadcast_to(np.asarray(ub, dtype=float), x0.shape)
    if not (np.all(np.isfinite(lb)) and np.all(np.isfinite(ub))):
        raise ValueError("trf_fit needs finite bounds")
    if np.any(lb >= ub):
        raise ValueError("each lower bound must be below its upper bound")
    if not np.all((x0 >= lb) & (x0 <= ub)):
        raise ValueError("initial guess is outside of the bounds")
    return lb, ub


def trf_fit(
    fun: Callable[[FloatArray], FloatArray],
    jac: Callable[[FloatArray], FloatArray],
    x0: FloatArray,
    lb: FloatArray,
    ub: FloatArray,
    *,
    ftol: float = 1e-8,
    xtol: float = 1e-8,
    gtol: float = 1e-8,
) -> tuple[FloatArray, float]:
    """``least_squares(fun, x0, jac=jac, bounds=(lb, ub), method="trf", x_scale="jac")``'s point
    and cost (module docstring). The bounds must be finite and ``x0`` within them."""
    x0 = np.atleast_1d(np.asarray(x0, dtype=float))
    lb, ub = _checked_bounds(x0, lb, ub)
    x = _make_strictly_feasible(x0, lb, ub, 1e-10)
    f = np.atleast_1d(np.asarray(fun(x.copy()), dtype=float))
    if f.ndim != 1 or not np.all(np.isfinite(f)):
        raise ValueError("residuals must be a finite vector at the initial point")
    j = np.atleast_2d(np.asarray(jac(x.copy()), dtype=float))
    m, n = j.shape
    if n != x.size or m != f.size:
        raise ValueError(f"jacobian must be ({f.size}, {x.size}), got {j.shape}")
    nfev, max_nfev = 1, x.size * 100
    cost = 0.5 * np.dot(f, f)
    g = j.T.dot(f)
    scale_inv = np.sum(j**2, axis=0) ** 0.5
    scale_inv[scale_inv == 0] = 1
    scale = 1 / scale_inv
    v, dv = _scaling(x, g, lb, ub)
    v[dv != 0] *= scale_inv[dv != 0]
    delta = _norm(x * scale_inv / v**0.5)
    if delta == 0:
        delta = 1.0
    f_aug = np.zeros(m + n)
    j_aug = np.empty((m + n, n))
    alpha = 0.0
    done = False
    while True:
        v, dv = _scaling(x, g, lb, ub)
        g_norm = float(np.max(np.abs(g * v)))
        if g_norm < gtol:
            done = True
        if done or nfev == max_nfev:
            break
        v[dv != 0] *= scale_inv[dv != 0]
        d = v**0.5 * scale
        diag_h = g * dv * scale
        g_h = d * g
        f_aug[:m] = f
        j_aug[:m] = j * d
        j_h = j_aug[:m]
        j_aug[m:] = np.diag(diag_h**0.5)
        u, s, vt = scipy.linalg.svd(j_aug, full_matrices=False, check_finite=False)
        vv = vt.T
        uf = u.T.dot(f_aug)
        theta = max(0.995, 1 - g_norm)
        actual_reduction = -1.0
        while actual_reduction <= 0 and nfev < max_nfev:
            p_h, alpha = _solve_trust_region(n, m, uf, s, vv, delta, alpha)
            p = d * p_h
            step, step_h, predicted = _select_step(x, j_h, diag_h, g_h, p, p_h, d, delta, lb, ub, theta)
            x_new = _make_strictly_feasible(x + step, lb, ub, 0.0)
            f_new = np.atleast_1d(np.asarray(fun(x_new.copy()), dtype=float))
            nfev += 1
            step_h_norm = _norm(step_h)
            if not np.all(np.isfinite(f_new)):
                delta = 0.25 * step_h_norm
                continue
            cost_new = 0.5 * np.dot(f_new, f_new)
            actual_reduction = cost - cost_new
            radius, converged = _judge_step(
                actual_reduction, predicted, step_h_norm, _norm(step), _norm(x), delta, cost, ftol, xtol
            )
            if converged:
                done = True
                break
            delta_new = float(radius)
            alpha *= delta / delta_new
            delta = delta_new
        if actual_reduction > 0:
            x, f, cost = x_new, f_new, cost_new
            j = np.atleast_2d(np.asarray(jac(x.copy()), dtype=float))
            g = j.T.dot(f)
            scale_inv = np.maximum(np.sum(j**2, axis=0) ** 0.5, scale_inv)
            scale = 1 / scale_inv
    return x, float(cost)


# Many problems at once. The batch below is the method above on B problems of the same size in
# lockstep: one round is one trial step of every unfinished problem (an outer iteration of the
# loop above, or one more try of its inner loop: a rejected step leaves the point, gradient and
# scaling unchanged, so the round recomputes the very SVD the inner loop would reuse). Arrays are
# (k, n) parameters and (k, m) residuals of the k problems still running; NumPy's batched SVD
# replaces SciPy's per problem, so the points agree with :func:`trf_fit`'s to rounding, not bits.

BatchResiduals = Callable[[FloatArray, NDArray[np.intp]], FloatArray]


def _norm_rows(x: FloatArray) -> FloatArray:
    return np.sqrt(np.einsum("ki,ki->k", x, x))


def _step_to_bound_rows(
    x: FloatArray, s: FloatArray, lb: FloatArray, ub: FloatArray
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Per row the stride along ``s`` to the first bound, and which components reach it."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        steps = np.where(s != 0, np.maximum((lb - x) / s, (ub - x) / s), np.inf)
    min_step = steps.min(axis=1)
    return min_step, (steps == min_step[:, None]) & (s != 0)


def _quadratic_rows(j: FloatArray, g: FloatArray, s: FloatArray, diag: FloatArray) -> FloatArray:
    js = np.einsum("kmn,kn->km", j, s)
    q = np.einsum("km,km->k", js, js) + np.einsum("kn,kn->k", s * diag, s)
    return 0.5 * q + np.einsum("kn,kn->k", s, g)


def _quadratic_1d_rows(
    j: FloatArray, g: FloatArray, s: FloatArray, diag: FloatArray, s0: FloatArray | None = None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    v = np.einsum("kmn,kn->km", j, s)
    a = 0.5 * (np.einsum("km,km->k", v, v) + np.einsum("kn,kn->k", s * diag, s))
    b = np.einsum("kn,kn->k", g, s)
    c = np.zeros_like(a)
    if s0 is not None:
        u = np.einsum("kmn,kn->km", j, s0)
        b = b + np.einsum("km,km->k", u, v) + np.einsum("kn,kn->k", s0 * diag, s)
        c = 0.5 * np.einsum("km,km->k", u, u) + np.einsum("kn,kn->k", g, s0)
        c = c + 0.5 * np.einsum("kn,kn->k", s0 * diag, s0)
    return a, b, c


def _minimize_1d_rows(
    a: FloatArray, b: FloatArray, lb: FloatArray, ub: FloatArray, c: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Per row the minimum of ``a t² + b t + c`` over ``[lb, ub]`` (the bounds first on a tie)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        extremum = -0.5 * b / a
    inner = (a != 0) & (lb < extremum) & (extremum < ub)
    ts = np.stack([lb, ub, np.where(inner, extremum, lb)], axis=1)
    y = ts * (a[:, None] * ts + b[:, None]) + c[:, None]
    y[:, 2] = np.where(inner, y[:, 2], np.inf)
    k = np.argmin(y, axis=1)
    rows = np.arange(k.size)
    return ts[rows, k], y[rows, k]


def _solve_trust_region_rows(
    n: int,
    m: NDArray[np.intp],
    uf: FloatArray,
    s: FloatArray,
    vt: FloatArray,
    delta: FloatArray,
    initial_alpha: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """:func:`_solve_trust_region` per row (``m`` each problem's residual count)."""

    def phi_and_derivative(alpha: FloatArray) -> tuple[FloatArray, FloatArray]:
        denom = s**2 + alpha[:, None]
        p_norm = _norm_rows(suf / denom)
        return p_norm - delta, -np.sum(suf**2 / denom**3, axis=1) / p_norm

    suf = s * uf
    full_rank = (s[:, -1] > EPS * m * s[:, 0]) & (m >= n)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        gauss_newton = -np.einsum("kji,kj->ki", vt, uf / s)
        inside = full_rank & (_norm_rows(gauss_newton) <= delta)
        alpha_upper = _norm_rows(suf) / delta
        phi, phi_prime = phi_and_derivative(np.zeros_like(delta))
        alpha_lower = np.where(full_rank, -phi / phi_prime, 0.0)
        alpha = np.where(
            ~full_rank & (initial_alpha == 0),
            np.maximum(0.001 * alpha_upper, np.sqrt(alpha_lower * alpha_upper)),
            initial_alpha,
        )
        running = ~inside
        for _ in range(10):
            if not running.any():
                break
            reset = running & ((alpha < alpha_lower) | (alpha > alpha_upper))
            alpha = np.where(
                reset, np.maximum(0.001 * alpha_upper, np.sqrt(alpha_lower * alpha_upper)), alpha
            )
            phi, phi_prime = phi_and_derivative(alpha)
            alpha_upper = np.where(running & (phi < 0), alpha, alpha_upper)
            ratio = phi / phi_prime
            alpha_lower = np.where(running, np.maximum(alpha_lower, alpha - ratio), alpha_lower)
            alpha = np.where(running, alpha - (phi + delta) * ratio / delta, alpha)
            running &= ~(np.abs(phi) < 0.01 * delta)
        p = -np.einsum("kji,kj->ki", vt, suf / (s**2 + alpha[:, None]))
        p *= (delta / _norm_rows(p))[:, None]
    return np.where(inside[:, None], gauss_newton, p), np.where(inside, 0.0, alpha)


@dataclass(frozen=True, slots=True)
class _Subproblems:
    """One round's scaled trust-region subproblems, a row each: the points, the scaled Jacobians
    ``j_h``, the bound terms ``diag_h``, the scaled gradients ``g_h``, the scaling ``d``, the radii,
    the bounds and the step-back factors ``theta``."""

    x: FloatArray
    j_h: FloatArray
    diag_h: FloatArray
    g_h: FloatArray
    d: FloatArray
    delta: FloatArray
    lb: FloatArray
    ub: FloatArray
    theta: FloatArray

    def rows(self, rows: NDArray[np.intp]) -> _Subproblems:
        return _Subproblems(*(getattr(self, f.name)[rows] for f in fields(self)))


def _select_step_rows(
    sub: _Subproblems, p: FloatArray, p_h: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`_select_step` per row."""
    x, j_h, diag_h, g_h, lb, ub = sub.x, sub.j_h, sub.diag_h, sub.g_h, sub.lb, sub.ub
    xp = x + p
    step, step_h = p.copy(), p_h.copy()
    predicted = -_quadratic_rows(j_h, g_h, p_h, diag_h)
    out = np.flatnonzero(~np.all((xp >= lb) & (xp <= ub), axis=1))
    if out.size == 0:
        return step, step_h, predicted
    sub = sub.rows(out)
    x, j_h, diag_h, g_h, d, delta, lb, ub, theta = (getattr(sub, f.name) for f in fields(sub))
    p, p_h = p[out], p_h[out]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        p_stride, hits = _step_to_bound_rows(x, p, lb, ub)
        r_h = np.where(hits, -p_h, p_h)
        r = d * r_h
        p = p * p_stride[:, None]
        p_h = p_h * p_stride[:, None]
        # the reflected step's stride to the trust region's border
        a = np.einsum("kn,kn->k", r_h, r_h)
        b = np.einsum("kn,kn->k", p_h, r_h)
        c = np.einsum("kn,kn->k", p_h, p_h) - delta**2
        if np.any(a == 0):
            raise ValueError("`s` is zero.")
        if np.any(c > 0):
            raise ValueError("`x` is not within the trust region.")
        q = -(b + np.copysign(np.sqrt(b * b - a * c), b))
        to_tr = np.maximum(q / a, c / q)
        to_bound, _ = _step_to_bound_rows(x + p, r, lb, ub)
        r_stride = np.minimum(to_bound, to_tr)
        positive = r_stride > 0
        r_lo = np.where(positive, (1 - theta) * p_stride / r_stride, 0.0)
        r_hi = np.where(positive, np.where(r_stride == to_bound, theta * to_bound, to_tr), -1.0)
        reflect = r_lo <= r_hi
        qa, qb, qc = _quadratic_1d_rows(j_h, g_h, r_h, diag_h, s0=p_h)
        r_stride, r_value = _minimize_1d_rows(qa, qb, r_lo, r_hi, qc)
        r_h = np.where(reflect[:, None], r_h * r_stride[:, None] + p_h, r_h)
        r = r_h * d
        r_value = np.where(reflect, r_value, np.inf)
        p *= theta[:, None]
        p_h *= theta[:, None]
        p_value = _quadratic_rows(j_h, g_h, p_h, diag_h)
        # the scaled gradient step
        ag_h = -g_h
        ag = d * ag_h
        to_tr = delta / _norm_rows(ag_h)
        to_bound, _ = _step_to_bound_rows(x, ag, lb, ub)
        ag_stride = np.where(to_bound < to_tr, theta * to_bound, to_tr)
        qa, qb, _ = _quadratic_1d_rows(j_h, g_h, ag_h, diag_h)
        ag_stride, ag_value = _minimize_1d_rows(qa, qb, np.zeros_like(qa), ag_stride, np.zeros_like(qa))
        ag_h = ag_h * ag_stride[:, None]
        ag = ag * ag_stride[:, None]
    take_p = (p_value < r_value) & (p_value < ag_value)
    take_r = ~take_p & (r_value < p_value) & (r_value < ag_value)
    step[out] = np.where(take_p[:, None], p, np.where(take_r[:, None], r, ag))
    step_h[out] = np.where(take_p[:, None], p_h, np.where(take_r[:, None], r_h, ag_h))
    predicted[out] = -np.where(take_p, p_value, np.where(take_r, r_value, ag_value))
    return step, step_h, predicted


def trf_fit_batch(
    fun: BatchResiduals,
    jac: Callable[[FloatArray, NDArray[np.intp]], FloatArray],
    x0: FloatArray,
    lb: FloatArray,
    ub: FloatArray,
    m: NDArray[np.intp] | None = None,
    *,
    ftol: float = 1e-8,
    xtol: float = 1e-8,
    gtol: float = 1e-8,
) -> tuple[FloatArray, FloatArray]:
    """:func:`trf_fit` on B problems of n parameters at once; their points (B, n) and costs (B,).

    ``fun(x, rows)``: the residuals (k, M) of problems ``rows`` (k,) at their points ``x`` (k, n);
    ``jac(x, rows)``: their Jacobians (k, M, n). A problem with fewer residuals than M pads with
    zero residuals and zero Jacobian rows and gives its count in ``m`` (B,) (it decides whether
    the problem's Jacobian has full rank). ``x0``, ``lb``, ``ub``: (B, n), finite bounds.
    """
    x0 = np.asarray(x0, dtype=float)
    if x0.ndim != 2:
        raise ValueError(f"x0 must be (B, n) starting points, got shape {x0.shape}")
    lb, ub = _checked_bounds(x0, lb, ub)
    n_problems, n = x0.shape
    every = np.arange(n_problems)
    x = _make_strictly_feasible(x0, lb, ub, 1e-10)
    f = np.asarray(fun(x.copy(), every), dtype=float)
    if f.ndim != 2 or f.shape[0] != n_problems or not np.all(np.isfinite(f)):
        raise ValueError("residuals must be finite (B, M) at the initial points")
    j = np.asarray(jac(x.copy(), every), dtype=float)
    if j.shape != (*f.shape, n):
        raise ValueError(f"jacobians must be {(*f.shape, n)}, got {j.shape}")
    rows_m = np.full(n_problems, f.shape[1]) if m is None else np.asarray(m)
    nfev, max_nfev = np.ones(n_problems, dtype=int), n * 100
    cost = 0.5 * np.einsum("km,km->k", f, f)
    g = np.einsum("kmn,km->kn", j, f)
    scale_inv = np.sqrt(np.einsum("kmn,kmn->kn", j, j))
    scale_inv[scale_inv == 0] = 1
    v, dv = _scaling(x, g, lb, ub)
    v[dv != 0] *= scale_inv[dv != 0]
    delta = _norm_rows(x * scale_inv / v**0.5)
    delta[delta == 0] = 1.0
    alpha = np.zeros(n_problems)
    running = np.ones(n_problems, dtype=bool)
    eye = np.eye(n)
    while True:
        v, dv = _scaling(x, g, lb, ub)
        g_norm = np.max(np.abs(g * v), axis=1)
        running &= (g_norm >= gtol) & (nfev < max_nfev)
        k = np.flatnonzero(running)
        if k.size == 0:
            break
        xk, gk, lbk, ubk, dvk, inv_k = x[k], g[k], lb[k], ub[k], dv[k], scale_inv[k]
        scale = 1 / inv_k
        d = np.where(dvk != 0, v[k] * inv_k, v[k]) ** 0.5 * scale
        diag_h = gk * dvk * scale
        g_h = d * gk
        j_h = j[k] * d[:, None, :]
        u, s, vt = np.linalg.svd(
            np.concatenate([j_h, diag_h[:, :, None] ** 0.5 * eye], axis=1), full_matrices=False
        )
        uf = np.einsum("kmi,km->ki", u[:, : f.shape[1]], f[k])
        theta = np.maximum(0.995, 1 - g_norm[k])
        p_h, alpha_k = _solve_trust_region_rows(n, rows_m[k], uf, s, vt, delta[k], alpha[k])
        sub = _Subproblems(xk, j_h, diag_h, g_h, d, delta[k], lbk, ubk, theta)
        step, step_h, predicted = _select_step_rows(sub, d * p_h, p_h)
        x_new = _make_strictly_feasible(xk + step, lbk, ubk, 0.0)
        f_new = np.asarray(fun(x_new.copy(), k), dtype=float)
        nfev[k] += 1
        step_h_norm = _norm_rows(step_h)
        finite = np.all(np.isfinite(f_new), axis=1)
        delta_k = delta[k]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            cost_new = 0.5 * np.einsum("km,km->k", f_new, f_new)
            actual = cost[k] - cost_new
            delta_new, converged = _judge_step(
                actual, predicted, step_h_norm, _norm_rows(step), _norm_rows(xk), delta_k, cost[k], ftol, xtol
            )
            done = finite & converged
            going = finite & ~done
            alpha[k] = np.where(going, alpha_k * delta_k / delta_new, alpha_k)
        delta[k] = np.where(going, delta_new, np.where(finite, delta_k, 0.25 * step_h_norm))
        running[k[done]] = False
        better = finite & (actual > 0)
        if better.any():
            a = k[better]
            x[a], f[a], cost[a] = x_new[better], f_new[better], cost_new[better]
            j_a = np.asarray(jac(x[a].copy(), a), dtype=float)
            j[a] = j_a
            g[a] = np.einsum("kmn,km->kn", j_a, f[a])
            scale_inv[a] = np.maximum(np.sqrt(np.einsum("kmn,kmn->kn", j_a, j_a)), scale_inv[a])
    return x, cost
