"""``comp-daemon plan ballbar``: the poses of a ballbar campaign (seed 002, spec A.5–A.6).

Writes the plan as a ballbar campaign without ``bar_mm`` (``a1..a6``, ``pose_id``, ``cx, cy, cz``,
``arc``: ``docs/data-format.md``, "Ballbar and cross-bar campaigns"): ``--arcs k`` circular arcs through three
points on the pivot sphere, sampled every ``--step`` degrees, the flange at one orientation per
arc, axis values by the nominal inverse kinematics. The instrument fills in ``bar_mm``.

Before that it prints what the choice rests on (:mod:`comp_daemon.instruments.ballbar_plan`): the
variogram γ(h) of the error field over joint-space lags, with the step between two points of an
arc marked (smooth: neighbouring points say nearly the same), and, for k = 2..4 arcs of the plan,
the change rates of the mean and the variance of the error against random poses of the
measurement region, with the arc count whose variance rate is smallest.
"""

from __future__ import annotations

import argparse

import numpy as np

from comp_daemon.commands.errors import UserError
from comp_daemon.data.ballbar import ballbar_dataset
from comp_daemon.data.dataset import write_dataset
from comp_daemon.instruments.ballbar import PAPER_PIVOT_MM, PAPER_RADIUS_MM
from comp_daemon.instruments.ballbar_plan import (
    MAX_ARCS,
    ORIENTATIONS,
    arc_count_rates,
    ballbar_plan,
    variogram_table,
)
from comp_daemon.robot.description import PRESETS, load_robot

__all__ = ["register"]


def _triple(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected x,y,z in mm, got {text!r}") from None
    if len(values) != 3 or not all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"expected x,y,z in mm, got {text!r}")
    return values[0], values[1], values[2]


def register(subparsers: argparse._SubParsersAction) -> None:
    plan = subparsers.add_parser("plan", help="measurement plans: the poses of a ballbar campaign")
    sub = plan.add_subparsers(dest="plan_command", metavar="PLAN_COMMAND", required=True)
    bb = sub.add_parser("ballbar", help="write the poses of a ballbar campaign (CSV without bar_mm)")
    bb.add_argument(
        "--robot", required=True, help=f"preset ({', '.join(PRESETS)}) or path to a robot TOML file"
    )
    bb.add_argument(
        "--arcs", type=int, default=3, help=f"number of arcs, 1..{MAX_ARCS} (default 3, the spec's)"
    )
    bb.add_argument(
        "--orientation",
        choices=tuple(ORIENTATIONS),
        default="per-arc",
        help="flange orientation: a different one per arc (default; identifies the most), or the "
        "paper's vertical tool, or one tilted orientation",
    )
    bb.add_argument(
        "--pivot", type=_triple, default=PAPER_PIVOT_MM, help="nominal pivot x,y,z, robot base frame, mm"
    )
    bb.add_argument("--radius", type=float, default=PAPER_RADIUS_MM, help="bar length, mm (default 100)")
    bb.add_argument("--step", type=float, default=5.0, help="angle between points of an arc, deg (default 5)")
    bb.add_argument("--seed", type=int, default=0, help="seed of the random poses of the study (default 0)")
    bb.add_argument("--out", required=True, help="plan CSV to write")
    bb.set_defaults(func=_ballbar)


def _ballbar(args: argparse.Namespace) -> int:
    robot = load_robot(args.robot)
    if not 1 <= args.arcs <= MAX_ARCS:
        raise UserError(f"--arcs: 1..{MAX_ARCS}, got {args.arcs}")
    if args.radius <= 0:
        raise UserError(f"--radius: must be > 0, got {args.radius}")
    try:
        plan = ballbar_plan(
            robot,
            args.arcs,
            orientation=args.orientation,
            pivot_mm=args.pivot,
            radius_mm=args.radius,
            step_deg=args.step,
        )
    except ValueError as exc:
        raise UserError(f"plan ballbar: {exc}") from None
    same_arc = np.diff(plan.arc) == 0
    step_joint = round(float(np.median(np.linalg.norm(np.diff(plan.a_deg, axis=0)[same_arc], axis=1))), 2)
    lags, gamma = variogram_table(
        robot, sorted({step_joint, 5.0, 10.0, 20.0, 40.0, 60.0, 90.0, 120.0}), seed=args.seed
    )
    print(f"variogram of the error field (prior: spec Table 5 errors), {robot.name}:")
    for h, g in zip(lags, gamma, strict=True):
        mark = "  <- neighbouring points of an arc (median joint-space step)" if h == step_joint else ""
        print(f"  h {h:6.2f} deg  gamma {g:.5f} mm^2{mark}")
    print(
        f"  gamma at the arc step is {100 * float(gamma[list(lags).index(step_joint)] / gamma[-1]):.2f} % of "
        f"gamma(120 deg): points of one arc say nearly the same; the information is in the arcs"
    )
    try:
        rates = arc_count_rates(
            robot, orientation=args.orientation, pivot_mm=args.pivot, radius_mm=args.radius, seed=args.seed
        )
    except ValueError as exc:
        raise UserError(f"plan ballbar: {exc}") from None
    print("arc count (spec A.6): change rate of the error's mean / variance against the region")
    for k, m, v in zip(rates.arcs, rates.mean_rate, rates.variance_rate, strict=True):
        print(f"  {k} arcs: mean {100 * m:5.1f} %  variance {100 * v:5.1f} %")
    print(f"  smallest variance rate: {rates.chosen} arcs")
    n = len(plan.a_deg)
    ds = ballbar_dataset(
        plan.a_deg, plan.arc, plan.pivot_mm, pose_id=tuple(f"b{i + 1:04d}" for i in range(n)), source=args.out
    )
    write_dataset(ds, args.out)
    print(
        f"{n} poses on {args.arcs} arcs ({args.orientation} orientation, pivot "
        f"{', '.join(f'{v:g}' for v in plan.pivot_mm)} mm, R {plan.radius_mm:g} mm) -> {args.out}"
    )
    return 0
