"""MFO, improved MFO and WOA against Levenberg–Marquardt on seed 002's problems (spec A.7).

Identification: :func:`comp_daemon.instruments.solver_comparison.compare_solvers` on the spec's noise-free
default ballbar campaign (:func:`~comp_daemon.instruments.solver_comparison.spec_default_problem`), the
table ``comp-daemon evaluate CAMPAIGN.csv --solvers lm,mfo,imfo,woa`` prints for a campaign file.

IK: one target (FK of a pose) over the full joint box, R_t < 0.1 as the threshold, each answer
polished by least squares and checked by FK; LM is the product's damped least-squares IK from the
probe-down seed.

Run: ``OMP_NUM_THREADS=1 python -m benchmarks.bench_mfo`` (defaults N = 100, K_max = 300, seeds
0 1: about two minutes on one loaded core); ``--agents 500 --iterations 1000 --seeds 0 1 2`` is the
spec's setting (tens of minutes).
"""

from __future__ import annotations

import argparse
import time
from typing import Literal

import numpy as np

from benchmarks.machine import machine_line
from comp_daemon.estimation.mfo import solve_ik_mfo
from comp_daemon.instruments.ballbar import ballbar_lengths_mm, fit_ballbar
from comp_daemon.instruments.solver_comparison import (
    PROBE_DOWN_DEG,
    SPEC_TRUTH,
    compare_solvers,
    solver_table,
    spec_default_problem,
)
from comp_daemon.kinematics.inverse import solve_ik_axes
from comp_daemon.kinematics.params import KinematicParams
from comp_daemon.kinematics.poe import irb120_table1, poe_flange_pose, poe_tcp_position_mm
from comp_daemon.robot.description import load_robot

Variant = Literal["mfo", "imfo", "woa"]


def _row(*cells: object) -> None:
    print("| " + " | ".join(str(c) for c in cells) + " |")


def identification(agents: int, iterations: int, seeds: list[int], variants: list[Variant]) -> None:
    """The table of ``comp-daemon evaluate --solvers`` on the spec's default problem."""
    problem = spec_default_problem(load_robot("irb120"))
    runs = compare_solvers(problem, ["lm", *variants], agents=agents, max_iter=iterations, seeds=seeds)
    lm = runs[0]
    print(f"campaign: {problem.name}, f = {lm.rows} rows, rank {lm.rank} of 15, noise 0")
    print("\n".join(solver_table(runs)))


def inverse_kinematics(agents: int, iterations: int, seeds: list[int], variants: list[Variant]) -> None:
    robot = load_robot("irb120")
    model = irb120_table1(robot)
    a_true = np.array([20.0, 10.0, 20.0, 30.0, 40.0, 50.0])
    pose = poe_flange_pose(model, a_true[None])[0]
    p = poe_tcp_position_mm(model, a_true[None])[0]
    print(f"\nIK target: FK of A = {a_true.tolist()} deg, full joint box, threshold R_t < 0.1")
    head = ["solver", "N", "K_max", "seed", "iterations to R_t < 0.1", "search R_t", "time / s"]
    _row(*head, "after polishing: ok", "position error / mm")
    print("|" + "---|" * 9)
    t0 = time.perf_counter()
    params = KinematicParams.from_robot(robot)
    _, res_lm = solve_ik_axes(
        params, robot.sign, robot.axis_limits_deg, p[None], pose[None, :3, :3], PROBE_DOWN_DEG[None]
    )
    t_lm = time.perf_counter() - t0
    lm_cells = (
        f"LM (damped least squares, seed {PROBE_DOWN_DEG.tolist()})",
        "–",
        "–",
        "–",
        res_lm.iterations,
    )
    _row(*lm_cells, "–", f"{t_lm:.3f}", bool(res_lm.ok[0]), f"{res_lm.position_error_mm[0]:.1e}")
    for variant in variants:
        for seed in seeds:
            ik = solve_ik_mfo(
                model,
                robot.axis_limits_deg,
                p,
                pose[:3, :3],
                variant=variant,
                n_agents=agents,
                max_iter=iterations,
                seed=seed,
                target=0.1,
            )
            s = ik.search
            cells = (
                variant,
                agents,
                iterations,
                seed,
                s.reached_at or "–",
                f"{s.fun:.3g}",
                f"{s.time_s:.2f}",
            )
            _row(*cells, ik.ok, f"{ik.position_error_mm:.1e}")


def ballbar_fit_time() -> None:
    problem = spec_default_problem(load_robot("irb120"))
    a4 = np.vstack([problem.a_fit, problem.a_check])
    bar = ballbar_lengths_mm(problem.model, a4, SPEC_TRUTH, problem.pivot_mm)
    times = []
    for _ in range(5):
        t0 = time.perf_counter()
        fit_ballbar(problem.model, a4, bar, problem.pivot_mm)
        times.append(time.perf_counter() - t0)
    print(f"\nballbar LM fit of 4 arcs ({bar.size} rows): median {np.median(times):.3f} s", end="")
    print(f", max {max(times):.3f} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--agents", type=int, default=100)
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--ik-agents", type=int, default=500)
    ap.add_argument("--ik-iterations", type=int, default=200)
    ap.add_argument("--variants", nargs="+", default=["imfo", "mfo", "woa"], choices=["mfo", "imfo", "woa"])
    args = ap.parse_args()
    print(machine_line())
    identification(args.agents, args.iterations, args.seeds, args.variants)
    inverse_kinematics(args.ik_agents, args.ik_iterations, args.seeds, args.variants)
    ballbar_fit_time()


if __name__ == "__main__":
    main()
