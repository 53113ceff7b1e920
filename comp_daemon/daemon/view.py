"""What the HTTP service sees of the running daemon: :class:`CellView`.

It implements :class:`~comp_daemon.service.daemon_view.DaemonView` (the state in a word, the
snapshot with the joints and the loop statistics, why a target cannot start now) from the
real-time process's mirrored loop, the executor and the telemetry's latest statistics, and
:class:`~comp_daemon.service.daemon_view.DaemonControl` by handing the operator's actions (grating
calibration, fault acknowledgement) to the daemon's parts; :meth:`CellView.rsi_report` adds the RSI stops
and restarts (``/api/status`` → ``rsi``). Every method returns at once: it reads attributes
that the event loop replaces whole, no I/O, no waiting.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

from comp_daemon.daemon.grating_calibrator import GratingCalibrator
from comp_daemon.daemon.realtime import Realtime
from comp_daemon.daemon.rsi_sessions import RsiSessions
from comp_daemon.daemon.targets import Targets
from comp_daemon.daemon.telemetry import Telemetry
from comp_daemon.rt.safety import SafetyState
from comp_daemon.service.daemon_view import DaemonSnapshot, JointStatus, LoopStats

__all__ = ["CellView"]

_STALE = frozenset({"stale", "silent", "no_data"})


class CellView:
    """The daemon as the HTTP service sees it; see the module docstring."""

    def __init__(
        self,
        realtime: Realtime,
        targets: Targets,
        gratings: GratingCalibrator,
        rsi_sessions: RsiSessions,
        telemetry: Telemetry,
    ) -> None:
        self.realtime = realtime
        self.targets = targets
        self.gratings = gratings
        self.rsi_sessions = rsi_sessions
        self.telemetry = telemetry

    def state_word(self) -> str:
        runtime, executor = self.realtime.runtime, self.targets.executor
        if runtime is None:
            return "starting"
        core = runtime.core
        if core.state is SafetyState.STOPPING:
            return "stopped"
        if self.gratings.calibrating:
            return "calibrating gratings"
        if core.state is SafetyState.FAULT:
            return "fault"
        if executor is not None and executor.phase is not None:
            return "holding" if core.state is SafetyState.SETTLED else executor.phase
        if core.state is SafetyState.SETTLED:
            return "holding"
        sessions = self.rsi_sessions
        stopped = bool(sessions.stops) and not sessions.running  # a recorded stop not yet re-armed
        return "idle" if runtime.rsi_alive() and not stopped else "waiting for RSI"

    def status_line(self) -> str:
        """The state word and the target in hand (systemd's STATUS=)."""
        status = self.state_word()
        current = self.targets.current()
        if current is not None:
            status += f" (target {current})"
        return status

    # ------------------------------------------------------------------------------ DaemonView

    def snapshot(self) -> DaemonSnapshot:
        runtime, executor = self.realtime.runtime, self.targets.executor
        if runtime is None:
            return DaemonSnapshot(state="starting", time=time.time(), hold_reason="the daemon is starting")
        core = runtime.core
        hold = None
        if core.fault is not None:
            hold = f"{core.fault.kind} ({core.fault.reaction}): {core.fault.detail}"
        elif executor is not None and executor.blocked_reason is not None:
            hold = executor.blocked_reason
        joints = []
        by_joint = {row["joint"]: row for row in runtime.joint_rows()}
        for j in range(1, 7):
            row = by_joint.get(j)
            axis = None if runtime.last_actual_deg is None else runtime.last_actual_deg[j - 1]
            if row is None:
                joints.append(JointStatus(joint=j, axis_deg=axis, correction_deg=0.0))
                continue
            encoder = row["encoder"]
            health = "ok" if encoder == "ok" else ("stale" if encoder in _STALE else "fault")
            joints.append(
                JointStatus(
                    joint=j,
                    axis_deg=axis,
                    target_deg=row["target_deg"],
                    grating_deg=row["grating_deg"],
                    error_deg=row["error_deg"],
                    correction_deg=row["correction_deg"],
                    encoder=health,  # type: ignore[arg-type]
                    encoder_detail=row["encoder_detail"],
                    reading_age_ms=row["reading_age_ms"],
                )
            )
        return DaemonSnapshot(
            state=self.state_word(),
            time=time.time(),
            hold_reason=hold,
            current_target_id=None if executor is None else executor.current_target_id,
            phase=None if executor is None else executor.phase,
            joints=tuple(joints),
            loop=self.telemetry.loop_stats,
        )

    def readiness_reasons(self) -> list[str]:
        runtime = self.realtime.runtime
        if runtime is None:
            return ["the daemon is starting"]
        reasons = runtime.readiness_reasons()
        if self.targets.motion is None:
            reasons.append("no motion port configured (run --motion HOST:PORT, or --sim)")
        if self.gratings.calibrating:
            reasons.append("grating calibration in progress")
        return reasons

    def loop_stats(self) -> LoopStats:
        return self.telemetry.loop_stats

    def rsi_report(self) -> dict[str, Any]:
        """The RSI sessions: each stop with its cause, cycles, late replies and what happens next."""
        return self.rsi_sessions.report()

    # ------------------------------------------------------------------------------ DaemonControl

    def start_grating_calibration(self, poses_deg: Sequence[Sequence[float]] | None, by: str) -> None:
        self.gratings.start(poses_deg, by)

    def grating_status(self) -> dict[str, Any]:
        return self.gratings.status()

    def acknowledge_fault(self, by: str) -> dict[str, Any] | None:
        cleared = self.realtime.acknowledge_fault(by)
        if cleared is not None:
            self.targets.wake()  # the queue may go on
        return cleared
