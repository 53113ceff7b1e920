"""The trial report's figures (matplotlib, inline SVG through :mod:`comp_daemon.common.plots`).

Plot ids (each figure is ``<figure id="plot-ID">``):

``error-histogram``
    frequency of the 3-D error of the target points, one colour per method, shared bins
    (seed 000 Fig. 11);
``error-histogram-per-method``
    the same counts as one panel per method (every run of Table 2), mean and max in the title;
``point-errors-x``, ``-y``, ``-z``, ``-3d``
    the error x, y, z and 3-D of every target point in visiting order, per method (Figs 7–10);
``iso9283``
    vAP and RP per ISO 9283 test point without and with joint feedback (Fig. 6).

A figure with nothing finite to draw shows a "no data" panel.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from comp_daemon.common.plots import (
    figure_html,
    figure_legend,
    finite_xy,
    legend_if_labelled,
    new_figure,
    no_data,
    styled,
)
from comp_daemon.trial.result import TrialResult
from comp_daemon.trial.stats import histogram

__all__ = [
    "COLORS",
    "error_histogram_figure",
    "iso_figure",
    "method_histograms_figure",
    "point_error_figures",
]

COLORS = {
    "uncompensated": "#c0392b",
    "kinematic": "#e67e22",
    "feedback": "#8e44ad",
    "kinematic+feedback": "#2980b9",
    "chebyshev+feedback": "#27ae60",
    "chebyshev-seed000+feedback": "#16a085",
}
OTHER = "#555555"


def _errors_3d(result: TrialResult, keys: Sequence[str]) -> dict[str, np.ndarray]:
    out = {}
    for k in keys:
        e = np.linalg.norm(result.runs[k].errors_mm(), axis=1)
        out[k] = e[np.isfinite(e)]
    return out


@styled
def error_histogram_figure(result: TrialResult, keys: Sequence[str]) -> str:
    """Grouped bars per bin: share of the target points of each method (seed 000 Fig. 11)."""
    fig, (ax,) = new_figure(7.9, 3.1)
    title = "Frequency of the 3-D positioning error of the target points"
    errs = {k: v for k, v in _errors_3d(result, keys).items() if v.size}
    if not errs:
        no_data(ax, "no target point was measured", title)
    else:
        h = histogram(errs)
        edges = np.asarray(h["edges_mm"], dtype=float)
        centres = 0.5 * (edges[:-1] + edges[1:])
        width = float(edges[1] - edges[0])
        slot = 0.85 * width / len(errs)
        for i, k in enumerate(errs):
            share = 100.0 * np.asarray(h["share"][k], dtype=float)
            x = centres - 0.425 * width + (i + 0.5) * slot
            ax.bar(x, share, width=slot, color=COLORS.get(k, OTHER), label=result.runs[k].label)
        ax.set_xticks(edges)
        ax.tick_params(axis="x", labelrotation=45 if len(edges) > 10 else 0)
        ax.set_xlim(edges[0], edges[-1])
        ax.set_xlabel("3-D error (mm)")
        ax.set_ylabel("share of target points (%)")
        ax.grid(axis="x", visible=False)
        ax.set_title(title)
        legend_if_labelled(ax)
    return figure_html(
        fig,
        "error-histogram",
        "Frequency of the 3-D positioning error of the target points (seed 000 Fig. 11): share of "
        "the points per bin, one colour per method.",
    )


@styled
def method_histograms_figure(result: TrialResult, keys: Sequence[str]) -> str:
    """One histogram panel per method (every row of Table 2) on shared bins and axes."""
    n = max(1, len(keys))
    ncols = min(3, n)
    nrows = -(-n // ncols)
    fig, axes = new_figure(10.0, 2.3 * nrows + 0.3, nrows, ncols)
    errs = _errors_3d(result, keys)
    filled = {k: v for k, v in errs.items() if v.size}
    h = histogram(filled) if filled else None
    top = max((max(c) for c in h["counts"].values()), default=1) if h else 1
    for i, ax in enumerate(axes):
        if not keys:
            no_data(ax, "the trial has no run with a measured target point", "3-D error per method")
            continue
        if i >= len(keys):
            ax.set_visible(False)
            continue
        k = keys[i]
        run = result.runs[k]
        if h is None or k not in filled:
            no_data(ax, "no target point of this run was measured", run.label)
            continue
        edges = np.asarray(h["edges_mm"], dtype=float)
        ax.stairs(h["counts"][k], edges, fill=True, color=COLORS.get(k, OTHER), alpha=0.8)
        e = filled[k]
        ax.set_title(f"{run.label}\nmean {e.mean():.3f}, max {e.max():.3f} mm", fontsize=8)
        ax.set_xlim(edges[0], edges[-1])
        ax.set_ylim(0, top * 1.1)
        ax.set_xlabel("3-D error (mm)")
        ax.set_ylabel("target points")
    return figure_html(
        fig,
        "error-histogram-per-method",
        "3-D error of the target points, one histogram per method of Table 2 (shared bins).",
    )


@styled
def point_error_figures(result: TrialResult, keys: Sequence[str]) -> str:
    """Error x, y, z and 3-D of every target point in visiting order, one line per method: four
    figures (``point-errors-x``, ``-y``, ``-z``, ``-3d``)."""
    out = []
    for name, col in (("x", 0), ("y", 1), ("z", 2), ("3-D", None)):
        fig, (ax,) = new_figure(9.0, 2.6)
        title = f"error {name} per target point" + (" (eq. 27)" if col is None else "")
        drawn = False
        for k in keys:
            run = result.runs[k]
            e = run.measured_mm - run.wanted_mm
            y = np.linalg.norm(e, axis=1) if col is None else e[:, col]
            y = np.where(run.ok, y, np.nan)
            x = np.arange(1, run.n + 1, dtype=float)
            if finite_xy(x, y)[0].size:
                ax.plot(x, y, lw=1.2, color=COLORS.get(k, OTHER), label=run.label)
                drawn = True
        if not drawn:
            no_data(ax, "no target point was measured", title)
        else:
            ax.set_title(title)
            ax.set_xlabel("target point (visiting order)")
            ax.set_ylabel("mm")
            if col is not None:
                ax.axhline(0.0, color="#bbbbbb", lw=0.8)
            figure_legend(fig, ncols=3)
        out.append(
            figure_html(
                fig,
                "point-errors-" + ("3d" if col is None else name),
                f"Error {name} (tracker − wanted TCP, robot base frame) of every target point in visiting "
                "order (seed 000 Figs 7–10); a gap is a target that did not finish.",
            )
        )
    return "".join(out)


@styled
def iso_figure(result: TrialResult) -> str:
    """vAP per test point without and with joint feedback, and the largest RP (seed 000 Fig. 6)."""
    runs = result.iso.get("runs", {})
    without = runs.get("without", {}).get("stats")
    with_ = runs.get("with", {}).get("stats")
    fig, (ax,) = new_figure(7.9, 3.0)
    title = "ISO 9283: vAP and RP per test point"
    series: list[tuple[str, list[float], str]] = []
    if without is not None:
        series.append(("vAP, robot alone", without["vap_mm"], "#c0392b"))
    if with_ is not None:
        series.append(("vAP, with joint feedback", with_["vap_mm"], "#27ae60"))
    if without is not None:
        series.append(("RP (largest direction), robot alone", without["rp_max_mm"], "#7f8c8d"))
    if with_ is not None:
        series.append(("RP, with joint feedback", with_["rp_max_mm"], "#bdc3c7"))
    n = max((len(v) for _, v, _ in series), default=0)
    if n == 0:
        no_data(ax, "the ISO 9283 test did not run", title)
    else:
        pos = np.arange(n, dtype=float)
        width = 0.8 / len(series)
        for i, (label, vals, color) in enumerate(series):
            v = np.full(n, np.nan)
            v[: len(vals)] = np.asarray(vals, dtype=float)
            bars = ax.bar(pos - 0.4 + (i + 0.5) * width, v, width=width, color=color, label=label)
            ax.bar_label(bars, fmt="%.3f", fontsize=6.5, padding=1)
        ax.set_xticks(pos, [f"P{i + 1}" for i in range(n)])
        ax.set_ylabel("mm")
        ax.grid(axis="x", visible=False)
        ax.set_title(title)
        ax.margins(y=0.15)
        legend_if_labelled(ax)
    return figure_html(
        fig,
        "iso9283",
        "ISO 9283 vAP and RP per test point, robot alone and with joint feedback (seed 000 Fig. 6), mm.",
    )
