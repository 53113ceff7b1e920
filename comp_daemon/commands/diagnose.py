"""``comp-daemon diagnose DATA --robot ROBOT [--json OUT.json] [--report OUT.html]``: the gap diagnosis.

Reads a measurement data set (CSV, or JSON records when the file name ends in ``.json``), runs the
diagnosis of ``docs/diagnosis-output.md`` against the robot's nominal twin, and writes the JSON
document (to ``--json``, else to stdout) and, with ``--report``, the self-contained HTML report.
Outputs are written only when the whole diagnosis succeeded, each through a temporary file that is
renamed into place. On a terminal, stderr shows a spinner with the elapsed time while it runs
(:mod:`comp_daemon.commands.progress`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from comp_daemon.commands.data import read_options_of, reader_options
from comp_daemon.commands.options import add_settings, settings_of
from comp_daemon.commands.progress import progress
from comp_daemon.common.atomic import write_text_atomic
from comp_daemon.data.dataset import read_dataset_file
from comp_daemon.diagnosis import DiagnoseOptions, diagnose
from comp_daemon.diagnosis.options import diagnose_options
from comp_daemon.diagnosis.report import render_report_html
from comp_daemon.diagnosis.result import Diagnosis
from comp_daemon.estimation.registration import BASE_FRAME_MAX_RMS_MM
from comp_daemon.models.effects import EFFECTS
from comp_daemon.preparation.options import DiagnosisSettings
from comp_daemon.robot.description import PRESETS, load_robot


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "diagnose",
        help="sim-to-real gap diagnosis: which unmodelled effect, on which joints, how far the error shrinks",
        description="Diagnose the gap between a robot's nominal twin and tracker measurements: a ladder from "
        "the nominal twin through geometric calibration and the significant non-geometric effects "
        f"({', '.join(EFFECTS)}), chosen on fit rows by cross-validation and judged on check rows.",
    )
    p.add_argument(
        "data", metavar="DATA", help="measurement data set (CSV per docs/data-format.md, or .json records)"
    )
    p.add_argument("--robot", required=True, help=f"preset ({', '.join(PRESETS)}) or path to a TOML file")
    p.add_argument(
        "--json",
        dest="json_out",
        type=Path,
        metavar="OUT.json",
        help="write the diagnosis here (default: print it)",
    )
    p.add_argument("--report", type=Path, metavar="OUT.html", help="also write the HTML report here")
    reader_options(p)
    add_settings(p, DiagnosisSettings)
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    robot = load_robot(args.robot)
    options = diagnose_options(settings_of(args, DiagnosisSettings))
    # the row floor is the geometric step's, on the fit rows (diagnosis.ladder.diagnose says it)
    dataset = read_dataset_file(
        Path(args.data),
        limits_deg=robot.axis_limits_deg,
        min_rows=0,
        kind="measurement",
        options=read_options_of(args),
    )
    for target in (args.json_out, args.report):
        if target is not None and not target.expanduser().parent.is_dir():
            raise ValueError(f"cannot write {target}: no such directory")
    with progress(f"diagnosing {len(dataset)} rows of {dataset.source}") as steps:
        diag = diagnose(dataset, robot, options)
        doc = json.dumps(diag.to_json(), indent=2, ensure_ascii=False)
        steps.note("writing the report")
        report = render_report_html(diag) if args.report is not None else None
    if diag.split_drawn:
        print(diag.split_message, file=sys.stderr)
    if diag.directions is not None and diag.directions.note:
        print(f"{diag.dataset.source}: {diag.directions.note}", file=sys.stderr)
    if args.json_out is None:
        print(doc)
    else:
        write_text_atomic(args.json_out.expanduser(), doc + "\n")
    if report is not None:
        write_text_atomic(args.report.expanduser(), report)
    if args.json_out is not None:  # the document went to a file: its summary on the terminal
        print("\n".join(summary_lines(diag, robot.name, options)))
    return 0


def summary_lines(diag: Diagnosis, robot: str, options: DiagnoseOptions) -> list[str]:
    """The terminal summary of a diagnosis: the baseline, each rung, the noise floor and what is
    unmodelled, then what the reader should know about the data and the comparison."""
    lines = [
        f"{robot}: baseline {diag.baseline_check_rms_mm:.4f} mm RMS on {len(diag.check_rows)} check rows"
    ]
    if options.frame == "base" and diag.baseline_check_rms_mm > BASE_FRAME_MAX_RMS_MM:
        lines.append(
            f"--frame base, but the nominal twin misses the measurements by "
            f"{diag.baseline_check_rms_mm:.1f} mm RMS (more than {BASE_FRAME_MAX_RMS_MM:g} mm): they "
            "look like a tracker's frame; the baseline and the geometric shrink then measure the "
            "frame, not the robot (--frame auto or tracker registers it first)"
        )
    for s in diag.steps:
        joints = ",".join(map(str, s.joints)) or "-"
        flag = "significant" if s.significant else "not significant"
        lines.append(
            f"  {s.effect:<10s} joints {joints:<12s} check {s.check_rms_mm:.4f} mm "
            f"(shrink {s.shrink_pct:5.1f} %)  {flag}"
        )
    lines.append(
        f"unmodelled: {', '.join(diag.unmodelled) or 'none found'}; "
        f"unexplained {diag.unexplained_rms_mm:.4f} mm, {_floor(diag, options.tracker_sigma_mm)}"
    )
    lines.extend(unnamed["summary"] for unnamed in diag.unnamed)
    if diag.agreement is not None and not diag.agreement.agree:
        lines.append(diag.agreement.describe())
    return lines + _caveats(diag)


def _floor(diag: Diagnosis, declared_mm: float | None) -> str:
    """The noise floor, where it comes from, and the unexplained error against it."""
    floor = (
        "no noise floor (no repeats, no --tracker-sigma-mm or sigma_mm, no second target): "
        "not compared with noise"
        if diag.noise_floor_mm is None
        else f"noise floor {diag.noise_floor_mm:.4f} mm ({diag.noise_floor_source})"
    )
    floor += _against_floor(diag)
    if declared_mm is not None and diag.noise_floor_source not in (None, "declared"):
        floor += f"; --tracker-sigma-mm not used: the {diag.noise_floor_source} measure the noise"
    return floor


def _caveats(diag: Diagnosis) -> list[str]:
    """What the data assumed (the clock, the approach directions), what could not be tested, what
    the remainder follows, and the compensation models compared."""
    lines = []
    timed = [s.effect for s in diag.steps if s.significant and s.effect in ("drift", "step")]
    if timed and diag.obs.clock_name != "t_s":
        lines.append(
            f"clock: the row order (no t_s column): {' and '.join(timed)} assume the rows are in "
            "the order they were measured"
        )
    if diag.directions is not None and diag.directions.inferred:
        named = "named" if "backlash" in diag.unmodelled else "tested"
        assumed = (
            " (assumed to be the order the robot visited the poses)"
            if diag.directions.order == "row order"
            else ""
        )
        lines.append(
            f"directions: backlash {named} on approach directions inferred from the "
            f"{diag.directions.order}{assumed}; give dir1..dir6 to make them certain"
        )
    untested = untested_effects(diag.skipped)
    if untested:
        lines.append(f"not tested: {untested}")
    found = [r for r in diag.residual_structure if r.significant]
    if found:
        lines.append("remainder follows: " + ", ".join(f"{r.against} ({r.share_pct:.0f} %)" for r in found))
    if diag.remainder_model is not None and diag.remainder_model.tried:
        lines.append(diag.remainder_model.describe())
    if diag.model_comparison is not None:
        lines.append(f"models: {diag.model_comparison.describe()}")
    return lines


#: above this multiple of the noise floor the unexplained error is said not to be noise
NOT_NOISE_RATIO = 2.0


def _against_floor(diag: Diagnosis) -> str:
    """The unexplained error as a multiple of the noise floor, and what that multiple says."""
    if diag.noise_floor_mm is None or diag.noise_floor_mm <= 0:
        return ""
    ratio = diag.unexplained_rms_mm / diag.noise_floor_mm
    if ratio > NOT_NOISE_RATIO:
        return f" ({ratio:.1f} x the floor: not noise; an error the effects tried do not name remains)"
    return f" ({ratio:.1f} x the floor: within the noise)"


def untested_effects(skipped: list[dict[str, Any]]) -> str:
    """The effects the data could not test on any joint (their skipped entries cover all six joints,
    or the effect has no joints), each with its reasons, the one covering the most joints first."""
    joints: dict[str, set[int]] = {}
    reasons: dict[str, dict[str, int]] = {}
    for entry in skipped:
        effect, on = entry["effect"], entry.get("joints") or []
        joints.setdefault(effect, set()).update(on if on else range(1, 7))
        by_reason = reasons.setdefault(effect, {})
        by_reason[entry["reason"]] = by_reason.get(entry["reason"], 0) + (len(on) if on else 6)
    out = []
    for effect, on in joints.items():
        if len(on) >= 6:
            ranked = sorted(reasons[effect], key=lambda r: -reasons[effect][r])
            out.append(f"{effect} ({' / '.join(ranked)})")
    return "; ".join(out)
