"""Figures for the HTML reports, drawn by matplotlib and embedded as inline SVG.

Every report figure is a :class:`matplotlib.figure.Figure` made by :func:`new_figure` (an Agg
canvas, never pyplot, so no GUI backend is loaded), drawn by a function wrapped in
:func:`styled` (the report style; one figure at a time, from any thread; nested calls share the
outer one's style context) and turned into one ``<figure>`` element by :func:`figure_html`: the
SVG inline, text kept as text, no external resource, no script.

The figure is drawn once. Its margins are computed beforehand by :func:`fit_layout` from the
text the axes will carry (tick labels as the locators and formatters will make them, axis labels,
titles, offset texts, figure legends) instead of by a layout engine that draws every figure a
second time to measure it. Layers with many points are
embedded as pixels (``rasterized=True``, PNG at :data:`RASTER_DPI` inside the SVG).

Element ids inside each SVG are prefixed with the plot's id and matplotlib's hashed ids are
salted with it, so several figures share one page without id clashes and the same data gives
the same bytes (tests compare structure, not pixels).

A panel that has nothing finite to draw says so (:func:`no_data`) instead of failing.
"""

from __future__ import annotations

import functools
import gc
import html
import io
import math
import re
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, ParamSpec, TypeVar

import numpy as np
from matplotlib import rc_context, rcParams
from matplotlib.axes import Axes
from matplotlib.axis import Axis
from matplotlib.backend_bases import RendererBase
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cbook import is_math_text
from matplotlib.figure import Figure
from matplotlib.font_manager import FontProperties
from matplotlib.text import Text
from matplotlib.textpath import text_to_path
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "PALETTE",
    "RASTER_ABOVE",
    "figure_html",
    "figure_legend",
    "finite_xy",
    "fit_layout",
    "has_finite",
    "legend_if_labelled",
    "new_figure",
    "no_data",
    "plot_style",
    "readable_log_axis",
    "shared_limits",
    "styled",
]

#: room for a legend right of the frame, over its measured width (browser fonts differ)
LEGEND_SLACK = 1.12

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
    # titles sit at the top of their axes (raised by fit_layout above a y offset text) instead
    # of being placed by measuring every tick label once more at each draw
    "axes.titley": 1.0,
}

#: scatter layers with more points than this are embedded as pixels (PNG inside the SVG), so a
#: report of thousands of poses stays small; axes, lines and text stay vector
RASTER_ABOVE = 150
RASTER_DPI = 100  # about one pixel per CSS pixel at the figure's size on the page

_ID = re.compile(r"[^A-Za-z0-9_-]")
# matplotlib's rcParams are global: figures are drawn one at a time, whichever thread asks
_LOCK = threading.RLock()
_HELD = threading.local()  # how deep this thread is inside plot_style
P = ParamSpec("P")
R = TypeVar("R")
#: space around the figure and between the panels' decorations (inches)
PAD_IN = 3 / 72


@contextmanager
def plot_style(plot_id: str | None = None) -> Iterator[None]:
    """The report style (SVG ids salted by ``plot_id`` for repeatable output), held by one thread.

    Only the outermost call copies and restores matplotlib's rcParams; a nested call (a figure
    drawn by a function that draws several) reuses that context and only sets the salt. The
    outermost call also pauses the cyclic garbage collector: matplotlib makes thousands of
    short-lived artists that refer to each other, and collecting them generation by generation
    while a page of figures is drawn costs about a tenth of the time; they are collected after."""
    depth = getattr(_HELD, "depth", 0)
    with _LOCK:
        if depth:
            salt = rcParams["svg.hashsalt"]
            _HELD.depth = depth + 1
            try:
                if plot_id is not None:
                    rcParams["svg.hashsalt"] = plot_id
                yield
            finally:
                rcParams["svg.hashsalt"] = salt
                _HELD.depth = depth
            return
        extra: dict[Any, Any] = {} if plot_id is None else {"svg.hashsalt": plot_id}
        collecting = gc.isenabled()
        gc.disable()
        try:
            with rc_context({**STYLE, **extra}):
                _HELD.depth = 1
                try:
                    yield
                finally:
                    _HELD.depth = 0
        finally:
            if collecting:
                gc.enable()


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
    """A figure on an Agg canvas with ``nrows × ncols`` axes (returned flat, row by row); no
    layout engine: :func:`figure_html` sets the margins with :func:`fit_layout` and draws once."""
    with plot_style():
        fig = Figure(figsize=(width_in, height_in))
        FigureCanvasAgg(fig)
        axes = fig.subplots(nrows, ncols, squeeze=False)
    return fig, [ax for row in axes for ax in row]


# text sizes (points) by (text, font size, weight, family): tick labels repeat across figures
_SIZES: dict[tuple[str, float, str, str], tuple[float, float]] = {}
_SIZES_MAX = 8192
# a browser hints small text, which can make it a few per cent wider than its outline metrics
_WIDTH_SPARE = 1.06


class _Measure:
    """Text sizes in points, measured as the SVG writer measures them (matplotlib's text-to-path
    metrics, whose mathtext cache lives as long as the process) and remembered; legends are
    measured by the figure's renderer."""

    def __init__(self, fig: Figure) -> None:
        self.fig = fig
        self.scale = 72.0 / fig.dpi
        self._renderer: RendererBase | None = None

    @property
    def renderer(self) -> RendererBase:
        """The figure's Agg renderer (made on first use: only legends need it)."""
        if self._renderer is None:
            self._renderer = self.fig.canvas.get_renderer()  # type: ignore[attr-defined]
        return self._renderer

    def size(self, text: str, fontsize: float, weight: str = "normal") -> tuple[float, float]:
        """Width and height (points) of ``text``: every line measured, lines one font height apart."""
        family = str(rcParams["font.family"])
        key = (text, fontsize, weight, family)
        got = _SIZES.get(key)
        if got is None:
            prop = FontProperties(size=fontsize, weight=weight)
            _, line_h, _ = text_to_path.get_text_width_height_descent("lp", prop, ismath=False)
            width = height = 0.0
            for line in [text] if is_math_text(text) else text.split("\n"):
                w, h, _ = text_to_path.get_text_width_height_descent(line, prop, ismath=is_math_text(line))
                width = max(width, w)
                height += max(h, line_h) * (1.2 if height else 1.0)
            got = (width * _WIDTH_SPARE, height)
            if len(_SIZES) >= _SIZES_MAX:
                _SIZES.clear()
            _SIZES[key] = got
        return got

    def text(self, t: Text) -> tuple[float, float]:
        """The axis-aligned width and height (points) of a Text artist as it will be drawn."""
        if not t.get_visible() or not t.get_text():
            return 0.0, 0.0
        w, h = self.size(t.get_text(), float(t.get_fontsize()), str(t.get_fontweight()))
        return _rotated(w, h, t.get_rotation())


def _rotated(w: float, h: float, degrees: float) -> tuple[float, float]:
    a = math.radians(degrees)
    return abs(w * math.cos(a)) + abs(h * math.sin(a)), abs(w * math.sin(a)) + abs(h * math.cos(a))


def _tick_labels(axis: Axis) -> tuple[list[tuple[float, str]], str]:
    """The tick labels ``axis`` will draw (position as a fraction of the axis, text), major and
    minor, and the offset text (empty when none): what its locators and formatters give for the
    current view, as the draw computes them."""
    lo, hi = sorted(axis.get_view_interval())
    out: list[tuple[float, str]] = []
    offset = ""
    scale = axis.get_transform()
    a, b = scale.transform([lo, hi]) if hi > lo else (0.0, 1.0)
    for major in (True, False):
        locator = axis.get_major_locator() if major else axis.get_minor_locator()
        formatter = axis.get_major_formatter() if major else axis.get_minor_formatter()
        locs = np.asarray(locator(), dtype=float)
        labels = formatter.format_ticks(list(locs)) if locs.size else []
        if major:
            offset = formatter.get_offset()
        tol = 1e-9 * max(abs(hi - lo), 1e-300)
        for loc, label in zip(locs, labels, strict=True):
            if label and lo - tol <= loc <= hi + tol:
                pos = (float(scale.transform([loc])[0]) - a) / ((b - a) or 1.0)
                out.append((pos, label))
    return out, offset


def _tick_style(axis: Axis) -> tuple[float, float, float, bool]:
    """Label font size, rotation (degrees), space from the spine to the label (points), labels on."""
    tick = axis.majorTicks[0]
    label = tick.label1
    pad = tick.get_pad()  # type: ignore[func-returns-value]  # the stub says None; it is the pad in points
    space = float(pad or 0.0) + tick.get_tick_padding()
    return float(label.get_fontsize()), float(label.get_rotation()), float(space), bool(label.get_visible())


@dataclass
class _Frame:
    """What the decorations of one axes need around its frame (points)."""

    y_ticks: float  # y tick labels and their spacing from the frame, left of it
    left: float  # the y tick labels and the y label
    x_ticks: float  # x tick labels and their spacing, below the frame
    bottom: float  # the x tick labels and the x label (or x offset text)
    top: float  # the title (and the y offset text under it)
    raise_title: float  # the y offset text the title must clear
    right: float  # a legend anchored right of the frame
    title_w: float  # the title's width, centred over the frame
    # x tick labels: position (fraction of the axis), reach left and right of their tick
    x_reach: list[tuple[float, float, float]]

    def sides(self, ax_w_pt: float) -> tuple[float, float]:
        """Left and right reach beyond the frame for an axes ``ax_w_pt`` wide (x tick labels at
        the ends and a title wider than the frame may stick out)."""
        over = max(0.0, (self.title_w - ax_w_pt) / 2)
        left, right = max(self.left, over), max(self.right, over)
        for pos, lo, hi in self.x_reach:
            left = max(left, lo - pos * ax_w_pt)
            right = max(right, pos * ax_w_pt + hi - ax_w_pt)
        return left, right


def _frame(ax: Axes, m: _Measure) -> _Frame:
    """Measure the decorations of ``ax``: tick labels, axis labels, offset texts, title, legend."""
    frame = _Frame(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, [])
    if not ax.axison:
        return frame
    labelpad = float(rcParams["axes.labelpad"])
    # y axis: tick labels left of the frame, the label left of them, the offset text above
    size, rot, space, on = _tick_style(ax.yaxis)
    ylabels, yoffset = _tick_labels(ax.yaxis)
    if on and ylabels:
        frame.y_ticks = space + max(_rotated(*m.size(t, size), rot)[0] for _, t in ylabels)
    frame.left = frame.y_ticks
    if ax.yaxis.label.get_text():
        frame.left += labelpad + m.text(ax.yaxis.label)[0]
    if yoffset:
        frame.raise_title = 3.0 + m.size(yoffset, float(ax.yaxis.offsetText.get_fontsize()))[1]
    # x axis: tick labels below (they may reach past either side), the label or offset below them
    size, rot, space, on = _tick_style(ax.xaxis)
    xlabels, xoffset = _tick_labels(ax.xaxis)
    if on and xlabels:
        ha = ax.xaxis.majorTicks[0].label1.get_horizontalalignment()
        heights = []
        for pos, t in xlabels:
            w, h = _rotated(*m.size(t, size), rot)
            heights.append(h)
            lo = w if ha == "right" else w / 2 if ha == "center" else 0.0
            frame.x_reach.append((pos, lo, w - lo))
        frame.x_ticks = space + max(heights)
    frame.bottom = frame.x_ticks
    below = max(m.text(ax.xaxis.label)[1], m.size(xoffset, size)[1] if xoffset else 0.0)
    if below:
        frame.bottom += labelpad + below
    # the title above the frame, raised over the y offset text
    frame.top = frame.raise_title
    if ax.title.get_text():
        frame.title_w, title_h = m.text(ax.title)
        frame.top += float(rcParams["axes.titlepad"]) + title_h
    # a legend anchored at the right edge of the frame (``bbox_to_anchor=(1, 1)``, ``loc="upper
    # left"``) takes its width there
    legend = ax.get_legend()
    if legend is not None and legend.get_visible():
        anchor = ax.transAxes.inverted().transform_bbox(legend.get_bbox_to_anchor())
        if anchor.x0 >= 1.0 - 1e-9:
            # text stays text in the SVG, and a browser's sans-serif runs up to a tenth wider
            width = legend.get_window_extent(m.renderer).width * m.scale * LEGEND_SLACK
            frame.right = legend.borderaxespad * legend.prop.get_size_in_points() + width
    return frame


def fit_layout(fig: Figure) -> None:
    """Set the figure's margins and the space between its panels so that every tick label, axis
    label, title and figure legend fits, with :data:`PAD_IN` to spare; no draw needed.

    The axes must come from one grid (:func:`new_figure`); hidden axes take no space. The axis
    labels are placed beside the measured tick labels, and a title is raised over its axes'
    offset text (``1e-5`` above the y axis) when there is one."""
    axes = [ax for ax in fig.axes if ax.get_visible() and ax.get_subplotspec() is not None]
    if not axes:
        return
    spec = axes[0].get_subplotspec()
    assert spec is not None
    nrows, ncols = spec.get_gridspec().get_geometry()
    fig_w, fig_h = (float(v) * 72.0 for v in fig.get_size_inches())
    pad = PAD_IN * 72.0
    m = _Measure(fig)
    # figure legends (``loc="outside lower center"``) take a band at the bottom
    legend_h = 0.0
    for leg in fig.legends:
        legend_h = max(legend_h, leg.get_window_extent(m.renderer).height * m.scale + pad)
    frames = [(ax, _frame(ax, m)) for ax in axes]
    ax_w = (fig_w - 2 * pad) / ncols * 0.85
    for _ in range(4):  # what sticks out (end tick labels, wide titles) depends on the axes' width
        lefts, rights = [0.0] * ncols, [0.0] * ncols
        bottoms, tops = [0.0] * nrows, [0.0] * nrows
        for ax, f in frames:
            sp = ax.get_subplotspec()
            assert sp is not None
            left, right = f.sides(ax_w)
            c0, c1, r0, r1 = sp.colspan.start, sp.colspan.stop - 1, sp.rowspan.start, sp.rowspan.stop - 1
            lefts[c0], rights[c1] = max(lefts[c0], left), max(rights[c1], right)
            bottoms[r1], tops[r0] = max(bottoms[r1], f.bottom), max(tops[r0], f.top)
        gap_w = max((rights[c] + lefts[c + 1] + pad for c in range(ncols - 1)), default=0.0)
        gap_h = max((bottoms[r] + tops[r + 1] + pad for r in range(nrows - 1)), default=0.0)
        left_pt, right_pt = pad + lefts[0], pad + rights[-1]
        bottom_pt, top_pt = pad + bottoms[-1] + legend_h, pad + tops[0]
        ax_w = max((fig_w - left_pt - right_pt - (ncols - 1) * gap_w) / ncols, 1.0)
    ax_h = max((fig_h - bottom_pt - top_pt - (nrows - 1) * gap_h) / nrows, 1.0)
    fig.subplots_adjust(
        left=left_pt / fig_w,
        right=1.0 - right_pt / fig_w,
        bottom=bottom_pt / fig_h,
        top=1.0 - top_pt / fig_h,
        wspace=gap_w / ax_w,
        hspace=gap_h / ax_h,
    )
    labelpad = float(rcParams["axes.labelpad"])
    for ax, f in frames:
        if not ax.axison:
            continue
        # where matplotlib would put them after measuring the drawn tick labels once more
        ax.yaxis.set_label_coords(-(f.y_ticks + labelpad) / ax_w, 0.5)
        ax.xaxis.set_label_coords(0.5, -(f.x_ticks + labelpad) / ax_h)
        if f.raise_title:
            ax.title.set_y(1.0 + f.raise_title / ax_h)


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
        if fig.get_layout_engine() is None:
            fit_layout(fig)
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
    return f'<figure class=plot id="{pid}">{svg}<figcaption>{html.escape(caption)}</figcaption></figure>'


def legend_if_labelled(ax: Axes, **kwargs: Any) -> None:
    """A legend when ``ax`` has labelled artists (none otherwise), right of the frame, off the data.

    :func:`fit_layout` makes room for it; ``kwargs`` go to :meth:`Axes.legend` (``ncols`` …)."""
    handles, labels = ax.get_legend_handles_labels()
    if labels:
        ax.legend(handles, labels, **{"loc": "upper left", "bbox_to_anchor": (1.0, 1.0), **kwargs})


def figure_legend(fig: Figure, *, ncols: int = 4) -> None:
    """One legend for all the panels of ``fig``, below them, off the data: every labelled artist,
    each label once (the panels of one figure share their labels). None when nothing is labelled."""
    entries: dict[str, Any] = {}
    for ax in fig.axes:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            entries.setdefault(label, handle)
    if entries:
        fig.legend(
            list(entries.values()), list(entries), loc="outside lower center", ncols=min(ncols, len(entries))
        )


def _plain_number(value: float, _position: object = None) -> str:
    return f"{value:g}"


def readable_log_axis(ax: Axes, which: str = "y") -> None:
    """A log axis whose ticks read as plain numbers (0.02, 0.05, 0.1, 0.2 …) at 1, 2 and 5 per
    decade, instead of matplotlib's ``4×10⁻¹`` minor labels."""
    axis = ax.yaxis if which == "y" else ax.xaxis
    axis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FuncFormatter(_plain_number))
    axis.set_minor_locator(LogLocator(base=10.0, subs="auto"))
    axis.set_minor_formatter(NullFormatter())


def shared_limits(values: Sequence[NDArray[np.float64]]) -> tuple[float, float] | None:
    """The common finite range of several arrays, or ``None`` when none has a finite value."""
    finite = [v[np.isfinite(v)] for v in values]
    finite = [v for v in finite if v.size]
    if not finite:
        return None
    return float(min(v.min() for v in finite)), float(max(v.max() for v in finite))
