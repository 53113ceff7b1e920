"""Tracker stations and 6-DOF probes: before (one frame for every row) and after (each station its
own frame, the probe's orientation observed), on campaigns of the project's own simulated cell.

For each seed, ``sim sample --tracker-frame --restation --probe-sigma-deg 0.01`` of the scenario
(station B: the tracker turned 50° about the vertical and moved 5 m) is judged on its check rows:

- **one frame**: what the tool did before a ``station`` column: one rigid registration of the
  nominal twin onto every fit row, then the kinematic calibration in that one frame (the unit rule
  now refuses such a file: its points spread ~4 times as far as one robot's);
- **per station**: the preparation every door shares (each station registered jointly with the
  kinematic calibration), then the kinematic calibration with the probe's orientation;
- **positions only**: the same without the ``qw…qz`` columns: the check RMS, and the standard
  errors of the wrist's lengths (``a5``, ``d5``) that the orientation pins down.

Run: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python -m benchmarks.stations_and_probes
[--scenario kr210-geometric] [--n 80,200] [--seeds 1,2,3]``
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from comp_daemon.data.table import Dataset
from comp_daemon.models.fitting import FitOptions
from comp_daemon.models.kinematic import calibrate_kinematic
from comp_daemon.models.registry import fit_spec, parse_model_name
from comp_daemon.preparation.campaign import prepare_campaign
from comp_daemon.robot.description import RobotDescription
from comp_daemon.sim.campaign import run_campaign
from comp_daemon.sim.scenario import load_scenario


def _rms(err: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def _one_frame(ds: Dataset, robot: RobotDescription) -> float:
    """The kinematic calibration with one registration for every fit row (the old path)."""
    assert ds.a_deg is not None and ds.xyz_mm is not None
    fit, check = ds.fit_rows(), ds.check_rows()
    kf = calibrate_kinematic(robot, ds.a_deg[fit], ds.xyz_mm[fit], frame="tracker")
    return _rms(ds.xyz_mm[check] - kf.model.predict_tcp_mm(ds.a_deg[check]))


def _prepared(ds: Dataset, robot: RobotDescription) -> tuple[float, dict[str, float]]:
    prepared = prepare_campaign(ds, robot)
    fitted = fit_spec(
        parse_model_name("kinematic"), robot, prepared.rows(prepared.fit_rows), FitOptions("tracker")
    )
    err = prepared.rows(prepared.check_rows).errors(fitted.model)
    std = {
        name: fitted.info["identified"][name]["std"]
        for name in ("a5", "d5")
        if name in fitted.info["identified"]
    }
    return _rms(err), std


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenario", default="kr210-geometric")
    parser.add_argument("--n", default="80,200", help="poses per campaign (comma-separated)")
    parser.add_argument("--seeds", default="1,2,3")
    args = parser.parse_args()
    scenario = load_scenario(args.scenario)
    robot = scenario.robot
    sigma = scenario.noise.tracker_sigma_mm
    print(
        f"scenario {scenario.name}: tracker σ {sigma} mm per axis "
        f"(noise floor √3·σ = {np.sqrt(3) * sigma:.4f} mm)"
    )
    print(
        "poses seed | check RMS mm: one frame | per station, pos+orientation | per station, positions only"
        " | std a5/d5 mm: pos+orientation | positions only"
    )
    for n in (int(v) for v in args.n.split(",")):
        for seed in (int(v) for v in args.seeds.split(",")):
            ds = run_campaign(
                scenario, n, seed=seed, in_tracker_frame=True, restation=True, probe_sigma_deg=0.01
            )
            one = _one_frame(ds, robot)
            both, std_both = _prepared(ds, robot)
            pos, std_pos = _prepared(dataclasses.replace(ds, probe_q_wxyz=None), robot)
            print(
                f"{n:5d} {seed:4d} | {one:8.3f} | {both:8.4f} | {pos:8.4f} | "
                f"{std_both.get('a5', float('nan')):.3f}/{std_both.get('d5', float('nan')):.3f} | "
                f"{std_pos.get('a5', float('nan')):.3f}/{std_pos.get('d5', float('nan')):.3f}"
            )


if __name__ == "__main__":
    main()
