"""The grating calibration routine (seed 000, step 1) run by the daemon on the cell.

For every calibration pose the robot approaches the pose twice, once from below and once from
above on the grating joints (``approach_deg`` beyond it), so that joint backlash enters the fit
with both signs and averages out of the zero. At each standstill the routine averages
``sample_cycles`` telegrams: the controller's axis values (``AIPos``) and the gratings' raw counts
(taken through the RSI handler, so both come from the same cycles). A reading is used only when
the axis values and counts are still (spread within ``still_deg`` / ``still_counts``); otherwise
it waits and samples again. The counts → angle maps are then fitted per joint
(:func:`comp_daemon.rt.grating_cal.fit_joint_map`), stored as the next version, and the loop uses
them from the next telegram on.

Units: deg (controller axis values), counts of the scale resolution.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from comp_daemon.common.logs import get_logger
from comp_daemon.rt.executor import MotionPort
from comp_daemon.rt.grating_cal import (
    GratingCalibration,
    GratingCalibrationError,
    build_calibration,
    default_calibration_poses,
    fit_joint_map,
    save_calibration,
)
from comp_daemon.rt.loop import CycleSample

__all__ = [
    "GratingGeometry",
    "SamplingLoop",
    "approach_points",
    "calibrate_gratings",
    "default_calibration_poses",
]

log = get_logger(__name__)


class SamplingLoop(Protocol):
    """What the calibration needs of the loop (the daemon's ``RemoteRuntime``, or a ``LoopRuntime``)."""

    joints: tuple[int, ...]

    async def samples(self, n: int, timeout_s: float) -> list[CycleSample]: ...

    def set_calibration(self, calibration: GratingCalibration | None) -> None: ...


@dataclass(frozen=True, slots=True)
class GratingGeometry:
    radius_mm: float
    resolution_nm: float = 50.0


async def _still_reading(
    runtime: SamplingLoop,
    n_joints: int,
    *,
    settle_cycles: int,
    sample_cycles: int,
    still_deg: float,
    still_counts: int,
    attempts: int,
    cycle_timeout_s: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Mean axis values (6,) and mean counts (n_joints,) over a still stretch of telegrams."""

    async def take(n: int) -> list[CycleSample]:
        try:
            return await runtime.samples(n, timeout_s=1.0 + n * cycle_timeout_s)
        except TimeoutError:
            raise GratingCalibrationError(f"no RSI telegrams: {n} cycles did not arrive in time") from None

    await take(settle_cycles)
    why = "no telegrams"
    for _ in range(attempts):
        samples = await take(sample_cycles)
        if any(s.actual_deg is None for s in samples):
            why = "telegrams without AIPos"
            continue
        if any(c is None for s in samples for c in s.counts):
            why = "a grating had no valid reading"
            await take(settle_cycles)
            continue
        axes = np.array([s.actual_deg for s in samples], dtype=float)
        counts = np.array([s.counts for s in samples], dtype=float).reshape(len(samples), n_joints)
        if np.ptp(axes, axis=0).max() > still_deg or np.ptp(counts, axis=0).max() > still_counts:
            why = "the robot was not still"
            await take(settle_cycles)
            continue
        return axes.mean(axis=0), counts.mean(axis=0)
    raise GratingCalibrationError(f"no still reading after {attempts} attempts: {why}")


def approach_points(
    target_deg: NDArray[np.float64], joints: Sequence[int], approach_deg: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The two points a calibration pose is approached from: ``approach_deg`` below it and above
    it on every grating joint (1-based ``joints``), the other axes at the pose's values, so that
    backlash enters the readings with both signs (module docstring)."""
    below, above = np.array(target_deg, dtype=float), np.array(target_deg, dtype=float)
    for j in joints:
        below[j - 1] -= approach_deg
        above[j - 1] += approach_deg
    return below, above


async def calibrate_gratings(
    runtime: SamplingLoop,
    motion: MotionPort,
    poses: Sequence[Sequence[float]],
    geometry: Mapping[int, GratingGeometry],
    directory: Path,
    *,
    approach_deg: float = 0.5,
    settle_cycles: int = 25,
    sample_cycles: int = 10,
    still_deg: float = 2e-4,
    still_counts: int = 30,
    attempts: int = 5,
    min_readings: int = 6,
    min_span_deg: float = 10.0,
    cycle_timeout_s: float = 0.05,
    progress: Callable[[int, int], None] | None = None,
) -> GratingCalibration:
    """Run the routine (module docstring); returns the stored calibration, already in use.

    ``progress(done, total)`` is called with the poses measured so far: (0, n) before the first
    move, then after each pose."""
    joints = runtime.joints
    missing = [j for j in joints if j not in geometry]
    if missing:
        raise GratingCalibrationError(f"no grating geometry (radius) for joints {missing}")
    axis_rows: list[NDArray[np.float64]] = []
    count_rows: list[NDArray[np.float64]] = []
    if progress is not None:
        progress(0, len(poses))
    for p, pose in enumerate(poses):
        target = np.asarray(pose, dtype=float)
        for before in approach_points(target, joints, approach_deg):
            await motion.move_to(tuple(before))
            await motion.move_to(tuple(target))
            axes, counts = await _still_reading(
                runtime,
                len(joints),
                settle_cycles=settle_cycles,
                sample_cycles=sample_cycles,
                still_deg=still_deg,
                still_counts=still_counts,
                attempts=attempts,
                cycle_timeout_s=cycle_timeout_s,
            )
            axis_rows.append(axes)
            count_rows.append(counts)
        log.info(f"grating calibration: pose {p + 1}/{len(poses)} measured")
        if progress is not None:
            progress(p + 1, len(poses))
    axes_all = np.array(axis_rows)
    counts_all = np.array(count_rows)
    maps = [
        fit_joint_map(
            j,
            counts_all[:, i],
            axes_all[:, j - 1],
            radius_mm=geometry[j].radius_mm,
            resolution_nm=geometry[j].resolution_nm,
            min_readings=min_readings,
            min_span_deg=min_span_deg,
        )
        for i, j in enumerate(joints)
    ]
    created = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())

    def store() -> GratingCalibration:
        cal = build_calibration(directory, maps, created)
        save_calibration(directory, cal)
        return cal

    calibration = await asyncio.to_thread(store)
    runtime.set_calibration(calibration)
    for m in calibration.joints:
        log.info(
            f"grating A{m.joint}: scale {m.scale:.6f}, zero {m.zero_deg:.6f} deg, residual rms "
            f"{m.residual_rms_deg:.6f} / max {m.residual_max_deg:.6f} deg over {m.n_readings} readings"
        )
    return calibration
