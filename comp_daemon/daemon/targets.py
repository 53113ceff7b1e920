"""The daemon's target executor and what it follows of the store.

:class:`Targets` builds the :class:`~comp_daemon.rt.executor.TargetExecutor` over the store's queue,
the active model's compensator (:class:`~comp_daemon.daemon.compensation.ActiveModelCompensator`,
unless one is given), the cell's motion port and the loop, and follows the store's commits (any
thread): the active model's id (no target is claimed without one) and new work (a batch accepted,
a model activated, a target queued), which wakes the executor.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable

from comp_daemon.common.logs import get_logger
from comp_daemon.daemon.compensation import ActiveModelCompensator
from comp_daemon.daemon.rt_process import RemoteRuntime
from comp_daemon.robot.description import RobotDescription
from comp_daemon.rt.executor import Compensator, MotionPort, TargetExecutor, TargetOutcome
from comp_daemon.service.config import CompensationSettings
from comp_daemon.service.store import EventRecord, Store

__all__ = ["Targets"]

log = get_logger(__name__)

_WAKING_EVENTS = ("batch.accepted", "model.activated", "target.queued")


class Targets:
    """See the module docstring. ``compensator``: in place of the active model's (tests)."""

    def __init__(
        self,
        robot: RobotDescription,
        settings: CompensationSettings,
        *,
        compensator: Compensator | None = None,
    ) -> None:
        self.robot = robot
        self.settings = settings
        self.compensator = compensator
        self.store: Store | None = None
        self.motion: MotionPort | None = None
        self.executor: TargetExecutor | None = None
        self.active_model_id: int | None = None

    # ------------------------------------------------------------------------------ the store

    def attach(self, store: Store) -> None:
        """Follow the store from now on: the active model, and new work for the executor."""
        self.store = store
        store.add_listener(self._on_store_event)

    def detach(self) -> None:
        if self.store is not None:
            self.store.remove_listener(self._on_store_event)

    def _on_store_event(self, event: EventRecord) -> None:
        """Store commits (any thread): follow the active model; wake the executor on new work."""
        if event.kind == "model.activated":
            self.active_model_id = int(event.message["model_id"])
        if event.kind in _WAKING_EVENTS:
            self.wake()

    # ------------------------------------------------------------------------------ the executor

    def start(self, runtime: RemoteRuntime, readiness: Callable[[], list[str]]) -> asyncio.Task[None] | None:
        """The executor's task (None without a motion port: nothing could move)."""
        store = self.store
        assert store is not None, "the store comes first"
        if self.motion is None:
            return None
        joints = [j - 1 for j in runtime.joints]
        compensator = self.compensator or ActiveModelCompensator(
            store,
            self.robot,
            joints,
            current_axes=lambda: runtime.last_actual_deg,
            limits=self.settings.limits(),
            mapping=self.settings.mapping,
        )

        def target_readiness() -> str | None:
            reasons = readiness()
            if self.active_model_id is None:
                reasons.append("no model is active")
            return "; ".join(reasons) if reasons else None

        self.executor = TargetExecutor(
            store,
            compensator,
            self.motion,
            runtime,
            joints=joints,
            readiness=target_readiness,
            on_outcome=_log_outcome,
        )
        return asyncio.create_task(self.executor.run(), name="executor")

    def wake(self) -> None:
        """Have the executor look at its queue now. Safe from any thread."""
        if self.executor is not None:
            self.executor.wake()

    def current(self) -> int | None:
        """The id of the target in hand, if any."""
        return None if self.executor is None else self.executor.current_target_id

    def stop_claiming(self) -> None:
        if self.executor is not None:
            self.executor.stop_claiming()

    async def stop(self, task: asyncio.Task[None] | None, timeout_s: float = 10.0) -> None:
        """Let the executor record the interrupted target, then end it."""
        if task is None:
            return
        try:
            async with asyncio.timeout(timeout_s):
                await task
        except TimeoutError:
            log.error(f"daemon: the executor did not finish within {timeout_s:g} s; cancelling it")
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        except Exception:
            log.exception("daemon: the executor failed")


def _log_outcome(outcome: TargetOutcome) -> None:
    log.info(f"daemon: target {outcome.target_id} {outcome.state} {outcome.reason or ''}".rstrip())
