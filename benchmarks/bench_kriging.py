"""Kriging prediction time (1 000 queries, 500 sampling points), and seed 001's comparison in simulation.

Run: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python -m benchmarks.bench_kriging`` (timing;
``--samples 10000`` fits local neighbourhoods, :data:`comp_daemon.models.kriging.DEFAULT_NEIGHBOURS`
nearest samples, beyond 2 000 samples; ``--neighbours K`` forces K, ``--neighbours dense`` one
dense system), ``… --scale`` (10 000 samples: fit and 1 000 predictions at 32 and 64 neighbours,
direction-blind and direction-aware, and the local predictions against the dense ones at 2 000
samples), and
``… python -m benchmarks.bench_kriging --seed001`` (seed 001's experiment on a simulated KR 210:
497 Latin-hypercube sampling + 300 validation poses in a 700 × 1200 × 900 mm box, A/B/C within
[−15, 15] × [−15, 5] × [−15, 15]°, the models of seed 001 Tables 6–7 side by side with the paper).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from benchmarks.machine import machine_info, machine_line
from comp_daemon.kinematics.forward import flange_pose
from comp_daemon.kinematics.inverse import solve_ik
from comp_daemon.kinematics.kuka_abc import abc_deg_to_matrix
from comp_daemon.kinematics.params import N_PARAMS, KinematicParams, axes_deg_to_q_rad, q_rad_to_axes_deg
from comp_daemon.models.base import ErrorModel
from comp_daemon.models.effects import EffectParams, twin_tcp_mm
from comp_daemon.models.kinematic import calibrate_kinematic
from comp_daemon.models.kriging import JointStateMetric, KrigingModel, fit_kriging, joint_space_semivariogram
from comp_daemon.models.nominal import NominalModel
from comp_daemon.robot.description import RobotDescription, load_robot

HOME_DEG = (0.0, -85.0, 125.0, 0.0, -40.0, 0.0)
BOX_CENTER_MM = (1800.0, 0.0, 1050.0)
BOX_SIZE_MM = (700.0, 1200.0, 900.0)  # seed 001 §3.1
ABC_LO_DEG = (-15.0, -15.0, -15.0)
ABC_HI_DEG = (15.0, 5.0, 15.0)
PAYLOAD_KG = 150.0  # a drilling end effector

# seed 001 Tables 6-7 (KUKA KR 500-3, validation points): 3-D mean / max, per-axis std (mm)
PAPER = {
    "kinematic": {"mean": 0.0944, "max": 0.25, "std": (0.0463, 0.0751, 0.0638)},
    "kinematic+ratio+backlash": {"mean": 0.0784, "max": 0.20, "std": (0.0357, 0.0570, 0.0513)},
    "kriging (direction-aware) on kinematic+ratio+backlash": {"mean": 0.0627, "max": 0.18, "std_z": 0.0363},
}


@dataclass(frozen=True, slots=True)
class Plant:
    """The hidden robot of the simulated campaign."""

    params: KinematicParams
    effects: EffectParams
    joint_noise_deg: NDArray[np.float64]
    tracker_sigma_mm: float


def seed001_plant(robot: RobotDescription) -> Plant:
    """A KR 210 sized like seed 001's KR 500-3: geometric errors, backlash (joints 1–3 smaller than
    4–6, as Table 1), ratio and cyclic transmission errors, gravity compliance under the end effector."""
    g = np.random.default_rng(100)
    dx = np.zeros(N_PARAMS)
    dx[:30] = g.normal(0.0, 1.0, 30) * np.tile([np.deg2rad(0.0045), 0.14, 0.14, np.deg2rad(0.0045), 0.0], 6)
    dx[30:33] = g.normal(0.0, 0.09, 3)
    dx[33:36] = g.normal(0.0, np.deg2rad(0.0025), 3)
    dx[36:39] = g.normal(0.0, 0.09, 3)
    k = np.arange(1, 3)
    amp = np.array([1.0, 1.0, 1.0, 1.5, 1.5, 1.5])[:, None] * 0.001 / np.sqrt(k)
    phase = g.uniform(0.0, 2.0 * np.pi, (6, 2))
    effects = EffectParams(
        backlash_deg=np.array([0.0012, 0.0012, 0.0012, 0.0036, 0.0036, 0.0036]),
        ratio=np.array([4e-5, -3e-5, 3.5e-5, 0.0, 0.0, 0.0]),
        cyclic_sin_deg=amp * np.cos(phase),
        cyclic_cos_deg=amp * np.sin(phase),
        compliance_rad_per_nm=np.array([1.2e-7, 1.2e-7, 1.8e-7, 6e-7, 6e-7, 6e-7]),
    )
    return Plant(
        KinematicParams.from_robot(robot).apply(dx), effects, np.array([0.0012] * 3 + [0.0024] * 3), 0.01
    )


def latin_hypercube(rng: np.random.Generator, n: int, d: int) -> NDArray[np.float64]:
    """(n, d) Latin-hypercube sample of the unit cube."""
    return (np.argsort(rng.random((d, n)), axis=1).T + rng.random((n, d))) / n


def box_poses(robot: RobotDescription, n: int, rng: np.random.Generator) -> NDArray[np.float64]:
    """(n, 6) axis values of Latin-hypercube poses in seed 001's box (nominal IK, seeded at home)."""
    params = KinematicParams.from_robot(robot)
    limits = np.sort(np.deg2rad(robot.axis_limits_deg) * robot.sign[:, None], axis=1)
    q_home = axes_deg_to_q_rad(np.asarray(HOME_DEG)[None, :], params.sign)
    r_home = flange_pose(params, q_home)[0, :3, :3]
    found: list[NDArray[np.float64]] = []
    have = 0
    while have < n:
        m = n - have
        u = latin_hypercube(rng, m, 6)
        p = np.asarray(BOX_CENTER_MM) + (u[:, :3] - 0.5) * np.asarray(BOX_SIZE_MM)
        abc = np.asarray(ABC_LO_DEG) + u[:, 3:] * (np.asarray(ABC_HI_DEG) - np.asarray(ABC_LO_DEG))
        res = solve_ik(params, limits, p, abc_deg_to_matrix(abc) @ r_home, np.repeat(q_home, m, axis=0))
        found.append(q_rad_to_axes_deg(res.q_rad[res.ok], params.sign))
        have += int(res.ok.sum())
    return np.concatenate(found)[:n]


def measure(
    robot: RobotDescription, plant: Plant, a_deg: NDArray[np.float64], rng: np.random.Generator
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Visit the poses in order: approach directions from the route, tracker readings (mm)."""
    prev = np.vstack([np.asarray(HOME_DEG)[None, :], a_deg[:-1]])
    d = np.sign(a_deg - prev)
    d[d == 0.0] = 1.0
    jitter = rng.normal(0.0, 1.0, a_deg.shape) * plant.joint_noise_deg
    p = twin_tcp_mm(robot, plant.params, plant.effects, a_deg + jitter, d, PAYLOAD_KG)
    return d, p + rng.normal(0.0, plant.tracker_sigma_mm, p.shape)


def _stats(err: NDArray[np.float64]) -> dict[str, Any]:
    dist = np.linalg.norm(err, axis=1)
    return {
        "mean": round(float(dist.mean()), 4),
        "max": round(float(dist.max()), 4),
        "std_xyz": [round(float(s), 4) for s in err.std(axis=0)],
    }


def seed001(seed: int, n_fit: int, n_check: int) -> dict[str, Any]:
    robot = load_robot("kr210")
    plant = seed001_plant(robot)
    rng = np.random.default_rng(seed)
    a = box_poses(robot, n_fit + n_check, rng)
    d, p = measure(robot, plant, a, rng)
    fit, chk = slice(0, n_fit), slice(n_fit, n_fit + n_check)
    pay = PAYLOAD_KG

    def check(model: ErrorModel) -> dict[str, Any]:
        return _stats(p[chk] - model.predict_tcp_mm(a[chk], d[chk], pay))

    out: dict[str, Any] = {"rows": {"fit": n_fit, "check": n_check}, "models": {}, "paper_kr500_3": PAPER}
    models = out["models"]
    t0 = time.perf_counter()
    kin = calibrate_kinematic(robot, a[fit], p[fit], frame="base", payload_kg=pay).model
    kin_bl = calibrate_kinematic(
        robot, a[fit], p[fit], dir=d[fit], payload_kg=pay, effects=("ratio", "backlash"), frame="base"
    ).model
    models["nominal"] = check(NominalModel(robot))
    floor = p[chk] - twin_tcp_mm(robot, plant.params, plant.effects, a[chk], d[chk], pay)
    models["noise floor (the hidden robot itself)"] = _stats(floor)
    models["kinematic"] = check(kin)
    models["kinematic+ratio+backlash"] = check(kin_bl)
    for label, base, direction in (
        ("kriging (blind) on nominal", NominalModel(robot), "blind"),
        ("kriging (blind) on kinematic", kin, "blind"),
        ("kriging (direction-aware) on kinematic", kin, "aware"),
        ("kriging (blind) on kinematic+ratio+backlash", kin_bl, "blind"),
        ("kriging (direction-aware) on kinematic+ratio+backlash", kin_bl, "aware"),
    ):
        kf = fit_kriging(base, a[fit], p[fit], dir=d[fit], payload_kg=pay, direction=direction)  # type: ignore[arg-type]
        models[label] = check(kf.model)
        models[label]["dir_separation_deg"] = float(kf.model.metric.dir_separation_deg[0])
        models[label]["variograms"] = [v.kind for v in kf.model.variograms]
    out["fit_time_s"] = round(time.perf_counter() - t0, 1)
    # seed 001 §2.1 (Figs 3-4): error similarity of geometric vs backlash errors in joint space
    zero = EffectParams.zeros()
    nominal = KinematicParams.from_robot(robot)
    a_s, d_s = a[fit], d[fit]
    e_geo = twin_tcp_mm(robot, plant.params, zero, a_s) - twin_tcp_mm(robot, nominal, zero, a_s)
    bl = EffectParams(backlash_deg=plant.effects.backlash_deg)
    e_bl = twin_tcp_mm(robot, nominal, bl, a_s, d_s) - twin_tcp_mm(robot, nominal, zero, a_s)

    def small_lag(err: NDArray[np.float64], sep: float) -> dict[str, float]:
        emp = joint_space_semivariogram(a_s, err, d_s, JointStateMetric(dir_separation_deg=np.full(6, sep)))
        k = int(np.argmax(emp.count >= 50))
        return {
            "lag_deg": round(float(emp.lag[k]), 1),
            "gamma_over_sill": round(float(emp.gamma[k].sum() / err.var(0).sum()), 3),
        }

    out["similarity"] = {
        "geometric_blind": small_lag(e_geo, 0.0),
        "backlash_blind": small_lag(e_bl, 0.0),
        "backlash_direction_aware_40deg": small_lag(e_bl, 40.0),
    }
    return out


Neighbours = int | Literal["auto"] | None


def timing(
    n_samples: int,
    n_queries: int,
    repeats: int,
    neighbours: Neighbours = "auto",
    direction: Literal["aware", "blind"] | list[float] | None = None,
) -> dict[str, Any]:
    """Fit on ``n_samples`` points of the seed 001 plant (direction separation 20° unless
    ``direction`` says otherwise), then time ``n_queries`` predictions of the residual."""
    robot = load_robot("kr210")
    plant = seed001_plant(robot)
    rng = np.random.default_rng(0)
    lo = np.array([-30.0, -110.0, 90.0, -60.0, -90.0, -90.0])
    hi = np.array([30.0, -60.0, 150.0, 60.0, -20.0, 90.0])
    a = lo + rng.random((n_samples + n_queries, 6)) * (hi - lo)
    d = rng.choice([-1.0, 1.0], a.shape)
    p = twin_tcp_mm(robot, plant.params, plant.effects, a, d, PAYLOAD_KG)
    t0, c0 = time.perf_counter(), time.process_time()
    model = fit_kriging(
        NominalModel(robot),
        a[:n_samples],
        p[:n_samples],
        dir=d[:n_samples],
        direction=[20.0] * 6 if direction is None else direction,
        neighbours=neighbours,
    ).model
    fit_s, fit_cpu_s = time.perf_counter() - t0, time.process_time() - c0
    q, qd = a[n_samples:], d[n_samples:]
    model.predict_residual_mm(q[:10], qd[:10])  # warm-up
    times, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        model.predict_residual_mm(q, qd)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return {
        "benchmark": "kriging_prediction",
        "samples": n_samples,
        "queries": n_queries,
        "repeats": repeats,
        "best_ms": round(min(times) * 1e3, 2),
        "median_ms": round(float(np.median(times)) * 1e3, 2),
        "fit_s": round(fit_s, 3),
        "fit_cpu_s": round(fit_cpu_s, 3),  # the process's CPU time: less sensitive to a shared machine
        "best_cpu_ms": round(min(cpu) * 1e3, 2),
        "load_average_1min": round(os.getloadavg()[0], 2),
        "solver": "dense" if model.neighbours is None else f"local, {model.neighbours} neighbours",
        "direction": "20 deg" if direction is None else direction,
        "date": dt.date.today().isoformat(),
        "machine": machine_info(),
    }


def local_vs_dense(n_samples: int, n_queries: int, neighbours: list[int]) -> dict[str, Any]:
    """Local neighbourhoods against the dense solution on the same fitted variograms and metric."""
    robot = load_robot("kr210")
    plant = seed001_plant(robot)
    rng = np.random.default_rng(3)
    lo = np.array([-30.0, -110.0, 90.0, -60.0, -90.0, -90.0])
    hi = np.array([30.0, -60.0, 150.0, 60.0, -20.0, 90.0])
    a = lo + rng.random((n_samples + n_queries, 6)) * (hi - lo)
    d = rng.choice([-1.0, 1.0], a.shape)
    p = (
        twin_tcp_mm(robot, plant.params, plant.effects, a, d, PAYLOAD_KG)
        + rng.normal(size=a[:, :3].shape) * 0.01
    )
    base = calibrate_kinematic(
        robot, a[:n_samples], p[:n_samples], dir=d[:n_samples], effects=("ratio", "backlash")
    )
    dense = fit_kriging(base.model, a[:n_samples], p[:n_samples], dir=d[:n_samples], neighbours=None).model
    q, qd, pq = a[n_samples:], d[n_samples:], p[n_samples:]

    def rms(e: NDArray[np.float64]) -> float:
        return round(float(np.sqrt(np.mean(np.sum(e**2, axis=1)))), 5)

    p_dense = dense.predict_tcp_mm(q, qd)
    out: dict[str, Any] = {
        "samples": n_samples,
        "checks": n_queries,
        "check_rms_mm": {
            "kinematic+ratio+backlash": rms(pq - base.model.predict_tcp_mm(q, qd)),
            "dense": rms(pq - p_dense),
        },
        "rms_gap_to_dense_mm": {},
    }
    for k in neighbours:
        local = KrigingModel(
            base.model,
            dense.metric,
            a[:n_samples],
            d[:n_samples],
            dense.residual_mm,
            dense.variograms,
            neighbours=k,
        )
        p_local = local.predict_tcp_mm(q, qd)
        out["check_rms_mm"][f"k={k}"] = rms(pq - p_local)
        out["rms_gap_to_dense_mm"][f"k={k}"] = rms(p_local - p_dense)
    return out


def scale(repeats: int) -> None:
    """10 000 samples: fit and 1 000 predictions at 32 and 64 neighbours; local vs dense at 2 000."""
    print(f"kriging at scale on {machine_line()}")
    for k in (32, 64):
        for direction in ("blind", "aware"):
            r = timing(10_000, 1000, repeats, neighbours=k, direction=direction)
            print(
                f"10 000 samples, {r['solver']}, direction-{direction}: fit {r['fit_s']} s "
                f"(CPU {r['fit_cpu_s']} s), 1 000 predictions best {r['best_ms']} ms "
                f"(CPU {r['best_cpu_ms']} ms), median {r['median_ms']} ms; "
                f"load average {r['load_average_1min']}",
                flush=True,
            )
    print(json.dumps(local_vs_dense(2000, 500, [16, 32, 64, 128])))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--samples", type=int, default=500)
    parser.add_argument("--queries", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--seed001", action="store_true", help="run seed 001's comparison instead")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--neighbours", default="auto", help="auto (default), dense, or a number")
    parser.add_argument("--scale", action="store_true", help="10 000 samples, local vs dense")
    args = parser.parse_args()
    if args.scale:
        scale(args.repeats)
        return
    neighbours: Neighbours = (
        "auto" if args.neighbours == "auto" else None if args.neighbours == "dense" else int(args.neighbours)
    )
    if args.seed001:
        result = seed001(args.seed, 497, 300)
        print(f"seed 001 comparison (simulated KR 210, 497 + 300 poses) on {machine_line()}")
        print(json.dumps(result, indent=1))
        return
    result = timing(args.samples, args.queries, args.repeats, neighbours)
    print(
        f"kriging prediction ({result['solver']}), {args.queries} queries on {args.samples} "
        f"sampling points: best "
        f"{result['best_ms']} ms, median {result['median_ms']} ms (fit {result['fit_s']} s)"
        f" on {machine_line()}"
    )
    print(json.dumps(result))


if __name__ == "__main__":
    main()
