"""Small inline-SVG charts for the diagnosis report: scatter/line panels, bar charts, histograms.

Every function returns one ``<svg>`` element as text, with no external resources, fonts or
scripts; sizes are in CSS pixels. Data coordinates map linearly onto the plot area, with "nice"
tick values (1, 2, 5 × 10^k).
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["Series", "bar_chart", "histograms", "panel"]

FloatArray = NDArray[np.float64]
FONT = "font-family:sans-serif;font-size:11px"
MARGIN_L, MARGIN_R, MARGIN_T, MARGIN_B = 58, 12, 22, 36


@dataclass(frozen=True)
class Series:
    """Points (``kind="points"``) or a polyline (``kind="line"``, drawn in the given order)."""

    x: FloatArray
    y: FloatArray
    color: str
    label: str
    kind: str = "points"
    radius: float = 2.0
    opacity: float = 0.55


def _nice_ticks(lo: float, hi: float, count: int = 5) -> list[float]:
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return []
    if hi <= lo:
        hi = lo + 1.0
    raw = (hi - lo) / max(count, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * mag >= raw)
    first = math.ceil(lo / step) * step
    ticks = []
    t = first
    while t <= hi + 1e-9 * step:
        ticks.append(0.0 if abs(t) < 1e-12 * step else t)
        t += step
    return ticks


def _fmt(v: float) -> str:
    if v == 0:
        return "0"
    a = abs(v)
    if a >= 1000 or a < 0.001:
        return f"{v:.1e}"
    return f"{v:.4g}"


def _range(values: Sequence[FloatArray], pad: float = 0.05) -> tuple[float, float]:
    finite = [v[np.isfinite(v)] for v in values if len(v)]
    finite = [v for v in finite if len(v)]
    if not finite:
        return 0.0, 1.0
    lo = float(min(v.min() for v in finite))
    hi = float(max(v.max() for v in finite))
    if hi - lo < 1e-15 * max(abs(lo), abs(hi), 1e-300):
        span = max(abs(lo), 1e-9)
        lo, hi = lo - span, hi + span
    span = hi - lo
    return lo - pad * span, hi + pad * span


class _Frame:
    def __init__(self, width: int, height: int, xr: tuple[float, float], yr: tuple[float, float]) -> None:
        self.w, self.h = width, height
        self.x0, self.x1 = xr
        self.y0, self.y1 = yr
        self.pw = width - MARGIN_L - MARGIN_R
        self.ph = height - MARGIN_T - MARGIN_B

    def px(self, x: FloatArray | float) -> FloatArray:
        return MARGIN_L + (np.asarray(x, dtype=float) - self.x0) / (self.x1 - self.x0) * self.pw

    def py(self, y: FloatArray | float) -> FloatArray:
        return MARGIN_T + (1.0 - (np.asarray(y, dtype=float) - self.y0) / (self.y1 - self.y0)) * self.ph

    def axes(self, title: str, xlabel: str, ylabel: str, xticks: bool = True) -> list[str]:
        out = [
            f'<rect x="{MARGIN_L}" y="{MARGIN_T}" width="{self.pw}" height="{self.ph}" '
            'fill="#fff" stroke="#888" stroke-width="0.8"/>',
            f'<text x="{MARGIN_L}" y="14" style="{FONT};font-weight:bold">{html.escape(title)}</text>',
            f'<text x="{MARGIN_L + self.pw / 2:.1f}" y="{self.h - 4}" text-anchor="middle" '
            f'style="{FONT}">{html.escape(xlabel)}</text>',
            f'<text transform="translate(12,{MARGIN_T + self.ph / 2:.1f}) rotate(-90)" text-anchor="middle" '
            f'style="{FONT}">{html.escape(ylabel)}</text>',
        ]
        for t in _nice_ticks(self.y0, self.y1):
            y = float(self.py(t))
            out.append(
                f'<line x1="{MARGIN_L}" x2="{MARGIN_L + self.pw}" y1="{y:.1f}" y2="{y:.1f}" '
                'stroke="#eee" stroke-width="0.8"/>'
            )
            out.append(
                f'<text x="{MARGIN_L - 4}" y="{y + 3.5:.1f}" text-anchor="end" '
                f'style="{FONT}">{_fmt(t)}</text>'
            )
        if xticks:
            for t in _nice_ticks(self.x0, self.x1):
                x = float(self.px(t))
                out.append(
                    f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{MARGIN_T + self.ph}" '
                    f'y2="{MARGIN_T + self.ph + 4}" '
                    'stroke="#888"/>'
                )
                out.append(
                    f'<text x="{x:.1f}" y="{MARGIN_T + self.ph + 15}" text-anchor="middle" '
                    f'style="{FONT}">{_fmt(t)}</text>'
                )
        if self.y0 < 0 < self.y1:
            y = float(self.py(0.0))
            out.append(
                f'<line x1="{MARGIN_L}" x2="{MARGIN_L + self.pw}" y1="{y:.1f}" y2="{y:.1f}" '
                'stroke="#bbb" stroke-width="1"/>'
            )
        return out


def _svg(width: int, height: int, body: list[str], label: str) -> str:
    return (
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
        f'viewBox="0 0 {width} {height}" role="img" aria-label="{html.escape(label)}">'
        + "".join(body)
        + "</svg>"
    )


def _legend(series: Sequence[Series], frame: _Frame) -> list[str]:
    out = []
    x = MARGIN_L + 6
    y = MARGIN_T + 12
    for s in series:
        if not s.label:
            continue
        out.append(f'<rect x="{x}" y="{y - 7}" width="8" height="8" fill="{s.color}"/>')
        out.append(f'<text x="{x + 11}" y="{y}" style="{FONT}">{html.escape(s.label)}</text>')
        y += 13
    del frame
    return out


def panel(
    series: Sequence[Series],
    *,
    title: str,
    xlabel: str,
    ylabel: str,
    width: int = 420,
    height: int = 260,
) -> str:
    """A scatter / line panel of several series on common axes."""
    xr = _range([s.x for s in series])
    yr = _range([s.y for s in series])
    frame = _Frame(width, height, xr, yr)
    body = frame.axes(title, xlabel, ylabel)
    for s in series:
        ok = np.isfinite(s.x) & np.isfinite(s.y)
        px, py = frame.px(s.x[ok]), frame.py(s.y[ok])
        if s.kind == "line":
            if len(px) >= 2:
                pts = " ".join(f"{a:.1f},{b:.1f}" for a, b in zip(px, py, strict=True))
                body.append(f'<polyline points="{pts}" fill="none" stroke="{s.color}" stroke-width="1.8"/>')
        else:
            body.append(f'<g fill="{s.color}" fill-opacity="{s.opacity}">')
            body.extend(
                f'<circle cx="{a:.1f}" cy="{b:.1f}" r="{s.radius}"/>' for a, b in zip(px, py, strict=True)
            )
            body.append("</g>")
    body += _legend(series, frame)
    return _svg(width, height, body, title)


def bar_chart(
    labels: Sequence[str],
    values: Sequence[float],
    colors: Sequence[str],
    *,
    title: str,
    ylabel: str,
    hline: float | None = None,
    width: int = 640,
    height: int = 280,
) -> str:
    """Vertical bars on a logarithmic scale (values span decades), values written on top, and an
    optional dashed reference line (the noise floor)."""
    vals = np.asarray(values, dtype=float)
    positive = vals[vals > 0]
    refs = np.concatenate([positive, [hline]]) if hline and hline > 0 else positive
    lo = float(refs.min()) if len(refs) else 1e-3
    hi = float(refs.max()) if len(refs) else 1.0
    y0 = math.floor(math.log10(lo) - 0.3)
    y1 = math.log10(hi) + 0.35
    frame = _Frame(width, height, (0.0, float(max(len(vals), 1))), (y0, y1))
    body = frame.axes(title, "", ylabel, xticks=False)
    body = [b for b in body if 'text-anchor="end"' not in b and 'stroke="#eee"' not in b]
    for k in range(y0, math.ceil(y1) + 1):
        for m in (1.0, 2.0, 5.0):
            t = math.log10(m) + k
            if not y0 <= t <= y1:
                continue
            y = float(frame.py(t))
            body.append(
                f'<line x1="{MARGIN_L}" x2="{MARGIN_L + frame.pw}" y1="{y:.1f}" y2="{y:.1f}" '
                'stroke="#eee" stroke-width="0.8"/>'
            )
            body.append(
                f'<text x="{MARGIN_L - 4}" y="{y + 3.5:.1f}" text-anchor="end" style="{FONT}">'
                f"{_fmt(m * 10.0**k)}</text>"
            )
    slot = frame.pw / max(len(vals), 1)
    base_y = MARGIN_T + frame.ph
    for i, (label, v, c) in enumerate(zip(labels, vals, colors, strict=True)):
        x = MARGIN_L + i * slot + 0.15 * slot
        y = float(frame.py(math.log10(v))) if v > 0 else base_y
        body.append(
            f'<rect x="{x:.1f}" y="{y:.1f}" width="{0.7 * slot:.1f}" height="{base_y - y:.1f}" fill="{c}"/>'
        )
        body.append(
            f'<text x="{x + 0.35 * slot:.1f}" y="{y - 3:.1f}" text-anchor="middle" style="{FONT}">'
            f"{_fmt(float(v))}</text>"
        )
        body.append(
            f'<text x="{x + 0.35 * slot:.1f}" y="{base_y + 14}" text-anchor="middle" '
            f'style="{FONT}">{html.escape(label)}</text>'
        )
    if hline is not None and hline > 0:
        y = float(frame.py(math.log10(hline)))
        body.append(
            f'<line x1="{MARGIN_L}" x2="{MARGIN_L + frame.pw}" y1="{y:.1f}" y2="{y:.1f}" '
            'stroke="#c0392b" stroke-dasharray="5,3" stroke-width="1.2"/>'
        )
    return _svg(width, height, body, title)


def histograms(
    groups: Sequence[tuple[str, FloatArray, str]],
    *,
    title: str,
    xlabel: str,
    bins: int = 30,
    width: int = 640,
    height: int = 260,
) -> str:
    """Overlaid step histograms (counts) of several samples on one common bin grid."""
    data = [np.asarray(v, dtype=float) for _, v, _ in groups]
    hi = max((float(v.max()) for v in data if len(v)), default=1.0) or 1.0
    edges = np.linspace(0.0, hi * 1.02, bins + 1)
    counts = [np.histogram(v, bins=edges)[0] for v in data]
    top = max((int(c.max()) for c in counts), default=1) * 1.1 or 1.0
    frame = _Frame(width, height, (0.0, float(edges[-1])), (0.0, float(top)))
    body = frame.axes(title, xlabel, "poses")
    for (label, _, color), c in zip(groups, counts, strict=True):
        xs = np.repeat(edges, 2)
        ys = np.concatenate([[0.0], np.repeat(c, 2), [0.0]])
        pts = " ".join(f"{a:.1f},{b:.1f}" for a, b in zip(frame.px(xs), frame.py(ys), strict=True))
        body.append(
            f'<polyline points="{pts}" fill="{color}" fill-opacity="0.18" stroke="{color}" '
            f'stroke-width="1.5"/>'
        )
        del label
    series = [Series(np.zeros(0), np.zeros(0), color, label) for label, _, color in groups]
    body += _legend(series, frame)
    return _svg(width, height, body, title)
