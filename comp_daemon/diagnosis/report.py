"""The diagnosis as one self-contained HTML page (inline SVG and CSS, no scripts, no external assets).

Sections: summary; the ladder as a table and a bar chart (check RMS per step, noise floor as a
line); for each significant effect, the residual before that step per axis (x, y, z, mm) against
the variable that drives the effect (axis value, gravity torque or temperature) with the effect's
fitted contribution drawn over it; per joint, the equivalent joint error of the post-geometric
residual against the axis value, by approach direction, with the fitted effects' share drawn
over it; histograms of the 3-D check error before and after; the remaining error per pose, per
joint angle, as a variogram over joint distance, against time, and measured against predicted;
the ``where`` tables; what was skipped and why, and the parameters geometry could not identify.
The fitted values of every step are tables (name, meaning, joint, unit, value, standard error:
:mod:`comp_daemon.diagnosis.param_table`), the selection rounds a table of the best candidates per
round. The figures are drawn by matplotlib in :mod:`comp_daemon.diagnosis.plots`; a print style
lays the page out for paper (A4 landscape, no figure or table split across pages), so that a
browser's "print to PDF" gives the report as a document.
"""

from __future__ import annotations

import html
from typing import Any

from comp_daemon.diagnosis.param_table import ParamRow, parameter_rows
from comp_daemon.diagnosis.result import Diagnosis
from comp_daemon.diagnosis.structure import describe_structure

__all__ = ["render_report_html"]


CSS = """
body{font-family:sans-serif;margin:24px;color:#222;max-width:1400px}
h1{font-size:20px}h2{font-size:16px;margin-top:28px;border-bottom:1px solid #ccc}
table{border-collapse:collapse;font-size:12px;margin:8px 0}
td,th{border:1px solid #ccc;padding:3px 7px;text-align:right}th{background:#f3f3f3}
td.l,th.l{text-align:left}.sig{color:#1a7f37;font-weight:bold}.nsig{color:#999}
.grid{display:flex;flex-wrap:wrap;gap:8px}
figure.plot{margin:10px 0}figcaption{font-size:12px;color:#555;max-width:1000px}
.summary{background:#f7f7f2;padding:10px;border-left:4px solid #2ca02c}
code{font-size:11px}h3{font-size:13px;margin:14px 0 4px}
table.values td:nth-child(n+5),table.rounds td{font-variant-numeric:tabular-nums}
td[rowspan]{vertical-align:top}
figure.plot svg{max-width:100%;height:auto}
@page{size:A4 landscape;margin:12mm}
@media print{
body{margin:0;max-width:none;font-size:10px}
h2{break-after:avoid;page-break-after:avoid}h3{break-after:avoid}
figure.plot,table,tr,.summary{break-inside:avoid;page-break-inside:avoid}
a{color:inherit;text-decoration:none}
.summary{border-left-color:#000;background:none}
}
"""


def _e(text: object) -> str:
    return html.escape(str(text))


def _num(v: float | None, digits: int = 4) -> str:
    if v is None:
        return "–"
    return f"{v:.{digits}g}"


def _ladder_table(diag: Diagnosis) -> str:
    rows = [
        "<tr><th class=l>step</th><th class=l>effect</th><th class=l>joints</th><th>significant</th>"
        "<th>parameters (total)</th><th>p-value</th><th>CV RMS (fit rows)</th><th>check RMS</th>"
        "<th>check max</th>"
        "<th>shrink</th><th class=l>note</th></tr>",
        "<tr><td class=l>0</td><td class=l>nominal</td><td class=l>–</td><td>–</td><td>0</td><td>–</td>"
        f"<td>–</td>"
        f"<td>{diag.baseline_check_rms_mm:.4f}</td><td>{diag.baseline_check_max_mm:.4f}</td><td>–</td>"
        f"<td class=l>{'registered to the tracker frame' if diag.frame == 'tracker' else ''}</td></tr>",
    ]
    for k, s in enumerate(diag.steps, start=1):
        sig = "<span class=sig>yes</span>" if s.significant else "<span class=nsig>no</span>"
        rows.append(
            f"<tr><td class=l>{k}</td><td class=l>{_e(s.effect)}</td>"
            f"<td class=l>{_e(', '.join(str(j) for j in s.joints) or '–')}</td><td>{sig}</td>"
            f"<td>{s.n_params}</td><td>{_num(s.p_value, 3)}</td><td>{_num(s.cv_rms_mm)}</td>"
            f"<td>{s.check_rms_mm:.4f}</td><td>{s.check_max_mm:.4f}</td><td>{s.shrink_pct:.1f} %</td>"
            f'<td class=l><a href="#values-{k}">fitted values</a></td></tr>'
        )
    return "<table>" + "".join(rows) + "</table>"


def _sigma_text(row: ParamRow) -> tuple[str, str]:
    """σ and |value| / σ of a fitted value, as table cells."""
    if row.sigma is None or row.sigma <= 0.0:
        return "–", "–"
    return f"{row.sigma:.2g}", f"{abs(row.value) / row.sigma:.1f}"


def _values_tables(diag: Diagnosis) -> str:
    """The fitted values of every step: name, where, unit, value, σ (cluster-robust) and value/σ."""
    rows = parameter_rows(diag)
    out = [
        "<p>Changes from the nominal twin (geometric step) and the effects' parameters, each with its "
        "cluster-robust standard error σ (poses as clusters) at the step's fit on the fit rows. "
        "|value| / σ below 2 means the data barely tell the value from zero.</p>"
    ]
    for k, step in enumerate(diag.steps, start=1):
        mine = [r for r in rows if r.step == k]
        sig = "significant" if step.significant else "not significant"
        out.append(
            f"<h3 id=values-{k}>Step {k}: {_e(step.effect)} ({sig})</h3>"
            "<table class=values><tr><th class=l>parameter</th><th class=l>meaning</th>"
            "<th class=l>joint / axis</th><th class=l>unit</th><th>value</th><th>σ</th>"
            "<th>|value| / σ</th></tr>"
        )
        for r in mine:
            sigma, ratio = _sigma_text(r)
            unit = "–" if r.unit == "1" else r.unit
            out.append(
                f"<tr><td class=l><code>{_e(r.name)}</code></td><td class=l>{_e(r.what)}</td>"
                f"<td class=l>{_e(r.where)}</td><td class=l>{_e(unit)}</td>"
                f"<td>{r.value:.4g}</td><td>{sigma}</td><td>{ratio}</td></tr>"
            )
        settings = {k2: v for k2, v in step.params.items() if not isinstance(v, dict) and k2 != "harmonics"}
        if settings:
            words = ", ".join(f"{_e(k2)} = {_e(v)}" for k2, v in settings.items())
            out.append(f"<tr><td class=l colspan=7>settings: {words}</td></tr>")
        out.append("</table>")
    return "".join(out)


def _selection_table(diag: Diagnosis) -> str:
    """Every selection round: the error before it, the best candidates, what was accepted."""
    if not diag.selection:
        return "<p>No selection round (no effect was tested).</p>"
    out = [
        "<table class=rounds><tr><th>round</th><th>CV RMS before (mm)</th><th>candidates</th>"
        "<th>p threshold</th><th class=l>candidate</th><th>CV RMS with it (mm)</th><th>p-value</th>"
        "<th class=l>outcome</th></tr>"
    ]
    for r in diag.selection:
        best = r.get("best") or [{}]
        outcome = f"accepted {r['accepted']}" if r.get("accepted") else "none accepted: stop"
        if r.get("preferred_simpler"):
            outcome += f" (simpler {r['preferred_simpler']} preferred)"
        extra = {k: v for k, v in r.items() if k not in _ROUND_KEYS}
        if extra:
            outcome += "; " + ", ".join(f"{k} {v}" for k, v in extra.items())
        span = len(best)
        for i, b in enumerate(best):
            chosen = b.get("candidate") is not None and b.get("candidate") == r.get("accepted")
            cand = f"<b>{_e(b.get('candidate', '–'))}</b>" if chosen else _e(b.get("candidate", "–"))
            head = (
                f"<td rowspan={span}>{_e(r.get('round', ''))}</td>"
                f"<td rowspan={span}>{_num(r.get('cv_rms_mm_before'))}</td>"
                f"<td rowspan={span}>{_e(r.get('candidates', ''))}</td>"
                f"<td rowspan={span}>{_num(r.get('p_threshold'), 2)}</td>"
                if i == 0
                else ""
            )
            tail = f"<td class=l rowspan={span}>{_e(outcome)}</td>" if i == 0 else ""
            out.append(
                f"<tr>{head}<td class=l>{cand}</td><td>{_num(b.get('cv_rms_mm'))}</td>"
                f"<td>{_num(b.get('p_value'), 2)}</td>{tail}</tr>"
            )
    out.append("</table>")
    return "".join(out)


_ROUND_KEYS = frozenset(
    ("round", "cv_rms_mm_before", "candidates", "p_threshold", "best", "preferred_simpler", "accepted")
)


def _floor_html(diag: Diagnosis) -> str:
    if diag.noise_floor_mm is None:
        return (
            "no noise floor: the data have no repeated poses and no tracker uncertainty was declared, "
            "so the remainder could not be compared with noise."
        )
    return f"noise floor {diag.noise_floor_mm:.4g} mm ({_e(diag.noise_floor_source)})."


def _structure_table(diag: Diagnosis) -> str:
    """The remainder tested against each variable (out of fold, against permutations)."""
    if not diag.residual_structure:
        return "<p>No variable to test the remainder against.</p>"
    rows = [
        "<tr><th>against</th><th>share of the remainder (out of fold)</th><th>p</th><th>significant</th></tr>"
    ]
    for r in diag.residual_structure:
        mark = "<b>yes</b>" if r.significant else "no"
        rows.append(
            f"<tr><td>{_e(r.against)}</td><td>{r.share_pct:.1f} %</td>"
            f"<td>{r.p_value:.3g}</td><td>{mark}</td></tr>"
        )
    words = describe_structure(diag.residual_structure)
    return (
        f"<p>Remainder of the final model on {_e(diag.remainder_rows)}; {_e(words)}</p>"
        "<table>" + "".join(rows) + "</table>"
    )


def _remainder_html(diag: Diagnosis) -> str:
    """The joint-space remainder model: whether it won out of fold, and what it took on check rows."""
    model = diag.remainder_model
    if model is None:
        return "<p>No joint-space remainder model was tried.</p>"
    words = f"<p>{_e(model.describe())}</p>"
    if not model.tried:
        return words
    scales = ", ".join(f"A{j} {v:.3g}°" for j, v in model.length_scales_deg.items())
    rows = [
        ("kept", "<b>yes</b>" if model.kept else "no"),
        ("why", _e(model.reason)),
        (
            "cross-validated RMS on fit rows, before → after",
            f"{_num(model.cv_rms_mm_before)} → {_num(model.cv_rms_mm_after)} mm",
        ),
        (
            "check RMS, before → after",
            f"{_num(model.check_rms_mm_before)} → {_num(model.check_rms_mm_after)} mm",
        ),
        ("length scales", _e(scales)),
        ("smooth part / noise (3-D RMS)", f"{_num(model.signal_rms_mm)} / {_num(model.noise_rms_mm)} mm"),
    ]
    table = "".join(f"<tr><th>{k}</th><td>{v}</td></tr>" for k, v in rows)
    return words + "<table>" + table + "</table>"


def _comparison_html(diag: Diagnosis) -> str:
    """The ladder beside the compensation models fitted on the same rows."""
    comparison = diag.model_comparison
    if comparison is None:
        return "<p>No compensation model was compared (<code>--compare-models none</code>).</p>"
    rows = [("the ladder (last significant step)", comparison.ladder_check_rms_mm, "")]
    rows += [(m["model"], m["check_rms_mm"], f"{m['cpu_s']:.2f}") for m in comparison.models]
    if comparison.remainder_check_rms_mm is not None:
        rows.append(("the ladder + its joint-space remainder model", comparison.remainder_check_rms_mm, ""))
    table = "".join(
        f"<tr><td class=l>{_e(name)}</td><td>{_num(rms)}</td><td>{cpu}</td></tr>" for name, rms, cpu in rows
    )
    skipped = "".join(f"<li>{_e(s['model'])}: {_e(s['reason'])}</li>" for s in comparison.skipped)
    return (
        f"<p>{_e(comparison.describe())}</p><table><tr><th class=l>model</th>"
        f"<th>check RMS (mm, {comparison.check_rows} rows)</th><th>fit CPU (s)</th></tr>{table}</table>"
        + (f"<p>Not compared:</p><ul>{skipped}</ul>" if skipped else "")
    )


def _where_tables(where: dict[str, Any]) -> str:
    axis = where["axis_rms_mm"]
    out = [
        "<table><tr><th>x RMS</th><th>y RMS</th><th>z RMS</th><th>3-D RMS</th></tr>"
        f"<tr><td>{axis['x']}</td><td>{axis['y']}</td><td>{axis['z']}</td><td>{where['rms_mm']}</td></tr></table>",
        "<table><tr><th>joint</th><th>equivalent RMS (deg)</th><th>share of the gap (%)</th>"
        "<th>mean dir +1 (deg)</th><th>mean dir −1 (deg)</th><th>step (deg)</th></tr>",
    ]
    for p in where["per_joint"]:
        d = p.get("vs_dir", {})
        out.append(
            f"<tr><td>{p['joint']}</td><td>{_num(p['equivalent_rms_deg'])}</td><td>{p['share_pct']}</td>"
            f"<td>{_num(d.get('plus', {}).get('mean_deg'))}</td>"
            f"<td>{_num(d.get('minus', {}).get('mean_deg'))}</td>"
            f"<td>{_num(d.get('step_deg'))}</td></tr>"
        )
    out.append(
        "</table><table><tr><th class=l>region</th><th>poses</th><th class=l>centre (mm)</th>"
        "<th>RMS (mm)</th><th>max (mm)</th></tr>"
    )
    for r in where["regions"]:
        centre = ", ".join(f"{v:.0f}" for v in r["centre_mm"])
        out.append(
            f"<tr><td class=l>{_e(r['region'])}</td><td>{r['n']}</td><td class=l>{centre}</td>"
            f"<td>{r['rms_mm']}</td><td>{r['max_mm']}</td></tr>"
        )
    out.append("</table>")
    flange = where.get("flange")
    if flange is not None:
        out.append(
            f"<table><tr><th>flange ({flange['targets']} targets, check rows)</th>"
            "<th>RMS</th><th>max</th></tr>"
            f"<tr><td class=l>position (mm)</td><td>{flange['position_rms_mm']}</td>"
            f"<td>{flange['position_max_mm']}</td></tr>"
            f"<tr><td class=l>orientation (deg)</td><td>{flange['orientation_rms_deg']}</td>"
            f"<td>{flange['orientation_max_deg']}</td></tr></table>"
        )
    return "".join(out)


def render_report_html(diag: Diagnosis) -> str:
    """The HTML report of a diagnosis (a complete document, UTF-8 text)."""
    # matplotlib is loaded when a report is drawn, not by every command and the daemon at start
    from comp_daemon.diagnosis.plots import report_figures

    figures = report_figures(diag)
    doc = diag.to_json()
    skipped = (
        "".join(
            f"<li>{_e(s['effect'])}"
            f"{' on joints ' + _e(', '.join(map(str, s['joints']))) if s['joints'] else ''}"
            f": {_e(s['reason'])}</li>"
            for s in diag.skipped
        )
        or "<li>none</li>"
    )
    unident = "".join(f"<li><code>{_e(u)}</code></li>" for u in diag.unidentifiable) or "<li>none</li>"
    unmodelled = ", ".join(doc["unmodelled"]) or "none"
    body = [
        "<!DOCTYPE html><html lang=en><head><meta charset=utf-8>",
        f"<title>Gap diagnosis – {_e(diag.robot.name)}</title><style>{CSS}</style></head><body>",
        f"<h1>Sim-to-real gap diagnosis: {_e(diag.robot.name)}</h1>",
        f"<p>Data <code>{_e(diag.dataset.source)}</code> ({len(diag.fit_rows)} fit rows, "
        f"{len(diag.check_rows)} check "
        f"rows; {_e(diag.split_message)}). Measured in the {_e(diag.frame)} frame. "
        f"Unmodelled effects: <b>{_e(unmodelled)}</b>; implicated joints: "
        f"<b>{_e(', '.join(map(str, doc['joints'])) or 'none')}</b>. "
        f"Unexplained {doc['unexplained_rms_mm']} mm RMS, " + _floor_html(diag) + "</p>",
        f"<p class=summary>{_e(diag.where['summary'])}</p>",
        "<h2>The ladder</h2>",
        _ladder_table(diag),
        figures["ladder"],
        "<h2>Fitted values</h2>",
        _values_tables(diag),
        "<h2>Residuals per axis, with each added effect</h2>",
        figures["effects"],
        "<h2>Per joint: equivalent joint error after the geometric step</h2>",
        figures["joints"],
        "<h2>Before and after (check rows)</h2>",
        figures["histograms"],
        "<h2>The remaining error</h2>",
        figures["residuals"],
        "<h2>Where the gap lies after the geometric step (all rows)</h2>",
        _where_tables(diag.where),
        "<h2>Structure in the remainder</h2>",
        _structure_table(diag),
        "<h2>Joint-space remainder model</h2>",
        _remainder_html(diag),
        "<h2>Beside the compensation models</h2>",
        _comparison_html(diag),
        "<h2>Not tested</h2><ul>",
        skipped,
        "</ul>",
        "<h2>Geometric parameters not identifiable from these poses</h2><ul>",
        unident,
        "</ul>",
        "<h2>Selection rounds</h2>",
        _selection_table(diag),
        "</body></html>",
    ]
    return "".join(body)
