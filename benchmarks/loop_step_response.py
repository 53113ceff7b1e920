"""Step responses of seed 000's joint loop on the simulated cell, target by target.

Run: ``python -m benchmarks.loop_step_response [--targets 25] [--lag 1 --lag 2] [--seed 0]``
(about 1 min per servo lag).

The assembled daemon (``Daemon`` with the simulated cell ``kr210-cell`` in its child process, the
plant with its play, ratio errors, gravity deflection and grating noise) calibrates its gratings
(seed 000 step 1, the default six poses), compensates with the nominal model, and runs
``--targets`` random targets, A1–A3 drawn uniformly within ±``--span`` degrees of the home pose,
one at a time. From the loop's cycle trace (``LoopRuntime.trace``: error = target − grating angle
per joint, every telegram) each target's correcting phase gives, per grating joint:

- ``e0``: the error when correcting starts (after the move has arrived);
- rough cycles: cycles whose step was the rough ±``rough_step_deg``;
- in band: cycles from the start until |e| stays ≤ ``settle_tolerance_deg`` (0.001°) to the end;
- settled report: cycles until the daemon reported settled (the band held for ``settle_dwell_ms``);
- overshoot: how far e went past zero against the sign of ``e0`` (deg);
- final: the target's ``final_joint_errors_deg`` (grating − target) as stored.

Printed per servo lag: targets done, the distributions (median, max) over targets of the slowest
joint, the largest overshoot and final error, and how often the hunting guard reduced kD.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.machine import machine_line
from comp_daemon.common.logs import configure_logging
from comp_daemon.daemon.app import Daemon, SimOptions
from comp_daemon.models.artifact import model_document
from comp_daemon.models.nominal import NominalModel
from comp_daemon.rt.safety import SafetyState
from comp_daemon.service.config import load_settings
from comp_daemon.service.store import ModelDraft

_WINDOW = (SafetyState.CORRECTING, SafetyState.SETTLED)


@dataclass(frozen=True)
class StepResponse:
    target_id: int
    state: str
    reason: str | None
    e0_deg: np.ndarray  # (joints,)
    rough_cycles: np.ndarray
    in_band_cycles: np.ndarray
    settled_cycles: int
    overshoot_deg: np.ndarray
    final_deg: np.ndarray


class _GuardCounter(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.count = 0

    def emit(self, record: logging.LogRecord) -> None:
        if "hunting guard" in record.getMessage():
            self.count += 1


def analyse(
    trace: list[tuple[int, int, SafetyState, tuple[float, ...], tuple[float, ...]]],
    joints: tuple[int, ...],
    tol_deg: float,
    rough_step_deg: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, np.ndarray]:
    """The last correcting phase in ``trace``: e0, rough cycles, in-band cycles, settled cycle, overshoot."""
    end = max(i for i, entry in enumerate(trace) if entry[2] in _WINDOW)
    start = end
    while start > 0 and trace[start - 1][2] in _WINDOW:
        start -= 1
    window = trace[start : end + 1]
    e = np.array([entry[3] for entry in window], dtype=float)  # (cycles, joints): target − grating
    ak = np.array([[entry[4][j - 1] for j in joints] for entry in window], dtype=float)
    e0 = e[0]
    outside = np.abs(e) > tol_deg
    in_band = np.array(
        [(np.flatnonzero(outside[:, i]).max() + 1) if outside[:, i].any() else 0 for i in range(len(joints))]
    )
    rough = np.sum(np.isclose(np.abs(ak), rough_step_deg, rtol=0, atol=1e-12), axis=0)
    settled = next((i for i, entry in enumerate(window) if entry[2] is SafetyState.SETTLED), len(window))
    overshoot = np.maximum(0.0, np.max(-np.sign(e0) * e, axis=0))
    return e0, rough, in_band, settled, overshoot


async def run_lag(lag: int, n_targets: int, span_deg: float, seed: int) -> dict[str, Any]:
    root = Path(tempfile.mkdtemp(prefix=f"step-lag{lag}-"))
    cfg = root / "config.toml"
    cfg.write_text(
        f'[http]\nport = 0\n[store]\ndata_dir = "{root / "data"}"\nsynchronous = "normal"\n'
        '[rsi]\nlisten_port = 0\n[log]\nlevel = "WARNING"\n',
        encoding="utf-8",
    )
    settings = load_settings(cfg)
    configure_logging(settings.log.level, "console")
    daemon = Daemon(settings, sim=SimOptions(scenario="kr210-cell", seed=seed, servo_lag_cycles=lag))
    guard = _GuardCounter()
    logging.getLogger("comp_daemon.rt.executor").addHandler(guard)
    run = asyncio.create_task(daemon.run())
    responses: list[StepResponse] = []
    try:
        async with asyncio.timeout(60):
            await daemon.started.wait()
        runtime, store = daemon.realtime.runtime, daemon.store
        assert runtime is not None and store is not None and daemon.sim_info is not None
        while not runtime.rsi_alive():
            await asyncio.sleep(0.05)
        await daemon.gratings.calibrate()
        doc = model_document(NominalModel(daemon.robot), data_sha256="0" * 64, frame="base")
        model = await asyncio.to_thread(store.add_model, ModelDraft("nominal", None, doc, {}, None))
        await asyncio.to_thread(store.activate_model, model.id)
        home = np.array(daemon.sim_info.home_deg)
        rng = np.random.default_rng(seed)
        cs = settings.controller
        for k in range(n_targets):
            a = home.copy()
            a[:3] += rng.uniform(-span_deg, span_deg, 3)
            target = {f"a{i + 1}": round(float(v), 4) for i, v in enumerate(a)}
            _, stored, _ = await asyncio.to_thread(store.submit_batch, f"step-{k}", "bench", [target])
            tid = stored[0].id
            async with asyncio.timeout(60):
                while (rec := await asyncio.to_thread(store.get_target, tid)).state not in (
                    "done",
                    "failed",
                    "cancelled",
                    "interrupted",
                ):
                    await asyncio.sleep(0.05)
            joints = runtime.joints
            e0, rough, in_band, settled, overshoot = analyse(
                list(runtime.trace), joints, cs.settle_tolerance_deg, cs.rough_step_deg
            )
            final = rec.final_joint_errors_deg or {}
            responses.append(
                StepResponse(
                    tid,
                    rec.state,
                    rec.reason,
                    e0,
                    rough,
                    in_band,
                    settled,
                    overshoot,
                    np.array([final.get(f"A{j}", np.nan) for j in joints], dtype=float),
                )
            )
        assert daemon.sim is not None
        controller = json.loads(await daemon.sim.command("status"))["controller"]
    finally:
        daemon.request_stop("figures done")
        await asyncio.wait_for(run, 30)
        logging.getLogger("comp_daemon.rt.executor").removeHandler(guard)
        shutil.rmtree(root, ignore_errors=True)
    done = [r for r in responses if r.state == "done"]
    slowest_band = np.array([r.in_band_cycles.max() for r in done])
    settled_cycles = np.array([r.settled_cycles for r in done])
    return {
        "lag": lag,
        "targets": len(responses),
        "done": len(done),
        "failed": [(r.target_id, r.state, r.reason) for r in responses if r.state != "done"],
        "e0_abs_max_deg": float(max(np.abs(r.e0_deg).max() for r in responses)),
        "rough_cycles_max": int(max(r.rough_cycles.max() for r in responses)),
        "in_band_median": float(np.median(slowest_band)) if done else float("nan"),
        "in_band_max": int(slowest_band.max()) if done else -1,
        "settled_median": float(np.median(settled_cycles)) if done else float("nan"),
        "settled_max": int(settled_cycles.max()) if done else -1,
        "overshoot_max_deg": float(max(r.overshoot_deg.max() for r in responses)),
        "overshoot_median_deg": float(np.median([r.overshoot_deg.max() for r in responses])),
        "final_abs_max_deg": float(max(np.nanmax(np.abs(r.final_deg)) for r in done))
        if done
        else float("nan"),
        "hunting_guard": guard.count,
        "controller_late": controller.get("late_total"),
        "per_target": [
            {
                "id": r.target_id,
                "state": r.state,
                "e0_deg": r.e0_deg.round(5).tolist(),
                "rough": r.rough_cycles.tolist(),
                "in_band": r.in_band_cycles.tolist(),
                "settled": r.settled_cycles,
                "overshoot_deg": r.overshoot_deg.round(5).tolist(),
                "final_deg": r.final_deg.round(6).tolist(),
            }
            for r in responses
        ],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--targets", type=int, default=25)
    parser.add_argument("--lag", type=int, action="append", help="servo lag in cycles (default 1 and 2)")
    parser.add_argument("--span", type=float, default=10.0, help="targets within ±span deg of home (A1–A3)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--verbose", action="store_true", help="also print every target")
    args = parser.parse_args(argv)
    print(f"machine: {machine_line()}")
    print(
        "lag | done | max |e0| | rough cycles max | in 0.001° band: median / max "
        "| settled report: median / max | overshoot: median / max | final |e| max "
        "| hunting guard | controller late"
    )
    for lag in args.lag or [1, 2]:
        r = asyncio.run(run_lag(lag, args.targets, args.span, args.seed))
        print(
            f"{lag} | {r['done']}/{r['targets']} | {r['e0_abs_max_deg']:.4f}° | {r['rough_cycles_max']} "
            f"| {r['in_band_median']:.0f} / {r['in_band_max']} "
            f"| {r['settled_median']:.0f} / {r['settled_max']} "
            f"| {r['overshoot_median_deg']:.5f}° / {r['overshoot_max_deg']:.5f}° "
            f"| {r['final_abs_max_deg']:.5f}° | {r['hunting_guard']} | {r['controller_late']}"
        )
        if r["failed"]:
            print(f"   not done: {r['failed']}")
        if args.verbose:
            for t in r["per_target"]:
                print(f"   {t}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
