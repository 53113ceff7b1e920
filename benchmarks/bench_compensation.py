"""Compensation throughput: wanted TCP poses → commanded axis values, in targets per second.

For each model kind fitted on a simulated campaign (``kr210-cell``, 200 poses), the target points of
seed 000's box (Latin hypercube, A/B/C ±10°, seeded from their nominal axis values) are compensated
(:func:`comp_daemon.models.compensation.compensate`: model prediction and inverse kinematics iterated
to 1e-6 mm) — in one batch (the offline ``comp-daemon compensate``), and one target at a time (what
the daemon's executor does per target, through its ``ActiveModelCompensator`` path without the store).

Run: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python -m benchmarks.bench_compensation``
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from benchmarks.machine import machine_info, machine_line
from comp_daemon.models.base import ErrorModel
from comp_daemon.models.compensation import compensate, nominal_targets
from comp_daemon.models.kriging import fit_kriging
from comp_daemon.models.registry import fit_model
from comp_daemon.sim.campaign import run_campaign, sample_poses
from comp_daemon.sim.scenario import load_scenario


def _best(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times), float(np.median(times))


def models(n_poses: int) -> dict[str, ErrorModel]:
    scenario = load_scenario("kr210-cell")
    data = run_campaign(scenario, n_poses, seed=0)
    assert data.a_deg is not None and data.xyz_mm is not None and data.dir is not None
    robot, a, p = scenario.robot, data.a_deg, data.xyz_mm
    d = data.dir.astype(float)
    kw: dict[str, Any] = {"dir": d, "payload_kg": data.payload_kg, "frame": "base"}
    out: dict[str, ErrorModel] = {
        "nominal": fit_model("nominal", robot, a, p, **kw).model,
        "kinematic": fit_model("kinematic", robot, a, p, **kw).model,
        "kinematic+ratio+backlash": fit_model(
            "kinematic", robot, a, p, effects=("ratio", "backlash"), **kw
        ).model,
        "chebyshev m=3": fit_model("chebyshev", robot, a, p, order=3, **kw).model,
    }
    out["kriging on kinematic+ratio+backlash"] = fit_kriging(
        out["kinematic+ratio+backlash"], a, p, dir=d, payload_kg=data.payload_kg, direction=[20.0] * 6
    ).model
    return out


def run(n_targets: int, n_single: int, repeats: int, n_poses: int) -> dict[str, Any]:
    scenario = load_scenario("kr210-cell")
    fitted = models(n_poses)
    poses = sample_poses(scenario, n_targets, np.random.default_rng(5))
    a_nom = poses.a_deg
    wanted, rot = nominal_targets(fitted["nominal"], a_nom)
    dirs = np.ones_like(a_nom)
    rows = []
    for name, model in fitted.items():
        compensate(model, wanted[:2], rot[:2], a_seed_deg=a_nom[:2], dir=dirs[:2], tol_mm=1e-6)  # warm-up
        res_holder: list[Any] = []

        def batch(model: ErrorModel = model, holder: list[Any] = res_holder) -> None:
            holder[:] = [compensate(model, wanted, rot, a_seed_deg=a_nom, dir=dirs, tol_mm=1e-6)]

        def single(model: ErrorModel = model) -> None:
            for i in range(n_single):
                compensate(
                    model, wanted[i : i + 1], rot[i : i + 1], a_seed_deg=a_nom[i : i + 1],
                    dir=dirs[i : i + 1], tol_mm=1e-6,
                )  # fmt: skip

        b_best, b_med = _best(batch, repeats)
        s_best, s_med = _best(single, max(1, repeats // 2))
        res = res_holder[0]
        rows.append(
            {
                "model": name,
                "batch_targets_per_s": round(n_targets / b_best, 1),
                "batch_median_targets_per_s": round(n_targets / b_med, 1),
                "single_ms_per_target": round(1e3 * s_best / n_single, 3),
                "single_median_ms_per_target": round(1e3 * s_med / n_single, 3),
                "iterations": int(res.iterations),
                "converged": bool(res.converged),
                "max_residual_mm": float(np.max(res.residual_mm)),
            }
        )
    return {
        "benchmark": "compensation_throughput",
        "targets": n_targets,
        "single_targets": n_single,
        "campaign_poses": n_poses,
        "repeats": repeats,
        "rows": rows,
        "date": dt.date.today().isoformat(),
        "machine": machine_info(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--targets", type=int, default=1000, help="targets in the batch (default 1000)")
    parser.add_argument("--single", type=int, default=50, help="targets compensated one by one (default 50)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--poses", type=int, default=200, help="campaign poses the models are fitted on")
    args = parser.parse_args()
    result = run(args.targets, args.single, args.repeats, args.poses)
    print(f"compensation throughput, {args.targets} targets (to 1e-6 mm) on {machine_line()}")
    print(f"{'model':<38} {'batch targets/s':>16} {'one target (ms)':>16} {'iterations':>10}")
    for r in result["rows"]:
        print(
            f"{r['model']:<38} {r['batch_targets_per_s']:>16.0f} {r['single_ms_per_target']:>16.2f} "
            f"{r['iterations']:>10}"
        )
    print(json.dumps(result))


if __name__ == "__main__":
    main()
