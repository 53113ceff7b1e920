"""The cell as the daemon drives it: the RSI endpoint and the gratings (in the real-time process), the
motion port, the target executor, the grating calibration, and with ``sim`` the simulated cell.

- **RSI and gratings**: :class:`~comp_daemon.daemon.rt_process.RealtimeProcess` starts the child
  that answers each telegram in its receive callback with one O(joints) step of the safety machine
  and seed 000's controller on the latest grating readings, one reader task per grating beside it.
  The daemon sees and commands the loop through its :class:`~comp_daemon.daemon.rt_process.RemoteRuntime`.
- **Executor**: :class:`comp_daemon.rt.executor.TargetExecutor` takes queued targets one at a time,
  compensates, commands the motion, arms the loop and records the outcome.
- **Grating calibration**: seed 000 step 1 (:mod:`comp_daemon.daemon.gratings`), on request.
- **Simulated cell** (``sim``): a child process (:mod:`comp_daemon.daemon.simcell`) that the daemon
  talks to over UDP, pseudo-terminals and TCP, exactly as to the line. Its controller re-arms RSI
  ``rearm_after_s`` after a stop, as an operator restarting the program does.
- **RSI sessions**: a watch task records each RSI stop with its cause and each restart
  (:class:`comp_daemon.daemon.rsi_sessions.RsiSessions`, in the store's event log and on ``/api/status``).

The daemon (:mod:`comp_daemon.daemon.app`) decides the order of the steps; this module does them.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from comp_daemon.common.logs import get_logger
from comp_daemon.daemon.compensation import ActiveModelCompensator
from comp_daemon.daemon.gratings import GratingGeometry, calibrate_gratings, default_calibration_poses
from comp_daemon.daemon.motion import LineMotionPort
from comp_daemon.daemon.rsi_sessions import RsiSessions
from comp_daemon.daemon.rt_process import ReaderMirror, RealtimeProcess, RemoteRuntime, RtProcessError
from comp_daemon.daemon.simcell import SimCellInfo, SimCellProcess
from comp_daemon.robot.description import RobotDescription
from comp_daemon.rt.controller import JointLoopSettings
from comp_daemon.rt.encoder_reader import EncoderReaderConfig, LinearGratingCalibration
from comp_daemon.rt.executor import Compensator, MotionPort, TargetExecutor, TargetOutcome
from comp_daemon.rt.grating_cal import GratingCalibration
from comp_daemon.rt.link import LoopStart, RtStart
from comp_daemon.rt.rsi_server import RsiServerConfig, RsiServerStats
from comp_daemon.rt.safety import SafetySettings, SafetyState
from comp_daemon.rt.scheduling import other_cpus, resolve_cpu
from comp_daemon.service.config import ControllerSettings, Settings
from comp_daemon.service.store import EventRecord, Store

__all__ = ["Cell", "SimOptions", "loop_settings_from", "safety_settings_from"]

log = get_logger(__name__)

_ACTIVE_STATES = (SafetyState.ARMED, SafetyState.CORRECTING, SafetyState.SETTLED)


@dataclass(frozen=True, slots=True)
class SimOptions:
    """The simulated cell brought up beside the daemon (``run --sim``)."""

    scenario: str = "kr210-cell"
    seed: int = 0
    servo_lag_cycles: int = 1
    rearm_after_s: float | None = 5.0  # the controller restarts RSI this long after a stop (None: never)


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


class Cell:
    """The real-time process, the motion port, the executor and the calibration. See the module docstring."""

    def __init__(
        self,
        settings: Settings,
        robot: RobotDescription,
        *,
        sim: SimOptions | None = None,
        motion_address: tuple[str, int] | None = None,
        compensator: Compensator | None = None,
        clock_ns: Callable[[], int] = time.perf_counter_ns,
        tick_s: float = 0.05,
        stop_grace_cycles: int = 3,
    ) -> None:
        self.settings = settings
        self.robot = robot
        self.sim_options = sim
        self.motion_address = motion_address
        self.compensator = compensator
        self.clock_ns = clock_ns
        self.tick_s = tick_s
        self.stop_grace_cycles = stop_grace_cycles
        self.gratings_dir = Path(settings.store.data_dir) / "gratings"
        self.store: Store | None = None
        self.rtp: RealtimeProcess | None = None
        self.runtime: RemoteRuntime | None = None
        self.executor: TargetExecutor | None = None
        self.motion: MotionPort | None = None
        self.readers: dict[int, ReaderMirror] = {}
        self.geometry: dict[int, GratingGeometry] = {}
        self.sim: SimCellProcess | None = None
        self.sim_info: SimCellInfo | None = None
        self.home_deg: tuple[float, ...] | None = None
        self.rsi_sessions = RsiSessions(
            timeout_count=settings.rsi.timeout_count, record_event=self._record_event
        )
        self._rsi_watch: asyncio.Task[None] | None = None
        self.active_model_id: int | None = None
        self.calibrating = False
        self._cal_task: asyncio.Task[None] | None = None
        self._cal_error: str | None = None
        self._cal_started_at: float | None = None
        self._cal_finished_at: float | None = None
        self._cal_poses: tuple[int, int] | None = None  # (measured, total) of the last attempt

    # ------------------------------------------------------------------------------ start

    async def start_realtime(self, on_lost: Callable[[str], None]) -> None:
        """Start the real-time process and open the RSI endpoint there (the controller must find it
        listening before RSI_ON); the job workers are then kept off its CPU (``settings.jobs``)."""
        settings = self.settings
        rsi = settings.rsi
        if len(rsi.controller_allow) > 1:
            log.warning(
                f"rsi: {len(rsi.controller_allow)} controller addresses configured; "
                f"accepting {rsi.controller_allow[0]}"
            )
        local = self.sim_options is not None
        rsi_config = RsiServerConfig(
            controller_host="127.0.0.1" if local else rsi.controller_allow[0],
            bind_host="127.0.0.1" if local else rsi.listen_host,
            bind_port=rsi.listen_port,
            cycle_ms=float(rsi.cycle_ms),
            sen_type=rsi.sen_type,
        )
        rt = settings.realtime
        self.rtp = RealtimeProcess(
            RtStart(
                rsi=rsi_config,
                cpu=resolve_cpu(rt.cpu),
                priority=rt.priority,
                cpu_wakeup_latency_us=None if rt.cpu_wakeup_latency_us < 0 else rt.cpu_wakeup_latency_us,
                tick_s=self.tick_s,
                grace_cycles=self.stop_grace_cycles,
                log_level=logging.getLogger("comp_daemon").getEffectiveLevel(),
            ),
            clock_ns=self.clock_ns,
            on_lost=on_lost,
        )
        await self.rtp.start()
        rest = other_cpus(self.rtp.describe()["cpu"])
        if rt.keep_jobs_off_cpu and not settings.jobs.cpus and rest:
            jobs = settings.jobs.model_copy(update={"cpus": sorted(rest)})
            self.settings = settings.model_copy(update={"jobs": jobs})
        # one line: what was granted, and what was refused with the reason
        say = log.warning if self.rtp.describe()["notes"] else log.info
        say(f"daemon: real-time loop: {self.realtime_word()}")

    async def start_cell(self, calibration: GratingCalibration | None) -> None:
        """The simulated cell (or the configured ports and motion gateway), then the grating readers
        and the loop in the real-time process."""
        assert self.rtp is not None, "the real-time process comes first"
        settings = self.settings
        enc, rsi = settings.encoders, settings.rsi
        ports: dict[int, tuple[str, int]] = {j.joint: (j.port, j.bits) for j in enc.joints}
        self.geometry = {j.joint: GratingGeometry(j.radius_mm, j.resolution_nm) for j in enc.joints}
        move_timeout_s = settings.controller.move_timeout_s
        if self.sim_options is not None:
            opts = self.sim_options
            address = self.rsi_address
            assert address is not None
            self.sim = SimCellProcess(
                rsi_port=address[1],
                link_dir=Path(settings.store.data_dir) / "sim",
                scenario=opts.scenario,
                seed=opts.seed,
                cycle_ms=rsi.cycle_ms,
                servo_lag_cycles=opts.servo_lag_cycles,
                timeout_count=rsi.timeout_count,
                sen_type=rsi.sen_type,
                rearm_after_s=opts.rearm_after_s,
            )
            info = self.sim_info = await self.sim.start()
            self.rsi_sessions.controller_status = self.sim.controller_status
            self.rsi_sessions.rearm_after_s = opts.rearm_after_s
            ports = {j: (path, info.bits) for j, path in info.gratings.items()}
            self.geometry = {j: GratingGeometry(info.radius_mm, info.resolution_nm) for j in info.gratings}
            self.motion = LineMotionPort(info.motion_host, info.motion_port, timeout_s=move_timeout_s)
            self.home_deg = info.home_deg
        elif self.motion_address is not None:
            self.motion = LineMotionPort(*self.motion_address, timeout_s=move_timeout_s)

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
        spec = LoopStart(
            tuple(reader_specs),
            calibration,
            safety_settings_from(settings.controller),
            loop_settings_from(settings.controller, rsi.cycle_ms),
            rsi.sen_type,
        )
        self.runtime = await self.rtp.start_loop(spec)
        self.readers = dict(self.rtp.readers)
        self._rsi_watch = asyncio.create_task(self._watch_rsi(), name="rsi sessions")

    async def _watch_rsi(self, period_s: float = 0.1) -> None:
        """Record RSI stops and restarts (:class:`RsiSessions`) until the loop stops."""
        while True:
            await asyncio.sleep(period_s)
            runtime, stats, rtp = self.runtime, self.rsi_stats, self.rtp
            if runtime is None or stats is None or rtp is None:
                continue
            try:
                await self.rsi_sessions.observe(runtime, stats, report_age_s=rtp.report_age_s())
            except Exception:  # a recording failure must not end the watch
                log.exception("daemon: recording the RSI session failed")

    async def _record_event(self, kind: str, message: dict[str, Any]) -> None:
        if self.store is not None:
            await asyncio.to_thread(self.store.add_event, kind, message)

    def attach_store(self, store: Store) -> None:
        """Follow the store from now on: the active model, and new work for the executor."""
        self.store = store
        store.add_listener(self._on_store_event)

    def detach_store(self) -> None:
        if self.store is not None:
            self.store.remove_listener(self._on_store_event)

    def start_executor(self, readiness: Callable[[], list[str]]) -> asyncio.Task[None] | None:
        """The target executor's task (None without a motion port: nothing could move)."""
        runtime, store = self.runtime, self.store
        assert runtime is not None and store is not None, "the store and the loop come first"
        if self.motion is None:
            return None
        compensator = self.compensator or ActiveModelCompensator(
            store,
            self.robot,
            [j - 1 for j in runtime.joints],
            current_axes=lambda: runtime.last_actual_deg,
            limits=self.settings.compensation.limits(),
            mapping=self.settings.compensation.mapping,
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
            joints=[j - 1 for j in runtime.joints],
            readiness=target_readiness,
            on_outcome=self._on_outcome,
        )
        return asyncio.create_task(self.executor.run(), name="executor")

    @staticmethod
    def _on_outcome(outcome: TargetOutcome) -> None:
        log.info(f"daemon: target {outcome.target_id} {outcome.state} {outcome.reason or ''}".rstrip())

    def _on_store_event(self, event: EventRecord) -> None:
        """Store commits (any thread): follow the active model; wake the executor on new work."""
        if event.kind == "model.activated":
            self.active_model_id = int(event.message["model_id"])
        if event.kind in ("batch.accepted", "model.activated", "target.queued") and self.executor is not None:
            self.executor.wake()

    # ------------------------------------------------------------------------------ what it is doing

    @property
    def rsi_address(self) -> tuple[str, int] | None:
        if self.rtp is None or not self.rtp.info:
            return None
        host, port = self.rtp.info["rsi_address"]
        return str(host), int(port)

    @property
    def rsi_stats(self) -> RsiServerStats | None:
        """The RSI endpoint's counters and latency rings (mirrored from the real-time process)."""
        return None if self.rtp is None else self.rtp.rsi_stats

    def realtime_alive(self) -> bool:
        """The real-time process runs and has reported within the last second."""
        rtp = self.rtp
        if rtp is None or not rtp.alive:
            return False
        age = rtp.report_age_s()
        return age is not None and age <= 1.0

    def realtime_word(self) -> str:
        """Where and how the real-time process runs, for the operator (``loop.realtime``)."""
        if self.rtp is None:
            return "not started"
        d = self.rtp.describe()
        where = "any CPU" if d["cpu"] is None else f"CPU {d['cpu']}"
        word = f"own process (pid {d['pid']}) on {where}, {d['scheduler']} scheduling"
        if d["cpu_wakeup_latency_us"] is not None:
            word += f", CPU wake-up latency ≤ {d['cpu_wakeup_latency_us']} µs requested"
        jobs = self.settings.jobs.cpus
        if jobs:
            word += f"; job workers on CPU {', '.join(map(str, jobs))}"
        if d["notes"]:
            word += "; " + "; ".join(d["notes"])
        return word

    def target_active(self) -> bool:
        runtime = self.runtime
        busy = runtime is not None and runtime.core.state in _ACTIVE_STATES
        return busy or (self.executor is not None and self.executor.current_target_id is not None)

    # ------------------------------------------------------------------------------ operator actions

    def acknowledge_fault(self, by: str) -> dict[str, Any] | None:
        """Clear a latched fault (an operator's acknowledgement; a stop must also be cleared on the
        robot); returns the fault that was cleared, or None."""
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
        runtime.reset()
        if self.executor is not None:
            self.executor.wake()
        log.info(f"daemon: fault {cleared['kind']} acknowledged by {by}")
        return cleared

    def start_grating_calibration(self, poses_deg: Sequence[Sequence[float]] | None, by: str) -> None:
        """Start :meth:`calibrate_gratings` in the background (the HTTP route); RuntimeError if it cannot."""
        if self.runtime is None or self.motion is None:
            raise RuntimeError("the daemon has no loop or no motion port")
        if self.calibrating or (self._cal_task is not None and not self._cal_task.done()):
            raise RuntimeError("a grating calibration is already running")
        if self.target_active():
            raise RuntimeError("a target is active; calibrate between targets")
        poses = None if poses_deg is None else [tuple(float(v) for v in p) for p in poses_deg]
        self._cal_error = None
        self._cal_started_at, self._cal_finished_at = time.time(), None
        self._cal_poses = None

        def measured(done: int, total: int) -> None:
            self._cal_poses = (done, total)

        async def run() -> None:
            try:
                cal = await self.calibrate_gratings(poses, progress=measured)
                log.info(f"daemon: grating calibration v{cal.version} started by {by} is in use")
            except Exception as exc:
                self._cal_error = str(exc) or type(exc).__name__
                log.error(f"daemon: grating calibration started by {by} failed: {self._cal_error}")
                if self.store is not None:
                    await asyncio.to_thread(
                        self.store.add_event, "gratings.failed", {"error": self._cal_error, "by": by}
                    )
            finally:
                self._cal_finished_at = time.time()

        self._cal_task = asyncio.get_running_loop().create_task(run(), name="grating-calibration")

    def grating_status(self) -> dict[str, Any]:
        cal = None if self.runtime is None else self.runtime.calibration
        return {
            "calibrating": self.calibrating or (self._cal_task is not None and not self._cal_task.done()),
            "calibration": None if cal is None else cal.to_dict(),
            "last_error": self._cal_error,
            "started_at": self._cal_started_at,
            "finished_at": self._cal_finished_at,
            "poses_measured": None if self._cal_poses is None else self._cal_poses[0],
            "poses_total": None if self._cal_poses is None else self._cal_poses[1],
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
        if runtime.core.state in _ACTIVE_STATES:
            raise RuntimeError("a target is active; calibrate between targets")
        if poses is None:
            home = self.home_deg if self.home_deg is not None else runtime.last_actual_deg
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

    # ------------------------------------------------------------------------------ stop

    def stop_loop(self) -> None:
        """No new targets; zero steps and ``Stop = 1`` from the next telegram; the target is reported."""
        if self.executor is not None:
            self.executor.stop_claiming()
        if self._rsi_watch is not None:
            self._rsi_watch.cancel()  # the stop that follows is the daemon's own (daemon.stopped)
        if self._cal_task is not None and not self._cal_task.done():
            self._cal_task.cancel()  # its moves end with the robot's Stop below
        if self.runtime is not None:
            try:
                self.runtime.shutdown()
            except RtProcessError as exc:  # it has gone: it went safe on its own
                log.error(f"daemon: {exc}")

    async def stop_executor(self, task: asyncio.Task[None] | None, timeout_s: float = 10.0) -> None:
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

    async def close_rsi(self) -> None:
        """Let the controller see ``Stop = 1`` for the grace cycles, then stop listening."""
        rtp = self.rtp
        if rtp is not None:
            with contextlib.suppress(RtProcessError, TimeoutError):  # it has gone already
                await rtp.close_rsi(self.stop_grace_cycles)

    async def stop_realtime(self) -> None:
        if self.rtp is not None:
            code = await self.rtp.stop()
            log.info(f"daemon: real-time process exited with {code}")

    async def stop_sim(self) -> None:
        if self.sim is not None:
            code = await self.sim.stop()
            log.info(f"daemon: simulated cell exited with {code}")

    def final_state(self, reason: str) -> dict[str, Any]:
        """The loop's last state, as written to ``daemon-state.json`` and the store's event log."""
        runtime = self.runtime
        assert runtime is not None
        core = runtime.core
        stats = self.rsi_stats
        return {
            "time": time.time(),
            "reason": reason,
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
            "rsi": None if stats is None else stats.snapshot() | {"latency": None, "jitter": None},
        }
