"""An effect is named only when its parametric form explains what it claims, against a flexible
alternative of the same driver.

A ``ratio`` or ``cyclic`` error of joint j says: joint j's angle is off by a function of its own
axis value A_j, of one fixed form. The flexible alternative of the same driver lets **every**
joint's angle be off by any smooth function of A_j: per joint i a Chebyshev polynomial of degree
:data:`FLEX_DEGREE` in A_j (scaled to its range on the fit rows; the constant is the geometric
θ offset), mapped to the TCP through joint i's column of the twin's Jacobian. Both are fitted
beside everything else the ladder accepted (the effect itself set to zero), linearised at the
selection's final fit, and compared by their k-fold cross-validated error on the fit rows (the
folds of the selection). When the flexible one is lower by more than :data:`FLEX_GAIN`, the
effect's form does not explain the error it was chosen for: the effect is not named, and the error
is reported as "an error of axes … that no effect of the vocabulary names" with the driver, the
joints whose angle error carries it (those whose block of the flexible fit, alone, explains within
:data:`JOINT_SHARE` as much as the best block) and its size (the RMS of the flexible part over the
fit rows). It is not spread over other named effects: the ladder is built without it.

Effects of other drivers (backlash: the approach direction; compliance: the gravity torque;
thermal: the temperature; drift and step: the clock) keep the selection's tests alone.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.polynomial import chebyshev
from numpy.typing import NDArray

from comp_daemon.diagnosis.candidates import Candidate
from comp_daemon.diagnosis.fitting import FitResult, at_fit, linearize
from comp_daemon.diagnosis.selection import Context, names_of

__all__ = ["Unnamed", "flexible_attribution"]

FloatArray = NDArray[np.float64]

#: effects whose driver is their own joint's axis value, tested against the flexible alternative
AXIS_DRIVEN = ("ratio", "cyclic")
#: degree of each joint's angle error in the driving axis value (Chebyshev, constant left out)
FLEX_DEGREE = 4
#: the flexible alternative must lower the cross-validated RMS by more than this share
FLEX_GAIN = 0.05
#: a joint carries the unnamed error when its block alone explains within this share of the best block
JOINT_SHARE = 0.2


@dataclass(frozen=True)
class Unnamed:
    """An error the vocabulary does not name, found where an effect stood in for it."""

    instead_of: str  # the candidate it would have been named as, e.g. "cyclic J2"
    driver_axis: int  # 1-based: the axis value it follows
    joints: list[int]  # 1-based: the joints whose angle error carries it
    rms_mm: float  # RMS of the flexible part on the fit rows (3-D)
    cv_rms_mm_effect: float
    cv_rms_mm_flexible: float

    @property
    def axes(self) -> list[int]:
        return sorted({self.driver_axis, *self.joints})

    def describe(self) -> str:
        axes = ", ".join(str(a) for a in self.axes)
        carried = ", ".join(f"A{j}" for j in self.joints)
        return (
            f"An error of axes {axes} ({self.rms_mm:.3f} mm) that no effect of the vocabulary names: "
            f"the angle error of {carried} follows A{self.driver_axis}. {self.instead_of} does not explain "
            f"it (cross-validated {self.cv_rms_mm_effect:.4f} mm against {self.cv_rms_mm_flexible:.4f} "
            f"mm for any joint's angle error as a smooth function of A{self.driver_axis}), "
            "so it is not named."
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "axes": self.axes,
            "driver_axis": self.driver_axis,
            "joints": self.joints,
            "rms_mm": float(f"{self.rms_mm:.4g}"),
            "instead_of": self.instead_of,
            "cv_rms_mm_effect": float(f"{self.cv_rms_mm_effect:.6g}"),
            "cv_rms_mm_flexible": float(f"{self.cv_rms_mm_flexible:.6g}"),
            "summary": self.describe(),
        }


def flexible_attribution(
    ctx: Context, fit: FitResult, accepted: list[Candidate]
) -> tuple[list[Candidate], list[Unnamed]]:
    """``accepted`` without the axis-driven effects a flexible alternative of their driver beats
    clearly out of fold, and what those stood in for (module docstring)."""
    kept = list(accepted)
    unnamed: list[Unnamed] = []
    for cand in accepted:
        if cand.effect not in AXIS_DRIVEN or cand.joint is None:
            continue
        others = [c for c in kept if c is not cand]
        point = dataclasses.replace(
            fit, effects=fit.effects.with_values(list(cand.names), np.zeros(len(cand.names)))
        )
        found = _against_flexible(ctx, point, others, cand)
        if found is not None:
            kept = others
            unnamed.append(found)
    return kept, unnamed


def _against_flexible(
    ctx: Context, point: FitResult, others: list[Candidate], cand: Candidate
) -> Unnamed | None:
    assert cand.joint is not None
    names = names_of(others)
    own = ctx.own_cols(len(names))
    param = ctx.problem(point, [*names, *cand.names])
    cv_effect = param.cv_rms_mm(ctx.own_cols(len(names) + len(cand.names)))
    flex_cols = _flexible_columns(ctx, point, cand.joint)
    flex = ctx.problem(point, names, extra=flex_cols)
    start = ctx.n_base + len(names)
    block = FLEX_DEGREE
    extra = [start + k for k in range(flex_cols.shape[2])]
    cv_flex = flex.cv_rms_mm(own + extra)
    if not cv_flex < (1.0 - FLEX_GAIN) * cv_effect:
        return None
    sse_without, sse_with = flex.sse(own), flex.sse(own + extra)
    gain = max(sse_without - sse_with, 0.0)
    # the joints whose angle error carries it: each block alone, those within JOINT_SHARE of the best
    alone = [
        sse_without - flex.sse(own + [k for k in extra if start + i * block <= k < start + (i + 1) * block])
        for i in range(6)
    ]
    best = max(alone)
    joints = [i + 1 for i, g in enumerate(alone) if best > 0 and g >= (1.0 - JOINT_SHARE) * best]
    rms = float(np.sqrt(gain / max(flex.n, 1)))
    return Unnamed(cand.label, cand.joint, joints or [cand.joint], rms, cv_effect, cv_flex)


def _flexible_columns(ctx: Context, point: FitResult, driver: int) -> FloatArray:
    """(n_fit, 3, 6·FLEX_DEGREE): every joint's angle error as a Chebyshev polynomial of A_driver."""
    obs = at_fit(ctx.obs_fit, point)
    _, jac = linearize(ctx.mass, point.params, point.effects, [], obs)
    theta = jac[:, :, 0:30:5]  # (n, 3, 6): the joint angles' columns
    a = obs.a_deg[:, driver - 1]
    lo, hi = float(a.min()), float(a.max())
    x = (2.0 * a - lo - hi) / (hi - lo) if hi > lo else np.zeros_like(a)
    basis = chebyshev.chebvander(x, FLEX_DEGREE)[:, 1:]  # (n, FLEX_DEGREE), the constant left out
    cols = theta[:, :, :, None] * basis[:, None, None, :]  # (n, 3, 6, FLEX_DEGREE)
    return cols.reshape(len(a), 3, 6 * FLEX_DEGREE)
