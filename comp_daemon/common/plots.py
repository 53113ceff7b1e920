"""Figures for the HTML reports, drawn by matplotlib and embedded as inline SVG.

Every report figure is a :class:`matplotlib.figure.Figure` made by :func:`new_figure` (an Agg
canvas, never pyplot, so no GUI backend is loaded), drawn by a function wrapped in
:func:`styled` (the report style; one figure at a time, from any thread) and turned into one
``<figure>`` element by :func:`figure_html`: the SVG inline, text kept as text,
no external resource, no script. Element ids inside each SVG are prefixed with the plot's id
and matplotlib's hashed ids are salted with it, so several figures share one page without id
clashes and the same data gives the same bytes (tests compare structure, not pixels).

A panel that has nothing finite to draw says so (:func:`no_data`) instead of failing.
"""

from __future__ import annotations

import functools
import html
import io
import re
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, ParamSpec, TypeVar

import numpy as np
from matplotlib import rc_context
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "PALETTE",
    "RASTER_ABOVE",
    "figure_html",
    "finite_xy",
    "has_finite",
    "legend_if_labelled",
    "new_figure",
    "no_data",
    "plot_style",
    "shared_limits",
    "styled",
]

PALETTE = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#17becf", "#7f7f7f")

STYLE: dict[Any, Any] = {  # rc keys (matplotlib types them as literals)
    "font.family": "sans-serif",
    "font.size": 8.5,
    "axes.titlesize": 9,
    "axes.titleweight": "bold",
    "axes.labelsize": 8.5,
    "axes.grid": True,
    "grid.color": "#e6e6e6",
    "grid.linewidth": 0.6,
    "axes.edgecolor": "#888888",
    "axes.linewidth": 0.8,
    "legend.fontsize": 7.5,
    "legend.frameon": False,
    "legend.markerscale": 2.0,
    "xtick.labelsize": 7.5,
    "ytick.labelsize": 7.5,
    "svg.fonttype": "none",
    "figure.dpi": 100,
}

#: scatter layers with more points than this are embedded as pixels (PNG inside the SVG), so a
#: report of thousands of poses stays small; axes, lines and text stay vector
RASTER_ABOVE = 150
RASTER_DPI = 120

_ID = re.compile(r"[^A-Za-z0-9_-]")
# matplotlib's rcParams are global: figures are drawn one at a time, whichever thread asks
_LOCK = threading.RLock()
P = ParamSpec("P")
R = TypeVar("R")


@contextmanager
def plot_style(plot_id: str | None = None) -> Iterator[None]:
    """The report style (SVG ids salted by ``plot_id`` for repeatable output), held by one thread."""
    extra: dict[Any, Any] = {} if plot_id is None else {"svg.hashsalt": plot_id}
    with _LOCK, rc_context({**STYLE, **extra}):
        yield


def styled(draw: Callable[P, R]) -> Callable[P, R]:
    """Run a figure-drawing function in the report style (rcParams are read as artists are made)."""

    @functools.wraps(draw)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        with plot_style():
            return draw(*args, **kwargs)

    return wrapper


def new_figure(
    width_in: float, height_in: float, nrows: int = 1, ncols: int = 1
) -> tuple[Figure, list[Axes]]:
    """A figure on an Agg canvas with ``nrows × ncols`` axes (returned flat, row by row)."""
    with plot_style():
        fig = Figure(figsize=(width_in, height_in), layout="constrained")
        FigureCanvasAgg(fig)
        axes = fig.subplots(nrows, ncols, squeeze=False)
    return fig, [ax for row in axes for ax in row]


def finite_xy(x: ArrayLike, y: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The pairs of ``x`` and ``y`` that are both finite."""
    xa = np.asarray(x, dtype=float).ravel()
    ya = np.asarray(y, dtype=float).ravel()
    ok = np.isfinite(xa) & np.isfinite(ya)
    return xa[ok], ya[ok]


def no_data(ax: Axes, why: str, title: str | None = None) -> None:
    """Turn ``ax`` into a panel that says there is nothing to draw, and why."""
    ax.clear()
    ax.set_xticks([])
    ax.set_yticks([])
    ax.grid(False)
    ax.set_facecolor("#fafafa")
    if title:
        ax.set_title(title)
    ax.text(0.5, 0.5, f"no data: {why}", ha="center", va="center", color="#777777", wrap=True,
            transform=ax.transAxes)  # fmt: skip


def has_finite(*arrays: ArrayLike) -> bool:
    """Whether every array has at least one finite value."""
    return all(np.isfinite(np.asarray(a, dtype=float)).any() for a in arrays)


def _svg_text(fig: Figure, plot_id: str) -> str:
    buf = io.StringIO()
    with plot_style(plot_id):
        fig.savefig(
            buf,
            format="svg",
            dpi=RASTER_DPI,
            metadata={"Date": None, "Creator": None, "Format": None, "Type": None},
        )
    text = buf.getvalue()
    text = text[text.index("<svg") :]
    text = text.replace(' xmlns:xlink="http://www.w3.org/1999/xlink"', "").replace("xlink:href=", "href=")
    text = text.replace(' id="', f' id="{plot_id}-').replace("url(#", f"url(#{plot_id}-")
    text = text.replace('href="#', f'href="#{plot_id}-')
    text = re.sub(
        r'<svg width="([\d.]+)pt" height="([\d.]+)pt"',
        lambda m: (
            f'<svg width="{float(m[1]) * 4 / 3:.0f}" height="{float(m[2]) * 4 / 3:.0f}" '
            'style="max-width:100%;height:auto" role="img"'
        ),
        text,
        count=1,
    )
    return text.strip()


def figure_html(fig: Figure, plot_id: str, caption: str, *, label: str | None = None) -> str:
    """``fig`` as ``<figure id="plot-…">`` with the SVG inline and ``caption`` below it.

    ``label`` (default: the caption) is the SVG's accessible name."""
    pid = "plot-" + _ID.sub("-", plot_id)
    svg = _svg_text(fig, pid)
    svg = svg.replace(' role="img"', f' role="img" aria-label="{html.escape(label or caption)}"', 1)
    fig.clear()
    return f'<figure class=plot id="{pid}">{svg}<figcaption>{html.escape(caption)}</figcaption></figure>'


def legend_if_labelled(ax: Axes, **kwargs: Any) -> None:
    """A legend when ``ax`` has labelled artists (none otherwise)."""
    handles, labels = ax.get_legend_handles_labels()
    if labels:
        ax.legend(handles, labels, **kwargs)


def shared_limits(values: Sequence[NDArray[np.float64]]) -> tuple[float, float] | None:
    """The common finite range of several arrays, or ``None`` when none has a finite value."""
    finite = [v[np.isfinite(v)] for v in values]
    finite = [v for v in finite if v.size]
    if not finite:
        return None
    return float(min(v.min() for v in finite)), float(max(v.max() for v in finite))
