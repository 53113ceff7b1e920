"""FK + identification Jacobian for 10 000 poses on one core (aim: under 50 ms).

Run: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python -m benchmarks.bench_kinematics``
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import time

import numpy as np

from benchmarks.machine import machine_info, machine_line
from comp_daemon.kinematics.forward import chain, identification_jacobian
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.robot.description import load_robot


def run(n: int, repeats: int) -> dict[str, object]:
    robot = load_robot("kr210")
    params = KinematicParams.from_robot(robot)
    lim = robot.axis_limits_deg
    q = axes_deg_to_q_rad(np.random.default_rng(0).uniform(lim[:, 0], lim[:, 1], (n, 6)), robot.sign)
    chain(params, q[:10])  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        ch = chain(params, q)
        identification_jacobian(params, q, ch)
        times.append(time.perf_counter() - t0)
    return {
        "benchmark": "fk_plus_identification_jacobian",
        "poses": n,
        "repeats": repeats,
        "best_ms": round(min(times) * 1e3, 2),
        "median_ms": round(float(np.median(times)) * 1e3, 2),
        "aim_ms": 50,
        "date": dt.date.today().isoformat(),
        "machine": machine_info(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--poses", type=int, default=10_000)
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    result = run(args.poses, args.repeats)
    print(
        f"FK + identification Jacobian, {args.poses} poses: best {result['best_ms']} ms, "
        f"median {result['median_ms']} ms (aim < 50 ms) on {machine_line()}"
    )
    print(json.dumps(result))


if __name__ == "__main__":
    main()
