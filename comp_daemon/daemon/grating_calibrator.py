"""The grating calibration as an operator's action: run it between targets, report how it went.

:class:`GratingCalibrator` runs :func:`comp_daemon.daemon.gratings.calibrate_gratings` (seed 000,
step 1) on the cell's loop and motion port, from the HTTP route in the background
(:meth:`~GratingCalibrator.start`, progress and the last error in :meth:`~GratingCalibrator.status`)
or awaited (:meth:`~GratingCalibrator.calibrate`). It refuses while a target is active; the executor
claims nothing while it runs and is woken when it ends.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

from comp_daemon.common.logs import get_logger
from comp_daemon.daemon.gratings import calibrate_gratings, default_calibration_poses
from comp_daemon.daemon.ports import CellPorts
from comp_daemon.daemon.realtime import Realtime
from comp_daemon.robot.description import RobotDescription
from comp_daemon.rt.grating_cal import GratingCalibration

__all__ = ["GratingCalibrator"]

log = get_logger(__name__)

RecordEvent = Callable[[str, dict[str, Any]], Awaitable[None]]


class GratingCalibrator:
    """See the module docstring. ``target_active()``: whether the executor holds a target;
    ``on_finished()``: called when a calibration ends (the executor looks at its queue again);
    ``record_event(kind, message)``: the store's event log."""

    def __init__(
        self,
        realtime: Realtime,
        robot: RobotDescription,
        directory: Path,
        *,
        target_active: Callable[[], bool],
        on_finished: Callable[[], None],
        record_event: RecordEvent,
    ) -> None:
        self.realtime = realtime
        self.robot = robot
        self.directory = directory
        self.target_active = target_active
        self.on_finished = on_finished
        self.record_event = record_event
        self.ports = CellPorts()
        self.calibrating = False
        self._task: asyncio.Task[None] | None = None
        self._error: str | None = None
        self._started_at: float | None = None
        self._finished_at: float | None = None
        self._poses: tuple[int, int] | None = None  # (measured, total) of the last attempt

    def running(self) -> bool:
        return self.calibrating or (self._task is not None and not self._task.done())

    def start(self, poses_deg: Sequence[Sequence[float]] | None, by: str) -> None:
        """Start :meth:`calibrate` in the background (the HTTP route); RuntimeError if it cannot."""
        if self.realtime.runtime is None or self.ports.motion is None:
            raise RuntimeError("the daemon has no loop or no motion port")
        if self.running():
            raise RuntimeError("a grating calibration is already running")
        if self.target_active():
            raise RuntimeError("a target is active; calibrate between targets")
        poses = None if poses_deg is None else [tuple(float(v) for v in p) for p in poses_deg]
        self._error = None
        self._started_at, self._finished_at = time.time(), None
        self._poses = None

        def measured(done: int, total: int) -> None:
            self._poses = (done, total)

        async def run() -> None:
            try:
                cal = await self.calibrate(poses, progress=measured)
                log.info(f"daemon: grating calibration v{cal.version} started by {by} is in use")
            except Exception as exc:
                self._error = str(exc) or type(exc).__name__
                log.error(f"daemon: grating calibration started by {by} failed: {self._error}")
                await self.record_event("gratings.failed", {"error": self._error, "by": by})
            finally:
                self._finished_at = time.time()

        self._task = asyncio.get_running_loop().create_task(run(), name="grating-calibration")

    def status(self) -> dict[str, Any]:
        runtime = self.realtime.runtime
        cal = None if runtime is None else runtime.calibration
        return {
            "calibrating": self.running(),
            "calibration": None if cal is None else cal.to_dict(),
            "last_error": self._error,
            "started_at": self._started_at,
            "finished_at": self._finished_at,
            "poses_measured": None if self._poses is None else self._poses[0],
            "poses_total": None if self._poses is None else self._poses[1],
        }

    async def calibrate(
        self, poses: Sequence[Sequence[float]] | None = None, **options: Any
    ) -> GratingCalibration:
        """Run seed 000's grating calibration on the cell (no target may be active); the default
        poses spread around the robot's home (or where it stands)."""
        runtime, motion = self.realtime.runtime, self.ports.motion
        if runtime is None or motion is None:
            raise RuntimeError("the daemon has no loop or no motion port")
        if self.calibrating:
            raise RuntimeError("a grating calibration is already running")
        if self.realtime.target_armed():
            raise RuntimeError("a target is active; calibrate between targets")
        if poses is None:
            home = self.ports.home_deg if self.ports.home_deg is not None else runtime.last_actual_deg
            if home is None:
                raise RuntimeError("no calibration poses given and no robot position known")
            poses = default_calibration_poses(home, runtime.joints, self.robot.axis_limits_deg)
        self.calibrating = True
        try:
            cal = await calibrate_gratings(
                runtime, motion, poses, self.ports.geometry, self.directory, **options
            )
        finally:
            self.calibrating = False
            self.on_finished()
        await self.record_event(
            "gratings.calibrated", {"version": cal.version, "joints": [asdict(m) for m in cal.joints]}
        )
        return cal

    def cancel(self) -> None:
        """End a background calibration (its moves end with the robot's Stop at shutdown)."""
        if self._task is not None and not self._task.done():
            self._task.cancel()
