"""The report figures (matplotlib, inline SVG): self-contained, repeatable, drawn once with every
label inside the figure and clear of its neighbours, and a "no data" panel instead of a crash when
a plot has nothing finite to draw."""

from __future__ import annotations

import re

import numpy as np
import pytest
from matplotlib.axis import Axis
from matplotlib.backend_bases import RendererBase
from matplotlib.figure import Figure
from matplotlib.transforms import Bbox

from comp_daemon.common.plots import RASTER_ABOVE, figure_html, new_figure, no_data, plot_style
from comp_daemon.diagnosis.plots import (
    check_histogram_figure,
    effect_figure,
    joint_error_figure,
    ladder_figure,
    predicted_measured_figure,
    remainder_time_figure,
    residual_joint_figure,
    residual_pose_figure,
    variogram_figure,
)
from comp_daemon.trial.plots import (
    error_histogram_figure,
    iso_figure,
    method_histograms_figure,
    point_error_figures,
)
from comp_daemon.trial.result import PointRun, TrialResult

NAN3 = np.full((12, 3), np.nan)
NAN6 = np.full((12, 6), np.nan)


def _figure(page: str, plot_id: str) -> str:
    found = re.findall(rf'<figure class=plot id="plot-{plot_id}">(.*?)</figure>', page, re.S)
    assert len(found) == 1, f"{plot_id}: {len(found)} figures"
    return found[0]


def _line_figure(plot_id: str, x: np.ndarray) -> str:
    fig, (ax,) = new_figure(3.0, 2.0)
    ax.plot(x, x**2, label="x²")
    ax.scatter(x, -x, s=4)
    return figure_html(fig, plot_id, "a <test> figure")


def test_figure_is_inline_svg_with_its_own_ids_and_the_same_bytes_each_time() -> None:
    x = np.linspace(0.0, 1.0, 30)
    a, b, c = _line_figure("one", x), _line_figure("one", x), _line_figure("two", x)
    assert a == b
    assert a.startswith('<figure class=plot id="plot-one"><svg ') and a.endswith("</figure>")
    assert "<figcaption>a &lt;test&gt; figure</figcaption>" in a and 'aria-label="a &lt;test&gt; figure"' in a
    assert re.findall(r"https?://[^\"' ]*", a) == ["http://www.w3.org/2000/svg"]
    assert "<?xml" not in a and "DOCTYPE" not in a and "xlink" not in a and "<script" not in a
    ids = re.findall(r'\bid="([^"]+)"', a)
    assert ids[0] == "plot-one" and all(i.startswith("plot-one") for i in ids)
    refs = re.findall(r'(?:href="#|url\(#)([^")]+)', a)
    assert refs and set(refs) <= set(ids)  # every reference points inside the same figure
    assert not set(ids) & set(re.findall(r'\bid="([^"]+)"', c))
    assert "data:image/png" not in a  # few points: vector


def test_many_points_are_embedded_as_pixels_inside_the_svg() -> None:
    dense = _line_figure("dense", np.linspace(0.0, 1.0, RASTER_ABOVE * 3))
    # the scatter is one embedded image; the line and the axes stay vector
    fig, (ax,) = new_figure(3.0, 2.0)
    ax.scatter(np.arange(RASTER_ABOVE * 3.0), np.arange(RASTER_ABOVE * 3.0), rasterized=True)
    raster = figure_html(fig, "raster", "many")
    assert raster.count("data:image/png;base64,") == 1 and "<text" in raster
    assert "<use" in dense  # without rasterized=True every marker is drawn as a vector


def test_no_data_panel_says_why() -> None:
    fig, (ax,) = new_figure(3.0, 2.0)
    ax.plot([0, 1], [0, 1])
    no_data(ax, "nothing was measured", "title")
    out = figure_html(fig, "empty", "empty")
    assert "no data: nothing was measured" in out and ">title<" in out


def _crowded_figure() -> Figure:
    """Six panels whose decorations vary: wide, negative and tiny (offset text) tick values,
    rotated tick labels, a two-line title, a title wider than its panel, legends right of the last
    column, a figure legend."""
    fig, axes = new_figure(10.5, 5.6, 2, 3)
    x = np.linspace(0.0, 1.0, 50)
    values = [-123456.75 + 0.5 * x, 3e-6 * x, x, 1000.0 * x - 600.0, x**2, 7.0 * x]
    for k, (ax, y) in enumerate(zip(axes, values, strict=True)):
        ax.plot(1e4 * x if k == 4 else x, y, label=f"series {k}")
        ax.set_title(f"panel {k}: y against x" + ("\nsecond line" if k == 2 else ""))
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("a long quantity (mm²)")
    axes[5].set_title("panel 5: a title wider than its panel, which the panels make room for")
    axes[3].set_xticks([0.0, 0.5, 1.0], ["nominal", "geometric J1,2,3", "ratio J2"], rotation=20, ha="right")
    axes[5].legend(loc="upper left", bbox_to_anchor=(1.0, 1.0))
    axes[2].legend(loc="upper left", bbox_to_anchor=(1.0, 1.0))
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center")
    return fig


def _drawn_tick_labels(axis: Axis, kind: str, renderer: RendererBase) -> dict[str, Bbox]:
    """The extents of the tick labels ``axis`` draws (those of ticks inside its view)."""
    lo, hi = sorted(axis.get_view_interval())
    tol = 1e-9 * (hi - lo)
    pairs = zip(axis.get_majorticklocs(), axis.get_majorticklabels(), strict=True)
    return {
        f"{kind} {t.get_text()}": t.get_window_extent(renderer)
        for loc, t in pairs
        if t.get_text() and lo - tol <= loc <= hi + tol
    }


def test_figure_is_drawn_once_with_every_label_inside_and_clear_of_the_others() -> None:
    with plot_style():
        fig = _crowded_figure()
        draws: list[object] = []
        draw = fig.draw

        def counted(renderer: object) -> None:
            draws.append(renderer)
            draw(renderer)  # type: ignore[arg-type]

        fig.draw = counted  # type: ignore[method-assign]
        out = figure_html(fig, "crowded", "six panels")
        assert len(draws) == 1 and fig.get_layout_engine() is None
        assert "1e" in out  # the offset text of the tiny values is drawn
        del fig.draw
        fig.draw_without_rendering()
        r = fig.canvas.get_renderer()  # type: ignore[attr-defined]
        page = Bbox.from_bounds(-1.0, -1.0, fig.bbox.width + 2.0, fig.bbox.height + 2.0)
        boxes = []
        for ax in fig.axes:
            parts = {
                "title": ax.title.get_window_extent(r),
                "ylabel": ax.yaxis.label.get_window_extent(r),
                "xlabel": ax.xaxis.label.get_window_extent(r),
                **_drawn_tick_labels(ax.yaxis, "ytick", r),
                **_drawn_tick_labels(ax.xaxis, "xtick", r),
            }
            if ax.yaxis.offsetText.get_text():
                parts["offset"] = ax.yaxis.offsetText.get_window_extent(r)
            legend = ax.get_legend()
            if legend is not None:
                parts["legend"] = legend.get_window_extent(r)
            for name, box in parts.items():
                assert page.containsx(box.x0) and page.containsx(box.x1), (ax.get_title(), name)
                assert page.containsy(box.y0) and page.containsy(box.y1), (ax.get_title(), name)
            # the labels clear of the tick labels, the title clear of the offset text
            ticks = [b for n, b in parts.items() if n.startswith(("ytick", "xtick"))]
            for name in ("ylabel", "xlabel", "title"):
                assert not any(parts[name].overlaps(b) for b in ticks), (ax.get_title(), name)
            if "offset" in parts:
                assert not parts["title"].overlaps(parts["offset"]), ax.get_title()
            tight = ax.get_tightbbox(r)
            assert tight is not None
            boxes.append(tight)
        assert len(fig.axes) == 6 and any(ax.yaxis.offsetText.get_text() for ax in fig.axes)
        # no panel's decorations reach into another panel's, nor into the figure legend
        for i, a in enumerate(boxes):
            assert page.containsx(a.x0) and page.containsx(a.x1) and page.containsy(a.y0)
            assert not a.overlaps(fig.legends[0].get_window_extent(r))
            for b in boxes[i + 1 :]:
                assert not a.overlaps(b)


@pytest.mark.parametrize(
    ("plot_id", "draw", "panels"),
    [
        ("ladder", lambda: ladder_figure(["nominal", "geometric"], [np.nan, 0.0], [True], None, None), 1),
        (
            "effect-step-2",
            lambda: effect_figure(
                2, "backlash", np.full(12, np.nan), "A2 (deg)", NAN3, NAN3, "backlash", as_line=True
            ),
            3,
        ),
        ("joint-error", lambda: joint_error_figure(NAN6, NAN6, None, None, {}), 6),
        ("check-histogram", lambda: check_histogram_figure([("t", [("a", np.array([np.nan]), "#000")])]), 1),
        ("residual-pose", lambda: residual_pose_figure(NAN3, np.zeros(12, bool), "geometric"), 1),
        ("residual-pose", lambda: residual_pose_figure(np.zeros((0, 3)), np.zeros(0, bool), "geometric"), 1),
        ("residual-joint", lambda: residual_joint_figure(NAN6, NAN3, "geometric"), 6),
        ("residual-joint", lambda: residual_joint_figure(np.zeros((0, 6)), np.zeros((0, 3)), "geometric"), 6),
        ("variogram", lambda: variogram_figure(NAN6, NAN3, "geometric"), 1),
        ("variogram", lambda: variogram_figure(np.zeros((2, 6)), np.zeros((2, 3)), "geometric"), 1),
        ("variogram", lambda: variogram_figure(np.zeros((9, 6)), np.ones((9, 3)), "geometric"), 1),
        (
            "remainder-time",
            lambda: remainder_time_figure(None, "pose_order", np.zeros((0, 3)), "geometric"),
            1,
        ),
        ("remainder-time", lambda: remainder_time_figure(np.full(12, np.nan), "t_s", NAN3, "geometric"), 1),
        (
            "predicted-measured",
            lambda: predicted_measured_figure(NAN3, NAN3, np.zeros(12, bool), "geometric"),
            3,
        ),
    ],
)
def test_diagnosis_plot_without_finite_data_shows_no_data(plot_id: str, draw, panels: int) -> None:
    body = _figure(draw(), plot_id)
    assert body.count("no data:") == panels


def test_diagnosis_plots_draw_the_finite_part() -> None:
    rng = np.random.default_rng(3)
    a = rng.uniform(-90, 90, (40, 6))
    resid = rng.normal(0, 0.02, (40, 3))
    resid[5] = np.nan
    check = np.arange(40) % 3 == 0
    for page in (
        residual_pose_figure(resid, check, "geometric"),
        residual_joint_figure(a, resid, "geometric"),
        variogram_figure(a, resid, "geometric"),
        remainder_time_figure(np.linspace(0, 2, 40), "t_s", resid, "geometric"),
        predicted_measured_figure(resid * 10, resid * 10 + 0.001, check, "geometric"),
    ):
        assert "no data" not in page and "<svg" in page
    assert "hours since the first pose (t_s)" in remainder_time_figure(
        np.linspace(0, 2, 40), "t_s", resid, "x"
    )
    assert "γ x" in variogram_figure(a, resid, "geometric")


def _empty_result() -> TrialResult:
    result = TrialResult(plan={"sizes": {}}, started_at="2026-11-25T12:00:00Z", environment={})
    wanted = np.zeros((8, 3))
    run = PointRun.empty("kinematic", "kinematic calibration", "targets", wanted, feedback=False)
    result.runs["kinematic"] = run  # every point NaN: nothing measured
    return result


def test_trial_plots_without_data_show_no_data() -> None:
    result = _empty_result()
    assert "no data:" in _figure(error_histogram_figure(result, ["kinematic"]), "error-histogram")
    assert "no data:" in _figure(error_histogram_figure(result, []), "error-histogram")
    page = point_error_figures(result, ["kinematic"])
    for name in ("x", "y", "z", "3d"):
        assert "no data:" in _figure(page, f"point-errors-{name}")
    assert "no data:" in _figure(
        method_histograms_figure(result, ["kinematic"]), "error-histogram-per-method"
    )
    assert "no data:" in _figure(method_histograms_figure(result, []), "error-histogram-per-method")
    assert "ISO 9283 test did not run" in _figure(iso_figure(result), "iso9283")


def test_degenerate_inputs_draw_without_warnings() -> None:
    # one pose, constant values, one empty group: drawn (pytest turns any warning into an error)
    one3, one6 = np.array([[0.01, -0.02, 0.0]]), np.zeros((1, 6))
    same3, same6 = np.full((5, 3), 0.01), np.zeros((5, 6))
    pages = [
        ladder_figure(["nominal"], [1.0], [], 1.0, "repeats"),
        check_histogram_figure([("t", [("a", np.array([]), "#000"), ("b", np.array([0.1]), "#111")])]),
        residual_pose_figure(one3, np.array([True]), "geometric"),
        residual_joint_figure(one6, one3, "geometric"),
        residual_joint_figure(same6, same3, "geometric"),
        remainder_time_figure(np.zeros(5), "t_s", same3, "geometric"),
        predicted_measured_figure(one3, one3, np.array([False]), "geometric"),
        predicted_measured_figure(same3, same3, np.zeros(5, bool), "geometric"),
        effect_figure(2, "thermal", np.full(5, 20.0), "temp_c (°C)", same3, same3, "thermal", as_line=True),
    ]
    for page in pages:
        assert "<svg" in page and "no data" not in page
    assert "no data:" in variogram_figure(same6, same3, "geometric")  # every pair at distance 0


def test_trial_plots_of_one_point_and_half_an_iso_test() -> None:
    result = _empty_result()
    run = result.runs["kinematic"]
    run.measured_mm[0] = [0.1, 0.0, 0.0]
    run.state[0] = "done"
    result.iso = {"runs": {"without": {"stats": {"vap_mm": [0.3], "rp_max_mm": [0.05]}}}}
    pages = {
        "error-histogram": error_histogram_figure(result, ["kinematic"]),
        "error-histogram-per-method": method_histograms_figure(result, ["kinematic"]),
        "point-errors-3d": point_error_figures(result, ["kinematic"]),
        "iso9283": iso_figure(result),
    }
    for plot_id, page in pages.items():
        assert "no data" not in _figure(page, plot_id), plot_id
    assert ">vAP, robot alone<" in pages["iso9283"] and ">vAP, with joint feedback<" not in pages["iso9283"]
