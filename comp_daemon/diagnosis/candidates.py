"""The candidates of the effect selection, what the data allows of them, and parameters as JSON.

A candidate is one effect of :data:`~comp_daemon.models.effects.EFFECT_CATALOGUE` on one joint (or,
for an effect that is not per joint, on the whole robot), in catalogue order. A candidate whose data
is absent or does not vary (:meth:`~comp_daemon.models.effects.Effect.unfit_reason`) or whose TCP
signature is a combination of the model's columns is skipped with the reason.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.diagnosis.result import rounded
from comp_daemon.kinematics.params import PARAM_NAMES, KinematicParams
from comp_daemon.models.effects import (
    EFFECT_CATALOGUE,
    EFFECTS,
    EffectParams,
    MassModel,
    effect_by_name,
    effect_data,
)
from comp_daemon.models.rows import MeasuredRows

__all__ = [
    "CANDIDATE_RTOL",
    "JOINTS",
    "Candidate",
    "all_candidates",
    "data_reasons",
    "effect_params_json",
    "geometric_json_key",
    "geometric_params_json",
    "group_skips",
    "unidentifiable_candidates",
]

FloatArray = NDArray[np.float64]
JOINTS = (1, 2, 3, 4, 5, 6)
#: a candidate is unidentifiable when less than this fraction of its (unit) columns is left after
#: projecting out the model's columns
CANDIDATE_RTOL = 1e-4


@dataclass(frozen=True)
class Candidate:
    """One effect on one joint (``joint`` None for an effect of the whole robot) and its names."""

    effect: str
    joint: int | None
    names: tuple[str, ...]
    searched: int = 1  # positions tried for a setting chosen on the fit rows (the step's moment)

    @property
    def label(self) -> str:
        return self.effect if self.joint is None else f"{self.effect} J{self.joint}"


def all_candidates(harmonics: int) -> list[Candidate]:
    """Every candidate: the per-joint effects joint by joint, then the whole-robot ones."""
    out: list[Candidate] = []
    for e in EFFECT_CATALOGUE:
        if e.per_joint:
            out += [Candidate(e.name, j, tuple(e.names([j], harmonics))) for j in JOINTS]
    for e in EFFECT_CATALOGUE:
        if not e.per_joint:
            out.append(Candidate(e.name, None, tuple(e.names([], harmonics))))
    return out


def data_reasons(
    cands: Sequence[Candidate],
    obs_fit: MeasuredRows,
    mass: MassModel,
    params: KinematicParams,
    jac_theta_norm: FloatArray,
) -> dict[Candidate, str]:
    """Why candidates cannot be fitted from these data (absent columns, no variation)."""
    moves_tcp = jac_theta_norm > 1e-6 * max(float(jac_theta_norm.max(initial=0.0)), 1e-300)
    data = effect_data(mass, params, obs_fit, moves_tcp)
    reasons: dict[Candidate, str] = {}
    for c in cands:
        why = effect_by_name(c.effect).unfit_reason(data, c.joint)
        if why is not None:
            reasons[c] = why
    return reasons


def unidentifiable_candidates(
    cands: Sequence[Candidate], jac_base: FloatArray, jac_cand: dict[Candidate, FloatArray]
) -> set[Candidate]:
    """Candidates whose unit columns are (nearly) in the span of the base model's columns."""
    norms = np.linalg.norm(jac_base, axis=0)
    base = jac_base[:, norms > 0] / norms[norms > 0]
    qmat, _ = np.linalg.qr(base)
    out: set[Candidate] = set()
    for c in cands:
        cols = jac_cand[c]
        cn = np.linalg.norm(cols, axis=0)
        if np.any(cn == 0):
            out.add(c)
            continue
        cols = cols / cn
        rest = cols - qmat @ (qmat.T @ cols)
        sv = np.linalg.svd(rest, compute_uv=False)
        if sv.min() < CANDIDATE_RTOL:
            out.add(c)
    return out


def group_skips(reasons: dict[Candidate, str]) -> list[dict[str, Any]]:
    """The ``skipped`` list: one entry per effect and reason, with its joints, in catalogue order."""
    grouped: dict[tuple[str, str], list[int]] = {}
    for c, why in reasons.items():
        grouped.setdefault((c.effect, why), [])
        if c.joint is not None:
            grouped[(c.effect, why)].append(c.joint)
    order = {e: i for i, e in enumerate(EFFECTS)}
    items = sorted(grouped.items(), key=lambda kv: (order[kv[0][0]], kv[1][:1]))
    return [{"effect": e, "joints": sorted(js), "reason": why} for (e, why), js in items]


_GEOMETRIC_KEYS = {
    "theta": ("theta_deg", True),
    "d": ("d_mm", False),
    "a": ("a_mm", False),
    "alpha": ("alpha_deg", True),
    "beta": ("beta_deg", True),
}


def geometric_json_key(k: int) -> tuple[str, str, bool]:
    """Where parameter ``k`` (layout of :data:`PARAM_NAMES`) sits in a geometric step's ``params``:
    its group (``a_mm``, ``base_deg`` …), its key there (the joint, or the axis) and whether it is an
    angle (radians inside, degrees in the document)."""
    name = PARAM_NAMES[k]
    if k < 30:
        group, is_angle = _GEOMETRIC_KEYS[name[:-1]]
        return group, name[-1], is_angle
    if k < 33:
        return "base_mm", name[-1], False
    if k < 36:
        return "base_deg", name[-2:], True
    return "tool_mm", name[-1], False


def geometric_params_json(
    fitted: KinematicParams, start: KinematicParams, free: NDArray[np.bool_]
) -> dict[str, Any]:
    """The fitted geometric increments of the free parameters (deg for angles, mm for lengths)."""
    dx = fitted.difference(start)
    out: dict[str, Any] = {}
    for k in np.flatnonzero(free):
        group, key, is_angle = geometric_json_key(int(k))
        value = float(dx[k])
        out.setdefault(group, {})[key] = rounded(math.degrees(value) if is_angle else value)
    return out


def effect_params_json(effect: str, joints: Sequence[int], eff: EffectParams) -> dict[str, Any]:
    """The fitted values of ``effect`` on ``joints``, keyed by the catalogue's ``json_key``.

    An effect with harmonic arrays leads with ``harmonics`` (K); per-joint arrays map the joint
    (as a string) to its value, harmonic arrays to the list over k; a scalar is its value; the
    effect's settings (``t_ref_c`` of thermal) follow.
    """
    entry = effect_by_name(effect)
    out: dict[str, Any] = {}
    if any(arr.layout == "harmonic" for arr in entry.arrays):
        out["harmonics"] = eff.n_harmonics
    for arr, value in zip(entry.arrays, eff.of(entry), strict=True):
        if arr.layout == "scalar":
            out[arr.json_key] = rounded(float(value))
        elif arr.layout == "joint":
            out[arr.json_key] = {str(j): rounded(float(value[j - 1])) for j in joints}
        else:
            out[arr.json_key] = {str(j): [rounded(float(v)) for v in value[j - 1]] for j in joints}
    for setting in entry.settings:
        value = getattr(eff, setting)
        out[setting] = None if isinstance(value, float) and not math.isfinite(value) else value
    return out
