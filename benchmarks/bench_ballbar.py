"""Ballbar and cross-bar calibration: fit time (aim: a ballbar fit of 4 arcs in under 1 s) and the
arc-count study (how the tracker check error falls with the number of arcs).

Fit time: a simulated 4-arc ballbar campaign (``irb120-geometric``, 128 rows) read from its CSV and
fitted (:func:`comp_daemon.instruments.campaign_fit.fit_campaign`), and an 18-placement cross-bar
campaign (``mh6-cell``, 72 rows), each ``--repeats`` times.

Arc-count study (``--study``): for k = 1..6 arcs and each seed, a k-arc ballbar campaign on the
hidden robot of ``irb120-geometric`` is fitted and its model judged on the check rows of a tracker
campaign of the same robot (frame registered on the fit rows), next to the nominal model and the
tracker calibrations (``poe``, ``kinematic``) fitted on those fit rows.

Near-dependent pairs (``--pairs``): for hidden robots drawn with the geometric errors of
``irb120-geometric`` (scenario seeds ``--robots``), a 3-arc ballbar campaign is fitted with its
near-dependent pairs kept and with the weaker of each held at zero (``fix_near_dependent``), and each
model is judged on a tracker campaign's check rows (frame registered on the fit rows); a 5-arc
campaign with one arc held out gives the held-out arc's bar error of both; and again with every POE
error pulled toward zero (``ridge``).

Run: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python -m benchmarks.bench_ballbar [--study] [--pairs]``
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.machine import machine_info, machine_line
from comp_daemon.data.campaigns import campaign_of, read_campaign
from comp_daemon.data.dataset import write_dataset
from comp_daemon.instruments.ballbar_plan import ORIENTATIONS
from comp_daemon.instruments.campaign_fit import fit_campaign, registered_prediction
from comp_daemon.models.registry import fit_model
from comp_daemon.sim.bars import run_ballbar_campaign, run_crossbar_campaign
from comp_daemon.sim.campaign import run_campaign
from comp_daemon.sim.scenario import load_scenario


def _rms(err: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def fit_times(repeats: int) -> list[dict[str, Any]]:
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for form, scenario, make in (
            ("ballbar, 4 arcs", "irb120-geometric", lambda s: run_ballbar_campaign(s, arcs=4, seed=1)),
            (
                "cross-bar, 18 placements",
                "mh6-cell",
                lambda s: run_crossbar_campaign(s, placements=18, seed=1),
            ),
        ):
            sc = load_scenario(scenario)
            path = Path(tmp) / "campaign.csv"
            write_dataset(make(sc), path)
            times, info = [], {}
            for _ in range(repeats):
                t0 = time.perf_counter()
                campaign = read_campaign(path, limits_deg=sc.robot.axis_limits_deg)
                fitted, _ = fit_campaign(sc.robot, campaign)
                times.append(time.perf_counter() - t0)
                info = fitted.info
            out.append(
                {
                    "form": form,
                    "rows": info["rows"],
                    "rank": info["rank"],
                    "best_s": round(min(times), 4),
                    "median_s": round(float(np.median(times)), 4),
                }
            )
    return out


def arc_study(
    seeds: list[int], arcs: list[int], n_tracker: int, orientation: Any = "per-arc"
) -> dict[str, Any]:
    sc = load_scenario("irb120-geometric")
    robot = sc.robot
    rows: dict[str, list[float]] = {}
    ranks: dict[int, int] = {}
    for seed in seeds:
        trk = run_campaign(sc, n_tracker, seed=100 + seed, in_tracker_frame=True)
        assert trk.a_deg is not None and trk.xyz_mm is not None and trk.split is not None
        fit, check = trk.fit_rows(), trk.check_rows()
        for name in ("nominal", "poe", "kinematic"):
            model = fit_model(name, robot, trk.a_deg[fit], trk.xyz_mm[fit]).model
            pred = model.predict_tcp_mm(trk.a_deg[check])
            rows.setdefault(f"tracker {name}", []).append(_rms(trk.xyz_mm[check] - pred))
        for k in arcs:
            campaign = campaign_of(run_ballbar_campaign(sc, arcs=k, seed=seed, orientation=orientation))
            assert campaign is not None
            fitted, _ = fit_campaign(robot, campaign)
            pred, _ = registered_prediction(fitted.model, trk.a_deg[fit], trk.xyz_mm[fit], trk.a_deg[check])
            rows.setdefault(f"ballbar {k} arcs", []).append(_rms(trk.xyz_mm[check] - pred))
            ranks[k] = int(fitted.info["rank"])
    return {
        "seeds": seeds,
        "tracker_poses": n_tracker,
        "orientation": orientation,
        "check_rms_mm": rows,
        "ballbar_rank": ranks,
    }


def pair_study(robot_seeds: list[int], n_tracker: int) -> dict[str, Any]:
    base = load_scenario("irb120-geometric")
    rows: list[dict[str, Any]] = []
    for robot_seed in robot_seeds:
        sc = dataclasses.replace(base, seed=robot_seed)
        trk = run_campaign(sc, n_tracker, seed=100, in_tracker_frame=True)
        assert trk.a_deg is not None and trk.xyz_mm is not None
        fit, check = trk.fit_rows(), trk.check_rows()
        nominal = fit_model("nominal", sc.robot, trk.a_deg[fit], trk.xyz_mm[fit]).model
        row: dict[str, Any] = {
            "robot_seed": robot_seed,
            "nominal": _rms(trk.xyz_mm[check] - nominal.predict_tcp_mm(trk.a_deg[check])),
        }
        three = campaign_of(run_ballbar_campaign(sc, arcs=3, seed=1))
        five = campaign_of(run_ballbar_campaign(sc, arcs=5, seed=1, check_arcs=1))
        assert three is not None and five is not None
        for mode in ("keep", "fix", "ridge"):
            how = {"fix_near_dependent": mode == "fix", "ridge": mode == "ridge"}
            fitted, _ = fit_campaign(sc.robot, three, **how)
            pred, _ = registered_prediction(fitted.model, trk.a_deg[fit], trk.xyz_mm[fit], trk.a_deg[check])
            _, held_out = fit_campaign(sc.robot, five, **how)
            row[mode] = {
                "tracker_check_rms_mm": _rms(trk.xyz_mm[check] - pred),
                "held_out_arc_bar_rms_mm": held_out["bar_error_rms_mm"]["after"],
                "held": [p["fixed"] for p in fitted.info["near_dependent_fixed"]],
                "dl4_mm": fitted.info["identified"].get("dl4", {}).get("value"),
            }
        rows.append(row)
    return {"robot_seeds": robot_seeds, "tracker_poses": n_tracker, "rows": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--study", action="store_true", help="also run the arc-count study")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--arcs", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6])
    ap.add_argument("--tracker-poses", type=int, default=200)
    ap.add_argument("--pairs", action="store_true", help="run the near-dependent pair study")
    ap.add_argument("--robots", type=int, nargs="+", default=[1202, *range(1, 16)])
    ap.add_argument(
        "--orientation", choices=tuple(ORIENTATIONS), default="per-arc", help="of the study's arcs"
    )
    args = ap.parse_args()
    doc: dict[str, Any] = {"date": dt.date.today().isoformat(), "machine": machine_info()}
    doc["fit"] = fit_times(args.repeats)
    for r in doc["fit"]:
        print(
            f"{r['form']}: {r['rows']} rows, rank {r['rank']}, best {r['best_s']} s, median {r['median_s']} s"
        )
    if args.study:
        study = arc_study(args.seeds, args.arcs, args.tracker_poses, args.orientation)
        doc["arc_study"] = study
        print(
            f"check-row 3-D RMS / mm on irb120-geometric, {args.orientation} orientation, seeds {args.seeds} "
            f"({args.tracker_poses} tracker poses):"
        )
        for name, values in study["check_rms_mm"].items():
            print(
                f"  {name:<22} "
                + "  ".join(f"{v:.4f}" for v in values)
                + f"   median {np.median(values):.4f}"
            )
        print("  ballbar rank by arcs: " + ", ".join(f"{k}: {r}" for k, r in study["ballbar_rank"].items()))
    if args.pairs:
        pairs = pair_study(args.robots, args.tracker_poses)
        doc["pair_study"] = pairs
        print(
            "near-dependent pairs kept / weaker held at zero / ridge, 3-arc ballbar, irb120-geometric's "
            "errors:"
        )
        print(
            "  robot seed | nominal | tracker check RMS keep fix ridge | held-out arc bar RMS keep fix ridge "
            "| held"
        )
        for r in pairs["rows"]:
            k, f, g = r["keep"], r["fix"], r["ridge"]
            track = "  ".join(f"{m['tracker_check_rms_mm']:.3f}" for m in (k, f, g))
            bar = "  ".join(f"{m['held_out_arc_bar_rms_mm']:.4f}" for m in (k, f, g))
            print(f"  {r['robot_seed']:>10} | {r['nominal']:.3f} | {track} | {bar} | {', '.join(f['held'])}")
        for what in ("tracker_check_rms_mm", "held_out_arc_bar_rms_mm"):
            keep = [r["keep"][what] for r in pairs["rows"]]
            for mode in ("fix", "ridge"):
                other = [r[mode][what] for r in pairs["rows"]]
                better = sum(b < a for a, b in zip(keep, other, strict=True))
                print(
                    f"  {what}: median keep {np.median(keep):.4f}, {mode} {np.median(other):.4f}; "
                    f"{mode} lower on {better} of {len(keep)}"
                )
    print(machine_line())
    print(json.dumps(doc))


if __name__ == "__main__":
    main()
