"""``comp-daemon sim sample|report``: measurement campaigns and figures of the simulated cell.

The command line (:mod:`comp_daemon.cli`) imports this module only when the ``sim`` command runs.

``sim sample`` writes a data set (``docs/data-format.md``) measured on a scenario's hidden robot;
``sim report`` measures the scenario's raw error figures (nominal twin vs tracker, robot base
frame) and its ISO 9283 multi-directional pose accuracy variation against the pose repeatability.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from typing import Any

import numpy as np

from comp_daemon.data.dataset import write_dataset
from comp_daemon.robot.description import PRESETS, load_robot
from comp_daemon.sim.bars import CAMPAIGN_SCENARIOS, run_ballbar_campaign, run_crossbar_campaign
from comp_daemon.sim.campaign import iso9283_multidirection, raw_error_stats, run_campaign
from comp_daemon.sim.scenario import PRESET_SCENARIOS, Scenario, load_scenario


def register(subparsers: argparse._SubParsersAction) -> None:
    sim = subparsers.add_parser("sim", help="the simulated drilling cell: measurement campaigns, figures")
    sub = sim.add_subparsers(dest="sim_command", metavar="SIM_COMMAND", required=True)
    scen_help = (
        f"preset ({', '.join(PRESET_SCENARIOS)}) or path to a scenario TOML (default kr210-cell); "
        "ballbar or crossbar: a campaign of that instrument (see --cell)"
    )
    robot_help = f"use this robot description ({', '.join(PRESETS)} or a path) instead of the scenario's"

    sample = sub.add_parser("sample", help="write a measurement campaign (data set CSV) of a scenario")
    sample.add_argument("--scenario", default="kr210-cell", help=scen_help)
    sample.add_argument("--n", type=int, required=True, help="number of poses (Latin hypercube)")
    sample.add_argument("--out", required=True, help="CSV file to write")
    sample.add_argument("--seed", type=int, default=None, help="campaign seed (poses, noise, split)")
    sample.add_argument("--robot", default=None, help=robot_help)
    sample.add_argument("--repeats", type=int, default=None, help="measure every pose this many times")
    sample.add_argument(
        "--tracker-frame",
        action="store_true",
        help="report x, y, z in the tracker's own frame (the scenario's [cell] tracker pose)",
    )
    sample.add_argument(
        "--restation",
        action="store_true",
        help="move the tracker half-way through (a second session): station column A/B, station B's "
        "frame turned 50 deg about the vertical and moved 5 m",
    )
    sample.add_argument(
        "--probe-sigma-deg",
        type=float,
        default=None,
        metavar="DEG",
        help="measure with a 6-DOF probe: its orientation (qw..qz) with this noise per axis (deg), "
        "and sigma_mm (the tracker's sigma) on every row",
    )
    sample.add_argument("--no-gratings", action="store_true", help="leave out the g columns")
    sample.add_argument(
        "--targets",
        type=int,
        default=None,
        help="reflectors on the flange measured at every pose (x,y,z, x2,y2,z2 …; default: the scenario's)",
    )
    sample.add_argument(
        "--cell",
        default=None,
        help="with --scenario ballbar|crossbar: the scenario whose hidden robot is measured (default "
        + ", ".join(f"{k}: {v}" for k, v in CAMPAIGN_SCENARIOS.items())
        + "); --n is then the number of arcs / cross placements",
    )
    sample.set_defaults(func=_sample)

    report = sub.add_parser(
        "report", help="raw error figures and ISO 9283 multi-direction test of a scenario"
    )
    report.add_argument("--scenario", default="kr210-cell", help=scen_help)
    report.add_argument("--n", type=int, default=204, help="poses of the raw error campaign (default 204)")
    report.add_argument("--seed", type=int, default=0, help="campaign seed (default 0)")
    report.add_argument("--robot", default=None, help=robot_help)
    report.add_argument("--cycles", type=int, default=30, help="ISO 9283 cycles per pose and direction")
    report.add_argument("--json", action="store_true", help="print JSON instead of text")
    report.set_defaults(func=_report)


def _scenario(args: argparse.Namespace) -> Scenario:
    scenario = load_scenario(args.scenario)
    if args.robot is not None:
        scenario = dataclasses.replace(scenario, robot=load_robot(args.robot))
    return scenario


def _positive(value: int | None, flag: str) -> None:
    if value is not None and value < 1:
        raise ValueError(f"{flag} must be >= 1, got {value}")


def _sample(args: argparse.Namespace) -> int:
    _positive(args.n, "--n")
    _positive(args.repeats, "--repeats")
    _positive(args.targets, "--targets")
    if args.scenario in CAMPAIGN_SCENARIOS:
        for flag, value in (("--targets", args.targets), ("--probe-sigma-deg", args.probe_sigma_deg)):
            if value is not None:
                raise ValueError(f"{flag} is for pose campaigns, not a {args.scenario} campaign")
        if args.restation:
            raise ValueError(f"--restation is for pose campaigns, not a {args.scenario} campaign")
        return _sample_bars(args)
    scenario = _scenario(args)
    dataset = run_campaign(
        scenario,
        args.n,
        seed=args.seed,
        repeats=args.repeats,
        in_tracker_frame=args.tracker_frame,
        gratings=not args.no_gratings,
        targets=args.targets,
        restation=args.restation,
        probe_sigma_deg=args.probe_sigma_deg,
    )
    write_dataset(dataset, args.out)
    assert dataset.split is not None
    n_check = int((dataset.split == "check").sum())
    print(
        f"wrote {len(dataset.split)} rows ({len(dataset.split) - n_check} fit, {n_check} check) of scenario "
        f"{scenario.name} to {args.out}",
        file=sys.stderr,
    )
    return 0


def _sample_bars(args: argparse.Namespace) -> int:
    """A ballbar (--n arcs) or cross-bar (--n placements) campaign (:mod:`comp_daemon.sim.bars`)."""
    cell = args.cell or CAMPAIGN_SCENARIOS[args.scenario]
    scenario = load_scenario(cell)
    if args.robot is not None:
        scenario = dataclasses.replace(scenario, robot=load_robot(args.robot))
    seed = 0 if args.seed is None else args.seed
    if args.scenario == "ballbar":
        dataset = run_ballbar_campaign(scenario, arcs=args.n, seed=seed, repeats=args.repeats or 1)
        what = f"{args.n} arcs"
    else:
        dataset = run_crossbar_campaign(scenario, placements=args.n, seed=seed)
        what = f"{args.n} cross placements"
    write_dataset(dataset, args.out)
    print(
        f"wrote {len(dataset)} rows ({what}) of a {args.scenario} campaign on {cell} to {args.out}",
        file=sys.stderr,
    )
    return 0


def _report(args: argparse.Namespace) -> int:
    _positive(args.n, "--n")
    if args.cycles < 2:
        raise ValueError(f"--cycles must be >= 2, got {args.cycles}")
    scenario = _scenario(args)
    raw = raw_error_stats(scenario, run_campaign(scenario, args.n, seed=args.seed, repeats=1))
    iso = iso9283_multidirection(scenario, seed=args.seed, n_cycles=args.cycles)
    doc: dict[str, Any] = {
        "scenario": scenario.name,
        "robot": scenario.robot.name,
        "seed": args.seed,
        "raw_error": {
            "poses": raw.n,
            "max_mm": round(raw.max_mm, 4),
            "mean_mm": round(raw.mean_mm, 4),
            "rms_mm": round(raw.rms_mm, 4),
            "axis_max_abs_mm": [round(float(v), 4) for v in raw.axis_max_abs_mm],
        },
        "iso9283": {
            "cycles": args.cycles,
            "points_mm": [[round(float(v), 1) for v in p] for p in iso.points_mm],
            "vap_mm": [round(float(v), 4) for v in iso.vap_mm],
            "rp_mm": [round(float(v), 4) for v in iso.rp_mm.max(axis=1)],
            "vap_over_rp": [round(float(v), 2) for v in iso.ratio],
            "rated_repeatability_mm": scenario.robot.repeatability_mm,
        },
    }
    if args.json:
        print(json.dumps(doc, indent=2))
        return 0
    print(f"scenario {scenario.name} ({scenario.robot.name}), seed {args.seed}")
    print(
        f"raw error, nominal twin vs tracker, {raw.n} poses: max {raw.max_mm:.3f} mm, "
        f"mean {raw.mean_mm:.3f} mm, rms {raw.rms_mm:.3f} mm"
    )
    rated = scenario.robot.repeatability_mm
    print(f"ISO 9283 multi-direction, {args.cycles} cycles x 3 directions (rated RP {rated} mm):")
    for k, p in enumerate(iso.points_mm):
        print(
            f"  P{k + 1} {np.array2string(p, precision=0)}: vAP {iso.vap_mm[k]:.3f} mm, "
            f"RP {iso.rp_mm[k].max():.3f} mm, vAP/RP {iso.ratio[k]:.1f}"
        )
    return 0
