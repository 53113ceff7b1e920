"""Fitting the twin for the diagnosis: registration, identifiability, Gauss–Newton, linear algebra.

Conventions: measured and predicted TCP positions are mm in the measurement (``world``) frame;
residuals are ``measured − predicted`` (mm), stacked pose by pose as (x, y, z) rows. The twin is a
:class:`~comp_daemon.kinematics.params.KinematicParams` (geometry, base frame, tool) plus an
:class:`~comp_daemon.models.effects.EffectParams`; the free parameters are a subset of the 39
geometric entries (:data:`~comp_daemon.kinematics.params.PARAM_NAMES`, units rad / mm) and a list
of effect parameter names (units of :mod:`comp_daemon.models.effects`).

Linear least squares is done with columns scaled to unit norm (the raw columns differ by up to
1e10 between a compliance and a length parameter), so that ranks and conditioning are unit-free.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.params import N_PARAMS, KinematicParams
from comp_daemon.models.effects import EffectParams, MassModel, twin_jacobian, twin_tcp_mm

__all__ = [
    "FitResult",
    "Observations",
    "fit_twin",
    "linearize",
    "predict_mm",
]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Observations:
    """The measured poses the diagnosis works on (rows in data-set order).

    ``dir`` (n, 6) holds −1/+1, or is ``None`` when the data has no approach directions;
    ``temp_c`` is ``None`` without temperatures. ``pose_group`` (n,) numbers the distinct commanded
    poses (repeats of a pose share a number); it is the unit of cross-validation folds and of the
    cluster-robust covariance. ``clock`` (n,) is the campaign clock of the time effects: hours
    since the first ``t_s``, or the row number when the data has no times (``clock_name`` says
    which: ``t_s`` or ``pose_order``).
    """

    a_deg: FloatArray
    xyz_mm: FloatArray
    dir: FloatArray | None
    payload_kg: FloatArray
    temp_c: FloatArray | None
    pose_group: NDArray[np.int64]
    clock: FloatArray | None = None
    clock_name: str = "pose_order"

    def __len__(self) -> int:
        return int(self.a_deg.shape[0])

    def take(self, idx: NDArray[np.int64]) -> Observations:
        return Observations(
            a_deg=self.a_deg[idx],
            xyz_mm=self.xyz_mm[idx],
            dir=None if self.dir is None else self.dir[idx],
            payload_kg=self.payload_kg[idx],
            temp_c=None if self.temp_c is None else self.temp_c[idx],
            pose_group=self.pose_group[idx],
            clock=None if self.clock is None else self.clock[idx],
            clock_name=self.clock_name,
        )


def predict_mm(
    mass: MassModel, params: KinematicParams, effects: EffectParams, obs: Observations
) -> FloatArray:
    """(n, 3) TCP of the twin at the observed poses (mm, world frame)."""
    return twin_tcp_mm(mass, params, effects, obs.a_deg, obs.dir, obs.payload_kg, obs.temp_c, clock=obs.clock)


def linearize(
    mass: MassModel,
    params: KinematicParams,
    effects: EffectParams,
    names: Sequence[str],
    obs: Observations,
) -> tuple[FloatArray, FloatArray]:
    """Residual (n, 3) and Jacobian (n, 3, 39 + len(names)) of the twin at the observed poses."""
    tcp, jac = twin_jacobian(
        mass, params, effects, list(names), obs.a_deg, obs.dir, obs.payload_kg, obs.temp_c, clock=obs.clock
    )
    return obs.xyz_mm - tcp, jac


@dataclass(frozen=True)
class FitResult:
    """A fitted twin and how the fit went."""

    params: KinematicParams
    effects: EffectParams
    rms_mm: float  # 3-D RMS residual over the rows fitted
    iterations: int
    converged: bool


def _solve_scaled(jac: FloatArray, rhs: FloatArray) -> FloatArray:
    norms = np.linalg.norm(jac, axis=0)
    norms[norms == 0.0] = 1.0
    step, *_ = np.linalg.lstsq(jac / norms, rhs, rcond=None)
    return np.asarray(step / norms)


def fit_twin(
    mass: MassModel,
    obs: Observations,
    params: KinematicParams,
    effects: EffectParams,
    geo_free: NDArray[np.bool_],
    names: Sequence[str],
    *,
    max_iter: int = 30,
    rtol: float = 1e-12,
) -> FitResult:
    """Gauss–Newton fit of the free geometric entries (mask of 39) and the named effect parameters.

    Starts from ``params`` / ``effects``; geometric steps are applied with
    :meth:`KinematicParams.apply` (the base-frame rotation as a left-multiplied small rotation, as
    the identification Jacobian defines it), effect steps are added. A step that raises the cost is
    halved (up to 20 times). Stops when the cost changes by less than ``rtol`` relative, or after
    ``max_iter`` iterations.
    """
    names = list(names)
    geo_idx = np.flatnonzero(geo_free)
    n_geo = len(geo_idx)
    cols = np.concatenate([geo_idx, N_PARAMS + np.arange(len(names))])

    def cost_of(p: KinematicParams, e: EffectParams) -> float:
        r = obs.xyz_mm - predict_mm(mass, p, e, obs)
        return float(np.sum(r * r))

    cost = cost_of(params, effects)
    converged = False
    iterations = 0
    for iterations in range(1, max_iter + 1):  # noqa: B007 - the count is reported
        resid, jac = linearize(mass, params, effects, names, obs)
        jf = jac[:, :, cols].reshape(-1, len(cols))
        step = _solve_scaled(jf, resid.reshape(-1))
        new_cost = cost
        t = 1.0
        for _ in range(20):
            dx = np.zeros(N_PARAMS)
            dx[geo_idx] = t * step[:n_geo]
            trial_p = params.apply(dx)
            trial_e = effects.add(names, t * step[n_geo:]) if names else effects
            new_cost = cost_of(trial_p, trial_e)
            if new_cost <= cost * (1.0 + 1e-12) + 1e-30:
                params, effects = trial_p, trial_e
                break
            t *= 0.5
        else:
            converged = True  # no descent direction left: at the optimum to numerical precision
            break
        change = abs(cost - new_cost)
        cost = new_cost
        if change <= rtol * max(cost, 1e-30):
            converged = True
            break
    rms = float(np.sqrt(cost / max(len(obs), 1)))
    return FitResult(params=params, effects=effects, rms_mm=rms, iterations=iterations, converged=converged)
