"""The daemon process: the order in which it starts and stops, its signals, systemd and the watchdog.

Two processes. The **real-time process** (:mod:`comp_daemon.rt.child`, pinned to a CPU the fit
workers keep off, ``SCHED_FIFO`` where permitted) holds the RSI endpoint, the grating readers and
the loop, so a reply never waits for an HTTP request, a store call, a compensation or this
interpreter's lock. **This process** holds the rest on one event loop; nothing on it blocks —
store calls, compensation and percentile statistics run in worker threads, fits in the service's
process pool. What it is made of:

- the real-time process and the daemon's mirror of its loop (:mod:`comp_daemon.daemon.realtime`);
- the cell's ports: gratings and motion, configured (:mod:`comp_daemon.daemon.ports`) or those of
  the simulated cell (:mod:`comp_daemon.daemon.simcell`);
- the target executor and what it follows of the store (:mod:`comp_daemon.daemon.targets`);
- the grating calibration (:mod:`comp_daemon.daemon.grating_calibrator`) and the RSI sessions
  (:mod:`comp_daemon.daemon.rsi_sessions`);
- telemetry (:mod:`comp_daemon.daemon.telemetry`): loop statistics, metrics, dashboard events;
- the view the HTTP service reads (:mod:`comp_daemon.daemon.view`);
- the HTTP service: uvicorn serving :func:`comp_daemon.service.api.create_app`.

Start-up: the store (locked against a second daemon or a restore, refused with one line when it is
damaged, missing or empty where a store existed, or on a full disk: :func:`open_store`); the
real-time process with the RSI endpoint (the controller must find it
listening before RSI_ON; the job workers are kept off its CPU); the HTTP service (heavy imports and
the job pool, before any cycle runs); the cell (simulated child or the configured ports, then the
grating readers and the loop); the executor and the supervisor; RSI_ON for the simulated cell.
The **backup** task copies the store into its backup folder every ``store.backup_interval_h`` (the
first copy at start when the newest is older), keeping ``store.backup_keep``; a failed backup is
logged and recorded, and never stops the daemon. The **supervisor** pings the systemd watchdog
every ``telemetry_s`` only while every task is alive, the real-time process reports and this loop
keeps its schedule.

Shutdown (SIGTERM/SIGINT): from the next telegram every reply carries ``AK`` = 0 and ``Stop`` = 1;
the active target is marked ``interrupted``; after ``stop_grace_cycles`` more cycles the RSI socket
closes, the loop's final state is written to ``<data_dir>/daemon-state.json`` and the store's event
log, the tasks stop in order (input first), and the process exits 0 (1 if a task failed). The
real-time process goes safe on its own should this process die first.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import signal
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

from comp_daemon import __version__
from comp_daemon.common.atomic import write_json_atomic
from comp_daemon.common.logs import get_logger
from comp_daemon.daemon.grating_calibrator import GratingCalibrator
from comp_daemon.daemon.ports import configured_ports
from comp_daemon.daemon.realtime import Realtime
from comp_daemon.daemon.rsi_sessions import RsiSessions
from comp_daemon.daemon.sdnotify import Notifier, watchdog_interval_s
from comp_daemon.daemon.simcell import SimOptions, start_simulated_cell
from comp_daemon.daemon.targets import Targets
from comp_daemon.daemon.telemetry import Telemetry
from comp_daemon.daemon.view import CellView
from comp_daemon.robot.description import load_robot
from comp_daemon.rt.executor import Compensator
from comp_daemon.rt.grating_cal import load_latest_calibration
from comp_daemon.service.config import Settings
from comp_daemon.service.events import EventBus
from comp_daemon.service.store import Store
from comp_daemon.service.store import files as store_files
from comp_daemon.sim_client import SimCellInfo, SimCellProcess

__all__ = ["Daemon", "SimOptions"]

log = get_logger(__name__)


class Daemon:
    """The assembled process; see the module docstring. ``view`` is what the HTTP service serves.

    Its parts: ``realtime`` (the real-time process and the loop's mirror), ``sim`` / ``sim_info``
    (the simulated cell, with ``--sim``), ``targets`` (the executor), ``gratings`` (the grating
    calibration), ``rsi_sessions``, ``telemetry`` and ``view``."""

    def __init__(
        self,
        settings: Settings,
        *,
        sim: SimOptions | None = None,
        motion_address: tuple[str, int] | None = None,
        compensator: Compensator | None = None,
        notifier: Notifier | None = None,
        clock_ns: Callable[[], int] = time.perf_counter_ns,
        tick_s: float = 0.05,
        telemetry_s: float = 0.25,
        stop_grace_cycles: int = 3,
    ) -> None:
        self.notifier = notifier if notifier is not None else Notifier()
        self.clock_ns = clock_ns
        self.tick_s = tick_s
        self.telemetry_s = telemetry_s
        self.robot = load_robot(settings.robot.name)
        self.data_dir = Path(settings.store.data_dir)
        self.state_path = self.data_dir / "daemon-state.json"
        self.bus = EventBus(settings.http.sse_queue_events)
        #: the settings in force (``jobs.cpus`` filled in once the real-time CPU is known)
        self.settings = settings
        self.sim_options = sim
        self.motion_address = motion_address
        self.realtime = Realtime(
            settings,
            local=sim is not None,
            clock_ns=clock_ns,
            tick_s=tick_s,
            stop_grace_cycles=stop_grace_cycles,
        )
        self.sim: SimCellProcess | None = None
        self.sim_info: SimCellInfo | None = None
        self.targets = Targets(self.robot, settings.compensation, compensator=compensator)
        self.gratings = GratingCalibrator(
            self.realtime,
            self.robot,
            self.data_dir / "gratings",
            target_active=self._target_active,
            on_finished=self.targets.wake,
            record_event=self._record_event,
        )
        self.rsi_sessions = RsiSessions(
            timeout_count=settings.rsi.timeout_count, record_event=self._record_event
        )
        self.telemetry = Telemetry(self.bus, float(settings.rsi.cycle_ms))
        self.view = CellView(self.realtime, self.targets, self.gratings, self.rsi_sessions, self.telemetry)
        self.store: Store | None = None
        self.http_port: int | None = None
        self.started = asyncio.Event()
        self.exit_code: int | None = None
        self._stop = asyncio.Event()
        self._stop_reason = ""
        self._tasks: dict[str, asyncio.Task[Any]] = {}
        self._uvicorn: Any = None
        self._store_lock: store_files.StoreLock | None = None
        self._backup_task: asyncio.Task[None] | None = None
        self._rsi_watch: asyncio.Task[None] | None = None

    # ------------------------------------------------------------------------------ between the parts

    def _target_active(self) -> bool:
        """A target is armed in the loop or in the executor's hands."""
        return self.realtime.target_armed() or self.targets.current() is not None

    async def _record_event(self, kind: str, message: dict[str, Any]) -> None:
        """Into the store's event log (nothing before the store is open)."""
        if self.store is not None:
            await asyncio.to_thread(self.store.add_event, kind, message)

    # ------------------------------------------------------------------------------ lifecycle

    def request_stop(self, reason: str = "requested") -> None:
        if not self._stop.is_set():
            self._stop_reason = reason
            log.info(f"daemon: stop requested ({reason})")
            self._stop.set()

    async def run(self) -> int:
        """Run until SIGTERM/SIGINT (or :meth:`request_stop`); returns the exit code."""
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            with contextlib.suppress(NotImplementedError, RuntimeError):
                loop.add_signal_handler(sig, self.request_stop, signal.Signals(sig).name)
        try:
            await self._start()
            self._freeze_startup_objects(collect=False)  # the service's own start-up objects too
            self.started.set()
            self.notifier.ready(f"comp-daemon {__version__}: loop running")
            log.info(f"daemon: running (RSI on {self.realtime.rsi_address}, HTTP on {self.http_port})")
            await self._wait()
        finally:
            await self._shutdown()
            for sig in (signal.SIGTERM, signal.SIGINT):
                with contextlib.suppress(NotImplementedError, RuntimeError):
                    loop.remove_signal_handler(sig)
        self.exit_code = 0 if self._stop_reason != "task failed" else 1
        return self.exit_code

    @staticmethod
    def _freeze_startup_objects(*, collect: bool) -> None:
        """Keep the collector's full passes short: they stall this event loop (HTTP, executor).

        After start-up the process holds some 126 000 long-lived objects (FastAPI, pydantic, SciPy,
        the robot model); one full pass over them took 108 ms on the two-core test machine
        (docs/benchmarks.md). ``gc.freeze`` moves them out of the collector's sight for good. With
        ``collect`` a full pass first drops start-up garbage (before the real-time process starts);
        afterwards ``freeze`` alone, which costs no pass.
        """
        if collect:
            gc.collect()
        gc.freeze()
        log.info(f"daemon: {gc.get_freeze_count()} start-up objects exempted from garbage collection")

    async def _start(self) -> None:
        from comp_daemon.service.api import open_store

        realtime, targets = self.realtime, self.targets
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self._store_lock = store_files.StoreLock(self.settings.store.db_path).acquire()
        store = self.store = await asyncio.to_thread(open_store, self.settings)
        targets.attach(store)
        active = await asyncio.to_thread(store.active_model, with_artifact=False)
        targets.active_model_id = None if active is None else active.id
        calibration = await asyncio.to_thread(load_latest_calibration, self.gratings.directory)

        # 1. the real-time process with the RSI endpoint, and the job workers kept off its CPU
        self._freeze_startup_objects(collect=True)
        self.settings = await realtime.start(on_lost=lambda reason: self.request_stop("task failed"))
        # 2. the HTTP service (heavy imports and the job pool start here, before any cycle runs)
        await self._start_http()
        # 3. the cell: simulated child or the configured ports, then the readers and the loop
        if self.sim_options is not None:
            address = realtime.rsi_address
            assert address is not None
            self.sim, ports = await start_simulated_cell(self.settings, self.sim_options, address[1])
            self.sim_info = self.sim.info
            self.rsi_sessions.controller_status = self.sim.controller_status
            self.rsi_sessions.rearm_after_s = self.sim_options.rearm_after_s
        else:
            ports = configured_ports(self.settings, self.motion_address)
        targets.motion = ports.motion
        self.gratings.ports = ports
        runtime = await realtime.start_loop(ports, calibration)
        self._rsi_watch = asyncio.create_task(self.rsi_sessions.watch(realtime), name="rsi sessions")
        # 4. the executor and the supervisor
        executor = targets.start(runtime, self.view.readiness_reasons)
        if executor is not None:
            self._tasks["executor"] = executor
        self._tasks["supervisor"] = asyncio.create_task(self._supervise(), name="supervisor")
        if self.settings.store.backup_interval_h > 0:
            self._backup_task = asyncio.create_task(self._backups(), name="store-backup")
        if self.sim is not None:
            await self.sim.rsi_on()  # the robot program's RSI_ON, once the daemon listens and runs
        await asyncio.to_thread(
            store.add_event,
            "daemon.started",
            {
                "version": __version__,
                "sim": asdict(self.sim_options) if self.sim_options else None,
                "rsi": list(realtime.rsi_address or ()),
                "http_port": self.http_port,
                "gratings": sorted(realtime.readers),
                "grating_calibration_version": None if calibration is None else calibration.version,
                "realtime": realtime.word(),
            },
        )

    async def _start_http(self) -> None:
        from comp_daemon.service.api import create_app
        from comp_daemon.service.http_server import build_http_server

        assert self.store is not None
        app = create_app(self.settings, self.store, self.view, bus=self.bus)
        # the guarded server: connection cap, header/body time limits, TCP_NODELAY, rate-limited
        # accept errors (service/http_server.py); binding here raises OSError if the port is taken
        http = build_http_server(app, self.settings.http)
        self.http_port = http.port
        self._uvicorn = http.server
        task = self._tasks["http"] = asyncio.create_task(http.serve(), name="http")
        for _ in range(500):
            if http.started or task.done():
                break
            await asyncio.sleep(0.01)
        if task.done():
            task.result()
        if not http.started:
            raise RuntimeError("the HTTP service did not start")

    async def _wait(self) -> None:
        stop = asyncio.ensure_future(self._stop.wait())
        try:
            while not self._stop.is_set():
                done, _ = await asyncio.wait(
                    [stop, *self._tasks.values()], return_when=asyncio.FIRST_COMPLETED
                )
                for task in done:
                    if task is stop:
                        continue
                    exc = None if task.cancelled() else task.exception()
                    log.error(f"daemon: task {task.get_name()} ended unexpectedly: {exc!r}")
                    self.request_stop("task failed")
        finally:
            stop.cancel()

    async def _shutdown(self) -> None:
        self.notifier.stopping(f"stopping: {self._stop_reason or 'startup failed'}")
        realtime = self.realtime
        # 1. no new targets; zero steps and Stop=1 from the next telegram; the target is reported
        self.targets.stop_claiming()
        if self._rsi_watch is not None:
            self._rsi_watch.cancel()  # the stop that follows is the daemon's own (daemon.stopped)
        self.gratings.cancel()  # its moves end with the robot's Stop below
        realtime.shutdown_loop()
        await self.targets.stop(self._tasks.pop("executor", None))
        # 2. let the controller see Stop=1 for a few cycles, then stop listening
        await realtime.close_rsi()
        # 3. persist the loop's final state
        if realtime.runtime is not None:
            doc = realtime.final_state(self._stop_reason)
            try:
                await asyncio.to_thread(write_json_atomic, self.state_path, doc)
                if self.store is not None:
                    await asyncio.to_thread(self.store.add_event, "daemon.stopped", doc)
            except Exception:
                log.exception("daemon: could not persist the final state")
        # 4. stop the rest: supervisor, the real-time process, HTTP, the simulated cell, the store
        for task in (self._tasks.pop("supervisor", None), self._backup_task):
            if task is not None:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
        await realtime.stop()
        if self._uvicorn is not None:
            self._uvicorn.should_exit = True
            http = self._tasks.pop("http", None)
            if http is not None:
                try:
                    async with asyncio.timeout(10.0):
                        await http
                except (TimeoutError, Exception):
                    log.exception("daemon: the HTTP service did not stop cleanly")
                    http.cancel()
        if self.sim is not None:
            code = await self.sim.stop()
            log.info(f"daemon: simulated cell exited with {code}")
        self.targets.detach()
        if self.store is not None:
            await asyncio.to_thread(self.store.close)
        if self._store_lock is not None:
            self._store_lock.release()
        self.notifier.close()
        log.info("daemon: stopped")

    # ------------------------------------------------------------------------------ backups

    async def _backups(self) -> None:
        """Back the store up every ``backup_interval_h``; the first one now if the newest is older."""
        conf = self.settings.store
        interval_s = conf.backup_interval_h * 3600.0
        backups = await asyncio.to_thread(store_files.list_backups, conf.backup_path, conf.db_path)
        wait_s = 0.0 if not backups else max(0.0, backups[-1].created_at + interval_s - time.time())
        while True:
            await asyncio.sleep(wait_s)
            wait_s = interval_s
            started = time.perf_counter()
            try:
                backup = await asyncio.to_thread(
                    store_files.make_backup, conf.db_path, conf.backup_path, keep=conf.backup_keep
                )
            except Exception as exc:  # a full backup disk must not stop the daemon
                log.error(f"store: backup failed: {exc}")
                with contextlib.suppress(Exception):
                    assert self.store is not None
                    await asyncio.to_thread(self.store.add_event, "store.backup_failed", {"error": str(exc)})
                continue
            took_s = round(time.perf_counter() - started, 3)
            log.info(f"store: backed up to {backup.path} ({backup.size_bytes} bytes, {took_s} s)")
            with contextlib.suppress(Exception):
                assert self.store is not None
                await asyncio.to_thread(
                    self.store.add_event,
                    "store.backup",
                    {"path": str(backup.path), "bytes": backup.size_bytes, "seconds": took_s},
                )

    # ------------------------------------------------------------------------------ supervisor

    async def _supervise(self) -> None:
        interval = watchdog_interval_s()
        last_watchdog = 0.0
        last_telemetry = 0.0
        last_tick_ns = self.clock_ns()
        while True:
            await asyncio.sleep(self.tick_s)
            now_ns = self.clock_ns()
            gap = (now_ns - last_tick_ns) * 1e-9
            last_tick_ns = now_ns
            now = time.monotonic()
            if now - last_telemetry >= self.telemetry_s:
                last_telemetry = now
                await self._telemetry()
            if interval is not None and now - last_watchdog >= interval and self._healthy(gap):
                last_watchdog = now
                self.notifier.watchdog()

    def _healthy(self, tick_gap_s: float) -> bool:
        """Alive tasks, a real-time process that reports, and an event loop that keeps its schedule."""
        if tick_gap_s > 1.0 or not self.realtime.alive():
            return False
        return not any(t.done() for t in self._tasks.values())

    async def _telemetry(self) -> None:
        realtime = self.realtime
        runtime, stats = realtime.runtime, realtime.rsi_stats
        if runtime is None or stats is None:
            return
        await self.telemetry.update(
            runtime, stats, realtime.readers, realtime=realtime.word(), state=self.view.state_word()
        )
        self.notifier.status(self.view.status_line())
