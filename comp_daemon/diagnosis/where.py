"""Where the gap lies: the error left after the geometric step, broken down by axis, joint and region.

Every figure here is about the residual ``measured − twin`` (mm, world frame) of the twin after the
geometric step, over all rows (fit and check), unless a field says otherwise.

* ``axis_rms_mm``: RMS of the x, y and z components.
* Per joint j: the *equivalent joint error* of each pose, the angle (deg) that joint j alone would
  have to be off by to explain the residual best, ``e_j = (∂p/∂θ_j · r) / |∂p/∂θ_j|²``; its RMS;
  its mean and the 3-D RMS per bin of the axis value ``A_j`` (error vs joint angle); its mean per
  approach direction and the step between them (error vs approach direction: about ``2·h`` for a
  backlash ``h``); and ``share_pct``, the share of the post-geometric sum of squares on the fit
  rows that the effects of that joint (the per-joint effects of the catalogue, as far as the data
  allows them) remove when added to the geometric model (in-sample, so noise buys a little).
* Regions: the workspace split at the median measured x, y and z into eight octants, each with its
  count, 3-D RMS and maximum.
* ``joints``: the joints of the significant effects; ``summary``: one paragraph in words.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.diagnosis.fitting import FitResult, linearize
from comp_daemon.diagnosis.result import Step, final_step, implicated_joints
from comp_daemon.diagnosis.stats import LinearProblem
from comp_daemon.models.effects import MassModel, effect_by_name
from comp_daemon.models.rows import MeasuredRows

__all__ = ["Baseline", "equivalent_joint_error_deg", "locate", "signed_pct"]

FloatArray = NDArray[np.float64]
N_ANGLE_BINS = 6


@dataclass(frozen=True)
class Baseline:
    """What the summary says about the start of the ladder and its end."""

    check_rms_mm: float  # the nominal (registered) twin on the check rows
    check_max_mm: float
    noise_floor_mm: float | None  # None: no independent evidence of the noise
    skipped: list[dict[str, Any]]  # the diagnosis's skip list
    noise_floor_source: str | None = None  # repeats, targets, declared
    structure: str = ""  # the remainder's structure in words (comp_daemon.diagnosis.structure)
    disagreement: str = ""  # fit and check rows disagree (comp_daemon.diagnosis.agreement): no advice


def _r(value: float, digits: int = 4) -> float:
    if not np.isfinite(value) or value == 0.0:
        return float(value)
    return float(f"{value:.{digits}g}")


def equivalent_joint_error_deg(resid_mm: FloatArray, jac_theta: FloatArray) -> FloatArray:
    """(n, 6) equivalent joint errors (deg) of residuals (n, 3) given ∂p/∂θ (n, 3, 6) in mm/rad.

    Joints that do not move the TCP at a pose get NaN.
    """
    num = np.einsum("nkj,nk->nj", jac_theta, resid_mm)
    den = np.einsum("nkj,nkj->nj", jac_theta, jac_theta)
    scale = np.nanmax(den) if den.size else 1.0
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(den > 1e-12 * scale, num / den, np.nan)
    return np.rad2deg(out)


def _angle_bins(a_deg: FloatArray, e_deg: FloatArray, dist_mm: FloatArray) -> list[dict[str, Any]]:
    lo, hi = float(a_deg.min()), float(a_deg.max())
    if hi - lo < 1e-9:
        return [
            {
                "a_deg": [_r(lo), _r(hi)],
                "n": len(a_deg),
                "mean_deg": _r(float(np.nanmean(e_deg))),
                "rms_mm": _r(float(np.sqrt(np.mean(dist_mm**2)))),
            }
        ]
    edges = np.linspace(lo, hi, N_ANGLE_BINS + 1)
    which = np.clip(np.searchsorted(edges, a_deg, side="right") - 1, 0, N_ANGLE_BINS - 1)
    out = []
    for b in range(N_ANGLE_BINS):
        sel = which == b
        if not sel.any():
            continue
        e = e_deg[sel]
        out.append(
            {
                "a_deg": [_r(float(edges[b])), _r(float(edges[b + 1]))],
                "n": int(sel.sum()),
                "mean_deg": _r(float(np.nanmean(e))) if np.isfinite(e).any() else None,
                "rms_mm": _r(float(np.sqrt(np.mean(dist_mm[sel] ** 2)))),
            }
        )
    return out


def _regions(xyz_mm: FloatArray, dist_mm: FloatArray) -> list[dict[str, Any]]:
    med = np.median(xyz_mm, axis=0)
    high = xyz_mm > med
    code = high[:, 0] * 4 + high[:, 1] * 2 + high[:, 2] * 1
    out = []
    for c in range(8):
        sel = code == c
        if not sel.any():
            continue
        name = " ".join(f"{ax}{'+' if (c >> (2 - k)) & 1 else '-'}" for k, ax in enumerate("xyz"))
        out.append(
            {
                "region": name,
                "n": int(sel.sum()),
                "centre_mm": [_r(float(v), 6) for v in xyz_mm[sel].mean(axis=0)],
                "rms_mm": _r(float(np.sqrt(np.mean(dist_mm[sel] ** 2)))),
                "max_mm": _r(float(dist_mm[sel].max())),
            }
        )
    return out


def locate(
    obs: MeasuredRows,
    mass: MassModel,
    steps: Sequence[Step],
    baseline: Baseline,
    problem: Callable[[FitResult, Sequence[str]], LinearProblem],
    joint_names: dict[int, list[str]],
) -> dict[str, Any]:
    """The ``where`` section of the diagnosis (see the module docstring).

    ``obs`` are all rows, ``steps`` the ladder (the first is the geometric step), ``problem`` the
    linear problem on the fit rows at a fit with extra columns, ``joint_names`` the effect
    parameters each joint's share is measured with.
    """
    geo = steps[0].fit
    resid, jac = linearize(mass, geo.params, geo.effects, [], obs)
    dist = np.linalg.norm(resid, axis=1)
    jac_theta = jac[:, :, 0:30:5]
    e_deg = equivalent_joint_error_deg(resid, jac_theta)
    lp = problem(geo, [n for j in sorted(joint_names) for n in joint_names[j]])
    n_geo = len(lp.col_norm) - sum(len(v) for v in joint_names.values())
    base_cols = list(range(n_geo))
    sse_geo = lp.sse(base_cols)
    per_joint = []
    pos = n_geo
    for j in range(1, 7):
        names = joint_names.get(j, [])
        cols = list(range(pos, pos + len(names)))
        pos += len(names)
        share = 100.0 * (1.0 - lp.sse(base_cols + cols) / sse_geo) if names and sse_geo > 0 else 0.0
        e = e_deg[:, j - 1]
        entry: dict[str, Any] = {
            "joint": j,
            "equivalent_rms_deg": _r(float(np.sqrt(np.nanmean(e**2)))) if np.isfinite(e).any() else None,
            "share_pct": round(share, 2),
            "vs_angle": _angle_bins(obs.a_deg[:, j - 1], e, dist),
        }
        if obs.dir is not None:
            by_dir: dict[str, Any] = {}
            for sign, key in ((1.0, "plus"), (-1.0, "minus")):
                sel = obs.dir[:, j - 1] == sign
                by_dir[key] = {
                    "n": int(sel.sum()),
                    "mean_deg": _r(float(np.nanmean(e[sel])))
                    if sel.any() and np.isfinite(e[sel]).any()
                    else None,
                    "rms_mm": _r(float(np.sqrt(np.mean(dist[sel] ** 2)))) if sel.any() else None,
                }
            plus, minus = by_dir["plus"]["mean_deg"], by_dir["minus"]["mean_deg"]
            by_dir["step_deg"] = None if plus is None or minus is None else _r(plus - minus)
            entry["vs_dir"] = by_dir
        per_joint.append(entry)
    regions = _regions(obs.xyz_mm, dist)
    axis_rms = np.sqrt(np.mean(resid**2, axis=0))
    out: dict[str, Any] = {
        "after": "geometric",
        "rows": "all",
        "axis_rms_mm": {ax: _r(float(v)) for ax, v in zip("xyz", axis_rms, strict=True)},
        "rms_mm": _r(float(np.sqrt(np.mean(dist**2)))),
        "joints": implicated_joints(steps),
        "per_joint": per_joint,
        "regions": regions,
    }
    out["summary"] = _summary(steps, baseline, out)
    return out


def _axes(joints: Sequence[int]) -> str:
    names = [f"A{j}" for j in joints]
    if not names:
        return "the structure"
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def signed_pct(value: float) -> str:
    """A signed percentage with one true minus sign: ``−6 %``, ``+4 %``, ``0 %``."""
    text = f"{abs(value):.0f}"
    if text == "0":
        return "0 %"
    return f"{'−' if value < 0 else '+'}{text} %"


def _fmt(mm: float) -> str:
    return f"{mm:.3f} mm"


def _floor_words(floor: float | None, source: str | None) -> str:
    if floor is None:
        return (
            ", and no noise floor is known (no repeated poses, no second target on the flange, no "
            "declared tracker uncertainty): "
            "the remainder could not be compared with noise."
        )
    return f", against a noise floor of {_fmt(floor)} ({source})."


def _left_words(left: float, floor: float | None, structured: bool, any_effect: bool) -> str:
    """What the remainder is: at the noise, above it, or not comparable with it."""
    further = "no further effect of the vocabulary" if any_effect else "no effect of the vocabulary"
    if floor is None:
        if structured:
            return f"{further.capitalize()} is significant; what is left is {_fmt(left)}."
        return (
            f"{further.capitalize()} is significant; what is left ({_fmt(left)}) could not be compared "
            "with noise: measure some poses several times, put several targets on the flange or declare "
            "the tracker's uncertainty."
        )
    if left <= 1.25 * floor:
        if any_effect:
            return f"What is left ({_fmt(left)}) is at the noise floor."
        return (
            "No non-geometric effect is significant and the remaining error is at the noise floor: "
            "a kinematic calibration is all this robot needs for these data."
        )
    return (
        f"What is left ({_fmt(left)}) is above the noise floor, but {further} is significant: "
        "look for an effect outside it (fixture, tracker set-up, dynamics)"
        + ("." if any_effect else " or measure more poses, directions, payloads or temperatures.")
    )


def _summary(steps: Sequence[Step], baseline: Baseline, where: dict[str, Any]) -> str:
    geo = steps[0]
    floor = baseline.noise_floor_mm
    parts = [
        f"The nominal twin misses the check points by {_fmt(baseline.check_rms_mm)} RMS "
        f"(max {_fmt(baseline.check_max_mm)}); geometric calibration "
        f"({geo.n_params} identifiable parameters) brings that to {_fmt(geo.check_rms_mm)} "
        f"(max {_fmt(geo.check_max_mm)})" + _floor_words(floor, baseline.noise_floor_source)
    ]
    axis = where["axis_rms_mm"]
    worst_axis = max(axis, key=lambda k: axis[k])
    worst_region = max(where["regions"], key=lambda r: r["rms_mm"]) if where["regions"] else None
    gap = f"The gap left after it is largest along {worst_axis} ({_fmt(axis[worst_axis])} RMS)"
    if worst_region is not None:
        gap += f" and in the region {worst_region['region']} ({_fmt(worst_region['rms_mm'])} RMS)"
    parts.append(gap + ".")
    effect_steps = [s for s in steps if s.significant and s.effect != "geometric"]
    if effect_steps:
        described = []
        for s in effect_steps:
            on = f" on {_axes(s.joints)}" if s.joints else ""
            described.append(
                f"{s.effect}{on} (check error {signed_pct(-s.shrink_pct)} to {_fmt(s.check_rms_mm)})"
            )
        parts.append("It is explained by " + "; then ".join(described) + ".")
    left = final_step(steps).check_rms_mm
    structured = "follows" in baseline.structure
    parts.append(_left_words(left, floor, structured, bool(effect_steps)))
    if baseline.structure:
        parts.append(baseline.structure)
    if baseline.disagreement:
        parts.append(baseline.disagreement)
    elif effect_steps:
        actions = [effect_by_name(s.effect).action.format(axes=_axes(s.joints)) for s in effect_steps]
        parts.append("To act: " + "; ".join(actions) + ".")
    skipped = [s for s in baseline.skipped if "combination" not in s["reason"]]
    if skipped:
        notes = "; ".join(f"{s['effect']}: {s['reason']}" for s in skipped[:3])
        parts.append(f"Not tested for lack of data — {notes}.")
    return " ".join(parts)
