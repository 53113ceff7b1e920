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
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

__all__ = ["trf_fit"]

FloatArray = NDArray[np.float64]
EPS = float(np.finfo(float).eps)


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
    lb = np.asarray(lb, dtype=float)
    ub = np.asarray(ub, dtype=float)
    if not (np.all(np.isfinite(lb)) and np.all(np.isfinite(ub))):
        raise ValueError("trf_fit needs finite bounds")
    if np.any(lb >= ub):
        raise ValueError("each lower bound must be below its upper bound")
    if not np.all((x0 >= lb) & (x0 <= ub)):
        raise ValueError("initial guess is outside of the bounds")
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
            # the trust region's radius from the step's quality
            if predicted > 0:
                ratio = actual_reduction / predicted
            elif predicted == actual_reduction == 0:
                ratio = 1.0
            else:
                ratio = 0.0
            delta_new = delta
            if ratio < 0.25:
                delta_new = 0.25 * step_h_norm
            elif ratio > 0.75 and step_h_norm > 0.95 * delta:
                delta_new = delta * 2.0
            step_norm = _norm(step)
            ftol_ok = actual_reduction < ftol * cost and ratio > 0.25
            xtol_ok = step_norm < xtol * (xtol + _norm(x))
            if ftol_ok or xtol_ok:
                done = True
                break
            alpha *= delta / delta_new
            delta = delta_new
        if actual_reduction > 0:
            x, f, cost = x_new, f_new, cost_new
            j = np.atleast_2d(np.asarray(jac(x.copy()), dtype=float))
            g = j.T.dot(f)
            scale_inv = np.maximum(np.sum(j**2, axis=0) ** 0.5, scale_inv)
            scale = 1 / scale_inv
    return x, float(cost)
