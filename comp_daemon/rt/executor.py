"""Target execution: one queued target at a time, in queue order, through the closed loop.

Lifecycle of a target (the store's states)::

    queued → compensating → moving → settling → done
                  └───────────┴─────────┴──→ failed (reason)      shutdown ──→ interrupted

1. *compensating*: the target is claimed from the queue (oldest first), its stored request read
   back as a :class:`~comp_daemon.data.target.Target` (a request that is not one fails the target),
   and compensated by the active model (``Compensator``, run in a worker thread: it may iterate a
   model and IK). A compensator refuses a target by raising ``ValueError`` (:class:`CompensationError` and the
   compensation library's refusals — unreachable, near the wrist singularity, too large an axis
   change, outside the model's region — are such errors); the target then fails with the refusal's
   message as its reason and is never driven. Any other exception is a fault of the compensator:
   the target fails too, and the traceback is logged.
2. *moving*: the loop is armed with the commanded axis values and the loop target (the
   compensated joint angles of the joints with gratings), then the robot is commanded
   (:class:`MotionPort`). Arrival is read off the RSI telegrams by the loop, not assumed.
3. *settling*: the loop drives the grating angles to the loop target (seed 000's rough + PD).
4. *done* once every controlled joint stayed within the tolerance for the dwell time, with the
   final joint errors (grating − target, deg, per joint ``A1``…); *failed* with the fault's reason
   otherwise. A target active at shutdown is marked *interrupted* for the operator.

A store that cannot be written (a full disk) never ends the executor. If a target's move cannot be
recorded, the target is failed at once (the loop released with its correction frozen; the robot
is not commanded if the move to *moving* could not be stored) and its final state is kept here
and written when the store takes writes again; no target is claimed meanwhile, and the reason is
shown as the executor's ``blocked_reason``.

Targets are only claimed while the daemon is ready for them (``readiness()`` returns None): RSI
telegrams arriving, a grating calibration, an active model, no latched stop. Otherwise they stay
queued and the reason is shown. The executor never blocks the event loop: store calls and the
compensation run in worker threads, waiting is on loop events.

Units: axis values and joint angles in deg (controller convention), times in s.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import math
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from comp_daemon.common.logs import get_logger
from comp_daemon.data.target import Target, TargetError
from comp_daemon.rt.safety import Arrived, Event, Faulted, FaultKind, Settled

__all__ = [
    "CompensatedTarget",
    "CompensationError",
    "Compensator",
    "LoopPort",
    "ModelMissingError",
    "MotionError",
    "MotionPort",
    "QueueWriteError",
    "TargetExecutor",
    "TargetOutcome",
    "TargetQueue",
]

log = get_logger("comp_daemon.rt.executor")


class CompensationError(ValueError):
    """The target cannot be compensated (unreachable, bad request, no model); the message says why."""


class ModelMissingError(CompensationError):
    """No active model, or the active model's artifact cannot be used."""


class MotionError(RuntimeError):
    """The robot refused or could not take the motion command."""


class QueueWriteError(RuntimeError):
    """The target queue (the store) could not record a move of a target; ``__cause__`` says why."""


@dataclass(frozen=True, slots=True)
class CompensatedTarget:
    """What a target becomes after compensation.

    ``commanded_deg``: the six axis values sent to the robot. ``loop_target_deg``: for each joint
    with a grating (in the loop's joint order), the joint angle the closed loop drives it to.
    """

    commanded_deg: tuple[float, ...]
    loop_target_deg: tuple[float, ...]
    model_id: int | None = None
    info: Mapping[str, Any] | None = None


#: Compensates one target (read from the store's ``request`` record); runs in a worker thread.
Compensator = Callable[[Target], CompensatedTarget]


class MotionPort(Protocol):
    """Commands robot motion.

    On the simulated cell the simulated controller's motion interface; on a real cell the robot
    program receives the axis values (see docs/daemon.md). ``move_to`` returns once the command is
    accepted, not on arrival: arrival is observed on the RSI telegrams.
    """

    async def move_to(self, axes_deg: Sequence[float]) -> None: ...


class LoopPort(Protocol):
    """The executor's handle on the real-time loop (implemented by the daemon's loop runtime)."""

    def arm(
        self, target_id: str, commanded_deg: Sequence[float], loop_target_deg: Sequence[float]
    ) -> None: ...

    def release(self) -> None: ...

    async def next_event(self) -> Event: ...


class TargetQueue(Protocol):
    """The part of :class:`comp_daemon.service.store.Store` the executor uses (synchronous)."""

    def claim_next_target(self) -> Any: ...

    def advance_target(
        self,
        target_id: int,
        state: str,
        *,
        reason: str | None = None,
        commanded_axes_deg: Sequence[float] | None = None,
        final_joint_errors_deg: Mapping[str, float | None] | None = None,
        compensation: Mapping[str, Any] | None = None,
    ) -> Any: ...


@dataclass(frozen=True, slots=True)
class TargetOutcome:
    target_id: int
    state: str  # done | failed | interrupted
    reason: str | None
    final_joint_errors_deg: Mapping[str, float | None] | None


class TargetExecutor:
    """Runs queued targets through compensation, motion and the closed loop; see the module docstring."""

    def __init__(
        self,
        queue: TargetQueue,
        compensate: Compensator,
        motion: MotionPort,
        loop: LoopPort,
        *,
        joints: Sequence[int],
        readiness: Callable[[], str | None],
        recheck_s: float = 1.0,
        motion_fault_grace_s: float = 0.5,
        on_outcome: Callable[[TargetOutcome], None] | None = None,
    ) -> None:
        self.queue = queue
        self.compensate = compensate
        self.motion = motion
        self.loop = loop
        self.joints = tuple(joints)  # 0-based indices of the joints with gratings
        self.readiness = readiness
        self.recheck_s = recheck_s
        self.motion_fault_grace_s = motion_fault_grace_s
        self.on_outcome = on_outcome
        self.current_target_id: int | None = None
        self.phase: str | None = None
        self.blocked_reason: str | None = None
        #: the latest outcomes (the store keeps them all; this is bounded for a daemon running for months)
        self.outcomes: deque[TargetOutcome] = deque(maxlen=256)
        #: final states the store could not take yet: (target id, state, reason, errors), oldest first
        self.unsaved: list[tuple[int, str, str | None, Mapping[str, float | None] | None]] = []
        self._queue_fault: str | None = None
        self._wakeup = asyncio.Event()
        self._stopping = False
        self._event_loop: asyncio.AbstractEventLoop | None = None

    # ------------------------------------------------------------------------------ control

    def wake(self) -> None:
        """Look at the queue now (new targets, a model activated). Safe from any thread."""
        loop = self._event_loop
        if loop is None:
            return
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if running is loop:
            self._wakeup.set()
        else:
            with contextlib.suppress(RuntimeError):  # the loop is closed: nothing to wake
                loop.call_soon_threadsafe(self._wakeup.set)

    def stop_claiming(self) -> None:
        """Finish (or let the loop fault) the current target, then claim nothing more."""
        self._stopping = True
        self.wake()

    async def run(self) -> None:
        """Claim and execute targets until :meth:`stop_claiming`; returns after the current target."""
        self._event_loop = asyncio.get_running_loop()
        while not self._stopping:
            reason = self.readiness()
            self.blocked_reason = reason or self._queue_fault  # a queue fault stands until a claim works
            if reason is None:
                with contextlib.suppress(QueueWriteError):  # kept; the claim shows if the store writes
                    await self._save_unsaved()
                try:
                    target = await self._write(self.queue.claim_next_target)
                except QueueWriteError as exc:
                    self.blocked_reason = f"the target queue cannot be written: {exc.__cause__}"
                    if self._queue_fault != self.blocked_reason:  # once, not every recheck
                        log.error(f"executor: no target claimed: {self.blocked_reason}")
                    self._queue_fault = self.blocked_reason
                    target = None
                else:
                    if self._queue_fault is not None:
                        log.info("executor: the target queue takes writes again")
                        self._queue_fault = None
                    if self.unsaved:  # the disk may have come back between the two writes: once more
                        with contextlib.suppress(QueueWriteError):
                            await self._save_unsaved()
                    self._drop_unsaved()
                if target is not None:
                    outcome = await self.execute(target)
                    self.outcomes.append(outcome)
                    if self.on_outcome is not None:
                        self.on_outcome(outcome)
                    continue
            self._wakeup.clear()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(self.recheck_s):
                    await self._wakeup.wait()

    # ------------------------------------------------------------------------------ one target

    async def execute(self, target: Any) -> TargetOutcome:
        """Run one claimed (compensating) target to its final state."""
        tid = int(target.id)
        self.current_target_id = tid
        self.phase = "compensating"
        try:
            return await self._execute(tid, target.request)
        except QueueWriteError as exc:
            reason = f"the store could not record the target: {exc.__cause__}; check the part"
            log.error(f"target {tid} failed: {reason}", target_id=tid)
            await self._save(tid, "failed", reason, None)
            return TargetOutcome(tid, "failed", reason, None)
        finally:
            self.current_target_id = None
            self.phase = None

    # ------------------------------------------------------------------------------ store writes

    async def _write(self, func: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """``func(*args, **kwargs)`` of the queue in a worker thread; failures as :class:`QueueWriteError`."""
        try:
            return await asyncio.to_thread(functools.partial(func, *args, **kwargs))
        except Exception as exc:
            raise QueueWriteError(str(exc)) from exc

    async def _save(
        self, tid: int, state: str, reason: str | None, errors: Mapping[str, float | None] | None
    ) -> None:
        """Record a final state; kept in :attr:`unsaved` if the store cannot take it now."""
        try:
            await self._write(
                self.queue.advance_target, tid, state, reason=reason, final_joint_errors_deg=errors
            )
        except QueueWriteError as exc:
            log.error(f"target {tid}: final state {state} kept until the store takes writes: {exc}")
            self.unsaved.append((tid, state, reason, errors))

    async def _save_unsaved(self) -> None:
        """Write the kept final states, oldest first; QueueWriteError at the first that still fails."""
        while self.unsaved:
            tid, state, reason, errors = self.unsaved[0]
            await self._write(
                self.queue.advance_target, tid, state, reason=reason, final_joint_errors_deg=errors
            )
            self.unsaved.pop(0)
            log.info(f"target {tid}: final state {state} recorded")

    def _drop_unsaved(self) -> None:
        """The store took a claim but refused a kept state: the target moved on meanwhile (e.g. it
        was marked interrupted); the store's state stands."""
        for tid, state, _reason, _errors in self.unsaved:
            log.error(f"target {tid}: the kept final state {state} could not be recorded; the store's stands")
        self.unsaved.clear()

    async def _finish(
        self,
        tid: int,
        state: str,
        reason: str | None,
        errors: Mapping[str, float | None] | None = None,
    ) -> TargetOutcome:
        await self._save(tid, state, reason, errors)
        words = f"target {tid} {state}" + (f": {reason}" if reason else "")
        log.info(words, target_id=tid, state=state, reason=reason)
        return TargetOutcome(tid, state, reason, errors)

    async def _execute(self, tid: int, request: Mapping[str, Any]) -> TargetOutcome:
        try:
            wanted = Target.from_record(request)
        except TargetError as exc:  # a queue row not written by the service's validation
            return await self._finish(tid, "failed", f"the queued request is not a target: {exc}")
        try:
            comp = await asyncio.to_thread(self.compensate, wanted)
        except ModelMissingError as exc:
            return await self._finish(tid, "failed", f"{FaultKind.MODEL_MISSING}: {exc}")
        except ValueError as exc:  # a refusal: CompensationError, or the library's own refusals
            return await self._finish(tid, "failed", f"compensation: {exc}")
        except Exception as exc:  # a bug in a model must fail the target, not the daemon
            log.exception("compensation failed", target_id=tid)
            return await self._finish(tid, "failed", f"compensation failed: {type(exc).__name__}: {exc}")
        if len(comp.commanded_deg) != 6 or len(comp.loop_target_deg) != len(self.joints):
            return await self._finish(tid, "failed", "compensation returned the wrong number of axis values")
        if self._stopping:
            return await self._finish(tid, "interrupted", "the daemon shut down before the target started")

        self.phase = "moving"
        await self._write(
            self.queue.advance_target,
            tid,
            "moving",
            commanded_axes_deg=list(comp.commanded_deg),
            compensation={"model_id": comp.model_id, **(comp.info or {})},
        )
        key = str(tid)
        try:
            self.loop.arm(key, comp.commanded_deg, comp.loop_target_deg)
        except Exception as exc:  # e.g. a stop latched since the readiness check
            return await self._finish(tid, "failed", f"the loop refused the target: {exc}")
        move: asyncio.Future[None] | None = asyncio.ensure_future(self.motion.move_to(comp.commanded_deg))
        get: asyncio.Future[Event] | None = None
        try:
            while True:
                if get is None:
                    get = asyncio.ensure_future(self.loop.next_event())
                waiting: set[asyncio.Future[Any]] = {get} if move is None else {get, move}
                done, _ = await asyncio.wait(waiting, return_when=asyncio.FIRST_COMPLETED)
                if get in done:
                    event, get = get.result(), None
                    outcome = await self._on_event(tid, key, event)
                    if outcome is not None:
                        return outcome
                    continue
                assert move is not None and move in done
                finished, move = move, None
                error = finished.exception()
                if error is None:
                    continue  # the robot took (or finished) the motion; arrival comes from the loop
                # a stopped robot is usually the loop's own doing: prefer the loop's reason
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(self.motion_fault_grace_s):
                        while True:
                            if get is None:
                                get = asyncio.ensure_future(self.loop.next_event())
                            event, get = await get, None
                            if event.target_id == key and isinstance(event, Faulted):
                                outcome = await self._on_event(tid, key, event)
                                assert outcome is not None
                                return outcome
                if not isinstance(error, MotionError):
                    log.error("motion command failed", target_id=tid, error=repr(error))
                return await self._finish(tid, "failed", f"motion: {error}")
        finally:
            self.loop.release()
            if get is not None:
                get.cancel()
            if move is not None:
                with contextlib.suppress(TimeoutError, Exception):
                    async with asyncio.timeout(self.motion_fault_grace_s):
                        await asyncio.shield(move)
                move.cancel()

    async def _on_event(self, tid: int, key: str, event: Event) -> TargetOutcome | None:
        if event.target_id != key:
            return None  # an event of an earlier target
        if isinstance(event, Arrived):
            self.phase = "settling"
            await self._write(self.queue.advance_target, tid, "settling")
            return None
        errors = self._errors(event.errors_deg)
        if isinstance(event, Settled):
            reduced = [
                f"A{j + 1}×{k:g}" for j, k in zip(self.joints, event.kd_scale, strict=False) if k < 1.0
            ]
            if reduced:
                log.warning("hunting guard reduced kD", target_id=tid, joints=", ".join(reduced))
            return await self._finish(tid, "done", None, errors)
        f = event.fault
        reason = f"{f.kind}: {f.detail}"
        if f.kind is FaultKind.SHUTDOWN:
            return await self._finish(
                tid, "interrupted", f"{reason}; corrections frozen, check the part", errors
            )
        return await self._finish(tid, "failed", f"{reason} ({f.reaction})", errors)

    def _errors(self, target_minus_grating_deg: Sequence[float]) -> dict[str, float | None]:
        """Reported as grating − target per joint ``A<n>`` (None where no reading was available)."""
        return {
            f"A{j + 1}": (None if math.isnan(e) else -e)
            for j, e in zip(self.joints, target_minus_grating_deg, strict=True)
        }
