"""The trial's report as a self-contained HTML page (:mod:`comp_daemon.trial.report` says what it shows).

The page loads nothing, runs no script, and prints on one page width; figures are drawn by
matplotlib and embedded as inline SVG (:mod:`comp_daemon.trial.plots`).
"""

from __future__ import annotations

import html
from typing import Any

import numpy as np

from comp_daemon.trial.plots import (
    COLORS,
    error_histogram_figure,
    iso_figure,
    method_histograms_figure,
    point_error_figures,
)
from comp_daemon.trial.report_data import (
    COMPARISONS,
    grating_scale,
    iso_retried,
    seed_figure,
    table_rows,
)
from comp_daemon.trial.result import TrialResult
from comp_daemon.trial.verdict import verdict

__all__ = ["render_html"]


def _e(text: object) -> str:
    return html.escape(str(text))


def _f(v: Any, digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "—"
    return f"{float(v):.{digits}f}"


def _html_table2(result: TrialResult) -> str:
    t2 = result.table2()
    head = (
        "<tr><th rowspan=2>method</th><th rowspan=2>n</th>"
        + "".join(f"<th colspan=3>{a}</th>" for a in "xyz")
        + "<th colspan=3>3-D (eq. 27)</th><th colspan=2>seed 000, 3-D</th></tr><tr>"
        + "<th>mean</th><th>std</th><th>max |·|</th>" * 3
        + "<th>mean</th><th>std</th><th>max</th><th>mean</th><th>max</th></tr>"
    )
    body = []
    for k in table_rows(result):
        st = t2[k]
        run = result.runs[k]
        failed = len(run.failures())
        label = _e(run.label) + (f" <small>({failed} failed)</small>" if failed else "")
        cells = "".join(
            f"<td>{st[a]['mean']:+.3f}</td><td>{st[a]['std']:.3f}</td><td>{st[a]['max_abs']:.3f}</td>"
            for a in "xyz"
        )
        d = st["3d"]
        body.append(
            f'<tr><td><span class="dot" style="background:{COLORS.get(k, "#555")}"></span>{label}</td>'
            f"<td>{st['n']}</td>{cells}<td><b>{d['mean']:.3f}</b></td><td>{d['std']:.3f}</td>"
            f"<td><b>{d['max']:.3f}</b></td><td class=paper>{seed_figure(k, 'mean') or '—'}</td>"
            f"<td class=paper>{seed_figure(k, 'max') or '—'}</td></tr>"
        )
    return f"<table class=num>{head}{''.join(body)}</table>"


def _html_iso_table(result: TrialResult) -> str:
    runs = result.iso.get("runs", {})
    pts = np.asarray(result.iso.get("points_mm", []), dtype=float)
    rows = []
    for i, p in enumerate(pts):
        cells = []
        for key in ("without", "with"):
            st = runs.get(key, {}).get("stats")
            if st is None:
                cells.append("<td>—</td>" * 3)
            else:
                cells.append(
                    f"<td>{st['vap_mm'][i]:.3f}</td><td>{st['rp_max_mm'][i]:.3f}</td><td>{st['ratio'][i]:.1f}</td>"
                )
        rows.append(f"<tr><td>P{i + 1} ({p[0]:.0f}, {p[1]:.0f}, {p[2]:.0f})</td>{''.join(cells)}</tr>")
    return (
        "<table class=num><tr><th rowspan=2>test point (mm)</th><th colspan=3>robot alone</th>"
        "<th colspan=3>with joint feedback</th></tr><tr>"
        + "<th>vAP</th><th>RP</th><th>vAP/RP</th>" * 2
        + f"</tr>{''.join(rows)}</table>"
    )


def _html_comparison(result: TrialResult) -> str:
    out = []
    for key, title in COMPARISONS:
        comp = result.comparison.get(key)
        if not comp:
            continue
        rows = comp["rows"]
        trs = []
        for label, m in comp["models"].items():
            if "table2" not in m:
                trs.append(f"<tr><td>{_e(label)}</td><td>{_e(m['paper'])}</td><td colspan=6>not fitted: "
                           f"{_e(m.get('error'))}</td></tr>")  # fmt: skip
                continue
            t = m["table2"]
            d = t["3d"]
            extra = []
            if m.get("order") is not None:
                extra.append(f"order {m['order']}")
            if "dir_separation_deg" in m:
                extra.append(f"ρ = {m['dir_separation_deg']:g}°")
            note = f" <small>({', '.join(extra)})</small>" if extra else ""
            trs.append(
                f"<tr><td>{_e(label)}{note}</td><td>{_e(m['paper'])}</td><td>{d['mean']:.3f}</td>"
                f"<td>{d['std']:.3f}</td><td>{d['max']:.3f}</td>"
                + "".join(f"<td>{t[a]['std']:.3f}</td>" for a in "xyz")
                + "</tr>"
            )
        out.append(
            f"<h3>On the {title}</h3><p>Fitted on the {rows['fit']} sampling points, judged on the "
            f"{rows['check']} target points at the commands of the nominal program "
            "(measured − predicted).</p>"
            "<table class=num><tr><th>model</th><th>method of</th><th>3-D mean</th><th>std</th><th>max</th>"
            f"<th>x std</th><th>y std</th><th>z std</th></tr>{''.join(trs)}</table>"
        )
    return "".join(out)


def _order(model: dict[str, Any]) -> str:
    """A model's Chebyshev order, or a dash for a kind that has none."""
    order = model.get("order")
    return "–" if order is None else str(order)


def _html_models(result: TrialResult) -> str:
    rows = []
    for label, m in result.models.items():
        st = m.get("server_table2", {}).get("model", {}).get("3d", {})
        rows.append(
            f"<tr><td>{_e(label)}</td><td>{m['id']}</td><td>{_e(m['kind'])}</td><td>{_e(_order(m))}</td>"
            f"<td>{m['dataset_id']}</td><td>{_e(m.get('fit_rows'))}</td><td>{_f(st.get('mean'))}</td>"
            f"<td>{_f(st.get('max'))}</td></tr>"
        )
    ds = "".join(
        f"<tr><td>{_e(name)}</td><td>{d['id']}</td><td>{d['rows']}</td><td>{d['fit_rows']}</td>"
        f"<td>{d['check_rows']}</td><td><code>{_e(d['sha256'][:16])}…</code></td></tr>"
        for name, d in result.datasets.items()
    )
    return (
        "<table><tr><th>data set</th><th>id</th><th>rows</th><th>fit</th><th>check</th><th>sha256</th></tr>"
        f"{ds}</table><table class=num><tr><th>model</th><th>id</th><th>kind</th><th>order</th>"
        "<th>data set</th><th>fit rows</th><th>check 3-D mean</th><th>check max</th></tr>"
        f"{''.join(rows)}</table>"
    )


CSS = """
body{font-family:system-ui,sans-serif;margin:24px auto;max-width:900px;color:#222;line-height:1.4}
h1{font-size:22px;margin-bottom:4px}h2{font-size:17px;margin-top:28px;border-bottom:1px solid #ddd}
h3{font-size:14px}table{border-collapse:collapse;margin:8px 0;font-size:12px}
td,th{border:1px solid #ddd;padding:2px 5px}th{background:#f4f4f4}
table.num td{text-align:right}table.num td:first-child,table.num td:nth-child(2){text-align:left}
td.paper{color:#666;font-style:italic}.dot{display:inline-block;width:9px;height:9px;margin-right:5px}
.summary{display:flex;gap:10px;flex-wrap:wrap;margin:14px 0}
.card{border:1px solid #ddd;border-radius:6px;padding:8px 12px;min-width:170px}
.card b{font-size:20px;display:block}.card small{color:#666}.ok{color:#1e8449}.bad{color:#c0392b}
.fig{margin:6px 0}figure.plot{margin:8px 0}figcaption{font-size:12px;color:#555}
small{color:#666}code{font-size:12px}
"""


def _html_cards(result: TrialResult) -> str:
    """The summary cards: the 3-D max and mean of seed 000's three methods, beside seed 000's figure."""
    t2 = result.table2()
    cards = []
    for k in ("uncompensated", "kinematic", "chebyshev+feedback"):
        if k in t2:
            d = t2[k]["3d"]
            seed = f"seed 000: {seed_figure(k, 'max')}" if seed_figure(k, "max") else ""
            cards.append(
                f'<div class=card><small>{_e(result.runs[k].label)}, max</small><b style="color:'
                f'{COLORS[k]}">{d["max"]:.3f} mm</b><small>mean {d["mean"]:.3f} · {seed}</small></div>'
            )
    return "".join(cards)


def _html_verdict(v: dict[str, Any]) -> str:
    """Whether the ordering of seed 000's Table 2 holds, and the trial's figures beside the claim."""
    if "ordering" not in v:
        return ""
    o, t = v["ordering"], v["claim"]["trial"]
    good = o["mean"] and o["max"]
    return (
        f"<p class={'ok' if good else 'bad'}><b>Ordering</b> (3-D mean and max): closed loop &lt; "
        f"kinematic calibration &lt; uncompensated: <b>{'holds' if good else 'does not hold'}</b>.</p>"
        f"<p><b>Seed 000's claim</b>: max 0.76 → 0.19 mm (−75 %; −55 % against kinematic calibration). "
        f"<b>This trial</b>: max {t['before_max']:.3f} → {t['after_max']:.3f} mm "
        f"(−{100 * t['reduction']:.0f} %; −{100 * t['vs_kinematic']:.0f} % against kinematic "
        f"calibration), every axis within ±{t['axis_max_abs']:.3f} mm.</p>"
    )


def _html_gratings(result: TrialResult) -> str:
    """The grating calibration's table, one row a joint (empty when it did not run)."""
    if not result.gratings:
        return ""
    rows = "".join(
        f"<tr><td>A{m['joint']}</td><td>{m['n_readings']}</td><td>{m['span_deg']:.1f}</td>"
        f"<td>{grating_scale(m):.6f}</td><td>{m['zero_deg']:.4f}</td><td>{m['residual_rms_deg']:.4f}</td>"
        f"<td>{m['residual_max_deg']:.4f}</td></tr>"
        for m in result.gratings["joints"]
    )
    return (
        "<table class=num><tr><th>joint</th><th>readings</th><th>span (°)</th><th>scale</th>"
        f"<th>zero (°)</th><th>residual rms (°)</th><th>max (°)</th></tr>{rows}</table>"
    )


def _html_run(result: TrialResult) -> str:
    """The run itself: RSI counters and reply latency, the targets that did not finish, those
    posted again, and the time of each phase."""
    loop = result.loop
    ctl, dmn = loop.get("controller", {}), loop.get("daemon", {})
    runs = [*result.sampling.values(), *result.runs.values()]
    failures = [
        f"<li>{_e(run.label)}, point {f['index'] + 1}: {_e(f['state'])} — {_e(f['reason'])}</li>"
        for run in runs
        for f in run.failures()
    ]
    retries = [
        f"<li>{_e(run.label)}, point {f['index'] + 1}: {_e(f['reason'])}</li>"
        for run in runs
        for f in run.retried
    ] + [f"<li>ISO 9283 with joint feedback, {_e(why)}</li>" for why in iso_retried(result)]
    phases = "".join(
        f"<tr><td>{_e(p['name'])}</td><td>{p['duration_s']:.0f}</td></tr>" for p in result.phases
    )
    failed = "<p>Targets that did not finish:</p><ul>" + "".join(failures) + "</ul>" if failures else ""
    retried = (
        "<p>Targets posted again after a failure that says the computer was busy (a grating reading or RSI "
        "telegrams late), each measured once done:</p><ul>" + "".join(retries) + "</ul>"
        if retries
        else ""
    )
    sent, late = _e(ctl.get("telegrams_sent")), _e(ctl.get("late_total"))
    return f"""<p>RSI: {sent} telegrams, {late} late replies counted by the
controller, {_e(ctl.get("overruns"))} controller overruns; reply latency p50 {_f(dmn.get("latency_p50_ms"))} /
p99 {_f(dmn.get("latency_p99_ms"))} / max {_f(dmn.get("latency_max_ms"))} ms (recent window); daemon exit
code {_e(loop.get("daemon_exit_code"))}.</p>
{failed}
{retried}
<table class=num><tr><th>phase</th><th>s</th></tr>{phases}</table>"""


def render_html(result: TrialResult, *, command: str | None = None) -> str:
    plan, sizes = result.plan, result.plan["sizes"]
    rows = table_rows(result)
    hist = error_histogram_figure(result, rows) + method_histograms_figure(result, rows)
    env = result.environment
    incomplete = "" if result.complete else f" · <b class=bad>incomplete: {_e(result.error)}</b>"
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>comp-daemon trial</title>
<meta name="viewport" content="width=device-width, initial-scale=1"><style>{CSS}</style></head><body>
<h1>Seed 000's experiment, end to end through the daemon</h1>
<div><small>scenario <b>{_e(plan["scenario"])}</b> (seed {plan["seed"]}, payload {plan["payload_kg"]:g} kg) ·
{sizes["n_sampling"]} sampling + {sizes["n_targets"]} target points ·
Chebyshev order {sizes["chebyshev_order"]}
· started {_e(result.started_at)} · {result.duration_s / 60:.1f} min · Python {_e(env.get("python"))},
{_e(env.get("cpus"))} CPUs{incomplete}
{"<br><code>" + _e(command) + "</code>" if command else ""}</small></div>
<div class=summary>{_html_cards(result)}</div>
{_html_verdict(verdict(result))}
<h2>Table 2: positioning error of the target points</h2>
<p>Error = tracker − wanted TCP, robot base frame, mm; per axis the signed components, 3-D the distance.
Seed 000 gives only the 3-D figures quoted in its text.</p>
{_html_table2(result)}
<div class=fig>{hist}</div>
<h2>Per target point (seed 000 Figs 7–10)</h2>
<div class=fig>{point_error_figures(result, rows)}</div>
<h2>ISO 9283 multi-directional pose accuracy (seed 000 Figs 5–6)</h2>
<p>Each test point approached from +x, +y and +z ({_e(result.iso.get("approach_mm"))} mm moves),
{_e(result.iso.get("cycles"))} cycles after {_e(result.iso.get("warmup_cycles"))} warm-up cycle(s);
vAP: largest
distance between the three directions' barycentres; RP = l̄ + 3·S_l of the worst direction; rated
repeatability ±{_e(result.iso.get("repeatability_rated_mm"))} mm.</p>
<div class=fig>{iso_figure(result)}</div>
{_html_iso_table(result)}
<h2>Seed 001's model comparison on the same data</h2>
{_html_comparison(result)}
<h2>Data sets and models (over the HTTP API)</h2>
{_html_models(result)}
<h2>Grating calibration (seed 000 step 1)</h2>
{_html_gratings(result)}
<h2>The run</h2>
{_html_run(result)}
</body></html>
"""
