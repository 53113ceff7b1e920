"""The real-time process as the daemon holds it: start, the loop's mirror, the operator's word, stop.

:class:`Realtime` starts the child (:class:`~comp_daemon.daemon.rt_process.RealtimeProcess`) with
the RSI endpoint open (the controller must find it listening before RSI_ON), then the grating
readers and the loop there (:meth:`Realtime.start_loop`, from the cell's ports), and afterwards
gives the daemon the loop's mirror (:attr:`Realtime.runtime`), the RSI counters and where and how
the process runs. At shutdown it has the loop reply ``Stop = 1`` and zero steps, closes RSI after
the grace cycles, records the loop's final state and stops the process.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

from comp_daemon.common.logs import get_logger
from comp_daemon.daemon.ports import CellPorts
from comp_daemon.daemon.rt_process import ReaderMirror, RealtimeProcess, RemoteRuntime, RtProcessError
from comp_daemon.rt.controller import JointLoopSettings
from comp_daemon.rt.encoder_reader import EncoderReaderConfig, LinearGratingCalibration
from comp_daemon.rt.grating_cal import GratingCalibration
from comp_daemon.rt.link import LoopStart, RtStart
from comp_daemon.rt.rsi_server import RsiServerConfig, RsiServerStats
from comp_daemon.rt.safety import Fault, SafetySettings, SafetyState
from comp_daemon.rt.scheduling import other_cpus, resolve_cpu
from comp_daemon.service.config import ControllerSettings, Settings

__all__ = ["ACTIVE_STATES", "Realtime", "loop_settings_from", "safety_settings_from"]

log = get_logger(__name__)

#: the loop's states while a target is armed, correcting or holding
ACTIVE_STATES = (SafetyState.ARMED, SafetyState.CORRECTING, SafetyState.SETTLED)


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


def _fault_words(f: Fault) -> dict[str, Any]:
    return {"kind": str(f.kind), "reaction": str(f.reaction), "detail": f.detail, "target_id": f.target_id}


class Realtime:
    """The real-time process and the daemon's mirror of its loop; see the module docstring.

    ``local``: the controller is on this host (the simulated cell): RSI binds and answers 127.0.0.1.
    """

    def __init__(
        self,
        settings: Settings,
        *,
        local: bool = False,
        clock_ns: Callable[[], int] = time.perf_counter_ns,
        tick_s: float = 0.05,
        stop_grace_cycles: int = 3,
    ) -> None:
        self.settings = settings
        self.local = local
        self.clock_ns = clock_ns
        self.tick_s = tick_s
        self.stop_grace_cycles = stop_grace_cycles
        self.process: RealtimeProcess | None = None
        self.runtime: RemoteRuntime | None = None
        self.readers: dict[int, ReaderMirror] = {}

    # ------------------------------------------------------------------------------ start

    async def start(self, on_lost: Callable[[str], None]) -> Settings:
        """Start the process with the RSI endpoint open; returns the settings in force from now on:
        the job workers kept off its CPU (``realtime.keep_jobs_off_cpu``, unless ``jobs.cpus`` is set)."""
        settings = self.settings
        rsi = settings.rsi
        if len(rsi.controller_allow) > 1:
            log.warning(
                f"rsi: {len(rsi.controller_allow)} controller addresses configured; "
                f"accepting {rsi.controller_allow[0]}"
            )
        rsi_config = RsiServerConfig(
            controller_host="127.0.0.1" if self.local else rsi.controller_allow[0],
            bind_host="127.0.0.1" if self.local else rsi.listen_host,
            bind_port=rsi.listen_port,
            cycle_ms=float(rsi.cycle_ms),
            sen_type=rsi.sen_type,
        )
        rt = settings.realtime
        self.process = RealtimeProcess(
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
        await self.process.start()
        rest = other_cpus(self.process.describe()["cpu"])
        if rt.keep_jobs_off_cpu and not settings.jobs.cpus and rest:
            jobs = settings.jobs.model_copy(update={"cpus": sorted(rest)})
            self.settings = settings.model_copy(update={"jobs": jobs})
        # one line: what was granted, and what was refused with the reason
        say = log.warning if self.process.describe()["notes"] else log.info
        say(f"daemon: real-time loop: {self.word()}")
        return self.settings

    async def start_loop(self, ports: CellPorts, calibration: GratingCalibration | None) -> RemoteRuntime:
        """One reader per grating port and the loop, in the real-time process."""
        assert self.process is not None, "the real-time process comes first"
        settings = self.settings
        enc, rsi = settings.encoders, settings.rsi
        reader_specs: list[tuple[EncoderReaderConfig, LinearGratingCalibration]] = []
        for joint, (port, bits) in sorted(ports.gratings.items()):
            geo = ports.geometry[joint]
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
        self.runtime = await self.process.start_loop(spec)
        self.readers = dict(self.process.readers)
        return self.runtime

    # ------------------------------------------------------------------------------ what it is doing

    @property
    def rsi_address(self) -> tuple[str, int] | None:
        if self.process is None or not self.process.info:
            return None
        host, port = self.process.info["rsi_address"]
        return str(host), int(port)

    @property
    def rsi_stats(self) -> RsiServerStats | None:
        """The RSI endpoint's counters and latency rings (mirrored from the real-time process)."""
        return None if self.process is None else self.process.rsi_stats

    def report_age_s(self) -> float | None:
        return None if self.process is None else self.process.report_age_s()

    def alive(self) -> bool:
        """The real-time process runs and has reported within the last second."""
        process = self.process
        if process is None or not process.alive:
            return False
        age = process.report_age_s()
        return age is not None and age <= 1.0

    def target_armed(self) -> bool:
        """The loop holds a target (armed, correcting or settled)."""
        return self.runtime is not None and self.runtime.core.state in ACTIVE_STATES

    def word(self) -> str:
        """Where and how the real-time process runs, for the operator (``loop.realtime``)."""
        if self.process is None:
            return "not started"
        d = self.process.describe()
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

    # ------------------------------------------------------------------------------ operator action

    def acknowledge_fault(self, by: str) -> dict[str, Any] | None:
        """Clear a latched fault (an operator's acknowledgement; a stop must also be cleared on the
        robot); returns the fault that was cleared, or None."""
        runtime = self.runtime
        if runtime is None or runtime.core.state is not SafetyState.FAULT or runtime.core.fault is None:
            return None
        cleared = _fault_words(runtime.core.fault)
        runtime.reset()
        log.info(f"daemon: fault {cleared['kind']} acknowledged by {by}")
        return cleared

    # ------------------------------------------------------------------------------ stop

    def shutdown_loop(self) -> None:
        """Zero steps and ``Stop = 1`` from the next telegram (the active target is reported)."""
        if self.runtime is not None:
            try:
                self.runtime.shutdown()
            except RtProcessError as exc:  # it has gone: it went safe on its own
                log.error(f"daemon: {exc}")

    async def close_rsi(self) -> None:
        """Let the controller see ``Stop = 1`` for the grace cycles, then stop listening."""
        if self.process is not None:
            with contextlib.suppress(RtProcessError, TimeoutError):  # it has gone already
                await self.process.close_rsi(self.stop_grace_cycles)

    async def stop(self) -> None:
        if self.process is not None:
            code = await self.process.stop()
            log.info(f"daemon: real-time process exited with {code}")

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
            "faults": [_fault_words(f) for f in runtime.fault_log],
            "rsi": None if stats is None else stats.snapshot() | {"latency": None, "jitter": None},
        }
