"""The daemon process: RSI loop, grating readers, target executor and the HTTP service.

Two event loops. The **real-time loop** runs on its own thread (:mod:`comp_daemon.rt.rt_thread`,
pinned to a CPU the fit workers keep off, ``SCHED_FIFO`` where permitted) and holds only the RSI
endpoint and the grating readers, so a reply never waits for an HTTP request, a store call or a
compensation. The **service loop** (the main thread) holds the rest; nothing on it blocks — store
calls, compensation and percentile statistics run in worker threads, fits in the service's process
pool. The two share :class:`~comp_daemon.daemon.runtime.LoopRuntime`, whose commands are
thread-safe. With ``[realtime] thread = false`` everything runs on the service loop (for comparison).

- **RSI**: the UDP endpoint (:mod:`comp_daemon.rt.rsi_server`) answers each telegram in its receive
  callback with :meth:`comp_daemon.daemon.runtime.LoopRuntime.handle` — one O(joints) step of the
  safety machine and seed 000's controller on the latest grating readings.
- **Encoders**: one :class:`comp_daemon.rt.encoder_reader.EncoderReader` task per grating, polling
  raw frames every cycle and reconnecting with back-off.
- **Executor**: :class:`comp_daemon.rt.executor.TargetExecutor` takes queued targets one at a time,
  compensates, commands the motion, arms the loop and records the outcome.
- **Supervisor**: every ``tick_s`` the loop's timers (telegrams stopped, move timeout); every
  ``telemetry_s`` metrics, dashboard events and the systemd watchdog ping — sent only while every
  other task is alive and the loop itself keeps its schedule.
- **HTTP**: uvicorn serving :func:`comp_daemon.service.api.create_app` with this daemon as its
  :class:`~comp_daemon.service.daemon_view.DaemonView`.

With ``sim`` the simulated cell runs in a child process (:mod:`comp_daemon.daemon.simcell`) and the
daemon talks to it over UDP, pseudo-terminals and TCP, exactly as to the line.

Shutdown (SIGTERM/SIGINT): the cycle in progress is complete by construction (the handler is
synchronous); from the next telegram every reply carries ``AK`` = 0 and ``Stop`` = 1; the active
target is marked ``interrupted``; after ``stop_grace_cycles`` more cycles the RSI socket closes, the
loop's final state is written to ``<data_dir>/daemon-state.json`` and the store's event log, the
tasks stop in order (input first), and the process exits 0.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import json
import logging
import os
import signal
import socket
import tempfile
import time
from collections.abc import Callable, Coroutine, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from comp_daemon import __version__
from comp_daemon.daemon.compensation import ActiveModelCompensator
from comp_daemon.daemon.gratings import GratingGeometry, calibrate_gratings, default_calibration_poses
from comp_daemon.daemon.motion import LineMotionPort
from comp_daemon.daemon.rt_process import LoopStart, RealtimeProcess, RemoteRuntime, RtProcessError, RtStart
from comp_daemon.daemon.runtime import LoopRuntime, LoopView
from comp_daemon.daemon.sdnotify import Notifier, watchdog_interval_s
from comp_daemon.daemon.simcell import SimCellInfo, SimCellProcess
from comp_daemon.robot.description import load_robot
from comp_daemon.rt.controller import JointLoopSettings
from comp_daemon.rt.encoder_reader import (
    EncoderReader,
    EncoderReaderConfig,
    LinearGratingCalibration,
)
from comp_daemon.rt.executor import Compensator, MotionPort, TargetExecutor, TargetOutcome
from comp_daemon.rt.grating_cal import GratingCalibration, load_latest_calibration
from comp_daemon.rt.rsi_codec import RobTelegram, SenReply
from comp_daemon.rt.rsi_server import RsiServerConfig, RsiServerProtocol, RsiServerStats, start_rsi_server
from comp_daemon.rt.rt_thread import RealtimeThread, RealtimeThreadConfig, other_cpus, resolve_cpu
from comp_daemon.rt.safety import SafetySettings, SafetyState
from comp_daemon.service import metrics
from comp_daemon.service.config import ControllerSettings, Settings
from comp_daemon.service.daemon_view import DaemonSnapshot, JointStatus, LoopStats
from comp_daemon.service.events import EventBus
from comp_daemon.service.store import EventRecord, Store

__all__ = ["Daemon", "SimOptions", "loop_settings_from", "safety_settings_from"]

log = logging.getLogger(__name__)

T = TypeVar("T")

_ZERO = (0.0,) * 6
_ENCODER_METRIC_KIND = {
    "crc": "crc",
    "error_bit": "error_bit",
    "silent": "timeout",
    "gone": "gone",
    "garbled": "garbled",
}


@dataclass(frozen=True, slots=True)
class SimOptions:
    """The simulated cell brought up beside the daemon (``run --sim``)."""

    scenario: str = "kr210-cell"
    seed: int = 0
    servo_lag_cycles: int = 1


def loop_settings_from(cs: ControllerSettings, cycle_ms: float) -> JointLoopSettings:
    return JointLoopSettings(
        cycle_s=cycle_ms / 1000.0,
        kp=cs.kp,
        kd=cs.kd,
        rough_step_deg=cs.rough_step_deg,
        rough_threshold_deg=cs.rough_threshold_deg,
        rough_reenter_deg=2.0 * cs.rough_threshold_deg,
        max_step_deg=cs.max_step_deg,
        max_total_deg=cs.max_total_deg,
    )


def safety_settings_from(cs: ControllerSettings) -> SafetySettings:
    return SafetySettings(
        settle_tolerance_deg=cs.settle_tolerance_deg,
        settle_dwell_s=max(cs.settle_dwell_ms / 1000.0, 1e-3),
        move_timeout_s=cs.move_timeout_s,
        settle_timeout_s=cs.settle_timeout_s,
    )


def _write_json_atomic(path: Path, doc: Mapping[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            json.dump(doc, fh, indent=2, default=str)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


class Daemon:
    """The assembled process; implements the service's ``DaemonView``. See the module docstring."""

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
        self.settings = settings
        self.sim_options = sim
        self.motion_address = motion_address
        self.compensator = compensator
        self.notifier = notifier if notifier is not None else Notifier()
        self.clock_ns = clock_ns
        self.tick_s = tick_s
        self.telemetry_s = telemetry_s
        self.stop_grace_cycles = stop_grace_cycles
        self.robot = load_robot(settings.robot.name)
        self.data_dir = Path(settings.store.data_dir)
        self.gratings_dir = self.data_dir / "gratings"
        self.state_path = self.data_dir / "daemon-state.json"
        self.bus = EventBus(settings.http.sse_queue_events)
        self.store: Store | None = None
        self.runtime: LoopRuntime | RemoteRuntime | None = None
        self.executor: TargetExecutor | None = None
        self.motion: MotionPort | None = None
        self.readers: dict[int, Any] = {}  # EncoderReader here, ReaderMirror with a real-time process
        self.geometry: dict[int, GratingGeometry] = {}
        self.sim: SimCellProcess | None = None
        self.sim_info: SimCellInfo | None = None
        self.rsi: RsiServerProtocol | None = None
        self.rt: RealtimeThread | None = None
        self.rtp: RealtimeProcess | None = None
        self.rsi_transport: asyncio.DatagramTransport | None = None
        self.http_port: int | None = None
        self.calibrating = False
        self._cal_task: asyncio.Task[None] | None = None
        self._cal_error: str | None = None
        self._cal_started_at: float | None = None
        self._cal_finished_at: float | None = None
        self.active_model_id: int | None = None
        self.started = asyncio.Event()
        self.exit_code: int | None = None
        self._stop = asyncio.Event()
        self._stop_reason = ""
        self._tasks: dict[str, asyncio.Task[Any]] = {}
        self._uvicorn: Any = None
        self._loop_stats = LoopStats(running=False)
        self._metric_marks: dict[str, int] = {}
        self._last_tick_ns = 0
        self._max_tick_gap_s = 0.0
        self._home: tuple[float, ...] | None = None

    # ------------------------------------------------------------------------------ lifecycle

    def request_stop(self, reason: str = "requested") -> None:
        if not self._stop.is_set():
            self._stop_reason = reason
            log.info("daemon: stop requested (%s)", reason)
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
            log.info("daemon: running (RSI on %s, HTTP on %s)", self.rsi_address, self.http_port)
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
        """Keep the collector's full passes short: they hold the GIL, and the real-time thread waits.

        After start-up the process holds some 126 000 long-lived objects (FastAPI, pydantic, SciPy, the
        robot model); one full pass over them held the GIL for 108 ms on the two-core test machine,
        eight RSI cycles without a reply (docs/benchmarks.md). ``gc.freeze`` moves them out of the
        collector's sight for good. With ``collect`` a full pass first drops start-up garbage; that
        pass is only made before the RSI endpoint listens — afterwards ``freeze`` alone, which costs
        no pass.
        """
        if collect:
            gc.collect()
        gc.freeze()
        log.info("daemon: %d start-up objects exempted from garbage collection", gc.get_freeze_count())

    @property
    def rsi_address(self) -> tuple[str, int] | None:
        if self.rtp is not None:
            if not self.rtp.info:
                return None
            host, port = self.rtp.info["rsi_address"]
            return str(host), int(port)
        if self.rsi_transport is None:
            return None
        host, port = self.rsi_transport.get_extra_info("sockname")[:2]
        return str(host), int(port)

    async def _start(self) -> None:
        from comp_daemon.service.api import open_store

        settings = self.settings
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.store = await asyncio.to_thread(open_store, settings)
        self.store.add_listener(self._on_store_event)
        active = await asyncio.to_thread(self.store.active_model, with_artifact=False)
        self.active_model_id = None if active is None else active.id
        calibration = await asyncio.to_thread(load_latest_calibration, self.gratings_dir)

        # 0. the real-time thread, and the job workers kept off its CPU; the one full collection
        #    of start-up garbage while no telegram can be waiting
        self._freeze_startup_objects(collect=True)
        await self._start_realtime()
        settings = self.settings

        # 1. RSI first: the controller (simulated or not) must find us listening before RSI_ON
        rsi = settings.rsi
        if len(rsi.controller_allow) > 1:
            n_allowed = len(rsi.controller_allow)
            log.warning(
                "rsi: %d controller addresses configured; accepting %s", n_allowed, rsi.controller_allow[0]
            )
        host = "127.0.0.1" if self.sim_options is not None else rsi.controller_allow[0]
        bind_host = "127.0.0.1" if self.sim_options is not None else rsi.listen_host
        rsi_config = RsiServerConfig(
            controller_host=host,
            bind_host=bind_host,
            bind_port=rsi.listen_port,
            cycle_ms=float(rsi.cycle_ms),
            sen_type=rsi.sen_type,
        )
        if self.settings.realtime.mode == "process":
            await self._start_rt_process(rsi_config)
        else:
            self.rsi_transport, self.rsi = await self._on_rt(
                start_rsi_server(self._handle, rsi_config, clock=self.clock_ns)
            )

        # 2. the HTTP service (heavy imports and the job pool start here, before any cycle runs)
        await self._start_http()

        # 3. the cell: simulated child, or the configured serial ports and motion gateway
        enc = settings.encoders
        ports: dict[int, tuple[str, int]] = {j.joint: (j.port, j.bits) for j in enc.joints}
        self.geometry = {j.joint: GratingGeometry(j.radius_mm, j.resolution_nm) for j in enc.joints}
        if self.sim_options is not None:
            opts = self.sim_options
            assert self.rsi_address is not None
            self.sim = SimCellProcess(
                rsi_port=self.rsi_address[1],
                link_dir=self.data_dir / "sim",
                scenario=opts.scenario,
                seed=opts.seed,
                cycle_ms=rsi.cycle_ms,
                servo_lag_cycles=opts.servo_lag_cycles,
                timeout_count=rsi.timeout_count,
                sen_type=rsi.sen_type,
            )
            info = self.sim_info = await self.sim.start()
            ports = {j: (path, info.bits) for j, path in info.gratings.items()}
            self.geometry = {j: GratingGeometry(info.radius_mm, info.resolution_nm) for j in info.gratings}
            self.motion = LineMotionPort(
                info.motion_host, info.motion_port, timeout_s=settings.controller.move_timeout_s
            )
            self._home = info.home_deg
        elif self.motion_address is not None:
            self.motion = LineMotionPort(*self.motion_address, timeout_s=settings.controller.move_timeout_s)

        reader_specs: list[tuple[EncoderReaderConfig, LinearGratingCalibration]] = []
        for joint, (port, bits) in sorted(ports.items()):
            geo = self.geometry[joint]
            cfg = EncoderReaderConfig(
                port=port,
                joint=joint,
                bits=bits,
                baudrate=enc.baudrate,
                poll_ms=enc.poll_period_ms,
                poll_lead_ms=enc.poll_lead_ms,
                reply_timeout_ms=min(enc.reply_timeout_ms, enc.poll_period_ms),
                stale_after_ms=enc.stale_after_ms,
                backoff_initial_ms=enc.reconnect_initial_ms,
                backoff_max_ms=enc.reconnect_max_ms,
            )
            reader_specs.append(
                (cfg, LinearGratingCalibration(geo.radius_mm, resolution_nm=geo.resolution_nm))
            )
        safety = safety_settings_from(settings.controller)
        loop_settings = loop_settings_from(settings.controller, rsi.cycle_ms)
        if self.rtp is not None:
            spec = LoopStart(tuple(reader_specs), calibration, safety, loop_settings, rsi.sen_type)
            self.runtime = await self.rtp.start_loop(spec)
            self.readers = dict(self.rtp.readers)
        else:
            readers = {
                cfg.joint: EncoderReader(cfg, geometry, clock=self.clock_ns) for cfg, geometry in reader_specs
            }
            runtime_here = LoopRuntime(
                readers,
                calibration=calibration,
                safety=safety,
                loop=loop_settings,
                sen_type=rsi.sen_type,
                clock_ns=self.clock_ns,
            )
            self.readers, self.runtime = dict(readers), runtime_here
            for joint, reader in readers.items():
                reader.next_telegram_ns = runtime_here.next_telegram_ns
                self._tasks[f"encoder-a{joint}"] = await self._rt_call(reader.start)

        # 4. the executor and the supervisor
        runtime = self.runtime
        compensator = self.compensator or ActiveModelCompensator(
            self.store,
            self.robot,
            [j - 1 for j in runtime.joints],
            current_axes=lambda: runtime.last_actual_deg,
        )
        if self.motion is not None:
            self.executor = TargetExecutor(
                self.store,
                compensator,
                self.motion,
                self.runtime,
                joints=[j - 1 for j in self.runtime.joints],
                readiness=self._target_readiness,
                on_outcome=self._on_outcome,
            )
            self._tasks["executor"] = asyncio.create_task(self.executor.run(), name="executor")

        self._tasks["supervisor"] = asyncio.create_task(self._supervise(), name="supervisor")
        if self.sim is not None:
            await self.sim.rsi_on()  # the robot program's RSI_ON, once the daemon listens and runs
        await asyncio.to_thread(
            self.store.add_event,
            "daemon.started",
            {
                "version": __version__,
                "sim": asdict(self.sim_options) if self.sim_options else None,
                "rsi": list(self.rsi_address or ()),
                "http_port": self.http_port,
                "gratings": sorted(self.readers),
                "grating_calibration_version": None if calibration is None else calibration.version,
                "realtime": self._realtime_word(),
            },
        )

    async def _start_realtime(self) -> None:
        cfg = self.settings.realtime
        if cfg.mode != "thread":
            return  # "process": started with the RSI endpoint (_start_rt_process)
        cpu = resolve_cpu(cfg.cpu)
        self.rt = RealtimeThread(
            RealtimeThreadConfig(
                cpu=cpu,
                realtime_priority=cfg.priority,
                switch_interval_s=cfg.switch_interval_ms / 1000.0,
                cpu_wakeup_latency_us=None if cfg.cpu_wakeup_latency_us < 0 else cfg.cpu_wakeup_latency_us,
            ),
            clock_ns=self.clock_ns,
        )
        await asyncio.to_thread(self.rt.start)
        self._keep_jobs_off(self.rt.pinned_cpu)
        log.info("daemon: real-time loop: %s", self._realtime_word())

    async def _start_rt_process(self, rsi_config: RsiServerConfig) -> None:
        cfg = self.settings.realtime
        self.rtp = RealtimeProcess(
            RtStart(
                rsi=rsi_config,
                cpu=resolve_cpu(cfg.cpu),
                priority=cfg.priority,
                cpu_wakeup_latency_us=None if cfg.cpu_wakeup_latency_us < 0 else cfg.cpu_wakeup_latency_us,
                tick_s=self.tick_s,
                grace_cycles=self.stop_grace_cycles,
                log_level=logging.getLogger("comp_daemon").getEffectiveLevel(),
            ),
            clock_ns=self.clock_ns,
            on_lost=lambda reason: self.request_stop("task failed"),
        )
        await self.rtp.start()
        self._keep_jobs_off(self.rtp.describe()["cpu"])
        log.info("daemon: real-time loop: %s", self._realtime_word())

    def _keep_jobs_off(self, cpu: int | None) -> None:
        rest = other_cpus(cpu)
        if self.settings.realtime.keep_jobs_off_cpu and not self.settings.jobs.cpus and rest:
            jobs = self.settings.jobs.model_copy(update={"cpus": sorted(rest)})
            self.settings = self.settings.model_copy(update={"jobs": jobs})

    @property
    def rsi_stats(self) -> RsiServerStats | None:
        """The RSI endpoint's counters and latency rings (mirrored from the real-time process)."""
        if self.rtp is not None:
            return self.rtp.rsi_stats
        return None if self.rsi is None else self.rsi.stats

    def _realtime_word(self) -> str:
        if self.rtp is not None:
            d = self.rtp.describe()
            kind = f"own process (pid {d['pid']})"
        elif self.rt is not None:
            d = self.rt.describe()
            kind = "own thread"
        else:
            return "one event loop with the HTTP side"
        where = "any CPU" if d["cpu"] is None else f"CPU {d['cpu']}"
        word = f"{kind} on {where}, {d['scheduler']} scheduling"
        if d["cpu_wakeup_latency_us"] is not None:
            word += f", CPU wake-up latency ≤ {d['cpu_wakeup_latency_us']} µs requested"
        jobs = self.settings.jobs.cpus
        if jobs:
            word += f"; job workers on CPU {', '.join(map(str, jobs))}"
        if d["notes"]:
            word += "; " + "; ".join(d["notes"])
        return word

    async def _on_rt(self, coro: Coroutine[Any, Any, T]) -> T:
        """Await a coroutine on the real-time loop (on this loop when there is no real-time thread)."""
        if self.rt is None:
            return await coro
        return await self.rt.run(coro)

    async def _rt_call(self, fn: Callable[..., T], *args: Any) -> T:
        """Call a function on the real-time loop (here when there is no real-time thread)."""
        return fn(*args) if self.rt is None else await self.rt.call(fn, *args)

    async def _start_http(self) -> None:
        import uvicorn

        from comp_daemon.service.api import create_app

        assert self.store is not None
        app = create_app(self.settings, self.store, self, bus=self.bus)

        class _Server(uvicorn.Server):
            @contextlib.contextmanager
            def capture_signals(self) -> Any:  # the daemon owns the signals
                yield

        http = self.settings.http
        sock = socket.socket(socket.AF_INET6 if ":" in http.host else socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((http.host, http.port))
        sock.set_inheritable(True)
        self.http_port = int(sock.getsockname()[1])
        config = uvicorn.Config(
            app,
            log_config=None,
            access_log=False,
            lifespan="on",
            timeout_graceful_shutdown=3,
            server_header=False,
        )
        server = _Server(config)
        self._uvicorn = server

        async def serve() -> None:
            try:
                await server.serve(sockets=[sock])
            except SystemExit as exc:  # uvicorn exits on a failed startup
                raise RuntimeError(f"the HTTP service failed to start ({exc})") from None
            finally:
                sock.close()

        self._tasks["http"] = asyncio.create_task(serve(), name="http")
        for _ in range(500):
            if server.started or self._tasks["http"].done():
                break
            await asyncio.sleep(0.01)
        if self._tasks["http"].done():
            self._tasks["http"].result()
        if not server.started:
            raise RuntimeError("the HTTP service did not start")

    async def _wait(self) -> None:
        stop = asyncio.ensure_future(self._stop.wait())
        try:
            while not self._stop.is_set():
                watched = [t for name, t in self._tasks.items() if not name.startswith("encoder")]
                done, _ = await asyncio.wait([stop, *watched], return_when=asyncio.FIRST_COMPLETED)
                for task in done:
                    if task is stop:
                        continue
                    name = task.get_name()
                    exc = None if task.cancelled() else task.exception()
                    log.error("daemon: task %s ended unexpectedly: %r", name, exc)
                    self.request_stop("task failed")
        finally:
            stop.cancel()

    async def _shutdown(self) -> None:
        self.notifier.stopping(f"stopping: {self._stop_reason or 'startup failed'}")
        runtime = self.runtime
        # 1. no new targets; zero steps and Stop=1 from the next telegram; the target is reported
        if self.executor is not None:
            self.executor.stop_claiming()
        if self._cal_task is not None and not self._cal_task.done():
            self._cal_task.cancel()  # its moves end with the robot's Stop below
        if runtime is not None:
            try:
                runtime.shutdown()
            except RtProcessError as exc:  # it has gone: it went safe on its own
                log.error("daemon: %s", exc)
        task = self._tasks.pop("executor", None)
        if task is not None:
            try:
                async with asyncio.timeout(10.0):
                    await task
            except TimeoutError:
                log.error("daemon: the executor did not finish within 10 s; cancelling it")
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
            except Exception:
                log.exception("daemon: the executor failed")
        # 2. let the controller see Stop=1 for a few cycles, then stop listening
        if runtime is not None and self._rsi_open() and runtime.rsi_alive():
            await runtime.wait_telegrams(self.stop_grace_cycles, self.settings.rsi.cycle_ms / 1000.0)
        if self.rtp is not None:
            with contextlib.suppress(RtProcessError, TimeoutError):  # it has gone already
                await self.rtp.close_rsi()
        if self.rsi_transport is not None:
            with contextlib.suppress(RuntimeError):  # the real-time thread is gone already
                await self._rt_call(self.rsi_transport.close)
        # 3. persist the loop's final state
        if runtime is not None:
            doc = self._final_state()
            try:
                await asyncio.to_thread(_write_json_atomic, self.state_path, doc)
                if self.store is not None:
                    await asyncio.to_thread(self.store.add_event, "daemon.stopped", doc)
            except Exception:
                log.exception("daemon: could not persist the final state")
        # 4. stop the rest: supervisor, encoders, HTTP, the simulated cell
        sup = self._tasks.pop("supervisor", None)
        if sup is not None:
            sup.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await sup
        if self.rtp is not None:
            code = await self.rtp.stop()
            log.info("daemon: real-time process exited with %s", code)
        for reader in self.readers.values():
            if isinstance(reader, EncoderReader):
                with contextlib.suppress(RuntimeError):
                    await self._on_rt(reader.stop())
        for name in [n for n in self._tasks if n.startswith("encoder")]:
            self._tasks.pop(name)
        if self.rt is not None:
            await asyncio.to_thread(self.rt.stop)
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
            log.info("daemon: simulated cell exited with %s", code)
        if self.store is not None:
            self.store.remove_listener(self._on_store_event)
            await asyncio.to_thread(self.store.close)
        self.notifier.close()
        log.info("daemon: stopped")

    def _final_state(self) -> dict[str, Any]:
        runtime = self.runtime
        assert runtime is not None
        core = runtime.core
        return {
            "time": time.time(),
            "reason": self._stop_reason,
            "state": str(core.state),
            "fault": None if core.fault is None else {k: str(v) for k, v in asdict(core.fault).items()},
            "last_ipoc": runtime.last_ipoc,
            "last_reply": {"ak_deg": list(runtime.last_ak_deg), "stop": runtime.last_stop},
            "replies_after_shutdown": runtime.replies_after_shutdown,
            "telegrams": runtime.telegrams,
            "total_correction_deg": list(core.total_correction_deg),
            "grating_calibration_version": None
            if runtime.calibration is None
            else runtime.calibration.version,
            "faults": [
                {
                    "kind": str(f.kind),
                    "reaction": str(f.reaction),
                    "detail": f.detail,
                    "target_id": f.target_id,
                }
                for f in runtime.fault_log
            ],
            "rsi": None
            if self.rsi_stats is None
            else self.rsi_stats.snapshot() | {"latency": None, "jitter": None},
        }

    # ------------------------------------------------------------------------------ the RSI handler

    def _handle(self, telegram: RobTelegram) -> SenReply:
        runtime = self.runtime
        if runtime is None:  # telegrams before the loop is assembled: no correction
            return SenReply(telegram.ipoc, _ZERO, False, self.settings.rsi.sen_type)
        assert isinstance(runtime, LoopRuntime), "with a real-time process its child answers"
        return runtime.handle(telegram)

    # ------------------------------------------------------------------------------ supervisor

    async def _supervise(self) -> None:
        interval = watchdog_interval_s()
        last_watchdog = 0.0
        last_telemetry = 0.0
        self._last_tick_ns = self.clock_ns()
        while True:
            await asyncio.sleep(self.tick_s)
            now_ns = self.clock_ns()
            gap = (now_ns - self._last_tick_ns) * 1e-9
            self._max_tick_gap_s = max(self._max_tick_gap_s, gap)
            self._last_tick_ns = now_ns
            if self.runtime is not None:
                self.runtime.tick()
            now = time.monotonic()
            if now - last_telemetry >= self.telemetry_s:
                last_telemetry = now
                await self._telemetry()
            if interval is not None and now - last_watchdog >= interval and self._healthy(gap):
                last_watchdog = now
                self.notifier.watchdog()

    def _rsi_open(self) -> bool:
        if self.rtp is not None:
            return self.rtp.alive
        return self.rsi_transport is not None and not self.rsi_transport.is_closing()

    def _healthy(self, tick_gap_s: float) -> bool:
        """Alive tasks, an open RSI socket, and event loops that keep their schedule."""
        if tick_gap_s > 1.0:
            return False
        if not self._rsi_open():
            return False
        if self.rtp is not None:
            age = self.rtp.report_age_s()
            if age is None or age > 1.0:
                return False
        if self.rt is not None:
            age = self.rt.heartbeat_age_s()
            if not self.rt.alive or age is None or age > 1.0:
                return False
        return not any(t.done() for t in self._tasks.values())

    async def _telemetry(self) -> None:
        runtime, stats = self.runtime, self.rsi_stats
        if runtime is None or stats is None:
            return
        # percentiles over the latency ring in a worker thread (copy here: the handler appends to it)
        lat = stats.latency.recent()
        jit = stats.jitter.recent()
        pct = await asyncio.to_thread(self._percentiles, lat, jit)
        self._loop_stats = LoopStats(
            running=runtime.rsi_alive(),
            cycle_ms=float(self.settings.rsi.cycle_ms),
            cycles=stats.answered,
            late_replies=stats.late,
            rejected=stats.foreign + stats.garbled,
            latency_p50_ms=pct[0],
            latency_p99_ms=pct[1],
            latency_max_ms=None if stats.latency.max is None else stats.latency.max / 1e6,
            jitter_p99_ms=pct[2],
            last_ipoc=runtime.last_ipoc,
            realtime=self._realtime_word(),
        )
        self._update_metrics(runtime, stats, lat)
        rows = runtime.joint_rows()
        self.bus.publish("loop", asdict(self._loop_stats) | {"state": self._state_word()})
        self.bus.publish("joints", {"joints": rows, "state": str(runtime.core.state)})
        status = self._state_word()
        if self.executor is not None and self.executor.current_target_id is not None:
            status += f" (target {self.executor.current_target_id})"
        self.notifier.status(status)

    @staticmethod
    def _percentiles(lat: np.ndarray, jit: np.ndarray) -> tuple[float | None, float | None, float | None]:
        p50 = p99 = j99 = None
        if lat.size:
            p50, p99 = (float(v) / 1e6 for v in np.percentile(lat, [50.0, 99.0]))
        if jit.size:
            j99 = float(np.percentile(np.abs(jit), 99.0)) / 1e6
        return p50, p99, j99

    def _delta(self, key: str, value: int) -> int:
        before = self._metric_marks.get(key, 0)
        self._metric_marks[key] = value
        return max(0, value - before)

    def _update_metrics(self, runtime: LoopView, stats: RsiServerStats, latencies_ns: np.ndarray) -> None:
        new = self._delta("answered", stats.answered)
        if new:
            metrics.RSI_TELEGRAMS.inc(new)
            for v in latencies_ns[-min(new, latencies_ns.size) :]:
                metrics.LOOP_REPLY_LATENCY.observe(float(v) / 1e9)
        late = self._delta("late", stats.late) + self._delta("superseded", stats.superseded)
        if late:
            metrics.RSI_LATE_REPLIES.inc(late)
        for reason, value in (("garbled", stats.garbled), ("foreign_address", stats.foreign)):
            d = self._delta(f"rejected.{reason}", value)
            if d:
                metrics.RSI_REJECTED.labels(reason=reason).inc(d)
        metrics.LOOP_RUNNING.set(1.0 if runtime.rsi_alive() else 0.0)
        for joint, reader in self.readers.items():
            for kind, count in reader.fault_counts.items():
                name = _ENCODER_METRIC_KIND.get(str(kind))
                d = self._delta(f"enc.{joint}.{kind}", count)
                if name is not None and d:
                    metrics.encoder_fault_counter(joint, name).inc(d)
            d = self._delta(f"enc.{joint}.warnings", reader.warnings)
            if d:
                metrics.encoder_fault_counter(joint, "warning_bit").inc(d)
        for row in runtime.joint_rows():
            j = str(row["joint"])
            metrics.ENCODER_STALE.labels(joint=j).set(0.0 if row["encoder"] == "ok" else 1.0)
            if row["error_deg"] is not None:
                metrics.JOINT_ERROR_DEG.labels(joint=j).set(row["error_deg"])
            metrics.JOINT_CORRECTION_DEG.labels(joint=j).set(row["correction_deg"])

    # ------------------------------------------------------------------------------ executor hooks

    def _target_readiness(self) -> str | None:
        reasons = self.readiness_reasons()
        if self.active_model_id is None:
            reasons.append("no model is active")
        return "; ".join(reasons) if reasons else None

    def _on_outcome(self, outcome: TargetOutcome) -> None:
        log.info("daemon: target %d %s %s", outcome.target_id, outcome.state, outcome.reason or "")

    def _on_store_event(self, event: EventRecord) -> None:
        """Store commits (any thread): follow the active model; wake the executor on new work."""
        if event.kind == "model.activated":
            self.active_model_id = int(event.message["model_id"])
        if event.kind in ("batch.accepted", "model.activated", "target.queued") and self.executor is not None:
            self.executor.wake()

    # ------------------------------------------------------------------------------ operator actions

    def reset_fault(self) -> None:
        """Operator acknowledgement of a latched fault (a stop must also be cleared on the robot)."""
        if self.runtime is not None:
            self.runtime.reset()
            if self.executor is not None:
                self.executor.wake()

    def acknowledge_fault(self, by: str) -> dict[str, Any] | None:
        """:meth:`reset_fault` for the HTTP side: returns the fault that was cleared (or None)."""
        runtime = self.runtime
        if runtime is None or runtime.core.state is not SafetyState.FAULT or runtime.core.fault is None:
            return None
        f = runtime.core.fault
        cleared = {
            "kind": str(f.kind),
            "reaction": str(f.reaction),
            "detail": f.detail,
            "target_id": f.target_id,
        }
        self.reset_fault()
        log.info("daemon: fault %s acknowledged by %s", cleared["kind"], by)
        return cleared

    def start_grating_calibration(self, poses_deg: Sequence[Sequence[float]] | None, by: str) -> None:
        """Start :meth:`calibrate_gratings` in the background (the HTTP route); RuntimeError if it cannot."""
        runtime = self.runtime
        if runtime is None or self.motion is None:
            raise RuntimeError("the daemon has no loop or no motion port")
        if self.calibrating or (self._cal_task is not None and not self._cal_task.done()):
            raise RuntimeError("a grating calibration is already running")
        busy = runtime.core.state in (SafetyState.ARMED, SafetyState.CORRECTING, SafetyState.SETTLED)
        if busy or (self.executor is not None and self.executor.current_target_id is not None):
            raise RuntimeError("a target is active; calibrate between targets")
        poses = None if poses_deg is None else [tuple(float(v) for v in p) for p in poses_deg]
        self._cal_error = None
        self._cal_started_at, self._cal_finished_at = time.time(), None

        async def run() -> None:
            try:
                cal = await self.calibrate_gratings(poses)
                log.info("daemon: grating calibration v%d started by %s is in use", cal.version, by)
            except Exception as exc:
                self._cal_error = str(exc) or type(exc).__name__
                log.error("daemon: grating calibration started by %s failed: %s", by, self._cal_error)
                if self.store is not None:
                    await asyncio.to_thread(
                        self.store.add_event, "gratings.failed", {"error": self._cal_error, "by": by}
                    )
            finally:
                self._cal_finished_at = time.time()

        self._cal_task = asyncio.get_running_loop().create_task(run(), name="grating-calibration")

    def grating_status(self) -> dict[str, Any]:
        runtime = self.runtime
        cal = None if runtime is None else runtime.calibration
        running = self.calibrating or (self._cal_task is not None and not self._cal_task.done())
        return {
            "calibrating": running,
            "calibration": None if cal is None else cal.to_dict(),
            "last_error": self._cal_error,
            "started_at": self._cal_started_at,
            "finished_at": self._cal_finished_at,
        }

    async def calibrate_gratings(
        self, poses: Sequence[Sequence[float]] | None = None, **options: Any
    ) -> GratingCalibration:
        """Run seed 000's grating calibration on the cell (no target may be active)."""
        runtime, motion = self.runtime, self.motion
        if runtime is None or motion is None:
            raise RuntimeError("the daemon has no loop or no motion port")
        if self.calibrating:
            raise RuntimeError("a grating calibration is already running")
        if runtime.core.state in (SafetyState.ARMED, SafetyState.CORRECTING, SafetyState.SETTLED):
            raise RuntimeError("a target is active; calibrate between targets")
        if poses is None:
            home = self._home if self._home is not None else runtime.last_actual_deg
            if home is None:
                raise RuntimeError("no calibration poses given and no robot position known")
            poses = default_calibration_poses(home, runtime.joints, self.robot.axis_limits_deg)
        self.calibrating = True
        try:
            cal = await calibrate_gratings(
                runtime, motion, poses, self.geometry, self.gratings_dir, **options
            )
        finally:
            self.calibrating = False
            if self.executor is not None:
                self.executor.wake()
        if self.store is not None:
            await asyncio.to_thread(
                self.store.add_event,
                "gratings.calibrated",
                {"version": cal.version, "joints": [asdict(m) for m in cal.joints]},
            )
        return cal

    # ------------------------------------------------------------------------------ DaemonView

    def _state_word(self) -> str:
        runtime = self.runtime
        if runtime is None:
            return "starting"
        core = runtime.core
        if core.state is SafetyState.STOPPING:
            return "stopped"
        if self.calibrating:
            return "calibrating gratings"
        if core.state is SafetyState.FAULT:
            return "fault"
        if self.executor is not None and self.executor.phase is not None:
            return "holding" if core.state is SafetyState.SETTLED else self.executor.phase
        if core.state is SafetyState.SETTLED:
            return "holding"
        return "idle" if runtime.rsi_alive() else "waiting for RSI"

    def snapshot(self) -> DaemonSnapshot:
        runtime = self.runtime
        if runtime is None:
            return DaemonSnapshot(state="starting", time=time.time(), hold_reason="the daemon is starting")
        core = runtime.core
        hold = None
        if core.fault is not None:
            hold = f"{core.fault.kind} ({core.fault.reaction}): {core.fault.detail}"
        elif self.executor is not None and self.executor.blocked_reason is not None:
            hold = self.executor.blocked_reason
        joints = []
        by_joint = {row["joint"]: row for row in runtime.joint_rows()}
        for j in range(1, 7):
            row = by_joint.get(j)
            axis = None if runtime.last_actual_deg is None else runtime.last_actual_deg[j - 1]
            if row is None:
                joints.append(JointStatus(joint=j, axis_deg=axis, correction_deg=0.0))
                continue
            encoder = row["encoder"]
            health = (
                "ok"
                if encoder == "ok"
                else ("stale" if encoder in ("stale", "silent", "no_data") else "fault")
            )
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
            state=self._state_word(),
            time=time.time(),
            hold_reason=hold,
            current_target_id=None if self.executor is None else self.executor.current_target_id,
            phase=None if self.executor is None else self.executor.phase,
            joints=tuple(joints),
            loop=self._loop_stats,
        )

    def readiness_reasons(self) -> list[str]:
        runtime = self.runtime
        if runtime is None:
            return ["the daemon is starting"]
        reasons = runtime.readiness_reasons()
        if self.motion is None:
            reasons.append("no motion port configured (run --motion HOST:PORT, or --sim)")
        if self.calibrating:
            reasons.append("grating calibration in progress")
        return reasons

    def loop_stats(self) -> LoopStats:
        return self._loop_stats
