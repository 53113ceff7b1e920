"""The fitted values of every ladder step as rows: name, joint, unit, value and standard error.

The report shows them as tables instead of the JSON of ``steps[].params``. The standard error of
each parameter is the cluster-robust one of the selection's Wald test (poses as clusters,
:meth:`comp_daemon.diagnosis.stats.LinearProblem.standard_errors`), computed at the step's fitted
twin on the fit rows, with the model of that step: the free geometric parameters and every effect
parameter accepted up to it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from comp_daemon.diagnosis.candidates import geometric_json_key
from comp_daemon.diagnosis.fitting import linearize
from comp_daemon.diagnosis.result import Diagnosis, Step
from comp_daemon.diagnosis.stats import LinearProblem
from comp_daemon.kinematics.params import N_PARAMS, PARAM_NAMES
from comp_daemon.models.effects import MassModel, effect_by_name
from comp_daemon.models.rows import MeasuredRows

__all__ = ["ParamRow", "parameter_rows"]

_GEOMETRIC_WORDS = {
    "theta": "joint angle offset θ",
    "d": "link offset d",
    "a": "link length a",
    "alpha": "link twist α",
    "beta": "link twist β (Hayati)",
}


@dataclass(frozen=True, slots=True)
class ParamRow:
    """One fitted parameter: ``name`` as the document's key, ``what`` in words, ``where`` (the
    joint, or the axis of a frame), ``unit``, ``value`` and ``sigma`` (None when not determined)."""

    step: int  # 1-based ladder step
    effect: str
    name: str
    what: str
    where: str
    unit: str
    value: float
    sigma: float | None


def parameter_rows(diag: Diagnosis) -> list[ParamRow]:
    """The fitted values of every step of ``diag``'s ladder, in ladder order."""
    if not diag.steps:
        return []
    geometric = diag.steps[0]
    free = np.array(
        [key in geometric.params.get(group, {}) for group, key, _ in map(geometric_json_key, range(N_PARAMS))]
    )
    geo_idx = np.flatnonzero(free)
    obs = diag.obs.take(diag.fit_rows)
    mass = MassModel.from_robot(diag.robot)
    rows: list[ParamRow] = []
    before: list[str] = []
    for number, step in enumerate(diag.steps, start=1):
        names = before + list(step.names)
        sigma = _standard_errors(mass, obs, step, geo_idx, names)
        if step.effect == "geometric":
            rows += _geometric_rows(number, step, geo_idx, sigma)
        else:
            own = sigma[len(geo_idx) + len(before) :] if sigma is not None else None
            rows += _effect_rows(number, step, diag.options.harmonics, own)
        if step.significant:
            before = names
    return rows


def _standard_errors(
    mass: MassModel, obs: MeasuredRows, step: Step, geo_idx: np.ndarray, names: list[str]
) -> np.ndarray | None:
    """Standard errors of [free geometric | names] at the step's fit, or None when not computable."""
    resid, jac = linearize(mass, step.fit.params, step.fit.effects, names, obs)
    columns = np.concatenate([jac[:, :, geo_idx], jac[:, :, N_PARAMS + np.arange(len(names))]], axis=2)
    n = columns.shape[0]
    if 3 * n <= columns.shape[2]:
        return None
    problem = LinearProblem(resid, columns, obs.pose_group, np.zeros(n, dtype=np.int64))
    out = problem.standard_errors(range(columns.shape[2]))
    return np.where(np.isfinite(out), out, np.nan)


def _sigma(sigma: np.ndarray | None, k: int, scale: float = 1.0) -> float | None:
    if sigma is None or not math.isfinite(float(sigma[k])):
        return None
    return float(sigma[k]) * scale


def _geometric_rows(number: int, step: Step, geo_idx: np.ndarray, sigma: np.ndarray | None) -> list[ParamRow]:
    rows = []
    for col, k in enumerate(geo_idx):
        group, key, is_angle = geometric_json_key(int(k))
        name = PARAM_NAMES[int(k)]
        if int(k) < 30:
            what, where = _GEOMETRIC_WORDS[name[:-1]], f"joint {key}"
        else:
            what = (
                ("base frame position" if is_angle is False else "base frame rotation") if k < 36 else "tool"
            )
            where = key
        scale = math.degrees(1.0) if is_angle else 1.0
        rows.append(
            ParamRow(
                step=number,
                effect=step.effect,
                name=f"{group}.{key}",
                what=what,
                where=where,
                unit="deg" if is_angle else "mm",
                value=float(step.params[group][key]),
                sigma=_sigma(sigma, col, scale),
            )
        )
    return rows


def _effect_rows(number: int, step: Step, harmonics: int, sigma: np.ndarray | None) -> list[ParamRow]:
    entry = effect_by_name(step.effect)
    position = {name: k for k, name in enumerate(step.names)}
    values = step.fit.effects.get(list(step.names)) if step.names else np.zeros(0)
    rows = []
    for arr in entry.arrays:
        joints: list[int | None] = [None] if arr.layout == "scalar" else list(step.joints)
        for joint in joints:
            for name in arr.names(joint or 0, harmonics):
                k = position.get(name)
                if k is None:
                    continue
                harmonic = name.rsplit("_", 1)[1] if arr.layout == "harmonic" else None
                where = "–" if joint is None else f"joint {joint}"
                rows.append(
                    ParamRow(
                        step=number,
                        effect=step.effect,
                        name=name,
                        what=arr.meaning + (f", harmonic {harmonic}" if harmonic else ""),
                        where=where,
                        unit=arr.unit,
                        value=float(values[k]),
                        sigma=_sigma(sigma, k),
                    )
                )
    return rows
