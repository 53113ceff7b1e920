"""MFO, improved MFO and WOA against Levenberg–Marquardt on seed 002's problems (spec A.7).

Identification: the noise-free default ballbar campaign of spec A.6 (IRB 120, Table 1 twists, tool
vertical, TCP on axis 6, three arcs, 103 points), truth = Table 5 errors with pivot offset
(0.8, −0.6, 0.5) mm. The metaheuristics search the canonical identifiable set inside the spec's box
(Δl ±1 mm, Δθ ±0.01 rad, Δo ±2 mm) and stop at H < 0.02 mm (the paper's threshold) or K_max. LM is
:func:`comp_daemon.models.ballbar.fit_ballbar` on the same columns. Columns: solver, N, K_max, seed,
iterations, objective evaluations, wall time, final H, reached?, held-out H (fourth arc at ψ = 45°),
largest distance from LM's parameters, parameters within 1 % of a bound.

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
from comp_daemon.kinematics.forward import flange_pose
from comp_daemon.kinematics.inverse import solve_ik_axes
from comp_daemon.kinematics.params import KinematicParams
from comp_daemon.kinematics.poe import PoeModel, irb120_table1, poe_flange_pose, poe_tcp_position_mm
from comp_daemon.models.ballbar import (
    PAPER_PIVOT_MM,
    arc_through_points,
    ballbar_lengths_mm,
    default_arcs,
    fit_ballbar,
    plan_ballbar_axes,
    sphere_point_mm,
)
from comp_daemon.models.mfo import at_bound, ballbar_objective, optimise, solve_ik_mfo
from comp_daemon.robot.description import load_robot

DL_MM = (0.4365, -0.4578, -0.0429, -0.0616, -0.4143, 0.0126)  # spec A.6 Table 5
DTHETA_RAD = (0.0007, 0.0024, -0.0044, -0.0048, 0.0047, 0.0051)
TRUTH = np.array([*DL_MM, *DTHETA_RAD, 0.8, -0.6, 0.5])
BOX = np.array([1.0] * 6 + [0.01] * 6 + [2.0] * 3)
SEED_DEG = np.array([0.0, 0.0, 0.0, 0.0, 90.0, 0.0])
Variant = Literal["mfo", "imfo", "woa"]


def _row(*cells: object) -> None:
    print("| " + " | ".join(str(c) for c in cells) + " |")


def _campaign() -> tuple[PoeModel, np.ndarray, np.ndarray, np.ndarray]:
    robot = load_robot("irb120")
    params = KinematicParams.from_robot(robot)
    vertical = flange_pose(params, np.deg2rad(SEED_DEG)[None] * robot.sign)[0, :3, :3]
    a_deg, _ = plan_ballbar_axes(
        params, robot.sign, robot.axis_limits_deg, default_arcs(), [vertical] * 3, SEED_DEG
    )
    arc4 = arc_through_points(*(sphere_point_mm(az, 45.0) for az in (-60.0, 0.0, 60.0)))
    a_check, _ = plan_ballbar_axes(params, robot.sign, robot.axis_limits_deg, [arc4], [vertical], SEED_DEG)
    return irb120_table1(robot), a_deg, a_check, robot.axis_limits_deg


def identification(agents: int, iterations: int, seeds: list[int], variants: list[Variant]) -> None:
    model, a_deg, a_check, _ = _campaign()
    bar = ballbar_lengths_mm(model, a_deg, TRUTH, PAPER_PIVOT_MM)
    bar_check = ballbar_lengths_mm(model, a_check, TRUTH, PAPER_PIVOT_MM)

    def held_out(theta: np.ndarray) -> float:
        return float(
            np.sqrt(np.mean((ballbar_lengths_mm(model, a_check, theta, PAPER_PIVOT_MM) - bar_check) ** 2))
        )

    t0 = time.perf_counter()
    lm = fit_ballbar(model, a_deg, bar, PAPER_PIVOT_MM)
    t_lm = time.perf_counter() - t0
    free = lm.report.identifiable_index
    print(f"campaign: default ballbar plan, f = {bar.size} rows, rank {lm.rank} of 15, noise 0")
    print(f"H before calibration {lm.h_before_mm:.3f} mm")
    print("not identifiable: " + ", ".join(lm.not_identifiable()))
    head = ["solver", "N", "K_max", "seed", "iterations", "evaluations", "time / s", "final H / mm"]
    _row(*head, "H < 0.02", "held-out H / mm", "max abs(x − x_LM)", "at bound")
    print("|" + "---|" * 12)
    lm_cells = (f"LM (improved, {free.size} columns)", "–", "–", "–", lm.iterations, "–", f"{t_lm:.2f}")
    _row(*lm_cells, f"{lm.h_after_mm:.2e}", "yes", f"{held_out(lm.theta):.2e}", 0, 0)
    objective = ballbar_objective(model, a_deg, bar, PAPER_PIVOT_MM, free)
    lb, ub = -BOX[free], BOX[free]
    for variant in variants:
        for seed in seeds:
            res = optimise(
                objective,
                lb,
                ub,
                variant=variant,
                n_agents=agents,
                max_iter=iterations,
                seed=seed,
                target=0.02,
            )
            theta = np.zeros(15)
            theta[free] = res.x
            dist = float(np.abs(res.x - lm.theta[free]).max())
            cells: list[object] = [variant, agents, iterations, seed, res.iterations, res.evaluations]
            cells += [f"{res.time_s:.1f}", f"{res.fun:.4f}", "yes" if res.reached_at else "no"]
            cells += [f"{held_out(theta):.4f}", f"{dist:.3g}", int(at_bound(res.x, lb, ub).sum())]
            _row(*cells)


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
        params, robot.sign, robot.axis_limits_deg, p[None], pose[None, :3, :3], SEED_DEG[None]
    )
    t_lm = time.perf_counter() - t0
    lm_cells = (f"LM (damped least squares, seed {SEED_DEG.tolist()})", "–", "–", "–", res_lm.iterations)
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
    model, a_deg, a_check, _ = _campaign()
    a4 = np.vstack([a_deg, a_check])
    bar = ballbar_lengths_mm(model, a4, TRUTH, PAPER_PIVOT_MM)
    times = []
    for _ in range(5):
        t0 = time.perf_counter()
        fit_ballbar(model, a4, bar, PAPER_PIVOT_MM)
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
