"""The improved Levenberg–Marquardt method of seed 000 (higher-order LM with two approximate steps).

Seed 000 (§2.1.2) identifies its Chebyshev coefficients with "an improved L-M algorithm with higher
order convergence" (its ref. [22]) and lists the steps; the formulas (eqs 14–19) are missing from the
seed text, so they are written out here from the listed steps and the method they name (the
multi-step LM of Fan and of Yang: one LM step plus two *approximate* LM steps that reuse the
Jacobian of the iteration, accepted by a trust-region ratio):

1. ``k = 1``; convergence accuracy ``phi`` (0.00001); optimisation factor ``upsilon_1 > m > 0``;
   ``0 < p0 < p1 < p2 < 1``.
2. ``J_k = J(x_k)``, ``F_k = F(x_k)`` (residual vector, here "position error").
3. adaptive damping ``mu_k = upsilon_k * ||F_k||**delta``; LM step
   ``d1 = -(J_kᵀJ_k + mu_k I)⁻¹ J_kᵀ F_k``.
4. ``y_k = x_k + d1``, approximate step ``d2 = -(J_kᵀJ_k + mu_k I)⁻¹ J_kᵀ F(y_k)``;
   ``z_k = y_k + d2``, approximate step ``d3 = -(J_kᵀJ_k + mu_k I)⁻¹ J_kᵀ F(z_k)``
   (same matrix: one factorisation per iteration, no new Jacobian).
5. total step ``s_k = d1 + d2 + d3``.
6. ratio ``r_k = Ared_k / Pred_k`` with ``Ared_k = ||F_k||² − ||F(x_k + s_k)||²`` and
   ``Pred_k = Σ_{j=1..3} ||F(w_j)||² − ||F(w_j) + J_k d_j||²`` over ``w = (x_k, y_k, z_k)``.
7. ``x_{k+1} = x_k + s_k`` if ``r_k ≥ p0`` else ``x_k``; ``upsilon_{k+1} = 4 upsilon_k`` if
   ``r_k < p1``, unchanged if ``p1 ≤ r_k ≤ p2``, ``max(upsilon_k / 4, m)`` if ``r_k > p2``.
8. ``k = k + 1`` and back to 2 until the error norm has converged or ``k`` reaches 100.

"Converged" is made concrete by these tests, each recorded as the result's ``reason``:

- ``ftol``: an accepted, well-predicted step (``r_k ≥ p1``) reduced ``||F||²`` by less than ``phi``
  of its value, and the linear model predicted no more (the seed's "error norm very close"); or,
  at a new Jacobian and a damping no larger than at the start (``upsilon_k ≤ upsilon_1``: a
  heavily damped step predicts little wherever it is), the LM step ``d1`` predicts a reduction
  below :data:`PRED_FTOL` of ``||F||²`` (``phi²`` by default): the point is converged far below
  ``phi``, and the approximate steps and their residuals are not made (at that level a cost's
  change is the model's and the rounding's noise, and a step taken there moves a prediction by
  less than ``sqrt(PRED_FTOL)·||F||``);
- ``gtol``: the residual is orthogonal to every Jacobian column to within ``gtol`` (the cosine
  ``max_j |J_jᵀF| / (||J_j|| ||F||)``; a least-squares optimum);
- ``xtol``: the step is below ``xtol`` relative to ``x`` (in the scaled variables);
- ``fatol``: ``||F||`` at most ``fatol`` (default 0: an exact zero);
- ``no_reduction``: the linear model predicts no reduction beyond rounding;
- ``max_iter``: 100 iterations without convergence.

Constants (the seed gives none): ``upsilon_1 = 1e-4``, ``m = 1e-8``, ``p0 = 1e-4``, ``p1 = 0.25``,
``p2 = 0.75``, ``delta = 1`` (the values of Fan's and Yang's experiments except ``upsilon_1``: with
scaled columns and a calibration's non-zero residual ``||F||``, ``1e-2`` damps the first steps so much
that the method needs seven iterations where ``1e-4`` needs four).

``x_scale``: an optional fixed change of variables ``x = x_scale * u`` (the solver iterates on ``u``).
``"jac"`` takes the column norms of the first Jacobian, which makes the identity damping
scale-free when the parameters mix units (mm and rad). The default is none: the method as written.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

__all__ = ["PRED_FTOL", "IterationRecord", "LMResult", "improved_lm", "next_upsilon"]

#: converged at a new Jacobian when the LM step predicts less than this fraction of ||F||² (module
#: docstring, ``ftol``); 0 turns the test off (every iteration then evaluates its steps)
PRED_FTOL = 1e-10

ResidualFn = Callable[[NDArray[np.float64]], NDArray[np.float64]]
JacobianFn = Callable[[NDArray[np.float64]], NDArray[np.float64]]


@dataclass(frozen=True, slots=True)
class IterationRecord:
    """One iteration k: cost ``||F_k||²/2``, damping ``mu_k``, ``upsilon_k``, ratio ``r_k``, accepted?"""

    k: int
    cost: float
    mu: float
    upsilon: float
    ratio: float
    accepted: bool
    step_norm: float


@dataclass(frozen=True, slots=True)
class LMResult:
    x: NDArray[np.float64]
    cost: float  # ||F(x)||² / 2 at the solution
    residual: NDArray[np.float64]
    jacobian: NDArray[np.float64]  # at the solution (or the last one made: jacobian_at_solution)
    iterations: int
    n_residual_evals: int
    n_jacobian_evals: int
    converged: bool
    reason: str  # ftol | gtol | xtol | fatol | no_reduction | max_iter
    time_s: float
    history: tuple[IterationRecord, ...] = field(default_factory=tuple)


def improved_lm(
    residual: ResidualFn,
    jacobian: JacobianFn,
    x0: NDArray[np.float64],
    *,
    phi: float = 1e-5,
    gtol: float = 1e-10,
    xtol: float = 1e-10,
    fatol: float = 0.0,
    max_iter: int = 100,
    upsilon1: float = 1e-4,
    m: float = 1e-8,
    p0: float = 1e-4,
    p1: float = 0.25,
    p2: float = 0.75,
    delta: float = 1.0,
    x_scale: Literal["jac"] | NDArray[np.float64] | None = None,
    jacobian_x0: NDArray[np.float64] | None = None,
    jacobian_at_solution: bool = True,
) -> LMResult:
    """Minimise ``||residual(x)||²`` from ``x0`` by the improved LM method (module docstring).

    ``residual(x)`` returns (M,), ``jacobian(x)`` returns (M, N) = dF/dx. ``jacobian_x0``: the
    Jacobian at ``x0`` when the caller has it already (an identifiability analysis at the start),
    used instead of a first ``jacobian(x0)``. ``jacobian_at_solution=False``: the result's
    Jacobian is the last one the iteration made (not evaluated again at the solution), for a
    caller that needs only the solution (a cross-validation fold).
    """
    if not (0.0 < p0 < p1 < p2 < 1.0):
        raise ValueError(f"need 0 < p0 < p1 < p2 < 1, got p0={p0}, p1={p1}, p2={p2}")
    if not (upsilon1 > m > 0.0):
        raise ValueError(f"need upsilon1 > m > 0, got upsilon1={upsilon1}, m={m}")
    t_start = time.perf_counter()
    x = np.array(x0, dtype=float, copy=True)
    if x.ndim != 1:
        raise ValueError(f"x0 must be a vector, got shape {x.shape}")
    ev = _Evaluations(residual, jacobian)

    f = ev.f(x)
    if jacobian_x0 is None:
        jac = ev.j(x)
    else:
        jac = np.asarray(jacobian_x0, dtype=float)
        if jac.shape != (f.size, x.size):
            raise ValueError(f"jacobian_x0 must have shape {(f.size, x.size)}, got {jac.shape}")
    scale = _variable_scale(x_scale, jac, x)
    ff = float(f @ f)
    upsilon = upsilon1
    history: list[IterationRecord] = []
    reason = "max_iter"
    eye = np.eye(x.size)
    k = 0
    need_jac = False
    fresh = True  # the Jacobian is new at x (the start, or an accepted step)
    while k < max_iter:
        k += 1
        if need_jac:  # step 2 at the point a step was accepted to
            jac = ev.j(x)
            need_jac = False
            fresh = True
        js = jac * scale  # Jacobian w.r.t. the scaled variables u = x / scale
        g = js.T @ f
        f_norm = np.sqrt(ff)
        stop = _stationary(js, g, f_norm, fatol, gtol)
        if stop is not None:
            reason = stop
            k -= 1
            break
        # step 3: adaptive damping and the LM step
        mu = upsilon * f_norm**delta
        try:
            factor = scipy.linalg.cho_factor(js.T @ js + mu * eye, lower=False, check_finite=False)
        except np.linalg.LinAlgError:
            upsilon *= 4.0
            fresh = False
            history.append(IterationRecord(k, 0.5 * ff, float(mu), upsilon, float("nan"), False, 0.0))
            continue
        d1 = _lm_step(factor, g)
        pred = _predicted(js, f, ff, d1)
        if fresh and upsilon <= upsilon1 and pred <= PRED_FTOL * ff:
            history.append(
                IterationRecord(
                    k, 0.5 * ff, float(mu), upsilon, float("nan"), False, float(np.linalg.norm(d1))
                )
            )
            reason = "ftol"
            break
        fresh = False
        # step 4: two approximate LM steps with the same Jacobian and factorisation
        y = x + scale * d1
        d2, pred2 = _approximate_step(factor, js, ev.f(y))
        pred += pred2
        z = y + scale * d2
        d3, pred3 = _approximate_step(factor, js, ev.f(z))
        pred += pred3
        s = d1 + d2 + d3  # step 5
        # step 6: actual against predicted reduction
        x_new = x + scale * s
        f_new = ev.f(x_new)
        ff_new = float(f_new @ f_new)
        ared = ff - ff_new
        step_norm = float(np.linalg.norm(s))
        u_norm = float(np.linalg.norm(x / scale))
        if not np.isfinite(ff_new):
            ratio = -np.inf
        elif pred <= 1e-15 * ff:
            history.append(IterationRecord(k, 0.5 * ff, float(mu), upsilon, float("nan"), False, step_norm))
            reason = "no_reduction"
            break
        else:
            ratio = ared / pred
        # step 7: accept, and the damping factor for the next iteration
        accepted = ratio >= p0
        history.append(
            IterationRecord(k, 0.5 * ff, float(mu), upsilon, float(ratio), bool(accepted), step_norm)
        )
        upsilon = next_upsilon(upsilon, ratio, m=m, p1=p1, p2=p2)
        if accepted:
            ff_old = ff
            x, f, ff = x_new, f_new, ff_new
            need_jac = True
            if ratio >= p1 and ared <= phi * ff_old and pred <= phi * ff_old:
                reason = "ftol"
                break
        if step_norm <= xtol * (u_norm + xtol):
            reason = "xtol"
            break
    if need_jac and jacobian_at_solution:
        jac = ev.j(x)
    return LMResult(
        x=x,
        cost=0.5 * ff,
        residual=f,
        jacobian=jac,
        iterations=k,
        n_residual_evals=ev.n_f,
        n_jacobian_evals=ev.n_j,
        converged=reason != "max_iter",
        reason=reason,
        time_s=time.perf_counter() - t_start,
        history=tuple(history),
    )


def next_upsilon(upsilon: float, ratio: float, *, m: float, p1: float, p2: float) -> float:
    """Step 7's damping factor after an iteration whose reduction ratio was ``ratio``: four times
    larger below ``p1``, four times smaller (not below ``m``) above ``p2``, unchanged between."""
    if ratio < p1:
        return 4.0 * upsilon
    if ratio > p2:
        return max(upsilon / 4.0, m)
    return upsilon


class _Evaluations:
    """The caller's residual and Jacobian as float arrays, with the number of calls of each."""

    def __init__(self, residual: ResidualFn, jacobian: JacobianFn) -> None:
        self._residual, self._jacobian = residual, jacobian
        self.n_f = self.n_j = 0

    def f(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        self.n_f += 1
        return np.asarray(self._residual(x), dtype=float)

    def j(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        self.n_j += 1
        return np.asarray(self._jacobian(x), dtype=float)


def _stationary(
    js: NDArray[np.float64], g: NDArray[np.float64], f_norm: float, fatol: float, gtol: float
) -> Literal["fatol", "gtol"] | None:
    """The tests that hold at a point before any step (module docstring): ``fatol`` when
    ``||F|| ≤ fatol``, ``gtol`` when the residual is orthogonal to every column of the scaled
    Jacobian ``js`` to within ``gtol`` (``g = jsᵀF``); None otherwise."""
    if f_norm <= fatol:
        return "fatol"
    col = np.linalg.norm(js, axis=0)
    cosine = np.abs(g) / np.where(col > 0.0, col * f_norm, 1.0)
    if float(cosine.max(initial=0.0)) <= gtol:
        return "gtol"
    return None


Factor = tuple[NDArray[np.float64], bool]  # Cholesky factor of JᵀJ + mu·I (scipy.linalg.cho_factor)


def _lm_step(factor: Factor, rhs: NDArray[np.float64]) -> NDArray[np.float64]:
    """``-(JᵀJ + mu I)⁻¹ rhs`` from the iteration's one factorisation."""
    return -np.asarray(scipy.linalg.cho_solve(factor, rhs, check_finite=False))


def _predicted(
    js: NDArray[np.float64], f_w: NDArray[np.float64], ff_w: float, d: NDArray[np.float64]
) -> float:
    """The linear model's predicted reduction ``||F(w)||² − ||F(w) + J d||²`` of a step ``d`` at ``w``."""
    return ff_w - float(np.sum((f_w + js @ d) ** 2))


def _approximate_step(
    factor: Factor, js: NDArray[np.float64], f_w: NDArray[np.float64]
) -> tuple[NDArray[np.float64], float]:
    """Step 4's approximate LM step at a point ``w`` with residual ``f_w`` (the iteration's Jacobian
    and factorisation, no new Jacobian) and the reduction the linear model predicts for it."""
    d = _lm_step(factor, js.T @ f_w)
    return d, _predicted(js, f_w, float(f_w @ f_w), d)


def _variable_scale(
    x_scale: Literal["jac"] | NDArray[np.float64] | None, jac: NDArray[np.float64], x: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The fixed change of variables ``x = scale · u`` (module docstring): ``"jac"`` the inverse
    column norms of the first Jacobian ``jac``, None ones, or the caller's positive array."""
    if isinstance(x_scale, str):
        if x_scale != "jac":
            raise ValueError(f"x_scale must be 'jac', an array or None, got {x_scale!r}")
        norms = np.linalg.norm(jac, axis=0)
        return np.asarray(1.0 / np.where(norms > 0.0, norms, 1.0))
    if x_scale is None:
        return np.ones_like(x)
    scale = np.asarray(x_scale, dtype=float)
    if scale.shape != x.shape or np.any(scale <= 0.0):
        raise ValueError("x_scale must be positive and shaped like x0")
    return scale
