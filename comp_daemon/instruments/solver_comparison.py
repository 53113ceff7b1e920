"""Solvers compared on one ballbar identification problem (seed 002, spec A.7, acceptance check 7).

A :class:`SolverProblem` is a set of ballbar lengths to identify the POE errors and pivot offset
from (fit rows) and, optionally, held-out lengths to judge the result on (check rows).
:func:`compare_solvers` runs Levenberg–Marquardt (:func:`comp_daemon.instruments.ballbar.fit_ballbar`,
once: it is deterministic) and each metaheuristic (:func:`comp_daemon.estimation.mfo.optimise`: ``mfo``,
``imfo`` the improved MFO, ``woa``) per seed on the columns LM finds identifiable, inside the spec's
box (Δl ±1 mm, Δθ ±0.01 rad, Δo ±2 mm) with the paper's stop H < 0.02 mm. One
:class:`SolverRun` per run; :func:`solver_table` lays them out with the spec's columns: campaign,
rows f, rank, noise σ; solver, N, K_max, seed; iterations, objective evaluations, wall time; final
H, whether H < 0.02 mm was reached; held-out H, the largest difference from LM's parameters on the
identifiable columns (LM reaches the least-squares minimum, so this is the metaheuristic's error in
the identifiable combinations); parameters within 1 % of a bound.

:func:`spec_default_problem` builds the spec's noise-free default campaign (IRB 120, Table 1 twists,
tool vertical, TCP on axis 6, three arcs of A.6, Table 5 errors with pivot offset (0.8, −0.6, 0.5)
mm; held out a fourth arc at ψ = 45°). ``comp-daemon evaluate CAMPAIGN.csv --solvers
lm,mfo,imfo,woa`` runs the comparison on a ballbar campaign file, ``benchmarks/bench_mfo.py`` on the
default problem.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, fields
from functools import partial
from typing import cast

import numpy as np
from numpy.typing import NDArray

from comp_daemon.common.logs import get_logger
from comp_daemon.estimation.mfo import DEFAULT_BOUNDS, Variant, at_bound, ballbar_objective, optimise
from comp_daemon.instruments.ballbar import (
    N_BALLBAR_PARAMS,
    PAPER_PIVOT_MM,
    arc_through_points,
    ballbar_lengths_mm,
    default_arcs,
    fit_ballbar,
    plan_ballbar_axes,
    sphere_point_mm,
)
from comp_daemon.kinematics.forward import flange_pose
from comp_daemon.kinematics.params import KinematicParams
from comp_daemon.kinematics.poe import PoeModel, irb120_table1
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "SOLVERS",
    "SPEC_BOX",
    "SPEC_TRUTH",
    "TARGET_H_MM",
    "SolverProblem",
    "SolverRun",
    "compare_solvers",
    "parse_solvers",
    "solver_table",
    "spec_default_problem",
]

_log = get_logger(__name__)

SOLVERS: tuple[str, ...] = ("lm", "mfo", "imfo", "woa")
TARGET_H_MM = 0.02  # the paper's stop
DL_MM = (0.4365, -0.4578, -0.0429, -0.0616, -0.4143, 0.0126)  # spec A.6 Table 5
DTHETA_RAD = (0.0007, 0.0024, -0.0044, -0.0048, 0.0047, 0.0051)
SPEC_TRUTH = np.array([*DL_MM, *DTHETA_RAD, 0.8, -0.6, 0.5])
SPEC_BOX = np.array(
    [DEFAULT_BOUNDS["dl"]] * 6 + [DEFAULT_BOUNDS["dtheta"]] * 6 + [DEFAULT_BOUNDS["pivot"]] * 3
)
PROBE_DOWN_DEG = np.array([0.0, 0.0, 0.0, 0.0, 90.0, 0.0])


@dataclass(frozen=True, slots=True)
class SolverProblem:
    """Ballbar lengths to identify from, and held-out lengths to judge on (``a_check`` may be empty)."""

    name: str
    model: PoeModel
    pivot_mm: NDArray[np.float64]
    a_fit: NDArray[np.float64]
    bar_fit: NDArray[np.float64]
    a_check: NDArray[np.float64]
    bar_check: NDArray[np.float64]
    noise_mm: float | None  # σ of the readings when known (simulated), else None

    def held_out_h(self, theta: NDArray[np.float64]) -> float | None:
        """RMS length error (mm) of ``theta`` on the check rows (None without any)."""
        if self.bar_check.size == 0:
            return None
        pred = ballbar_lengths_mm(self.model, self.a_check, theta, self.pivot_mm)
        return float(np.sqrt(np.mean((pred - self.bar_check) ** 2)))


@dataclass(frozen=True, slots=True)
class SolverRun:
    """One row of the comparison (module docstring)."""

    campaign: str
    rows: int
    rank: int
    noise_mm: float | None
    solver: str
    agents: int | None
    max_iter: int | None
    seed: int | None
    iterations: int
    evaluations: int | None
    time_s: float
    final_h_mm: float
    reached: bool
    held_out_h_mm: float | None
    max_diff_from_lm: float
    at_bound: int
    theta: NDArray[np.float64]

    def to_dict(self) -> dict[str, object]:
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "theta"}
        out["theta"] = self.theta.tolist()
        return out


def parse_solvers(text: str) -> list[str]:
    """The solvers named in ``text`` (comma-separated, from :data:`SOLVERS`), in the order given."""
    names = [t.strip().lower() for t in text.split(",") if t.strip()]
    unknown = [n for n in names if n not in SOLVERS]
    if not names or unknown:
        raise ValueError(f"--solvers: name some of {', '.join(SOLVERS)} (got {text!r})")
    if len(set(names)) != len(names):
        raise ValueError("--solvers: a solver is named twice")
    return names


def spec_default_problem(robot: RobotDescription) -> SolverProblem:
    """The spec's noise-free default ballbar campaign and its held-out fourth arc (module docstring)."""
    params = KinematicParams.from_robot(robot)
    vertical = flange_pose(params, np.deg2rad(PROBE_DOWN_DEG)[None] * robot.sign)[0, :3, :3]
    a_fit, _ = plan_ballbar_axes(
        params, robot.sign, robot.axis_limits_deg, default_arcs(), [vertical] * 3, PROBE_DOWN_DEG
    )
    arc4 = arc_through_points(*(sphere_point_mm(az, 45.0) for az in (-60.0, 0.0, 60.0)))
    a_check, _ = plan_ballbar_axes(
        params, robot.sign, robot.axis_limits_deg, [arc4], [vertical], PROBE_DOWN_DEG
    )
    model = irb120_table1(robot)
    pivot = np.asarray(PAPER_PIVOT_MM, dtype=float)
    return SolverProblem(
        name="spec default (3 arcs, tool vertical)",
        model=model,
        pivot_mm=pivot,
        a_fit=a_fit,
        bar_fit=ballbar_lengths_mm(model, a_fit, SPEC_TRUTH, pivot),
        a_check=a_check,
        bar_check=ballbar_lengths_mm(model, a_check, SPEC_TRUTH, pivot),
        noise_mm=0.0,
    )


def compare_solvers(
    problem: SolverProblem,
    solvers: Sequence[str] = SOLVERS,
    *,
    agents: int = 100,
    max_iter: int = 300,
    seeds: Sequence[int] = (0, 1),
    box: NDArray[np.float64] = SPEC_BOX,
) -> list[SolverRun]:
    """LM once and every metaheuristic of ``solvers`` per seed on ``problem`` (module docstring)."""
    t0 = time.perf_counter()
    lm = fit_ballbar(problem.model, problem.a_fit, problem.bar_fit, problem.pivot_mm)
    t_lm = time.perf_counter() - t0
    free = lm.report.identifiable_index
    run = partial(
        SolverRun,
        campaign=problem.name,
        rows=int(problem.bar_fit.size),
        rank=lm.rank,
        noise_mm=problem.noise_mm,
    )
    lb, ub = -box[free], box[free]
    runs: list[SolverRun] = []
    if "lm" in solvers:
        runs.append(
            run(
                solver=f"lm (improved, {free.size} columns)",
                agents=None,
                max_iter=None,
                seed=None,
                iterations=lm.iterations,
                evaluations=None,
                time_s=t_lm,
                final_h_mm=lm.h_after_mm,
                reached=lm.h_after_mm < TARGET_H_MM,
                held_out_h_mm=problem.held_out_h(lm.theta),
                max_diff_from_lm=0.0,
                at_bound=int(at_bound(lm.theta[free], lb, ub).sum()),
                theta=lm.theta,
            )
        )
    objective = ballbar_objective(problem.model, problem.a_fit, problem.bar_fit, problem.pivot_mm, free)
    for solver in solvers:
        if solver == "lm":
            continue
        for seed in seeds:
            res = optimise(
                objective,
                lb,
                ub,
                variant=cast(Variant, solver),
                n_agents=agents,
                max_iter=max_iter,
                seed=seed,
                target=TARGET_H_MM,
            )
            theta = np.zeros(N_BALLBAR_PARAMS)
            theta[free] = res.x
            runs.append(
                run(
                    solver=solver,
                    agents=agents,
                    max_iter=max_iter,
                    seed=seed,
                    iterations=res.iterations,
                    evaluations=res.evaluations,
                    time_s=res.time_s,
                    final_h_mm=res.fun,
                    reached=res.reached_at is not None,
                    held_out_h_mm=problem.held_out_h(theta),
                    max_diff_from_lm=float(np.abs(res.x - lm.theta[free]).max()),
                    at_bound=int(at_bound(res.x, lb, ub).sum()),
                    theta=theta,
                )
            )
            _log.info("solver_run", solver=solver, seed=seed, h_mm=res.fun, iterations=res.iterations)
    return runs


def _cell(value: object, fmt: str = "") -> str:
    if value is None:
        return "–"
    return format(value, fmt) if fmt else str(value)


def solver_table(runs: Sequence[SolverRun]) -> list[str]:
    """The comparison as a markdown table, one row per run (module docstring for the columns)."""
    head = (
        "campaign",
        "rows f",
        "rank",
        "noise σ / mm",
        "solver",
        "N",
        "K_max",
        "seed",
        "iterations",
        "evaluations",
        "time / s",
        "final H / mm",
        f"H < {TARGET_H_MM:g}",
        "held-out H / mm",
        "max abs(x − x_LM)",
        "at bound",
    )
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in runs:
        cells = (
            r.campaign,
            r.rows,
            r.rank,
            _cell(r.noise_mm, "g"),
            r.solver,
            _cell(r.agents),
            _cell(r.max_iter),
            _cell(r.seed),
            r.iterations,
            _cell(r.evaluations),
            f"{r.time_s:.2f}",
            f"{r.final_h_mm:.3g}",
            "yes" if r.reached else "no",
            _cell(r.held_out_h_mm, ".3g"),
            f"{r.max_diff_from_lm:.3g}",
            r.at_bound,
        )
        lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    return lines
