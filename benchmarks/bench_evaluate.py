"""``evaluate --models all`` model by model: the CPU time of each fit (its out-of-fold selection
included) and its check RMS, on the campaigns of docs/benchmarks.md, optionally with a cProfile of
each fit.

``python -m benchmarks.bench_evaluate --campaign real-like-1000x3 [--models all] [--profile 12]``

Campaigns (sampled by the simulator into ``--workdir`` the first time, seeds fixed):
``real-like-1000x3`` (``sim sample --scenario real-like --targets 3 --n 1000 --seed 1``),
``real-like-6000`` (``--targets 1 --n 6000 --seed 3``) and ``ur5`` (the real UR5 campaign of
benchmarks/real_campaigns/ur5_jacobi, converted by benchmarks/real_campaign_ur5.py; its rows are
split at random, as ``evaluate`` does without a split column). ``--profile N`` prints each fit's
N costliest functions by their own time and by cumulative time. The numeric libraries run one
thread (benchmarks/__init__).
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import pstats
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.machine import machine_line
from comp_daemon.data.dataset import Dataset, read_dataset
from comp_daemon.models.evaluation import error_statistics
from comp_daemon.models.fitting import FitOptions
from comp_daemon.models.registry import ALL_MODELS, fit_spec, parse_model_name, uses_directions
from comp_daemon.preparation.campaign import PreparedCampaign, PrepareOptions, prepare_campaign
from comp_daemon.robot.description import RobotDescription, load_robot

ROOT = Path(__file__).resolve().parents[1]
UR5_DIR = ROOT / "benchmarks" / "real_campaigns" / "ur5_jacobi"
CAMPAIGNS: dict[str, tuple[str, list[str]]] = {
    "real-like-1000x3": (
        "irb120",
        ["--scenario", "real-like", "--targets", "3", "--n", "1000", "--seed", "1"],
    ),
    "real-like-6000": ("irb120", ["--scenario", "real-like", "--targets", "1", "--n", "6000", "--seed", "3"]),
}


def campaign(name: str, workdir: Path) -> tuple[Path, str]:
    """The campaign's CSV (sampled on first use) and its robot."""
    path = workdir / f"{name}.csv"
    workdir.mkdir(parents=True, exist_ok=True)
    if name == "ur5":  # converted to a data set by benchmarks/real_campaign_ur5.py
        if not path.exists():
            subprocess.run(
                [sys.executable, "-m", "benchmarks.real_campaign_ur5", "--out", str(path)],
                check=True,
                stdout=subprocess.DEVNULL,
            )
        return path, str(UR5_DIR / "ur5.toml")
    robot, args = CAMPAIGNS[name]
    if not path.exists():
        subprocess.run(
            [sys.executable, "-m", "comp_daemon", "sim", "sample", *args, "--out", str(path)],
            check=True,
            stdout=subprocess.DEVNULL,
        )
    return path, robot


def prepared(path: Path, robot: RobotDescription) -> PreparedCampaign:
    """The campaign as ``evaluate --models all`` prepares it: directions inferred when missing, the
    split, the frame."""
    ds = read_dataset(path, limits_deg=robot.axis_limits_deg, min_rows=0, kind="measurement")
    return prepare_campaign(ds, robot, PrepareOptions(need_directions=True))


def bench_model(token: str, robot: RobotDescription, camp: PreparedCampaign, profile: int) -> dict[str, Any]:
    spec = parse_model_name(token)
    ds: Dataset = camp.dataset
    if uses_directions(spec) and ds.dir is None:
        return {"model": token, "skipped": "no directions"}
    check = camp.check_rows
    train = camp.rows(camp.fit_rows)
    prof = cProfile.Profile(time.process_time) if profile else None  # CPU time: less disturbed by load
    c0, t0 = time.process_time(), time.perf_counter()
    if prof is not None:
        prof.enable()
    fitted = fit_spec(spec, robot, train, FitOptions(frame=camp.frame))
    if prof is not None:
        prof.disable()
    cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    rows = camp.rows(check)
    pred = fitted.model.predict_tcp_mm(rows.a_deg, rows.dir, rows.payload_kg, rows.temp_c)
    stats = error_statistics(rows.xyz_mm, pred)
    sel = fitted.info.get("selection") or {}
    out = {
        "model": token,
        "cpu_s": cpu,
        "wall_s": wall,
        "check_rms_mm": stats["3d"]["rms"],
        "kept": sel.get("kept"),
        "dropped": sel.get("dropped"),
    }
    if prof is not None:
        for key in ("tottime", "cumulative"):
            text = io.StringIO()
            pstats.Stats(prof, stream=text).sort_stats(key).print_stats(profile)
            out[f"profile_{key}"] = text.getvalue()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--campaign", choices=[*CAMPAIGNS, "ur5"], default="real-like-1000x3")
    ap.add_argument("--models", default="all", help="comma-separated model names, or all")
    ap.add_argument("--profile", type=int, default=0, metavar="N")
    ap.add_argument(
        "--workdir", type=Path, default=Path(os.environ.get("TMPDIR", "/tmp")) / "comp-daemon-bench"
    )
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    opts = ap.parse_args()
    path, robot_name = campaign(opts.campaign, opts.workdir)
    robot = load_robot(robot_name)
    camp = prepared(path, robot)
    ds, fit_rows, check = camp.dataset, camp.fit_rows, camp.check_rows
    models = list(ALL_MODELS) if opts.models == "all" else [m.strip() for m in opts.models.split(",")]
    print(machine_line())
    print(f"{opts.campaign}: {len(ds)} rows ({len(fit_rows)} fit, {len(check)} check)")
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    results = []
    for token in models:
        r = bench_model(token, robot, camp, opts.profile)
        results.append(r)
        if "skipped" in r:
            print(f"{token:<36s} skipped: {r['skipped']}")
            continue
        print(
            f"{token:<36s} CPU {r['cpu_s']:6.2f} s  wall {r['wall_s']:6.2f} s  check RMS "
            f"{r['check_rms_mm']:.6f} mm  kept {r['kept']} dropped {r['dropped']}"
        )
        for key in ("profile_tottime", "profile_cumulative"):
            if key in r:
                print(r[key])
    total = sum(r.get("cpu_s", 0.0) for r in results)
    print(f"total CPU {total:.2f} s; load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if opts.json is not None:
        doc = {
            "machine": machine_line(),
            "campaign": opts.campaign,
            "load": os.getloadavg(),
            "results": results,
        }
        opts.json.write_text(json.dumps(doc, indent=1, default=lambda v: np.asarray(v).tolist()))


if __name__ == "__main__":
    main()
