"""The ballbar and cross-bar doors of ``comp-daemon fit`` and ``evaluate``.

- ``fit CAMPAIGN.csv --robot R --model poe|kinematic --out MODEL.json``: a ballbar campaign
  calibrates the ``poe`` model, a cross-bar campaign the ``kinematic`` model
  (:func:`comp_daemon.instruments.campaign_fit.fit_campaign`); the file's form is told by its columns.
  The artifact is an ordinary ``poe`` / ``kinematic`` model, which ``evaluate --calibrated`` and
  ``compensate`` take. The report names the rank reached and the directions the instrument cannot see.
- ``evaluate BALLBAR.csv --robot R --solvers lm,mfo,imfo,woa``: Levenberg–Marquardt and the
  metaheuristics of seed 002 identify the same ballbar problem (the campaign's fit arcs; the check
  arcs held out), one row per run (:mod:`comp_daemon.instruments.solver_comparison`, spec acceptance
  check 7); ``--json`` writes the runs.
- ``evaluate TRACKER.csv --calibrated MODEL.json,…``: each artifact, calibrated elsewhere, is judged
  on the tracker data's check rows next to the models fitted there; only its base frame is fitted,
  on the fit rows (:func:`comp_daemon.instruments.campaign_fit.registered_prediction`).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from comp_daemon.commands.data import read_options_of
from comp_daemon.commands.errors import UserError
from comp_daemon.commands.options import settings_of
from comp_daemon.common.atomic import write_json_atomic
from comp_daemon.data.ballbar import BallbarCampaign
from comp_daemon.data.bars import read_table, sniff_campaign_file
from comp_daemon.data.campaigns import campaign_of
from comp_daemon.data.columns import DatasetError
from comp_daemon.data.options import ReadOptions
from comp_daemon.data.table import Dataset
from comp_daemon.estimation.uncertainty import repeat_uncertainty
from comp_daemon.instruments.campaign_fit import registered_prediction, uncertainty_summary
from comp_daemon.instruments.solver_comparison import (
    SolverProblem,
    compare_solvers,
    parse_solvers,
    solver_table,
)
from comp_daemon.models.artifact import ModelArtifactError, load_model, save_model
from comp_daemon.models.covariance import near_dependent_note
from comp_daemon.models.evaluation import error_statistics
from comp_daemon.models.poe.calibration import layout_twists, paper_layout
from comp_daemon.preparation.campaign import CampaignError
from comp_daemon.preparation.options import FitSettings
from comp_daemon.preparation.pipeline import calibrate_campaign, nominal_tcp
from comp_daemon.robot.description import RobotDescription

__all__ = ["evaluate_calibrated", "evaluate_solvers", "fit_campaign_file", "is_campaign_file"]


def is_campaign_file(path: str, options: ReadOptions | None = None) -> bool:
    """Whether a file is a ballbar or cross-bar campaign (by its header, its fields separated as
    ``options`` say: the forms' one sniffer)."""
    return sniff_campaign_file(path, options) is not None


def fit_campaign_file(args: argparse.Namespace, robot: RobotDescription) -> int:
    """``fit`` of a ballbar or cross-bar campaign (module docstring), through the fit pipeline's
    :func:`comp_daemon.preparation.pipeline.calibrate_campaign`."""
    try:
        table = read_table(args.data, limits_deg=robot.axis_limits_deg, options=read_options_of(args))
        outcome = calibrate_campaign(table, robot, args.model, settings_of(args, FitSettings))
    except (DatasetError, CampaignError) as exc:
        raise UserError(str(exc)) from None
    fitted, check, info = outcome.fitted, outcome.check, outcome.info
    save_model(fitted.model, args.out, data_sha256=outcome.data_sha256, frame=fitted.frame, fit=info)
    print(
        f"{info['campaign']} campaign -> {fitted.model.kind} model: {check['fit_rows']} rows, "
        f"rank {info['rank']} of {info['parameters']}, residual RMS {info['rms_mm']:.4f} mm -> {args.out}"
    )
    for line in info["not_identifiable"]:
        print(f"  {line if line.startswith('not identifiable') else 'not identifiable: ' + line}")
    if info.get("ridge"):
        print(f"  ridge (--ridge): {info['ridge']}")
    for held in info.get("near_dependent_fixed", ()):
        other = next(n for n in held["pair"] if n != held["fixed"])
        print(
            f"  held at zero: {held['fixed']} (near-dependent on {other}, r {held['correlation']:+.3f}, "
            f"condition {held['condition']:.3g}; --fix-near-dependent)"
        )
    note = near_dependent_note(info)
    if note:
        print(f"  {note}")
    if "bar_error_rms_mm" in check:
        b = check["bar_error_rms_mm"]
        print(f"  check {check['check_rows']} rows: bar error RMS {b['before']:.4f} -> {b['after']:.4f} mm")
    summary = uncertainty_summary(info)
    if summary is not None:
        _print_uncertainty(summary, info["identified"])
    return 0


def _print_uncertainty(s: dict[str, Any], identified: dict[str, dict[str, float]]) -> None:
    """The uncertainty mode's lines of the ``fit`` summary (spec A.8)."""
    um, bm, rms = s["u_mm"], s["b_mm"], s["rms_mm"]
    reps = s["repeats"]
    count = f"{reps['min']}" if reps["min"] == reps["max"] else f"{reps['min']}-{reps['max']}"
    print(
        f"  uncertainty (spec A.8): {s['poses']} poses x {count} repeats, the last repeat the reading; "
        f"u {um['mean'] * 1000:.2f} um mean ({um['min'] * 1000:.2f}-{um['max'] * 1000:.2f}), "
        f"expanded b = 1.96 u (95 %) {bm['mean'] * 1000:.2f} um mean"
    )
    print(
        f"  residual RMS: unweighted {rms['unweighted'] * 1000:.2f} um, weighted 1/u^2 "
        f"{rms['weighted'] * 1000:.2f} um (chi2/dof {s['chi2_per_dof']:.2f}, covariance x "
        f"{s['covariance_scale']:.2f}), nested correction {rms['nested'] * 1000:.2f} um "
        f"({s['nested_rounds']} rounds, corrected {', '.join(str(c) for c in s['nested_corrected'])}; "
        f"{s['nested_stop']}; {s['flagged']} beyond b, flagged)"
    )
    for name, v in identified.items():
        unit = "rad" if name.startswith("dtheta") else "mm"
        print(f"    {name:8s} {v['value']:+.6g} {unit}  u {v['std']:.2g}  U(95 %) {1.96 * v['std']:.2g}")


def evaluate_calibrated(
    paths: str, robot: RobotDescription, dataset: Dataset, fit_rows: np.ndarray, check_rows: np.ndarray
) -> tuple[dict[str, dict[str, Any]], dict[str, dict[str, Any]]]:
    """(Table 2 statistics, fit info) of each artifact of ``paths`` (comma-separated) on the check rows."""
    assert dataset.a_deg is not None and dataset.xyz_mm is not None
    table: dict[str, dict[str, Any]] = {}
    fits: dict[str, dict[str, Any]] = {}
    for path in (p.strip() for p in paths.split(",") if p.strip()):
        try:
            loaded = load_model(path, robot)
        except ModelArtifactError as exc:
            raise UserError(str(exc)) from None
        pred, frame = registered_prediction(
            loaded.model,
            dataset.a_deg[fit_rows],
            dataset.xyz_mm[fit_rows],
            dataset.a_deg[check_rows],
            dataset.payload_kg[fit_rows],
            dataset.payload_kg[check_rows],
        )
        name = Path(path).name
        table[name] = error_statistics(dataset.xyz_mm[check_rows], pred)
        fits[name] = {"artifact": path, "kind": loaded.model.kind, "registered_frame": frame.tolist()}
    return table, fits


def _readings(campaign: BallbarCampaign, rows: np.ndarray) -> tuple[np.ndarray, float | None]:
    """The rows that are readings (the last repeat of each pose when poses are repeated) and the
    noise σ the repeats show (mean u, None without repeats)."""
    if not campaign.repeated:
        return rows, None
    groups = campaign.repeat_groups(rows)
    last = np.array([int(g[-1]) for g in groups], dtype=np.intp)
    u = [float(repeat_uncertainty(campaign.bar_mm[g][None, :]).u[0]) for g in groups if g.size > 1]
    return last, (float(np.mean(u)) if u else None)


def evaluate_solvers(args: argparse.Namespace, robot: RobotDescription) -> int:
    """``evaluate --solvers``: the solvers compared on a ballbar campaign's identification (module
    docstring). The file's split holds out whole arcs; without one, one arc of four or more is drawn
    (``--seed``), and with fewer every arc is fitted and no held-out error is given."""
    try:
        solvers = parse_solvers(args.solvers)
        seeds = [int(t) for t in str(args.solver_seeds).split(",") if t.strip()]
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if args.agents < 2 or args.iterations < 1 or not seeds:
        raise UserError("--agents must be >= 2, --iterations >= 1, --solver-seeds at least one seed")
    try:
        table = read_table(args.data, limits_deg=robot.axis_limits_deg, options=read_options_of(args))
        campaign = campaign_of(table, tcp_mm=nominal_tcp(robot), expect="ballbar")
    except DatasetError as exc:
        raise UserError(str(exc)) from None
    except ValueError as exc:
        raise UserError(f"{exc}; --solvers compares the identification of a ballbar campaign") from None
    assert isinstance(campaign, BallbarCampaign)
    arcs = np.unique(campaign.arc).size
    fraction = 1.0 / arcs if arcs >= 4 else 0.0
    fit_rows, check_rows, drawn = campaign.split(seed=args.seed, check_fraction=fraction)
    if drawn:
        held = sorted({int(k) for k in campaign.arc[check_rows]})
        print(f"{campaign.source}: no split column; arc(s) {held} held out")
    elif check_rows.size == 0:
        print(f"{campaign.source}: {arcs} arcs, no split column: every arc fitted, no held-out error")
    fit_rows, noise = _readings(campaign, fit_rows)
    check_rows, _ = _readings(campaign, check_rows)
    problem = SolverProblem(
        name=Path(campaign.source).name,
        model=layout_twists(robot, paper_layout(robot)),  # the layout fit_campaign identifies on
        pivot_mm=campaign.pivot_mm,
        a_fit=campaign.a_deg[fit_rows],
        bar_fit=campaign.bar_mm[fit_rows],
        a_check=campaign.a_deg[check_rows],
        bar_check=campaign.bar_mm[check_rows],
        noise_mm=noise,
    )
    runs = compare_solvers(problem, solvers, agents=args.agents, max_iter=args.iterations, seeds=seeds)
    print("\n".join(solver_table(runs)))
    if args.json:
        write_json_atomic(args.json, {"campaign": campaign.source, "runs": [r.to_dict() for r in runs]})
    return 0
