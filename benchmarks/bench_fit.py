"""Fit-time benchmark of the calibration core, and seed 000's improved LM against scipy.

Run: ``.venv/bin/python benchmarks/bench_fit.py [--sizes 100,1000,10000] [--repeat 3]``

1. Fit time of the kinematic calibration (MDH + base + tool; and with seed 001's ratio and backlash)
   and of the order-3 Chebyshev model for 100, 1 000 and 10 000 poses. Poses: the kr210-cell
   scenario's sampling box (seed 000: 600 × 1000 × 600 mm, A/B/C ±10°) by its nominal inverse
   kinematics; measurements: the scenario's hidden robot and joint effects plus 0.01 mm noise.
   Times are wall-clock, best of ``--repeat``, everything included (frame, identifiability, solver).
   The cross-validated order selection (5 folds × 5 orders × 2 thresholds) is timed at 100 and
   1 000 poses.
2. The same least-squares problems (kinematic, Chebyshev order 3 at 1 000 poses) solved by the
   improved LM of seed 000 and by ``scipy.optimize.least_squares`` (``method="lm"``, MINPACK, and
   ``"trf"``), same residual, Jacobian and start: iterations, function/Jacobian evaluations, time,
   final cost. Also Rosenbrock as a least-squares problem.
3. ``--kinds``: every model of the registry (``evaluate --models all``) fitted through
   :func:`comp_daemon.models.registry.fit_spec` at 100, 1 000 and 10 000 poses of the same
   campaign (with payloads 0 / 120 kg), once each: fit time (everything included) and the time of
   1 000 predictions. ``chebyshev:cv`` is timed up to 1 000 poses only (``--cv-max``).
4. ``--trial``: seed 000's experiment on the simulated cell (kr210-cell): 204 sampled poses, 100 fit
   the models, the other 104 are targets. Each model compensates the targets (``compensate``; the
   approach directions are those of the visiting order), the plant moves to the compensated
   commands and the tracker measures; Table 2 of the measured errors (measured − wanted).
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
import scipy
from scipy.optimize import least_squares

from comp_daemon.estimation.identifiability import analyze_identifiability, mdh_priority
from comp_daemon.estimation.lm import improved_lm
from comp_daemon.kinematics.kuka_abc import flange_rotation_of_tool_abc
from comp_daemon.kinematics.params import N_PARAMS, PARAM_NAMES, KinematicParams
from comp_daemon.models.base import ErrorModel
from comp_daemon.models.chebyshev import (
    ChebyshevProblem,
    chebyshev_identifiability,
    chebyshev_setup,
    fit_chebyshev,
    motion_range_deg,
    select_order,
)
from comp_daemon.models.compensation import compensate
from comp_daemon.models.effects import EffectParams, effect_param_names, twin_jacobian, twin_tcp_mm
from comp_daemon.models.evaluation import error_statistics, format_table2
from comp_daemon.models.kinematic import KinematicProblem, calibrate_kinematic
from comp_daemon.models.registry import ALL_MODELS, fit_model, fit_spec, parse_model_name
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.sim.campaign import measure_at, run_campaign, sample_poses
from comp_daemon.sim.plant import RobotPlant
from comp_daemon.sim.scenario import load_scenario
from comp_daemon.sim.tracker import LaserTracker


def machine_info() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as handle:
            for line in handle:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    load = os.getloadavg()[0]
    return (
        f"{cpu}; {os.cpu_count()} logical CPUs; load average {load:.2f}; "
        f"Python {platform.python_version()}; numpy {np.__version__}; scipy {scipy.__version__}; "
        f"{platform.system()} {platform.release()}"
    )


def best_time(fn: Callable[[], Any], repeat: int) -> tuple[float, Any]:
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def campaign(n: int, seed: int = 0) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray]:
    scen = load_scenario("kr210-cell")
    rng = np.random.default_rng(seed)
    poses = sample_poses(scen, n, rng)
    dirs = rng.choice([-1.0, 1.0], size=poses.a_deg.shape)
    eff = EffectParams(
        backlash_deg=scen.effects.backlash_deg,
        ratio=scen.effects.ratio,
        cyclic_sin_deg=scen.effects.cyclic_sin_deg,
        cyclic_cos_deg=scen.effects.cyclic_cos_deg,
    )
    p = twin_tcp_mm(scen.robot, scen.true_params(), eff, poses.a_deg, dirs)
    return scen.robot, poses.a_deg, p + rng.normal(size=p.shape) * 0.01, dirs


def fit_times(sizes: list[int], repeat: int) -> None:
    print(f"\n## fit time (s, best of {repeat}; all steps included)")
    print(f"{'poses':>6} | {'kinematic':>9} {'it':>3} | {'kin+ratio+backlash':>18} {'it':>3} | "
          f"{'chebyshev m=3':>13} {'it':>3} {'kept':>5} | {'CV order':>8}")  # fmt: skip
    for n in sizes:
        robot, a, p, dirs = campaign(n)
        t_k, kf = best_time(lambda: calibrate_kinematic(robot, a, p), repeat)  # noqa: B023
        t_e, ke = best_time(
            lambda: calibrate_kinematic(robot, a, p, dir=dirs, effects=["ratio", "backlash"]),  # noqa: B023
            repeat,
        )
        t_c, cf = best_time(lambda: fit_chebyshev(robot, a, p, 3), repeat)  # noqa: B023
        cv = "-"
        if n <= 1000:
            t_cv, sel = best_time(lambda: select_order(robot, a, p), 1)  # noqa: B023
            cv = f"{t_cv:.2f} (m={sel.order})"
        print(
            f"{n:>6} | {t_k:>9.3f} {kf.lm.iterations:>3} | {t_e:>18.3f} {ke.lm.iterations:>3} | "
            f"{t_c:>13.3f} {cf.lm.iterations:>3} {cf.report.n_identifiable:>5} | {cv:>8}"
        )


def kind_times(sizes: list[int], cv_max: int) -> None:
    print(
        "\n## every model of the registry: fit time (s, once, everything included; wall and the "
        "process's CPU time), 1 000 predictions (ms)"
    )
    print(f"{'model':<38} " + " ".join(f"{f'{n} fit':>10} {'cpu':>7} {'predict':>8}" for n in sizes))
    data = {}
    for n in sizes:
        robot, a, p, dirs = campaign(n)
        payload = np.where(np.arange(n) % 2 == 0, 0.0, 120.0)
        data[n] = (robot, MeasuredRows(a, p, dirs, payload))
    _, q_a, _, q_dirs = campaign(1000, seed=7)
    for name in ALL_MODELS:
        cells = []
        for n in sizes:
            if name == "chebyshev:cv" and n > cv_max:
                cells.append(f"{'-':>10} {'-':>8}")
                continue
            robot, rows = data[n]
            t0, c0 = time.perf_counter(), time.process_time()
            model = fit_spec(parse_model_name(name), robot, rows).model
            t_fit, c_fit = time.perf_counter() - t0, time.process_time() - c0
            t_pred, _ = best_time(lambda: model.predict_tcp_mm(q_a, q_dirs, 60.0), 3)  # noqa: B023
            cells.append(f"{t_fit:>10.3f} {c_fit:>7.3f} {1e3 * t_pred:>8.1f}")
        print(f"{name:<38} " + " ".join(cells) + f"  (load average {os.getloadavg()[0]:.1f})", flush=True)


def compare_solvers(repeat: int) -> None:
    print("\n## improved LM (seed 000) vs scipy.optimize.least_squares, same residual/Jacobian/start")
    robot, a, p, dirs = campaign(1000, seed=1)
    problems: dict[
        str, tuple[Callable[[np.ndarray], np.ndarray], Callable[[np.ndarray], np.ndarray], np.ndarray]
    ]
    problems = {}
    # Rosenbrock
    problems["rosenbrock"] = (
        lambda x: np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]]),
        lambda x: np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0]]),
        np.array([-1.2, 1.0]),
    )
    # kinematic calibration with ratio and backlash, identifiable subset, scaled variables
    start = KinematicParams.from_robot(robot)
    names = effect_param_names(["ratio", "backlash"])
    eff0 = EffectParams.zeros()
    _, jac0 = twin_jacobian(robot, start, eff0, names, a, dirs)
    rep = analyze_identifiability(jac0, (*PARAM_NAMES, *names), priority=mdh_priority(start, extra=names))
    idx = rep.identifiable_index
    eff_kept = [n for n in names if n in rep.identifiable]
    prob = KinematicProblem(robot, start, eff0, idx[idx < N_PARAMS], eff_kept, a, p, dirs, 0.0, None)
    problems["kinematic+ratio+backlash (1000 poses)"] = (prob.residual, prob.jacobian, np.zeros(idx.size))
    # Chebyshev order 3, the coefficients kept by the identifiability analysis
    st = chebyshev_setup(start, a, motion_range_deg(a), 3)
    cidx = chebyshev_identifiability(st, check_rank=False).identifiable_index
    cheb = ChebyshevProblem(st, cidx, p)
    problems[f"chebyshev m=3, {cidx.size} coefficients (1000 poses)"] = (
        cheb.residual,
        cheb.jacobian,
        np.zeros(cidx.size),
    )
    print(
        f"{'problem':<44} {'solver':<14} {'iter':>5} {'nfev':>5} {'njev':>5} {'time s':>8} {'final cost':>14}"
    )
    for label, (fun, jac, x0) in problems.items():
        scaled = label != "rosenbrock"
        t, r = best_time(lambda: improved_lm(fun, jac, x0, x_scale="jac" if scaled else None), repeat)  # noqa: B023
        print(f"{label:<44} {'improved LM':<14} {r.iterations:>5} {r.n_residual_evals:>5} "
              f"{r.n_jacobian_evals:>5} {t:>8.3f} {r.cost:>14.8g}")  # fmt: skip
        for method in ("lm", "trf"):
            kw: dict[str, Any] = {"x_scale": "jac"} if scaled else {}
            t, s = best_time(lambda: least_squares(fun, x0, jac=jac, method=method, **kw), repeat)  # noqa: B023
            nj = s.njev if s.njev is not None else "-"
            print(
                f"{'':<44} {'scipy ' + method:<14} {'-':>5} {s.nfev:>5} {nj!s:>5} {t:>8.3f} {s.cost:>14.8g}"
            )


def _visit_dirs(a_deg: np.ndarray, start_deg: np.ndarray) -> np.ndarray:
    """Approach direction of every axis when the poses are visited in order (sign of the last move)."""
    prev = np.vstack([start_deg, a_deg[:-1]])
    step = np.sign(a_deg - prev)
    out = np.empty_like(step)
    last = np.ones(6)
    for i, row in enumerate(step):
        last = np.where(row != 0.0, row, last)
        out[i] = last
    return out


def seed000_trial(seed: int) -> None:
    print("\n## seed 000 trial on the simulated cell (kr210-cell): 100 fit poses, 104 compensated targets")
    scen = load_scenario("kr210-cell")
    data = run_campaign(scen, 204, seed=seed)
    assert data.a_deg is not None and data.xyz_mm is not None
    assert data.target_xyz_mm is not None and data.target_abc_deg is not None
    fit = np.sort(np.random.default_rng(seed).permutation(204)[:100])
    check = np.setdiff1d(np.arange(204), fit)
    check = check[np.argsort(np.asarray(data.t_s)[check])]  # visit the targets in campaign order
    wanted = data.target_xyz_mm[check]
    rot = flange_rotation_of_tool_abc(data.target_abc_deg[check])
    a_nominal = data.a_deg[check]
    payload = data.payload_kg[check]
    dirs = _visit_dirs(a_nominal, scen.campaign.home_deg)
    models: dict[str, ErrorModel] = {}
    for token, kind, effects in (
        ("nominal", "nominal", ()),
        ("kinematic", "kinematic", ()),
        ("kinematic+ratio+backlash+compliance", "kinematic", ("ratio", "backlash", "compliance")),
        ("chebyshev (CV)", "chebyshev", ()),
        ("chebyshev m=3", "chebyshev", ()),
    ):
        order: int | Literal["cv"] | None = None
        if kind == "chebyshev":
            order = 3 if token.endswith("m=3") else "cv"
        models[token] = fit_model(
            kind, scen.robot, data.a_deg[fit], data.xyz_mm[fit], dir=np.asarray(data.dir, float)[fit],
            payload_kg=data.payload_kg[fit], order=order, effects=effects,
        ).model  # fmt: skip
    table: dict[str, dict[str, Any]] = {}
    for token, model in models.items():
        res = compensate(model, wanted, rot, a_seed_deg=a_nominal, dir=dirs, payload_kg=payload, tol_mm=1e-6)
        plant = RobotPlant.from_scenario(scen, seed=seed + 11)
        tracker = LaserTracker(scen.noise.tracker_sigma_mm, seed=seed + 12)
        measured = np.empty_like(wanted)
        for i in range(len(check)):
            if plant.payload_kg != payload[i]:
                plant.set_payload(float(payload[i]))
            m = measure_at(plant, tracker, res.a_deg[i], scen.motion.dwell_s, scen.cell.grating_radius_mm)
            measured[i] = m.xyz_mm
        table[token] = error_statistics(measured, wanted)
    print("error = measured - wanted TCP (mm), robot base frame; 'nominal' = uncompensated commands")
    print(format_table2(table))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="100,1000,10000")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument(
        "--trial", action="store_true", help="run seed 000's trial on the simulated cell only"
    )
    parser.add_argument("--seed", type=int, default=0, help="campaign seed of the trial")
    parser.add_argument("--kinds", action="store_true", help="time every model of the registry only")
    parser.add_argument("--cv-max", type=int, default=1000, help="largest campaign for chebyshev:cv")
    args = parser.parse_args()
    print("# bench_fit")
    print(machine_info())
    if args.trial:
        seed000_trial(args.seed)
        return
    if args.kinds:
        kind_times([int(s) for s in args.sizes.split(",")], args.cv_max)
        return
    fit_times([int(s) for s in args.sizes.split(",")], args.repeat)
    compare_solvers(args.repeat)


if __name__ == "__main__":
    main()
