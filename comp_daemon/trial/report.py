"""The trial's report: a text summary (the terminal) and a self-contained HTML page.

Both show Table 2 (seed 000) beside seed 000's figures, the ISO 9283 multi-directional pose
accuracy with and without joint feedback (seed 000 Fig. 6), the frequency histogram of the 3-D
errors (Fig. 11) and seed 001's model comparison on the same data. The HTML page adds the per-axis
error of every target point (Figs 7–10) and the details (models, data sets, loop statistics). It
loads nothing, runs no script, and prints on one page width. Numbers are mm unless marked.

The text is rendered here, the page in :mod:`comp_daemon.trial.report_html` (its figures, drawn by
matplotlib, in :mod:`comp_daemon.trial.plots`); what both pick out of the result is
:mod:`comp_daemon.trial.report_data`.
"""

from __future__ import annotations

import numpy as np

from comp_daemon.trial.report_data import COMPARISONS, grating_scale, iso_retried, seed_figure, table_rows
from comp_daemon.trial.report_html import render_html
from comp_daemon.trial.result import TrialResult
from comp_daemon.trial.stats import histogram
from comp_daemon.trial.verdict import verdict

__all__ = ["render_html", "render_text"]


def _text_table2(result: TrialResult) -> list[str]:
    t2 = result.table2()
    rows = table_rows(result)
    w = max(len(result.runs[k].label) for k in rows) if rows else 10
    head = (
        f"{'method':<{w}} {'n':>4} |"
        + "|".join(f" {a} mean    std max|.| " for a in "xyz")
        + "| 3-D mean   std   max | seed 000 mean  max"
    )
    lines = [head, "-" * len(head)]
    for k in rows:
        st = t2[k]
        cells = "|".join(
            f" {st[a]['mean']:>+6.3f} {st[a]['std']:>6.3f} {st[a]['max_abs']:>6.3f} " for a in "xyz"
        )
        d = st["3d"]
        lines.append(
            f"{result.runs[k].label:<{w}} {st['n']:>4} |{cells}|"
            f" {d['mean']:>8.3f} {d['std']:>5.3f} {d['max']:>5.3f} |"
            f" {seed_figure(k, 'mean'):>13} {seed_figure(k, 'max'):>4}"
        )
    return lines


def _text_iso(result: TrialResult) -> list[str]:
    runs = result.iso.get("runs", {})
    if not runs:
        return []
    pts = np.asarray(result.iso.get("points_mm", []), dtype=float)
    lines = [
        f"ISO 9283 multi-directional pose accuracy ({len(pts)} point(s) × 3 directions × "
        f"{result.iso.get('cycles')} cycles, {result.iso.get('approach_mm'):g} mm moves; rated "
        f"repeatability ±{result.iso.get('repeatability_rated_mm', float('nan')):g} mm)",
        f"{'point':<28} | {'without feedback: vAP':>21} {'RP':>6} {'vAP/RP':>6} | "
        f"{'with feedback: vAP':>18} {'RP':>6} {'vAP/RP':>6}",
    ]
    for i, p in enumerate(pts):
        cells = []
        for key in ("without", "with"):
            st = runs.get(key, {}).get("stats")
            if st is None:
                cells.append(
                    f"{'—':>21} {'':>6} {'':>6}" if key == "without" else f"{'—':>18} {'':>6} {'':>6}"
                )
                continue
            wd = 21 if key == "without" else 18
            cells.append(f"{st['vap_mm'][i]:>{wd}.3f} {st['rp_max_mm'][i]:>6.3f} {st['ratio'][i]:>6.1f}")
        name = f"P{i + 1} ({p[0]:.0f}, {p[1]:.0f}, {p[2]:.0f})"
        lines.append(f"{name:<28} | {cells[0]} | {cells[1]}")
    return lines


def _text_histogram(result: TrialResult) -> list[str]:
    rows = table_rows(result)
    if not rows:
        return []
    errs = {k: np.linalg.norm(result.runs[k].errors_mm(), axis=1) for k in rows}
    h = histogram(errs)
    edges = h["edges_mm"]
    lines = ["Frequency of the 3-D error (seed 000 Fig. 11): share of the target points per bin"]
    lines.append(f"{'bin (mm)':<14}" + "".join(f"{result.runs[k].label[:16]:>18}" for k in rows))
    for b in range(len(edges) - 1):
        cells = "".join(f"{100 * h['share'][k][b]:>17.0f}%" for k in rows)
        lines.append(f"{edges[b]:.3f}–{edges[b + 1]:.3f}  {cells}")
    return lines


def _text_comparison(result: TrialResult) -> list[str]:
    out: list[str] = []
    for key, title in COMPARISONS:
        comp = result.comparison.get(key)
        if not comp:
            continue
        rows = comp["rows"]
        out.append(
            f"Seed 001's comparison on the {title}: fitted on {rows['fit']} sampling points, "
            f"prediction error on {rows['check']} target points (mm)"
        )
        w = max(len(k) for k in comp["models"])
        out.append(
            f"{'model':<{w}} | {'mean':>6} {'std':>6} {'max':>6} | {'x std':>6} {'y std':>6} {'z std':>6}"
        )
        for label, m in comp["models"].items():
            if "table2" not in m:
                out.append(f"{label:<{w}} | not fitted: {m.get('error')}")
                continue
            t = m["table2"]
            d = t["3d"]
            out.append(
                f"{label:<{w}} | {d['mean']:>6.3f} {d['std']:>6.3f} {d['max']:>6.3f} | "
                + " ".join(f"{t[a]['std']:>6.3f}" for a in "xyz")
            )
        out.append("")
    return out


def render_text(result: TrialResult) -> str:
    plan = result.plan
    sizes = plan["sizes"]
    lines = [
        f"comp-daemon trial: seed 000's experiment on the simulated cell '{plan['scenario']}' (seed "
        f"{plan['seed']}, payload {plan['payload_kg']:g} kg), through the running daemon",
        f"{sizes['n_sampling']} sampling + {sizes['n_targets']} target points; Chebyshev order "
        f"{sizes['chebyshev_order']}; {result.duration_s / 60:.1f} min"
        + ("" if result.complete else f"; INCOMPLETE: {result.error}"),
        "",
    ]
    if result.gratings:
        g = ", ".join(
            f"A{m['joint']} scale {grating_scale(m):.5f} residual rms {m['residual_rms_deg']:.4f}°"
            for m in result.gratings["joints"]
        )
        lines += [f"Grating calibration v{result.gratings['version']}: {g}", ""]
    iso = _text_iso(result)
    if iso:
        lines += [*iso, ""]
    if result.runs:
        n = len(next(iter(result.runs.values())).state)
        lines += [
            f"Table 2: error of the {n} target points = tracker − wanted (robot base frame, mm)",
            *_text_table2(result),
            "",
            *_text_histogram(result),
            "",
        ]
    lines += _text_comparison(result)
    v = verdict(result)
    if "ordering" in v:
        o, c = v["ordering"], v["claim"]
        t = c["trial"]
        lines += [
            "Ordering (3-D mean and max): closed loop < kinematic calibration < uncompensated: "
            + ("yes" if o["mean"] and o["max"] else f"NO (mean: {o['mean']}, max: {o['max']})"),
            f"Seed 000's claim: max 0.76 → 0.19 mm (−75 %, −55 % against kinematic calibration). "
            f"This trial: max {t['before_max']:.3f} → {t['after_max']:.3f} mm "
            f"(−{100 * t['reduction']:.0f} %, "
            f"−{100 * t['vs_kinematic']:.0f} % against kinematic calibration); every axis within "
            f"±{t['axis_max_abs']:.3f} mm.",
        ]
    n_retried = sum(len(r.retried) for r in [*result.sampling.values(), *result.runs.values()])
    n_retried += len(iso_retried(result))
    n_failed = sum(len(r.failures()) for r in [*result.sampling.values(), *result.runs.values()])
    if n_retried or n_failed:
        lines.append(
            f"Targets of the daemon: {n_failed} failed (left out of the statistics), {n_retried} posted "
            "again after a failure of the computer (stale grating reading, RSI late); see the HTML report."
        )
    loop = result.loop
    if loop.get("controller"):
        ctl, dmn = loop["controller"], loop.get("daemon", {})
        p99 = dmn.get("latency_p99_ms")
        lines.append(
            f"RSI: {ctl.get('telegrams_sent')} telegrams, {ctl.get('late_total')} late replies seen by the "
            f"controller, reply latency p99 {p99 if p99 is None else f'{p99:.3f}'} ms; daemon exit code "
            f"{loop.get('daemon_exit_code')}"
        )
    return "\n".join(lines) + "\n"
