"""The diagnosis report's figures (matplotlib, inline SVG through :mod:`comp_daemon.common.plots`).

:func:`report_figures` computes what the figures show from a :class:`Diagnosis` and returns
one HTML ``<figure>`` per plot id:

``ladder``
    check RMS after each step of the ladder (log scale), the noise floor as a dashed line;
``effect-step-K``
    per added effect (step K), the residual before that step per axis (x, y, z) against the
    variable that drives the effect, with the effect's fitted contribution over it;
``geometric-order``
    with no effect beyond geometry, the residual after the geometric step per axis in row order;
``joint-error``
    per joint, the equivalent joint error of the post-geometric residual against the axis value,
    by approach direction, with the fitted effects' share;
``check-histogram``
    the 3-D check error before and after geometry (and after the effects);
``residual-pose``
    the remaining 3-D error per pose (fit and check rows);
``residual-joint``
    the remaining error (x, y, z) against each axis value, one panel per joint;
``variogram``
    Matheron's empirical semivariogram of the remaining error against the joint-space distance;
``remainder-time``
    the remaining error against the campaign clock (``t_s`` hours, or row order);
``predicted-measured``
    the measured deviation from the nominal twin against the model's prediction of it.

"Remaining" is after the last significant step (the geometric one when no effect is). The
drawing functions take plain arrays; a panel with nothing finite says "no data".
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.axes import Axes
from numpy.typing import NDArray

from comp_daemon.common.plots import (
    RASTER_ABOVE,
    figure_html,
    figure_legend,
    finite_xy,
    legend_if_labelled,
    new_figure,
    no_data,
    readable_log_axis,
    shared_limits,
    styled,
)
from comp_daemon.diagnosis.fitting import linearize, predict_mm
from comp_daemon.diagnosis.result import Diagnosis, Step
from comp_daemon.diagnosis.where import equivalent_joint_error_deg
from comp_daemon.estimation.variogram import empirical_semivariogram
from comp_daemon.models.effects import MassModel, effect_by_name, twin_inputs_of

__all__ = [
    "check_histogram_figure",
    "effect_figure",
    "joint_error_figure",
    "ladder_figure",
    "predicted_measured_figure",
    "remainder_time_figure",
    "report_figures",
    "residual_joint_figure",
    "residual_pose_figure",
    "variogram_figure",
]

FloatArray = NDArray[np.float64]
GREY, RED, BLUE, DARK, GREEN, ORANGE = "#8a8a8a", "#d62728", "#1f77b4", "#222222", "#2ca02c", "#ff7f0e"
AXIS_COLORS = {"x": "#1f77b4", "y": "#ff7f0e", "z": "#2ca02c", "3-D": "#222222"}
VARIOGRAM_MAX_POINTS = 1500  # pairs grow as n²: evenly spaced rows beyond this


def _scatter(ax: Axes, x: FloatArray, y: FloatArray, **kwargs: object) -> bool:
    xs, ys = finite_xy(x, y)
    if xs.size == 0:
        return False
    size = kwargs.pop("s", 7)
    ax.scatter(xs, ys, s=size, linewidths=0, rasterized=xs.size > RASTER_ABOVE, **kwargs)  # type: ignore[arg-type]
    return True


@styled
def ladder_figure(
    labels: Sequence[str],
    values: Sequence[float],
    significant: Sequence[bool],
    floor_mm: float | None,
    floor_source: str | None,
) -> str:
    """Check RMS per ladder step on a log scale; grey bars: not significant; dashed: noise floor."""
    vals = np.asarray(values, dtype=float)
    fig, (ax,) = new_figure(max(7.5, 1.3 * len(labels)), 2.9)
    # long step names ("geometric J1,2,3,4,5") stand slanted so that they do not run into each other
    slanted = len(labels) > 5 or sum(len(label) for label in labels) > 6 * len(labels)
    title = "Check RMS after each step"
    ok = np.isfinite(vals) & (vals > 0)
    if not ok.any():
        no_data(ax, "no step has a finite, positive check RMS", title)
    else:
        colors = [GREY] + [GREEN if s else "#cccccc" for s in significant]
        pos = np.arange(len(vals))
        ax.bar(pos[ok], vals[ok], color=[c for c, k in zip(colors, ok, strict=True) if k], width=0.7)
        for p, v in zip(pos[ok], vals[ok], strict=True):
            ax.annotate(f"{v:.4g}", (p, v), ha="center", va="bottom", fontsize=7, xytext=(0, 2),
                        textcoords="offset points")  # fmt: skip
        ax.set_yscale("log")
        ax.set_xticks(
            pos,
            list(labels),
            rotation=20 if slanted else 0,
            ha="right" if slanted else "center",
        )
        ax.grid(axis="x", visible=False)
        if floor_mm is not None and floor_mm > 0:
            ax.axhline(
                floor_mm, color=RED, ls="--", lw=1.2, label=f"noise floor {floor_mm:.4f} mm ({floor_source})"
            )
            legend_if_labelled(ax)
        readable_log_axis(ax)
        ax.set_ylabel("check RMS (mm, log)")
        ax.set_title(title)
    floor = (
        f"dashed: noise floor {floor_mm:.4f} mm ({floor_source})"
        if floor_mm is not None
        else "no noise floor known (no repeats, no second target, no declared tracker uncertainty)"
    )
    return figure_html(
        fig, "ladder", f"Check RMS after each step (mm, log scale); light grey: not significant; {floor}."
    )


@styled
def effect_figure(
    k: int,
    heading: str,
    x: FloatArray,
    xlabel: str,
    before: FloatArray,
    added: FloatArray,
    effect: str,
    *,
    as_line: bool,
) -> str:
    """Residual before step ``k`` per axis against the effect's driver, the effect's contribution over it."""
    fig, axes = new_figure(10.5, 2.9, 1, 3)
    order = np.argsort(np.where(np.isfinite(x), x, np.inf), kind="stable")
    driver = xlabel.split(" (")[0]  # the unit and any note stay in the axis label
    for axis, (ax, name) in enumerate(zip(axes, "xyz", strict=True)):
        title = f"{name}: residual vs {driver}"
        if not _scatter(ax, x, before[:, axis], color=GREY, alpha=0.55, label="residual before the step"):
            no_data(ax, "no finite residual against this driver", title)
            continue
        xs, ys = finite_xy(x[order], added[order, axis])
        if as_line:
            ax.plot(xs, ys, color=RED, lw=1.6, label=f"{effect} contribution")
        else:
            _scatter(ax, xs, ys, s=5, color=RED, alpha=0.9, label=f"{effect} contribution")
        ax.set_title(title)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(f"{name} (mm)")
    figure_legend(fig)
    return figure_html(
        fig,
        f"effect-step-{k}",
        f"Step {k}: {heading}: residual per axis before the step, and the fitted contribution.",
    )


@styled
def geometric_order_figure(resid: FloatArray) -> str:
    """The residual after the geometric step per axis, in campaign (row) order."""
    fig, axes = new_figure(10.5, 2.7, 1, 3)
    rows = np.arange(len(resid), dtype=float)
    for axis, (ax, name) in enumerate(zip(axes, "xyz", strict=True)):
        title = f"{name}: residual after geometric, in campaign order"
        if not _scatter(ax, rows, resid[:, axis], color=GREY, alpha=0.6):
            no_data(ax, "no finite residual", title)
            continue
        ax.set_title(title)
        ax.set_xlabel("row")
        ax.set_ylabel(f"{name} (mm)")
    return figure_html(
        fig, "geometric-order", "Residual after the geometric step per axis, in campaign order."
    )


@styled
def joint_error_figure(
    a_deg: FloatArray,
    e_resid: FloatArray,
    e_model: FloatArray | None,
    dirs: FloatArray | None,
    shares: dict[int, float],
) -> str:
    """Per joint, the equivalent joint error against the axis value (colours: approach direction)."""
    fig, axes = new_figure(10.5, 5.6, 2, 3)
    for j, ax in enumerate(axes, start=1):
        a, e = a_deg[:, j - 1], e_resid[:, j - 1]
        title = f"Joint {j}: equivalent error vs A{j} (share {shares.get(j, 0.0):.0f} %)"
        if not np.isfinite(e).any():
            no_data(ax, f"joint {j}'s error is not identifiable from these poses", title)
            continue
        if dirs is not None:
            for sign, color, label in ((1.0, RED, "approach +1"), (-1.0, BLUE, "approach −1")):
                sel = dirs[:, j - 1] == sign
                _scatter(ax, a[sel], e[sel], color=color, alpha=0.45, label=label)
        else:
            _scatter(ax, a, e, color=GREY, alpha=0.45, label="residual")
        if e_model is not None:
            _scatter(ax, a, e_model[:, j - 1], s=4, color=DARK, alpha=0.9, label="fitted effects")
        ax.set_title(title, fontsize=8)
        ax.set_xlabel(f"A{j} (deg)")
        ax.set_ylabel("equivalent joint error (deg)")
    figure_legend(fig)
    return figure_html(
        fig,
        "joint-error",
        "Per joint: the angle joint j alone would have to be off by to explain each pose's residual "
        "after the geometric step; colours give the approach direction, dark points what the fitted "
        "effects account for.",
    )


@styled
def check_histogram_figure(panels: Sequence[tuple[str, Sequence[tuple[str, FloatArray, str]]]]) -> str:
    """Overlaid histograms of the 3-D check error, one panel per (title, [(label, errors, colour)])."""
    fig, axes = new_figure(5.2 * len(panels), 2.9, 1, len(panels))
    for ax, (title, groups) in zip(axes, panels, strict=True):
        data = [np.asarray(v, dtype=float)[np.isfinite(v)] for _, v, _ in groups]
        top = max((float(d.max()) for d in data if d.size), default=0.0)
        if top <= 0.0:
            no_data(ax, "no finite check error", title)
            continue
        edges = np.linspace(0.0, top * 1.02, 31)
        for (label, _, color), d in zip(groups, data, strict=True):
            ax.hist(d, bins=edges.tolist(), histtype="stepfilled", color=color, alpha=0.2)
            ax.hist(
                d,
                bins=edges.tolist(),
                histtype="step",
                color=color,
                lw=1.4,
                label=f"{label} (RMS {np.sqrt(np.mean(d**2)) if d.size else np.nan:.3f})",
            )
        ax.set_title(title)
        ax.set_xlabel("3-D error (mm)")
        ax.set_ylabel("poses")
        legend_if_labelled(ax)
    return figure_html(
        fig,
        "check-histogram",
        "3-D error of the check rows before and after calibration (RMS in the legend, mm).",
    )


@styled
def residual_pose_figure(resid: FloatArray, check: NDArray[np.bool_], after: str) -> str:
    """The remaining 3-D error per pose in row order, fit rows and check rows apart."""
    fig, (ax,) = new_figure(10.5, 2.8)
    norm = np.linalg.norm(resid, axis=1) if resid.size else np.zeros(0)
    rows = np.arange(len(norm), dtype=float)
    title = f"3-D residual per pose after {after}"
    drawn = False
    for sel, color, label in ((~check, BLUE, "fit rows"), (check, ORANGE, "check rows")):
        xs, ys = finite_xy(rows[sel], norm[sel])
        if xs.size:
            ax.vlines(xs, 0.0, ys, color=color, lw=0.8, alpha=0.8, rasterized=xs.size > RASTER_ABOVE)
            _scatter(ax, xs, ys, s=6, color=color, label=label)
            drawn = True
    if not drawn:
        no_data(ax, "no finite residual", title)
    else:
        ax.set_title(title)
        ax.set_xlabel("pose (row)")
        ax.set_ylabel("3-D residual (mm)")
        ax.set_ylim(bottom=0.0)
        legend_if_labelled(ax)
    return figure_html(fig, "residual-pose", f"Remaining 3-D error of every pose after {after} (mm).")


@styled
def residual_joint_figure(a_deg: FloatArray, resid: FloatArray, after: str) -> str:
    """The remaining error per axis (x, y, z) against each joint's angle, one panel per joint."""
    fig, axes = new_figure(10.5, 5.6, 2, 3)
    lim = shared_limits([resid[:, i] for i in range(resid.shape[1])]) if resid.ndim == 2 else None
    for j, ax in enumerate(axes, start=1):
        title = f"residual vs A{j}"
        a = a_deg[:, j - 1] if a_deg.ndim == 2 and a_deg.shape[1] >= j else np.zeros(0)
        drawn = False
        for axis, name in enumerate("xyz"):
            if resid.ndim == 2 and resid.shape[1] > axis and a.size == len(resid):
                drawn |= _scatter(ax, a, resid[:, axis], s=5, color=AXIS_COLORS[name], alpha=0.55, label=name)
        if not drawn:
            no_data(ax, f"no finite residual against A{j}", title)
            continue
        ax.set_title(title)
        ax.set_xlabel(f"A{j} (deg)")
        ax.set_ylabel("residual (mm)")
        if lim is not None:
            pad = 0.05 * (lim[1] - lim[0] or 1.0)
            ax.set_ylim(lim[0] - pad, lim[1] + pad)
    figure_legend(fig)
    return figure_html(
        fig,
        "residual-joint",
        f"Remaining error per axis after {after} against each joint angle, one panel per joint (mm).",
    )


@styled
def variogram_figure(a_deg: FloatArray, resid: FloatArray, after: str, *, n_bins: int = 12) -> str:
    """Matheron's semivariogram (seed 001 eq. 12) of the remaining error per axis vs joint distance."""
    fig, (ax,) = new_figure(6.4, 3.2)
    title = f"Semivariogram of the residual after {after}"
    ok = np.isfinite(a_deg).all(axis=1) & np.isfinite(resid).all(axis=1) if len(resid) else np.zeros(0, bool)
    idx = np.flatnonzero(ok)
    note = ""
    if idx.size > VARIOGRAM_MAX_POINTS:
        idx = idx[np.linspace(0, idx.size - 1, VARIOGRAM_MAX_POINTS).round().astype(int)]
        note = f" ({VARIOGRAM_MAX_POINTS} evenly spaced rows of {int(ok.sum())})"
    vg = None
    if idx.size >= 3:
        try:
            vg = empirical_semivariogram(a_deg[idx], resid[idx], n_bins=n_bins)
        except ValueError:
            vg = None
    if vg is None or not np.isfinite(vg.gamma).any():
        no_data(ax, "fewer than 3 distinct poses with a finite residual", title)
    else:
        for c, name in enumerate("xyz"):
            lag, gam = finite_xy(vg.lag, vg.gamma[:, c])
            ax.plot(lag, gam, "o-", ms=3.5, lw=1.2, color=AXIS_COLORS[name], label=f"γ {name}")
        var = np.var(resid[idx], axis=0)
        for c, name in enumerate("xyz"):
            ax.axhline(var[c], color=AXIS_COLORS[name], ls=":", lw=0.9)
        ax.set_xlabel("joint-space distance (deg)")
        ax.set_ylabel("semivariance (mm²)")
        ax.set_ylim(bottom=0.0)
        ax.set_title(title)
        legend_if_labelled(ax)
    return figure_html(
        fig,
        "variogram",
        "Empirical semivariogram of the remaining error per axis against the Euclidean distance of "
        f"the axis values{note}, {n_bins} equal bins up to half the largest distance; dotted: each "
        "axis's variance. A curve rising from near zero means nearby poses share their error (what "
        "kriging can still take).",
    )


@styled
def remainder_time_figure(clock: FloatArray | None, clock_name: str, resid: FloatArray, after: str) -> str:
    """The remaining error per axis and in 3-D against the campaign clock (hours of ``t_s``, or row)."""
    fig, (ax,) = new_figure(10.5, 2.9)
    n = len(resid)
    t = np.arange(n, dtype=float) if clock is None or len(clock) != n else np.asarray(clock, dtype=float)
    xlabel = (
        "hours since the first pose (t_s)"
        if clock is not None and clock_name == "t_s"
        else "row (pose order)"
    )
    title = f"Residual after {after} against time"
    drawn = False
    if n:
        for axis, name in enumerate("xyz"):
            drawn |= _scatter(ax, t, resid[:, axis], s=5, color=AXIS_COLORS[name], alpha=0.5, label=name)
        drawn |= _scatter(
            ax, t, np.linalg.norm(resid, axis=1), s=5, color=AXIS_COLORS["3-D"], alpha=0.6, label="3-D"
        )
    if not drawn:
        no_data(ax, "no finite residual", title)
    else:
        ax.axhline(0.0, color="#bbbbbb", lw=0.8)
        ax.set_title(title)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("residual (mm)")
        legend_if_labelled(ax)
    return figure_html(fig, "remainder-time", f"Remaining error after {after} against {xlabel} (mm).")


@styled
def predicted_measured_figure(
    predicted: FloatArray, measured: FloatArray, check: NDArray[np.bool_], after: str
) -> str:
    """Measured deviation from the nominal twin against the model's predicted deviation, per axis."""
    fig, axes = new_figure(10.5, 3.3, 1, 3)
    for axis, (ax, name) in enumerate(zip(axes, "xyz", strict=True)):
        title = f"{name}: measured vs predicted"
        p = predicted[:, axis] if predicted.ndim == 2 and len(predicted) else np.zeros(0)
        m = measured[:, axis] if measured.ndim == 2 and len(measured) else np.zeros(0)
        drawn = False
        if p.size and p.size == m.size:
            drawn |= _scatter(ax, p[~check], m[~check], s=6, color=BLUE, alpha=0.5, label="fit rows")
            drawn |= _scatter(ax, p[check], m[check], s=6, color=ORANGE, alpha=0.7, label="check rows")
        if not drawn:
            no_data(ax, "no finite prediction and measurement", title)
            continue
        lim = shared_limits([p, m])
        if lim is not None:
            ax.plot(lim, lim, color=DARK, lw=0.9, ls="--", label="measured = predicted")
        ax.set_title(title)
        ax.set_xlabel(f"predicted {name} − nominal (mm)")
        ax.set_ylabel(f"measured {name} − nominal (mm)")
    figure_legend(fig)
    return figure_html(
        fig,
        "predicted-measured",
        f"Measured deviation from the nominal twin against the deviation the model after {after} "
        "predicts, per axis; the distance to the dashed line is the remaining error (mm).",
    )


def _driver(diag: Diagnosis, step: Step) -> tuple[FloatArray, str]:
    """The variable an effect depends on, per row, and its axis label (the catalogue's driver)."""
    inputs = twin_inputs_of(
        MassModel.from_robot(diag.robot),
        diag.baseline_fit.params,
        diag.obs,
        t_ref_c=diag.options.t_ref_c,
        step_at=diag.baseline_fit.effects.step_at,
    )
    return effect_by_name(step.effect).driver(inputs, step.joints[0] if step.joints else None)


def _effect_figures(diag: Diagnosis, preds: list[FloatArray]) -> list[str]:
    out = []
    for k, step in enumerate(diag.steps[1:], start=1):
        x, xlabel = _driver(diag, step)
        tag = "" if step.significant else " (not significant)"
        joints = (
            f" on joint{'s' if len(step.joints) > 1 else ''} {', '.join(map(str, step.joints))}"
            if step.joints
            else ""
        )
        smooth = effect_by_name(step.effect).smooth_driver and len(step.joints) == 1
        out.append(
            effect_figure(
                k + 1,
                f"{step.effect}{joints}{tag}",
                x,
                xlabel,
                diag.obs.xyz_mm - preds[k - 1],
                preds[k] - preds[k - 1],
                step.effect,
                as_line=smooth,
            )
        )
    return out


@styled
def report_figures(diag: Diagnosis) -> dict[str, str]:
    """Every figure of the report as HTML, by section: ``ladder``, ``effects`` (one or more
    figures), ``joints``, ``histograms``, ``residuals`` (per pose, per joint angle, variogram,
    against time, predicted vs measured)."""
    obs = diag.obs
    mass = MassModel.from_robot(diag.robot)
    preds = [predict_mm(mass, s.fit.params, s.fit.effects, obs) for s in diag.steps]
    final = max((k for k, s in enumerate(diag.steps) if s.significant), default=0)
    nominal = predict_mm(mass, diag.baseline_fit.params, diag.baseline_fit.effects, obs)
    after = "geometric calibration" if final == 0 else "the significant effects"
    resid = obs.xyz_mm - preds[final]
    check = np.zeros(len(obs), dtype=bool)
    check[diag.check_rows] = True

    labels = ["nominal"] + [
        f"{s.effect}{' J' + ','.join(map(str, s.joints)) if s.joints else ''}" for s in diag.steps
    ]
    ladder = ladder_figure(
        labels,
        [diag.baseline_check_rms_mm] + [s.check_rms_mm for s in diag.steps],
        [s.significant for s in diag.steps],
        diag.noise_floor_mm,
        diag.noise_floor_source,
    )
    effects = _effect_figures(diag, preds)
    if len(diag.steps) == 1:
        effects.append(geometric_order_figure(obs.xyz_mm - preds[0]))

    geo = diag.steps[0].fit
    lin_resid, jac = linearize(mass, geo.params, geo.effects, [], obs)
    jac_theta = jac[:, :, 0:30:5]
    shares = {int(p["joint"]): float(p["share_pct"]) for p in diag.where.get("per_joint", [])}
    joints = joint_error_figure(
        obs.a_deg,
        equivalent_joint_error_deg(lin_resid, jac_theta),
        equivalent_joint_error_deg(preds[final] - preds[0], jac_theta) if final > 0 else None,
        obs.dir,
        shares,
    )

    rows = diag.check_rows
    err_base = np.linalg.norm(obs.xyz_mm[rows] - nominal[rows], axis=1)
    err_geo = np.linalg.norm(obs.xyz_mm[rows] - preds[0][rows], axis=1)
    err_final = np.linalg.norm(obs.xyz_mm[rows] - preds[final][rows], axis=1)
    panels: list[tuple[str, Sequence[tuple[str, FloatArray, str]]]] = [
        (
            "before and after geometric calibration",
            [("nominal twin", err_base, GREY), ("after geometric", err_geo, BLUE)],
        )
    ]
    if final > 0:
        panels.append(
            (
                "before and after the effects",
                [("after geometric", err_geo, BLUE), ("after the significant effects", err_final, GREEN)],
            )
        )
    residuals = [
        residual_pose_figure(resid, check, after),
        residual_joint_figure(obs.a_deg, resid, after),
        variogram_figure(obs.a_deg, resid, after),
        remainder_time_figure(obs.clock, obs.clock_name, resid, after),
        predicted_measured_figure(preds[final] - nominal, obs.xyz_mm - nominal, check, after),
    ]
    return {
        "ladder": ladder,
        "effects": "<div class=grid>" + "".join(effects) + "</div>",
        "joints": joints,
        "histograms": check_histogram_figure(panels),
        "residuals": "".join(residuals),
    }
