"""Long work (fits, diagnoses) in a process pool, never in the event loop that runs the RSI loop.

A job kind is a picklable, module-level function plus a parent-side hook:

- ``func(*args, progress=reporter) -> dict`` runs in a worker process (niced, SIGINT ignored, its
  numeric libraries limited to ``jobs.threads`` threads before the job loads them).
  ``reporter(fraction, message=None)`` records progress (0..1) and raises :class:`JobCancelled`
  when the job was cancelled or ran out of time, so long functions should call it now and then.
- ``on_done(job, result) -> ModelDraft | None`` runs in the parent when the function returns; a
  model it returns is stored in the same transaction that marks the job done.

Lifecycle (in the store): ``queued`` (waiting for a worker) → ``running`` → ``done`` | ``failed``,
or ``cancelled`` at any time before that. A cancelled or timed-out job's result is discarded even if
the function finishes. Such a job is first asked to stop (its next progress report raises
:class:`JobCancelled`); if it still runs ``jobs.cancel_grace_s`` later, its worker process is killed,
so a function that never reports cannot hold a worker. The pool is then renewed and the other jobs
it held (running or waiting) are started again in the new one. Workers end themselves when the
daemon is gone (:func:`comp_daemon.service.orphans.exit_with_parent`), also after a ``kill -9``.

Failures are recorded as one line: the message of a ``ValueError`` (a problem with the input, e.g. a
``DatasetError`` with row and column) or "internal error (id …)" with the traceback in the log
under that id.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import multiprocessing
import os
import queue
import signal
import threading
import time
import traceback
import uuid
from collections.abc import Callable, Mapping
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any

from comp_daemon.common.logs import bound, get_logger
from comp_daemon.common.threads import set_numeric_threads
from comp_daemon.estimation import steps
from comp_daemon.service.config import JobSettings
from comp_daemon.service.metrics import JOBS_FINISHED
from comp_daemon.service.orphans import exit_with_parent
from comp_daemon.service.store import ConflictError, JobRecord, ModelDraft, Store, StoreError, StoreFullError

__all__ = ["JobCancelled", "JobKind", "JobRunner", "ProgressReporter", "json_safe"]

_log = get_logger("comp_daemon.jobs")
_CANCEL_SLOTS = 256
_PROGRESS_MIN_INTERVAL_S = 0.2
_KILL_RETRY_S = 0.25
_FULL_RETRY_S = 5.0  # marking a job failed on a full disk: the next try


class JobCancelled(Exception):
    """Raised inside a job function by its progress reporter once the job was cancelled."""


ResultHook = Callable[[JobRecord, Mapping[str, Any]], ModelDraft | None]


@dataclass(frozen=True, slots=True)
class JobKind:
    """A kind of job: ``name`` as stored, the worker function, the parent-side result hook, and what
    of the result the job row keeps (all of it by default)."""

    name: str
    func: Callable[..., Mapping[str, Any]]
    on_done: ResultHook | None = None
    job_result: Callable[[Mapping[str, Any]], Mapping[str, Any]] | None = None  # what the job row keeps


def json_safe(value: Any) -> Any:
    """``value`` with non-finite floats replaced by None and tuples/NumPy scalars made plain JSON."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Mapping):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    if isinstance(value, bool | int | str) or value is None:
        return value
    tolist = getattr(value, "tolist", None)
    if callable(tolist):  # NumPy arrays and scalars
        return json_safe(tolist())
    return str(value)


# ------------------------------------------------------------------------------ worker process side

_worker_queue: Any = None
_worker_cancel: Any = None


def _worker_init(
    progress_queue: Any,
    cancel_flags: Any,
    nice: int,
    cpus: tuple[int, ...] = (),
    parent_pid: int = 0,
    threads: int = 1,
) -> None:
    global _worker_queue, _worker_cancel
    # before a job loads NumPy: a worker pinned to fewer cores than the machine has would otherwise
    # start a BLAS thread per core, spinning against each other on its own core
    set_numeric_threads(threads)
    if parent_pid:
        exit_with_parent(parent_pid)
    _worker_queue = progress_queue
    _worker_cancel = cancel_flags
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if nice:
        with contextlib.suppress(OSError):
            os.nice(nice)
    if cpus and hasattr(os, "sched_setaffinity"):
        # off the real-time CPU (comp-daemon run refuses CPUs this machine lacks before it starts)
        with contextlib.suppress(OSError, ValueError):
            os.sched_setaffinity(0, set(cpus))


class ProgressReporter:
    """Given to a job function as ``progress``; call ``progress(fraction, message)``.

    The steps the fit reports while it runs (:mod:`comp_daemon.estimation.steps`: its cross-validation
    fits, its candidates) come through :meth:`step` and extend the job's last message with how
    many are done and how many remain ("fitting kriging:aniso: joint-weight candidates 12 of 49,
    37 to go"); they are also where a cancelled job stops.
    """

    def __init__(self, job_id: int) -> None:
        self.job_id = job_id
        self._last_sent = 0.0
        self._last_fraction = -1.0
        self._fraction = 0.0
        self._message: str | None = None

    def cancelled(self) -> bool:
        flags = _worker_cancel
        return flags is not None and self.job_id in flags[:]

    def __call__(self, fraction: float, message: str | None = None) -> None:
        fraction = float(fraction)
        if math.isfinite(fraction):
            self._fraction, self._message = fraction, message
        self._send(fraction, message)

    def step(self, what: str, done: int, total: int) -> None:
        """A step of the running fit (a :data:`comp_daemon.estimation.steps.StepListener`)."""
        left = max(total - done, 0)
        detail = f"{what} {done} of {total}, {left} to go"
        self._send(self._fraction, detail if not self._message else f"{self._message}: {detail}")

    def _send(self, fraction: float, message: str | None) -> None:
        if self.cancelled():
            raise JobCancelled(f"job {self.job_id} was cancelled")
        now = time.monotonic()
        if not math.isfinite(fraction):
            return
        if now - self._last_sent < _PROGRESS_MIN_INTERVAL_S and abs(fraction - self._last_fraction) < 0.05:
            return
        self._last_sent, self._last_fraction = now, fraction
        if _worker_queue is not None:
            with contextlib.suppress(Exception):
                _worker_queue.put_nowait(("progress", self.job_id, fraction, message))


def _worker_entry(
    job_id: int, func: Callable[..., Mapping[str, Any]], args: tuple[Any, ...]
) -> tuple[Any, ...]:
    """Runs in the worker: ('ok', result) | ('cancelled',) | ('error', user_message | None, traceback)."""
    if _worker_queue is not None:
        with contextlib.suppress(Exception):
            _worker_queue.put_nowait(("started", job_id, os.getpid()))
    reporter = ProgressReporter(job_id)
    try:
        if reporter.cancelled():
            return ("cancelled",)
        with steps.listening(reporter.step):
            result = func(*args, progress=reporter)
        return ("ok", json_safe(dict(result)))
    except JobCancelled:
        return ("cancelled",)
    except ValueError as exc:  # bad input: the message is meant for the user
        return ("error", str(exc) or type(exc).__name__, traceback.format_exc())
    except Exception:
        return ("error", None, traceback.format_exc())


# ------------------------------------------------------------------------------------- parent side


class JobRunner:
    """Owns the process pool; submits jobs, follows their progress, stores their results."""

    def __init__(self, store: Store, settings: JobSettings) -> None:
        self.store = store
        self.settings = settings
        self._kinds: dict[str, JobKind] = {}
        self._executor: ProcessPoolExecutor | None = None
        self._futures: dict[int, Future[tuple[Any, ...]]] = {}
        self._launched: dict[int, tuple[ProcessPoolExecutor, tuple[Any, ...]]] = {}  # pool, args
        self._pids: dict[int, int] = {}  # job id → the worker process running it
        self._killed: set[int] = set()  # jobs whose worker we killed
        self._broken_by_us: set[ProcessPoolExecutor] = set()  # pools broken by such a kill
        self._timers: dict[int, asyncio.TimerHandle] = {}
        self._tasks: set[asyncio.Future[None]] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._ctx = multiprocessing.get_context(settings.start_method)
        self._progress_queue: Any = None
        self._cancel_flags: Any = None
        self._cancel_next = 0
        self._reader: threading.Thread | None = None
        self._stopping = threading.Event()
        self._closing = False

    # ---- kinds

    def register(self, kind: JobKind) -> None:
        self._kinds[kind.name] = kind

    def kinds(self) -> list[str]:
        return sorted(self._kinds)

    def has_kind(self, name: str) -> bool:
        return name in self._kinds

    # ---- life cycle

    def start(self, loop: asyncio.AbstractEventLoop | None = None) -> None:
        """Create the pool lazily-started workers and the progress reader (call in the event loop)."""
        if self._executor is not None:
            return
        self._loop = loop if loop is not None else asyncio.get_running_loop()
        self._progress_queue = self._ctx.Queue()
        self._cancel_flags = self._ctx.Array("q", _CANCEL_SLOTS, lock=False)
        self._executor = self._new_executor()
        self._closing = False
        self._stopping.clear()
        self._reader = threading.Thread(target=self._read_progress, name="job-progress", daemon=True)
        self._reader.start()

    @property
    def workers(self) -> int:
        """The pool's size: ``jobs.workers``, or with 0 one per CPU the workers may use (``jobs.cpus``;
        without a list every CPU of this process but one, the real-time loop's)."""
        if self.settings.workers:
            return self.settings.workers
        if self.settings.cpus:
            return len(self.settings.cpus)
        cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
        return max(1, cpus - 1)

    def _new_executor(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(
            max_workers=self.workers,
            mp_context=self._ctx,
            initializer=_worker_init,
            initargs=(
                self._progress_queue,
                self._cancel_flags,
                self.settings.nice,
                tuple(self.settings.cpus),
                os.getpid(),
                self.settings.threads,
            ),
        )

    def _replace_broken_executor(self) -> None:
        """A worker died (killed, out of memory): the pool is unusable; start a fresh one."""
        old = self._executor
        if old is None or not getattr(old, "_broken", False):
            return
        _log.warning("job worker process died; starting a new pool")
        self._executor = self._new_executor()
        old.shutdown(wait=False)

    def shutdown(self) -> None:
        """Stop taking jobs, cancel what waits, end the workers (running jobs fail at the next start)."""
        self._closing = True
        executor, self._executor = self._executor, None
        for timer in self._timers.values():
            timer.cancel()
        self._timers.clear()
        if executor is not None:
            processes = list(getattr(executor, "_processes", {}).values())
            executor.shutdown(wait=False)  # not cancel_futures: see _stop_worker
            for proc in processes:
                with contextlib.suppress(Exception):
                    proc.terminate()
            for proc in processes:
                with contextlib.suppress(Exception):
                    proc.join(timeout=5)
        self._stopping.set()
        if self._progress_queue is not None:
            with contextlib.suppress(Exception):
                self._progress_queue.put_nowait(("stop",))
        if self._reader is not None:
            self._reader.join(timeout=5)
            self._reader = None
        if self._progress_queue is not None:
            with contextlib.suppress(Exception):
                self._progress_queue.close()
                self._progress_queue.join_thread()
            self._progress_queue = None
        self._futures.clear()

    @property
    def running(self) -> bool:
        return self._executor is not None

    # ---- submitting

    def launch(self, job: JobRecord, args: tuple[Any, ...]) -> None:
        """Hand a stored, queued job to the pool: ``kinds[job.kind].func(*args, progress=…)``.

        Thread-safe; call it from a worker thread (``asyncio.to_thread``): the first job of a pool
        starts a worker process, which takes milliseconds the event loop should not wait.
        """
        if self._executor is None or self._loop is None:
            raise RuntimeError("the job runner is not started")
        kind = self._kinds[job.kind]
        try:
            future = self._executor.submit(_worker_entry, job.id, kind.func, args)
        except BrokenProcessPool:
            self._replace_broken_executor()
            future = self._executor.submit(_worker_entry, job.id, kind.func, args)
        self._launched[job.id] = (self._executor, args)
        self._futures[job.id] = future
        loop = self._loop
        job_id = job.id

        def done(f: Future[tuple[Any, ...]]) -> None:
            with contextlib.suppress(RuntimeError):  # the loop closed before the job ended
                loop.call_soon_threadsafe(self._on_done, job_id, f)

        future.add_done_callback(done)

    def cancel(self, job_id: int, *, by: str | None = None) -> JobRecord:
        """Cancel a queued or running job (``ConflictError`` if it already finished)."""
        job = self.store.cancel_job(job_id, by=by)
        self._stop_worker(job_id)
        return job

    def _stop_worker(self, job_id: int) -> None:
        """Ask a cancelled or timed-out job to stop; kill its worker if it has not after the grace."""
        # No Future.cancel(): a pool that breaks later (a worker killed) fails on a cancelled future
        # in its manager thread (CPython 3.11), and then completes nothing more. A worker that takes
        # a flagged job returns at once.
        future = self._futures.get(job_id)
        if future is None or future.done() or self._cancel_flags is None:
            return
        self._cancel_flags[self._cancel_next % _CANCEL_SLOTS] = job_id
        self._cancel_next += 1
        loop = self._loop
        if loop is not None:
            with contextlib.suppress(RuntimeError):  # the loop closed: shutdown ends the workers
                loop.call_soon_threadsafe(
                    loop.call_later, self.settings.cancel_grace_s, self._kill_worker, job_id
                )

    def _kill_worker(self, job_id: int) -> None:
        """(In the loop) kill the worker still running a job that was asked to stop."""
        future = self._futures.get(job_id)
        launched = self._launched.get(job_id)
        if future is None or future.done() or launched is None:
            return  # it stopped
        pid = self._pids.get(job_id)
        if pid is None:  # not started yet (a worker finds the flag before it starts the job) or
            if self._loop is not None:  # its start not read yet: look again
                self._loop.call_later(_KILL_RETRY_S, self._kill_worker, job_id)
            return
        self._killed.add(job_id)
        self._broken_by_us.add(launched[0])
        _log.warning("job ignored its cancellation; killing its worker", job_id=job_id, pid=pid)
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)

    def _arm_timer(self, job_id: int) -> None:
        """Start the job's ``max_runtime_s`` clock (when a worker picked it up)."""
        # armed even if the job just ended: its time-out then finds it finished and does nothing
        if self._loop is not None and job_id not in self._timers:
            self._timers[job_id] = self._loop.call_later(
                self.settings.max_runtime_s, self._on_timeout, job_id
            )

    def _on_timeout(self, job_id: int) -> None:
        self._timers.pop(job_id, None)
        self._in_thread(self._time_out, job_id)

    def _in_thread(self, fn: Callable[..., None], *args: Any) -> None:
        """Run a store-writing step off the event loop (a commit may wait for the disk)."""
        task = asyncio.ensure_future(asyncio.to_thread(fn, *args))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _time_out(self, job_id: int) -> None:
        try:
            self.store.fail_job(
                job_id, f"took longer than jobs.max_runtime_s = {self.settings.max_runtime_s:g} s"
            )
        except StoreError:
            return
        JOBS_FINISHED.labels(kind=self._kind_of(job_id), state="failed").inc()
        self._stop_worker(job_id)

    def _kind_of(self, job_id: int) -> str:
        try:
            return self.store.get_job(job_id).kind
        except StoreError:
            return "unknown"

    # ---- completion (in the event loop)

    def _on_done(self, job_id: int, future: Future[tuple[Any, ...]]) -> None:
        if self._futures.get(job_id) is future:
            self._futures.pop(job_id)
        self._pids.pop(job_id, None)
        launched = self._launched.pop(job_id, None)
        killed = job_id in self._killed
        self._killed.discard(job_id)
        timer = self._timers.pop(job_id, None)
        if timer is not None:
            timer.cancel()
        if not future.cancelled() and isinstance(future.exception(), BrokenProcessPool):
            self._replace_broken_executor()
            if not killed and launched is not None and launched[0] in self._broken_by_us:
                # lost with the worker we killed for another job: start it again
                self._in_thread(self._relaunch, job_id, launched[1])
                return
        self._in_thread(self._complete, job_id, future)

    def _relaunch(self, job_id: int, args: tuple[Any, ...]) -> None:
        with bound(job_id=job_id):
            try:
                job = self.store.get_job(job_id)
            except StoreError:
                return
            if job.state not in ("queued", "running") or self._closing:
                return
            _log.info("job started again: its pool was renewed")
            self.launch(job, args)

    async def drain(self) -> None:
        """Wait until every finished job's result is stored (for an orderly shutdown and for tests)."""
        while self._tasks:
            await asyncio.gather(*list(self._tasks), return_exceptions=True)

    def _complete(self, job_id: int, future: Future[tuple[Any, ...]]) -> None:
        with bound(job_id=job_id):
            try:
                job = self.store.get_job(job_id)
            except StoreError:
                return
            if job.state not in ("queued", "running"):
                _log.info("job result discarded", state=job.state)
                return
            if future.cancelled():
                outcome: tuple[Any, ...] = ("cancelled",)
            else:
                exc = future.exception()
                if isinstance(exc, BrokenProcessPool):
                    if self._closing:  # we ended the workers: the next start's recovery marks the job
                        return
                    outcome = ("died",)
                elif exc is not None:
                    outcome = ("error", None, "".join(traceback.format_exception(exc)))
                else:
                    outcome = future.result()
            try:
                if job.state == "queued":
                    with contextlib.suppress(ConflictError):  # the worker's 'started' may have won
                        self.store.start_job(job_id)
                    job = self.store.get_job(job_id)
                self._store_outcome(job, outcome)
            except ConflictError as exc:  # cancelled or timed out meanwhile
                _log.info("job result discarded", reason=str(exc))
            except StoreFullError as exc:
                self._fail_on_full_disk(job, exc)

    def _fail_on_full_disk(self, job: JobRecord, exc: StoreFullError) -> None:
        """The job's outcome could not be stored for a full disk: the job fails with that sentence.
        Should even that small write fail, it is tried again every ``_FULL_RETRY_S`` until it is
        stored (a job must not stay ``running``); a restart's recovery marks it too."""
        message = f"the job's result could not be stored: {exc}; run the job again once there is room"
        try:
            self.store.fail_job(job.id, message)
        except ConflictError:
            return
        except StoreFullError:
            _log.error("job could not be marked failed: the disk is full; trying again", kind=job.kind)
            if self._loop is not None and not self._closing:
                with contextlib.suppress(RuntimeError):  # the loop has closed
                    self._loop.call_soon_threadsafe(
                        self._loop.call_later,
                        _FULL_RETRY_S,
                        self._in_thread,
                        self._fail_on_full_disk,
                        job,
                        exc,
                    )
            return
        JOBS_FINISHED.labels(kind=job.kind, state="failed").inc()
        _log.warning(
            "job failed: its result could not be stored, the disk is full", kind=job.kind, error=str(exc)
        )

    def _store_outcome(self, job: JobRecord, outcome: tuple[Any, ...]) -> None:
        status = outcome[0]
        if status == "ok":
            result: Mapping[str, Any] = outcome[1]
            kind = self._kinds.get(job.kind)
            try:
                draft = kind.on_done(job, result) if kind is not None and kind.on_done is not None else None
            except StoreFullError:
                raise  # the job fails naming the disk (_complete), not as an internal error
            except Exception:
                error_id = uuid.uuid4().hex[:12]
                _log.exception("job result could not be stored", error_id=error_id)
                self.store.fail_job(job.id, f"internal error (id {error_id})")
                JOBS_FINISHED.labels(kind=job.kind, state="failed").inc()
                return
            kept = kind.job_result(result) if kind is not None and kind.job_result is not None else result
            self.store.finish_job(job.id, kept, model=draft)
            JOBS_FINISHED.labels(kind=job.kind, state="done").inc()
            _log.info("job done", kind=job.kind)
        elif status == "died":
            _log.warning("job worker process died", kind=job.kind)
            self.store.fail_job(job.id, "the worker process ended unexpectedly (killed or out of memory)")
            JOBS_FINISHED.labels(kind=job.kind, state="failed").inc()
        elif status == "cancelled":
            if job.state in ("queued", "running"):
                self.store.cancel_job(job.id, by="worker")
            JOBS_FINISHED.labels(kind=job.kind, state="cancelled").inc()
        else:
            user_message, trace = outcome[1], outcome[2]
            if user_message is None:
                error_id = uuid.uuid4().hex[:12]
                _log.error("job failed", kind=job.kind, error_id=error_id, traceback=trace)
                message = f"internal error (id {error_id})"
            else:
                _log.info("job refused its input", kind=job.kind, error=user_message)
                message = user_message
            self.store.fail_job(job.id, message)
            JOBS_FINISHED.labels(kind=job.kind, state="failed").inc()

    # ---- progress (reader thread)

    def _read_progress(self) -> None:
        q = self._progress_queue
        while not self._stopping.is_set():
            try:
                item = q.get(timeout=0.5)
            except queue.Empty:
                continue
            except (EOFError, OSError):
                return
            try:
                if item[0] == "stop":
                    return
                if item[0] == "started":
                    self._pids[item[1]] = item[2]
                    job = self.store.get_job(item[1])
                    if job.state == "queued":
                        self.store.start_job(item[1])
                    if self._loop is not None:
                        with contextlib.suppress(RuntimeError):
                            self._loop.call_soon_threadsafe(self._arm_timer, item[1])
                elif item[0] == "progress":
                    self.store.set_job_progress(item[1], item[2], item[3])
            except StoreError:
                continue
            except Exception:
                _log.exception("job progress message could not be stored")
