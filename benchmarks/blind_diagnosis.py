"""Blind tests of the diagnosis over the full grid: hit rate and false-alarm rate.

Each case is a synthetic campaign (``tests/diagnosis_campaigns.py``: nominal robot + random
geometric errors + the withheld effects, tracker noise σ 0.01 mm per axis) diagnosed against the
nominal twin. A case is a *hit* when ``unmodelled`` names exactly the withheld effects and each of
their steps names exactly the withheld joints; a geometric-only campaign is a *false alarm* when
``unmodelled`` is not empty.

Sizes are the 3-D RMS of the effect's TCP signature that geometry cannot absorb, in multiples of the
noise floor (the tracker's 3-D noise, 0.0173 mm): ``near`` = 1×, ``large`` = 10×; ``--limit`` adds
a sweep of smaller sizes that shows where detection ends (not counted in the hit rate).

``--time`` adds plant campaigns with a withheld drift or step of a joint's zero (constant temperature,
one payload, no column naming them), sized like the others: a hit names exactly the withheld effect
with the full catalogue; with the vocabulary of diagnose.md alone the case is *honest* when the
remainder follows time, no joint effect is named and no noise floor is claimed (no repeats).

``--realistic`` runs instead the suite of campaigns as real cells produce them (:data:`REALISTIC`,
each scored right or wrong by its own rule, :func:`realistic_right`): directions only in the pose
order, an error outside the vocabulary (one axis' angle error driven by another axis), thermal
growth with the temperature rising with time, a wrist error seen only through further reflectors,
a tracker frame metres from the base, noise and repeats only, each effect alone, three together,
and two sessions with the tracker moved between the fit and the check rows.

Run: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python -m benchmarks.blind_diagnosis [--jobs 2]``
(``--realistic [--seeds 1]`` for the suite above)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections import defaultdict
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import numpy as np
from diagnosis_campaigns import (
    NOISE_FLOOR_MM,
    PLANT_NOISE_FLOOR_MM,
    make_campaign,
    plant_campaign,
    wrist_campaign,
)

from comp_daemon.diagnosis import DiagnoseOptions, diagnose
from comp_daemon.diagnosis.comparison import AGREE_PCT
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad

SIZES = {"near": 1.0, "large": 10.0}
LIMIT_SIZES = {"0.25x": 0.25, "0.5x": 0.5}
SINGLE = {
    "kr210": [
        ("backlash", 1),
        ("backlash", 2),
        ("backlash", 3),
        ("backlash", 5),
        ("ratio", 1),
        ("ratio", 2),
        ("ratio", 3),
        ("ratio", 4),
        ("cyclic", 1),
        ("cyclic", 2),
        ("cyclic", 3),
        ("cyclic", 5),
        ("compliance", 2),
        ("compliance", 3),
        ("compliance", 5),
        ("thermal", None),
    ],
    "irb120": [
        ("backlash", 1),
        ("backlash", 3),
        ("ratio", 2),
        ("ratio", 5),
        ("cyclic", 2),
        ("cyclic", 4),
        ("compliance", 2),
        ("compliance", 3),
        ("thermal", None),
    ],
}
PLANT_SINGLE = [
    ("backlash", 1),
    ("backlash", 2),
    ("backlash", 3),
    ("backlash", 5),
    ("ratio", 1),
    ("ratio", 2),
    ("ratio", 3),
    ("cyclic", 1),
    ("cyclic", 2),
    ("cyclic", 3),
    ("compliance", 2),
    ("compliance", 3),
    ("compliance", 5),
    ("thermal", None),
]
PAIRS = [
    (("backlash", 2), ("compliance", 3)),
    (("ratio", 1), ("thermal", None)),
    (("cyclic", 3), ("backlash", 1)),
    (("compliance", 2), ("ratio", 4)),
    (("backlash", 5), ("cyclic", 2)),
]


def plant_cases(seeds: int, nulls: int) -> list[dict[str, Any]]:
    """The same blind test on campaigns of the simulated plant (kr210-geometric + withheld effects),
    in seed 000's drilling box and in a wider calibration box."""
    out: list[dict[str, Any]] = []
    for box in ("drilling", "wide"):
        for effect, joint in PLANT_SINGLE:
            for size_name, size in SIZES.items():
                for seed in range(seeds):
                    out.append(
                        {
                            "kind": "plant",
                            "robot": "kr210",
                            "tracker": seed % 2 == 1,
                            "size": size_name,
                            "box": box,
                            "seed": 4000 + seed,
                            "withheld": [(effect, joint, size * PLANT_NOISE_FLOOR_MM)],
                        }
                    )
    for seed in range(nulls):
        out.append(
            {
                "kind": "plant-null",
                "robot": "kr210",
                "tracker": seed % 2 == 1,
                "size": "-",
                "box": ("drilling", "wide")[(seed // 2) % 2],
                "seed": 5000 + seed,
                "withheld": [],
            }
        )
    return out


#: time effects withheld from plant campaigns (constant temperature, one payload): no column names them
TIME_SINGLE = [("drift", None), ("step", 2), ("step", 3), ("step", 5)]
#: the vocabulary of shared/spec/diagnose.md, without the catalogue's time effects
SPEC_VOCABULARY = ("backlash", "ratio", "cyclic", "compliance", "thermal")


def time_cases(seeds: int) -> list[dict[str, Any]]:
    """Plant campaigns with a withheld drift or step, diagnosed with and without the time effects."""
    out: list[dict[str, Any]] = []
    for effect, joint in TIME_SINGLE:
        for size_name, size in SIZES.items():
            for seed in range(seeds):
                out.append(
                    {
                        "kind": "time",
                        "robot": "kr210",
                        "tracker": seed % 2 == 1,
                        "size": size_name,
                        "box": "wide",
                        "seed": 6000 + seed,
                        "withheld": [(effect, joint, size * PLANT_NOISE_FLOOR_MM)],
                    }
                )
    return out


def run_time_case(case: dict[str, Any]) -> dict[str, Any]:
    """Full catalogue: a hit names exactly the withheld effect. Spec vocabulary: ``honest`` when the
    remainder follows time, no joint effect is named and no noise floor is claimed."""
    camp = plant_campaign(
        case["withheld"],
        case["seed"],
        wide=True,
        tracker=case["tracker"],
        temp_drift_k_per_h=0.0,
        payloads=(0.0,),
    )
    t0 = time.perf_counter()
    doc = diagnose(camp.dataset, camp.robot).to_json()
    elapsed = time.perf_counter() - t0
    spec = diagnose(camp.dataset, camp.robot, DiagnoseOptions(effects=SPEC_VOCABULARY)).to_json()
    want = {e: sorted([] if j is None else [j]) for e, j, _ in case["withheld"]}
    got = {s["effect"]: s["joints"] for s in doc["steps"][1:] if s["significant"]}
    follows_time = any(
        r["significant"] and r["against"] in ("t_s", "pose_order") for r in spec["residual_structure"]
    )
    wrong = [s["effect"] for s in spec["steps"][1:] if s["significant"] and s["joints"]]
    return {
        **case,
        "withheld": [[e, j] for e, j, _ in case["withheld"]],
        "hit": got == want,
        "named": got,
        "honest": follows_time and not wrong and spec["noise_floor_mm"] is None,
        "spec_named": wrong,
        "seconds": round(elapsed, 3),
        "unexplained_rms_mm": doc["unexplained_rms_mm"],
        "noise_floor_mm": doc["noise_floor_mm"],
    }


def _comparison_of(doc: dict[str, Any]) -> dict[str, Any] | None:
    """The ladder beside the compensation models (``model_comparison``): the best and by how much."""
    comparison = doc.get("model_comparison")
    if comparison is None:
        return None
    return {
        k: comparison[k] for k in ("agree", "best", "best_check_rms_mm", "better_pct", "ladder_check_rms_mm")
    }


def cases(seeds: int, nulls: int, limit: bool) -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = []
    variants = [("kr210", False), ("kr210", True), ("irb120", False)]
    sizes = dict(SIZES, **(LIMIT_SIZES if limit else {}))
    for robot, tracker in variants:
        for effect, joint in SINGLE[robot]:
            for size_name, size in sizes.items():
                for seed in range(seeds):
                    out.append(
                        {
                            "kind": "single",
                            "robot": robot,
                            "tracker": tracker,
                            "size": size_name,
                            "seed": 1000 + seed,
                            "withheld": [(effect, joint, size * NOISE_FLOOR_MM)],
                        }
                    )
        for pair in PAIRS if robot == "kr210" else []:
            for size_name, size in SIZES.items():
                for seed in range(seeds):
                    out.append(
                        {
                            "kind": "pair",
                            "robot": robot,
                            "tracker": tracker,
                            "size": size_name,
                            "seed": 2000 + seed,
                            "withheld": [(e, j, size * NOISE_FLOOR_MM) for e, j in pair],
                        }
                    )
    for seed in range(nulls):
        robot, tracker = variants[seed % len(variants)]
        joint_noise = 0.002 if seed % 2 else 0.0
        out.append(
            {
                "kind": "null",
                "robot": robot,
                "tracker": tracker,
                "size": "-",
                "seed": 3000 + seed,
                "withheld": [],
                "joint_noise_deg": joint_noise,
            }
        )
    return out


#: the realistic suite: (name, robot, withheld (effect, joint, size in noise floors), how it is built)
REALISTIC: list[tuple[str, str, list[tuple[str, int | None, float]], str]] = [
    ("directions from the pose order", "kr210", [("backlash", 2, 5.0), ("backlash", 3, 5.0)], "no-dir"),
    ("coupling outside the vocabulary", "kr210", [], "coupling"),
    ("thermal, temperature rising with time", "kr210", [("thermal", None, 5.0)], "t_s"),
    ("wrist backlash seen by further reflectors", "irb120", [("backlash", 6, 0.0)], "wrist"),
    ("tracker frame far from the base", "kr210", [("ratio", 2, 5.0)], "tracker"),
    ("noise and repeats only", "kr210", [], "repeats"),
    ("backlash alone", "kr210", [("backlash", 1, 5.0)], "plain"),
    ("ratio alone", "kr210", [("ratio", 3, 5.0)], "plain"),
    ("cyclic alone", "kr210", [("cyclic", 2, 5.0)], "plain"),
    ("compliance alone", "kr210", [("compliance", 2, 5.0)], "plain"),
    ("thermal alone", "kr210", [("thermal", None, 5.0)], "plain"),
    (
        "three together",
        "kr210",
        [("backlash", 2, 5.0), ("cyclic", 1, 5.0), ("compliance", 3, 5.0)],
        "plain",
    ),
    ("two sessions, tracker moved", "kr210", [("ratio", 2, 5.0)], "sessions"),
]

#: the angle error of axis 3 driven by axis 2 in the coupling case: amplitude (deg)
COUPLING_DEG = 0.01


def realistic_cases(seeds: int) -> list[dict[str, Any]]:
    return [
        {
            "kind": "realistic",
            "name": name,
            "robot": robot,
            "build": build,
            "tracker": build == "tracker",
            "size": "-",
            "seed": 5000 + seed,
            "withheld": [(e, j, size * NOISE_FLOOR_MM) for e, j, size in withheld],
        }
        for name, robot, withheld, build in REALISTIC
        for seed in range(seeds)
    ]


def _rotation_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def realistic_dataset(case: dict[str, Any]) -> tuple[Any, Any]:
    """The campaign of one realistic case (data set, robot), built as its ``build`` says."""
    build, seed = case["build"], case["seed"]
    if build == "wrist":
        camp = wrist_campaign(seed, 0.03)
        return camp.dataset, camp.robot
    camp = make_campaign(
        case["robot"],
        seed,
        [] if build == "coupling" else case["withheld"],
        tracker=build == "tracker",
        with_dir=build != "no-dir",
        with_temp=any(e == "thermal" for e, _, _ in case["withheld"]),
        repeat_fraction=0.4 if build == "repeats" else 0.1,
    )
    ds = camp.dataset
    if build == "t_s":  # one pose a minute: the temperature and the clock rise together
        ds = dataclasses.replace(ds, t_s=60.0 * np.arange(len(ds), dtype=float))
    if build == "coupling":  # A3's angle error follows A2: no effect of the vocabulary has that form
        params = KinematicParams.from_robot(camp.robot)
        a = np.array(ds.a_deg)
        moved = a.copy()
        moved[:, 2] += COUPLING_DEG * np.sin(np.radians(3.0 * a[:, 1]))
        delta = tcp_position_mm(params, axes_deg_to_q_rad(moved, params.sign)) - tcp_position_mm(
            params, axes_deg_to_q_rad(a, params.sign)
        )
        ds = dataclasses.replace(ds, xyz_mm=np.asarray(ds.xyz_mm) + delta)
    if build == "sessions":  # the tracker moved between the fit and the check rows
        check = ds.check_rows()
        xyz = np.array(ds.xyz_mm)
        xyz[check] = xyz[check] @ _rotation_z(0.05).T + np.array([0.8, -0.3, 0.2])
        ds = dataclasses.replace(ds, xyz_mm=xyz)
    return ds, camp.robot


def realistic_right(case: dict[str, Any], doc: dict[str, Any]) -> bool:
    """Whether the diagnosis of a realistic case is right (what an engineer acting on it needs)."""
    got = {s["effect"]: s["joints"] for s in doc["steps"][1:] if s["significant"]}
    want = {
        e: sorted({j for ee, j, _ in case["withheld"] if ee == e and j is not None})
        for e, _, _ in case["withheld"]
    }
    build = case["build"]
    if build == "coupling":  # nothing of the vocabulary may be named
        return not got
    if build == "sessions":  # no effect advice while the fit and check rows disagree
        agreement = doc.get("fit_check_agreement", {})
        return agreement.get("agree") is False and "To act:" not in doc["where"]["summary"]
    if build == "repeats":
        return not got and doc["noise_floor_source"] == "repeats"
    if build == "wrist":
        return 6 in got.get("backlash", [])
    if build == "t_s":  # the physical driver, not the clock as well
        return got == {"thermal": []}
    if build == "no-dir":
        return got == want and doc.get("directions", {}).get("source") == "inferred"
    return got == want


def run_realistic_case(case: dict[str, Any]) -> dict[str, Any]:
    ds, robot = realistic_dataset(case)
    t0 = time.perf_counter()
    doc = diagnose(ds, robot).to_json()
    elapsed = time.perf_counter() - t0
    return {
        **case,
        "withheld": [[e, j] for e, j, _ in case["withheld"]],
        "hit": realistic_right(case, doc),
        "named": {s["effect"]: s["joints"] for s in doc["steps"][1:] if s["significant"]},
        "seconds": round(elapsed, 3),
        "unexplained_rms_mm": doc["unexplained_rms_mm"],
        "noise_floor_mm": doc["noise_floor_mm"],
        "model_comparison": _comparison_of(doc),
    }


def run_case(case: dict[str, Any]) -> dict[str, Any]:
    if case["kind"] == "time":
        return run_time_case(case)
    if case["kind"] == "realistic":
        return run_realistic_case(case)
    if case["kind"].startswith("plant"):
        camp = plant_campaign(
            case["withheld"], case["seed"], wide=case["box"] == "wide", tracker=case["tracker"]
        )
    else:
        camp = make_campaign(
            case["robot"],
            case["seed"],
            case["withheld"],
            tracker=case["tracker"],
            joint_noise_deg=case.get("joint_noise_deg", 0.0),
        )
    t0 = time.perf_counter()
    diag = diagnose(camp.dataset, camp.robot)
    elapsed = time.perf_counter() - t0
    doc = diag.to_json()
    want = {e: sorted([] if j is None else [j]) for e, j, _ in case["withheld"]}
    got = {s["effect"]: s["joints"] for s in doc["steps"][1:] if s["significant"]}
    hit = got == want
    return {
        **case,
        "withheld": [[e, j] for e, j, _ in case["withheld"]],
        "hit": hit,
        "named": got,
        "seconds": round(elapsed, 3),
        "unexplained_rms_mm": doc["unexplained_rms_mm"],
        "noise_floor_mm": doc["noise_floor_mm"],
        "first_p_times_m": doc["selection"][0]["best"][0]["p_value"] * doc["selection"][0]["candidates"]
        if doc["selection"]
        else None,
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seeds", type=int, default=3, help="random seeds per effect case (default 3)")
    parser.add_argument("--nulls", type=int, default=120, help="geometric-only campaigns (default 120)")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    parser.add_argument("--limit", action="store_true", help="add the detection-limit sweep (0.25x, 0.5x)")
    parser.add_argument(
        "--plant",
        action="store_true",
        help="also run the grid on campaigns of the simulated plant (kr210-geometric + effects)",
    )
    parser.add_argument(
        "--plant-nulls", type=int, default=60, help="geometric-only plant campaigns (default 60)"
    )
    parser.add_argument(
        "--time",
        action="store_true",
        help="also withhold the time effects (drift, step) from plant campaigns with no column naming them",
    )
    parser.add_argument(
        "--realistic", action="store_true", help="run only the realistic suite (REALISTIC), right/wrong"
    )
    parser.add_argument("--json", type=Path, help="write every case's result here")
    args = parser.parse_args()
    if args.realistic:
        realistic_main(args)
        return
    todo = cases(args.seeds, args.nulls, args.limit)
    if args.plant:
        todo += plant_cases(args.seeds, args.plant_nulls)
    if args.time:
        todo += time_cases(args.seeds)
    t0 = time.perf_counter()
    if args.jobs > 1:
        with ProcessPoolExecutor(args.jobs) as pool:
            results = list(pool.map(run_case, todo, chunksize=4))
    else:
        results = [run_case(c) for c in todo]
    wall = time.perf_counter() - t0
    table: dict[tuple[str, str, str], list[bool]] = defaultdict(list)
    for r in results:
        table[(r["kind"], r.get("box", "-"), r["size"])].append(r["hit"])
    print(f"{len(results)} campaigns in {wall:.0f} s")
    for (kind, box, size), hits in sorted(table.items()):
        label = "false alarms" if kind.endswith("null") else "hits"
        value = len(hits) - sum(hits) if kind.endswith("null") else sum(hits)
        print(f"  {kind:10s} {box:8s} {size:6s} {label}: {value}/{len(hits)}")
    for source, kinds in (("generator", ("single", "pair")), ("plant", ("plant",)), ("time", ("time",))):
        counted = [r["hit"] for r in results if r["kind"] in kinds and r["size"] in SIZES]
        nulls = [
            not r["hit"] for r in results if r["kind"] == ("null" if source == "generator" else "plant-null")
        ]
        if counted:
            print(
                f"{source}: hit rate (near + large): {sum(counted)}/{len(counted)} = "
                f"{100.0 * sum(counted) / len(counted):.1f} %"
            )
        if nulls:
            print(
                f"{source}: false-alarm rate (geometric only): {sum(nulls)}/{len(nulls)} = "
                f"{100.0 * sum(nulls) / len(nulls):.1f} %"
            )
    timed = [r for r in results if r["kind"] == "time"]
    if timed:
        honest = sum(r["honest"] for r in timed)
        print(
            f"time, spec vocabulary: remainder follows time, no joint effect named, no floor claimed: "
            f"{honest}/{len(timed)}"
        )
    misses = [r for r in results if not r["hit"] and (r["kind"].endswith("null") or r["size"] in SIZES)]
    for r in misses:
        print(
            f"  miss: {r['kind']} {r.get('box', '')} {r['robot']}{' tracker' if r['tracker'] else ''} "
            f"{r['size']} "
            f"seed {r['seed']} withheld {r['withheld']} named {r['named']}"
        )
    for r in timed:
        if not r["honest"]:
            print(
                f"  not honest (spec vocabulary): {r['size']} seed {r['seed']} {r['withheld']} "
                f"named {r['spec_named']}"
            )
    secs = sorted(r["seconds"] for r in results)
    print(f"diagnosis time per campaign: median {secs[len(secs) // 2]:.2f} s, max {secs[-1]:.2f} s")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


def realistic_main(args: argparse.Namespace) -> None:
    todo = realistic_cases(args.seeds)
    t0 = time.perf_counter()
    if args.jobs > 1:
        with ProcessPoolExecutor(args.jobs) as pool:
            results = list(pool.map(run_case, todo))
    else:
        results = [run_case(c) for c in todo]
    print(f"{len(results)} realistic campaigns in {time.perf_counter() - t0:.0f} s")
    for r in results:
        verdict = "right" if r["hit"] else "WRONG"
        models = r.get("model_comparison")
        beside = (
            ""
            if not models or models["best"] is None
            else f"; best model {models['best']} {models['better_pct']:+.0f} % vs the ladder"
            + ("" if models["agree"] else " (disagree)")
        )
        print(f"  {verdict:5s} {r['name']:45s} seed {r['seed']} named {r['named']}{beside}")
    right = sum(r["hit"] for r in results)
    print(f"right: {right}/{len(results)}")
    compared = [r["model_comparison"] for r in results if r.get("model_comparison")]
    if compared:
        agree = sum(bool(c["agree"]) for c in compared)
        within = f"the ladder within {AGREE_PCT:g} % of (or below) the best model compared"
        print(f"{within}: {agree}/{len(compared)}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
