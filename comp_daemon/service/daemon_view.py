"""What the HTTP side may see of the real-time daemon: the :class:`DaemonView` protocol.

The daemon implements it (cheap, non-blocking methods that copy the loop's latest numbers; called
from the event loop that runs both). Without a daemon, :class:`DetachedDaemonView` answers "not
running", so ``/ready`` says why the service is not ready rather than pretending.

Units: angles in degrees (``_deg``), times in milliseconds (``_ms``) or UNIX seconds (``time``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Literal, Protocol, runtime_checkable

__all__ = [
    "DaemonControl",
    "DaemonSnapshot",
    "DaemonView",
    "DetachedDaemonView",
    "EncoderHealth",
    "JointStatus",
    "LoopStats",
]

EncoderHealth = Literal["ok", "stale", "fault", "absent"]


@dataclass(frozen=True, slots=True)
class LoopStats:
    """Statistics of the RSI loop since it started (latencies over a recent window)."""

    running: bool
    cycle_ms: float | None = None
    cycles: int = 0
    late_replies: int = 0  # telegrams not answered within the cycle since the daemon started (late
    # replies plus telegrams superseded by a newer one); the same figure as the metric
    # comp_daemon_rsi_late_replies_total (see comp_daemon.daemon.telemetry)
    rejected: int = 0
    latency_p50_ms: float | None = None
    latency_p99_ms: float | None = None
    latency_max_ms: float | None = None
    jitter_p99_ms: float | None = None
    last_ipoc: int | None = None
    realtime: str | None = None  # where the RSI path runs: thread, CPU, scheduling, what was refused


@dataclass(frozen=True, slots=True)
class JointStatus:
    """One joint as the loop sees it now; grating fields are None for joints without a grating."""

    joint: int
    axis_deg: float | None = None
    target_deg: float | None = None
    grating_deg: float | None = None
    error_deg: float | None = None
    correction_deg: float = 0.0
    encoder: EncoderHealth = "absent"
    encoder_detail: str | None = None
    reading_age_ms: float | None = None


@dataclass(frozen=True, slots=True)
class DaemonSnapshot:
    """The daemon's state: ``state`` is a short word (``not running``, ``idle``, ``compensating``,
    ``moving``, ``settling``, ``holding``, ``stopped``…); ``hold_reason`` says why corrections are
    held at zero, when they are."""

    state: str
    time: float
    hold_reason: str | None = None
    current_target_id: int | None = None
    phase: str | None = None
    joints: tuple[JointStatus, ...] = field(default_factory=tuple)
    loop: LoopStats = field(default_factory=lambda: LoopStats(running=False))

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@runtime_checkable
class DaemonView(Protocol):
    """Implemented by the daemon; every method returns at once (no I/O, no waiting)."""

    def snapshot(self) -> DaemonSnapshot:
        """The current state, joints and loop statistics."""
        ...

    def readiness_reasons(self) -> list[str]:
        """Why the daemon is not ready (loop not running, an encoder stale…); empty when ready.

        The service adds "no model is active" itself, from the store.
        """
        ...

    def loop_stats(self) -> LoopStats:
        """The latest loop statistics."""
        ...


@runtime_checkable
class DaemonControl(Protocol):
    """Operator actions on the daemon (``/api/gratings``, ``/api/loop/reset-fault``); the daemon
    implements them, a view without a loop does not (the routes then answer 409 ``not_ready``)."""

    def start_grating_calibration(self, poses_deg: Sequence[Sequence[float]] | None, by: str) -> None:
        """Start seed 000's grating calibration in the background (``None``: the daemon's default
        poses). Raises ``RuntimeError`` saying why it cannot start now (one is running, a target is
        active, no loop or no motion port)."""

    def grating_status(self) -> dict[str, Any]:
        """``calibrating`` (bool), ``calibration`` (the calibration in use, its artifact dict, or
        None), ``last_error`` (why the last attempt failed, or None), ``started_at`` /
        ``finished_at`` (UNIX seconds of the last attempt, or None), ``poses_measured`` and
        ``poses_total`` (the last attempt's progress, or None before its first pose is known)."""
        ...

    def acknowledge_fault(self, by: str) -> dict[str, Any] | None:
        """Clear a latched fault (operator acknowledgement); returns the fault that was cleared
        (``kind``, ``reaction``, ``detail``, ``target_id``) or None when none was latched."""
        ...


class DetachedDaemonView:
    """The view when no daemon is attached (the HTTP service alone): nothing runs."""

    REASON = "the real-time loop is not running (no daemon attached to this service)"

    def __init__(self, clock: Any = None) -> None:
        import time

        self._clock = clock if clock is not None else time.time

    def snapshot(self) -> DaemonSnapshot:
        return DaemonSnapshot(state="not running", time=self._clock(), hold_reason=self.REASON)

    def readiness_reasons(self) -> list[str]:
        return [self.REASON]

    def loop_stats(self) -> LoopStats:
        return LoopStats(running=False)
