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

import dataclasses
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.params import N_PARAMS, TOOL_SLICE, KinematicParams
from comp_daemon.models.effects import (
    EffectParams,
    MassModel,
    TwinState,
    twin_jacobian_targets,
    twin_state_of,
)
from comp_daemon.models.rows import MeasuredRows

__all__ = [
    "FitResult",
    "at_fit",
    "by_poses",
    "fit_twin",
    "flange_mm",
    "linearize",
    "linearize_targets",
    "on_flange",
    "predict_mm",
    "project_out",
    "seen_from_flange",
]

FloatArray = NDArray[np.float64]


def by_poses(
    obs: MeasuredRows,
) -> list[tuple[MeasuredRows, list[tuple[NDArray[np.int64], FloatArray | None]]]]:
    """The targets grouped by the poses they were measured at: per group, the first target's
    observations and each member's rows and place on the flange (None for the TCP). The targets of
    a campaign share their poses, so there is one group and one twin evaluation for all of them."""
    groups: list[tuple[MeasuredRows, list[tuple[NDArray[np.int64], FloatArray | None]]]] = []
    for rows, sub, offset in obs.by_target():
        group = next((g for g in groups if g[0].same_poses(sub)), None)
        if group is None:
            groups.append((sub, [(rows, offset)]))
        else:
            group[1].append((rows, offset))
    return groups


def on_flange(st: TwinState, place_mm: FloatArray | None) -> FloatArray:
    """(n, 3) the twin's position of a point at ``place_mm`` on the flange (None: the TCP)."""
    if place_mm is None:
        return st.tcp_mm
    flange = st.chain.world_T_frame[:, 6]
    out: FloatArray = flange[:, :3, :3] @ place_mm + flange[:, :3, 3]
    return out


def predict_mm(
    mass: MassModel, params: KinematicParams, effects: EffectParams, obs: MeasuredRows
) -> FloatArray:
    """(n, 3) the twin's position of each row's target at the observed poses (mm, world frame).

    The targets of one pose share one twin (its gravity torques with the payload at the TCP)."""
    out = np.empty((len(obs), 3))
    for sub, members in by_poses(obs):
        st = twin_state_of(mass, params, effects, sub)
        for rows, offset in members:
            out[rows] = on_flange(st, offset)
    return out


def _jacobians(
    mass: MassModel,
    params: KinematicParams,
    effects: EffectParams,
    names: Sequence[str],
    obs: MeasuredRows,
) -> Iterator[tuple[NDArray[np.int64], FloatArray, FloatArray, FloatArray | None]]:
    """Per target: its rows, the twin's positions there and their Jacobian, and its place on the
    flange (None for the TCP); one twin per group of targets that share their poses."""
    for sub, members in by_poses(obs):
        parts = twin_jacobian_targets(
            mass, params, effects, list(names), [offset for _, offset in members], sub
        )
        for (rows, offset), (tcp, jac) in zip(members, parts, strict=True):
            yield rows, tcp, jac, offset


def linearize(
    mass: MassModel,
    params: KinematicParams,
    effects: EffectParams,
    names: Sequence[str],
    obs: MeasuredRows,
) -> tuple[FloatArray, FloatArray]:
    """Residual (n, 3) and Jacobian (n, 3, 39 + len(names)) of the twin at the observed poses.

    A further target sits at its own place on the flange: the tool's columns are zero on its rows
    (:func:`linearize_targets` also gives the derivatives by that place)."""
    resid, jac, _ = linearize_targets(mass, params, effects, names, obs)
    return resid, jac


def linearize_targets(
    mass: MassModel,
    params: KinematicParams,
    effects: EffectParams,
    names: Sequence[str],
    obs: MeasuredRows,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`linearize`, and (n, 3, 3·(K − 1)) the derivative of each row's position by its
    further target's place on the flange (zero on the other rows; (n, 3, 0) with one target)."""
    n_more = 0 if obs.target_offsets_mm is None or obs.target is None else len(obs.target_offsets_mm)
    tcp = np.empty((len(obs), 3))
    jac = np.empty((len(obs), 3, N_PARAMS + len(names)))
    tcols = np.zeros((len(obs), 3, 3 * n_more))
    for rows, tcp_k, jac_k, offset in _jacobians(mass, params, effects, names, obs):
        tcp[rows], jac[rows] = tcp_k, jac_k
        if offset is not None:
            assert obs.target is not None
            k = int(obs.target[rows[0]])
            tcols[rows, :, 3 * (k - 1) : 3 * k] = jac_k[:, :, TOOL_SLICE]
            jac[rows, :, TOOL_SLICE] = 0.0
    return obs.xyz_mm - tcp, jac, tcols


@dataclass(frozen=True)
class FitResult:
    """A fitted twin and how the fit went."""

    params: KinematicParams
    effects: EffectParams
    rms_mm: float  # 3-D RMS residual over the rows fitted
    iterations: int
    converged: bool
    target_offsets_mm: FloatArray | None = None  # the further targets' places on the flange, fitted


def at_fit(obs: MeasuredRows, fit: FitResult) -> MeasuredRows:
    """``obs`` with the further targets at the places ``fit`` found for them (unchanged otherwise)."""
    if obs.target is None or fit.target_offsets_mm is None:
        return obs
    return dataclasses.replace(obs, target_offsets_mm=fit.target_offsets_mm)


def flange_mm(
    mass: MassModel, params: KinematicParams, effects: EffectParams, obs: MeasuredRows
) -> tuple[FloatArray, FloatArray]:
    """The twin's flange rotation (n, 3, 3) and origin (n, 3, mm) at the observed poses."""
    st = twin_state_of(mass, params, effects, obs)
    flange = st.chain.world_T_frame[:, 6]
    return flange[:, :3, :3], flange[:, :3, 3]


def seen_from_flange(rot: FloatArray, origin: FloatArray, points_mm: FloatArray) -> FloatArray:
    """(3,) the mean of the points (n, 3) seen from the flange frames: the least-squares place on
    the flange of a target measured there."""
    return np.einsum("nji,nj->ni", rot, points_mm - origin).mean(axis=0)


def project_out(columns: FloatArray, *arrays: FloatArray) -> list[FloatArray]:
    """``arrays`` (n, 3[, m]) with the span of ``columns`` (n, 3, q) projected out of each."""
    if columns.shape[2] == 0:
        return list(arrays)
    t = columns.reshape(-1, columns.shape[2])
    norms = np.linalg.norm(t, axis=0)
    qmat, _ = np.linalg.qr(t / np.where(norms > 0, norms, 1.0))
    out = []
    for a in arrays:
        flat = a.reshape(len(t), -1)
        out.append((flat - qmat @ (qmat.T @ flat)).reshape(a.shape))
    return out


def _solve_scaled(jac: FloatArray, rhs: FloatArray) -> FloatArray:
    norms = np.linalg.norm(jac, axis=0)
    norms[norms == 0.0] = 1.0
    step, *_ = np.linalg.lstsq(jac / norms, rhs, rcond=None)
    return np.asarray(step / norms)


def _profiled_cost(
    mass: MassModel, obs: MeasuredRows, params: KinematicParams, effects: EffectParams
) -> tuple[float, MeasuredRows]:
    """The sum of squared errors (mm²) of the twin at ``obs`` with the further targets at their
    least-squares places on its flange, and the rows with them there (one twin evaluation for the
    targets that share their poses)."""
    if obs.target is None or obs.target_offsets_mm is None:
        r = obs.xyz_mm - predict_mm(mass, params, effects, obs)
        return float(np.sum(r * r)), obs
    offsets = np.array(obs.target_offsets_mm, dtype=float)
    sse = 0.0
    for sub, members in by_poses(obs):
        st = twin_state_of(mass, params, effects, sub)
        flange = st.chain.world_T_frame[:, 6]
        rot, origin = flange[:, :3, :3], flange[:, :3, 3]
        for rows, offset in members:
            measured = obs.xyz_mm[rows]
            if offset is None:
                pred = st.tcp_mm
            else:
                place = seen_from_flange(rot, origin, measured)
                offsets[int(obs.target[rows[0]]) - 1] = place
                pred = origin + rot @ place
            sse += float(np.sum((measured - pred) ** 2))
    return sse, dataclasses.replace(obs, target_offsets_mm=offsets)


def _gauss_newton_step(
    mass: MassModel,
    params: KinematicParams,
    effects: EffectParams,
    names: list[str],
    obs: MeasuredRows,
    cols: NDArray[np.int64],
) -> FloatArray:
    """The Gauss–Newton step of the columns ``cols`` at the twin, the further targets' places
    profiled out (variable projection)."""
    resid, jac, tcols = linearize_targets(mass, params, effects, names, obs)
    jac = jac[:, :, cols]
    if obs.target is not None:
        resid, jac = project_out(tcols, resid, jac)
    return _solve_scaled(jac.reshape(-1, len(cols)), resid.reshape(-1))


#: a step that raises the cost is halved at most this many times
MAX_HALVINGS = 20


def _descend(
    cost_at: Callable[[KinematicParams, EffectParams], tuple[float, MeasuredRows]],
    cost: float,
    params: KinematicParams,
    effects: EffectParams,
    names: list[str],
    geo_idx: NDArray[np.int64],
    step: FloatArray,
) -> tuple[KinematicParams, EffectParams, MeasuredRows, float] | None:
    """The first of ``t·step`` (t = 1, ½, ¼, …) that does not raise ``cost``: the twin there, its
    rows and its cost; None when no halving does."""
    n_geo = len(geo_idx)
    t = 1.0
    for _ in range(MAX_HALVINGS):
        dx = np.zeros(N_PARAMS)
        dx[geo_idx] = t * step[:n_geo]
        trial_p = params.apply(dx)
        trial_e = effects.add(names, t * step[n_geo:]) if names else effects
        new_cost, trial_obs = cost_at(trial_p, trial_e)
        if new_cost <= cost * (1.0 + 1e-12) + 1e-30:
            return trial_p, trial_e, trial_obs, new_cost
        t *= 0.5
    return None


def fit_twin(
    mass: MassModel,
    obs: MeasuredRows,
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
    halved (up to :data:`MAX_HALVINGS` times). Further targets sit at their least-squares places
    for each twin tried (:func:`_profiled_cost`). Stops when the cost changes by less than ``rtol``
    relative, or after ``max_iter`` iterations.
    """
    names = list(names)
    geo_idx = np.flatnonzero(geo_free)
    cols = np.concatenate([geo_idx, N_PARAMS + np.arange(len(names))])

    def cost_at(p: KinematicParams, e: EffectParams) -> tuple[float, MeasuredRows]:
        return _profiled_cost(mass, obs, p, e)

    cost, current = cost_at(params, effects)
    converged = False
    iterations = 0
    for iterations in range(1, max_iter + 1):  # noqa: B007 - the count is reported
        step = _gauss_newton_step(mass, params, effects, names, current, cols)
        found = _descend(cost_at, cost, params, effects, names, geo_idx, step)
        if found is None:
            converged = True  # no descent direction left: at the optimum to numerical precision
            break
        params, effects, current, new_cost = found
        change = abs(cost - new_cost)
        cost = new_cost
        if change <= rtol * max(cost, 1e-30):
            converged = True
            break
    rms = float(np.sqrt(cost / max(len(obs), 1)))
    return FitResult(
        params=params,
        effects=effects,
        rms_mm=rms,
        iterations=iterations,
        converged=converged,
        target_offsets_mm=current.target_offsets_mm,
    )
