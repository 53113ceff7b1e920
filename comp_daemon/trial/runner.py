"""Seed 000's experiment, end to end, through the running daemon (``comp-daemon trial``).

Phases (seed 000 §3; the numbers are those of the full trial, :data:`comp_daemon.trial.plan.FULL`):

1. **Grating calibration** (seed 000 step 1): ``POST /api/gratings/calibrate``, followed on
   ``GET /api/gratings``.
2. **ISO 9283 without feedback**: the robot program alone moves start point → test point, three
   test points × 3 directions × 30 cycles (after a warm-up cycle), 100 mm moves; the tracker
   measures each arrival after a dwell.
3. **Sampling, open loop**: the robot program visits the 100 sampling points; tracker.
4. **Targets, uncompensated**: the 104 target points at their nominal axis values; tracker.
   Phases 3 + 4 are uploaded as one data set (sampling rows ``fit``, target rows ``check``) and the
   kinematic model (and, in the quick trial, the Chebyshev model) is fitted over HTTP.
5. **Targets, kinematic calibration**: the kinematic model's artifact is fetched over HTTP, kept
   in the working directory (``models/model-ID.json``) and loaded from there as ``comp-daemon
   compensate`` loads a model file; the targets are compensated with it offline (seed 000's
   baseline); the robot program runs the compensated commands; tracker.
6. **ISO 9283 with feedback**: the nominal model is activated; each test point is a target of the
   daemon (start point by the robot program), measured once the daemon reports it settled.
7. **Sampling with feedback** (full trial): the 100 sampling points as targets of the daemon with
   the nominal model: the joint loop holds joints 1–3 at their commanded angles while the tracker
   measures ("the closed-loop feedback … ensure[s] the error sampling accuracy", seed 000 §4).
8. **Targets, feedback only** (full trial): the target points at their nominal axis values through
   the loop. Phases 7 + 8 are the closed-loop data set; the Chebyshev model of the trial's order
   (3, seed 000) and the kinematic model are fitted on it over HTTP.
9. **Targets, Chebyshev + feedback** (seed 000's method): the Chebyshev model is activated and the
   target points are posted as the nominal program's axis values; the daemon compensates, moves,
   closes the loop; tracker.
10. **Targets, Chebyshev (seed 000 mapping) + feedback**: the same model, its compensation mapped
    onto joints 1–3 as seed 000 §2.2 does (the wrist from the nominal inverse kinematics) instead of
    the daemon's six-axis inverse kinematics; the trial compensates the targets with the model's
    artifact and posts the commands under the nominal model (:meth:`_Trial.seed000_run`), so the
    two rows differ only in the mapping. ``TrialSizes.seed000_mapping`` turns the row off.
11. **Targets, kinematic + feedback** (full trial): the same as 9 with the closed-loop kinematic model.

Every run over the target points starts from the scenario's home pose, so the routes (and the
approach directions) are the same. All runs by the robot program alone come before the first target
of the daemon: ``RSI_ON(#RELATIVE)`` corrections stay applied after a target (docs/daemon.md), so a
robot-program run after a closed-loop one would carry its last correction.

The trial talks to the daemon only over HTTP (a bearer token), to the robot only through its program's
motion port, and measures only with the tracker (:mod:`comp_daemon.trial.cell`).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.models.base import ErrorModel
from comp_daemon.models.compensation import CompensationRefused, JointMapping, compensate
from comp_daemon.rt.grating_cal import default_calibration_poses
from comp_daemon.sim.scenario import load_scenario
from comp_daemon.trial.cell import CellError, CellSettings, TrialCell, environment
from comp_daemon.trial.compare import ComparisonData, compare_models
from comp_daemon.trial.plan import PlannedPoints, TrialPlan, TrialSizes, plan_trial
from comp_daemon.trial.result import PointRun, TrialResult
from comp_daemon.trial.session import Progress, ProgressEvent, TrialError, TrialSession
from comp_daemon.trial.stats import iso9283_statistics

__all__ = ["COMPARISON_PHASE", "ProgressEvent", "TrialError", "run_trial", "trial_phases", "with_sizes"]


class _Trial(TrialSession):
    """The phases of the trial (module docstring) on a :class:`TrialSession`."""

    async def open_run(self, run: PointRun, commands: NDArray[np.float64]) -> PointRun:
        """The robot program over the points (from home), the tracker at each."""
        t0 = time.monotonic()
        await self.cell.move(self.points.home_deg)
        for i, a in enumerate(commands):
            await self.cell.move(a)
            run.commanded_deg[i] = a
            run.measured_mm[i] = await self.settle_and_measure()
            run.grating_deg[i] = await self.gratings_now()
            run.state[i] = "open"
            if i % 4 == 3 or i == len(commands) - 1:
                self.tell(i + 1, len(commands), self.running_note(run))
        run.duration_s = time.monotonic() - t0
        return run

    async def loop_run(
        self, run: PointRun, pts: PlannedPoints, commands: NDArray[np.float64] | None = None
    ) -> PointRun:
        """The points as targets of the daemon, the tracker at each: the nominal program's axis
        values, or ``commands`` (n, 6) where given (a row that is nan is not run: it failed already)."""
        t0 = time.monotonic()
        await self.cell.move(self.points.home_deg)
        for i, a in enumerate(pts.a_nominal_deg if commands is None else commands):
            if not np.all(np.isfinite(a)):
                continue
            doc, retried = await self.target(a, f"{pts.name[0]}{i + 1:03d}")
            run.retried += [{"index": i, "reason": why} for why in retried]
            run.state[i] = doc["state"]
            run.reason[i] = doc.get("reason")
            if doc.get("commanded_axes_deg"):
                run.commanded_deg[i] = doc["commanded_axes_deg"]
            if doc["state"] == "done":
                run.measured_mm[i] = await self.cell.measure_mm()
                errors = doc.get("final_joint_errors_deg") or {}
                for j in range(3):
                    e = errors.get(f"A{j + 1}")
                    if e is not None and np.isfinite(run.commanded_deg[i, j]):
                        run.grating_deg[i, j] = run.commanded_deg[i, j] + float(e)
            if i % 2 == 1 or i == pts.n - 1:
                failed = sum(s != "done" for s in run.state[: i + 1])
                note = self.running_note(run) + (f"; {failed} failed" if failed else "")
                self.tell(i + 1, pts.n, note)
        run.duration_s = time.monotonic() - t0
        return run

    async def iso(self, feedback: bool) -> None:
        iso = self.points.iso
        s = self.sizes
        p_n = len(iso.points_mm)
        positions = np.full((p_n, 3, s.iso_cycles, 3), np.nan)
        total = p_n * s.iso_cycles * 3
        count = 0
        failed: list[str] = []
        retried: list[str] = []
        for p in range(p_n):
            for cycle in range(-s.iso_warmup_cycles, s.iso_cycles):
                for d in range(3):
                    await self.cell.move(iso.a_start_deg[p, d])
                    if feedback:
                        doc, again = await self.target(iso.a_point_deg[p], f"P{p + 1}-{'xyz'[d]}")
                        retried += [f"P{p + 1} {'xyz'[d]} cycle {cycle}: {why}" for why in again]
                        if doc["state"] != "done":
                            failed.append(f"P{p + 1} {'xyz'[d]} cycle {cycle}: {doc.get('reason')}")
                            continue
                        m = await self.cell.measure_mm()
                    else:
                        await self.cell.move(iso.a_point_deg[p])
                        m = await self.settle_and_measure()
                    if cycle >= 0:
                        positions[p, d, cycle] = m
                        count += 1
                        if count % 3 == 0:
                            self.tell(count, total)
        key = "with" if feedback else "without"
        entry: dict[str, Any] = {
            "positions_mm": positions.round(9).tolist(),
            "failed": failed,
            "retried": retried,
        }
        if np.all(np.isfinite(positions)):
            entry["stats"] = iso9283_statistics(positions)
        self.result.iso.setdefault("runs", {})[key] = entry

    # ------------------------------------------------------------------------------ the phases
    # Each phase fills its part of the result and returns the note its progress line ends with.

    async def calibrate_gratings(self) -> str:
        """Phase 1: the daemon's grating calibration (on the trial's poses when their count is not the
        daemon's own 6), followed until it ends."""
        s = self.sizes
        body = None
        if s.calibration_poses != 6:  # 6: the daemon's own poses
            robot, cell = self.scenario.robot, self.scenario.cell
            poses = default_calibration_poses(
                list(self.points.home_deg), cell.grating_joints, robot.axis_limits_deg, n=s.calibration_poses
            )
            body = {"poses": [list(p) for p in poses]}
        await self.cell.api("POST", "/api/gratings/calibrate", json=body)
        while (status := await self.cell.api("GET", "/api/gratings"))["calibrating"]:
            self.tell(0, 0, f"{time.monotonic() - self.phase_t0:.0f} s")
            await asyncio.sleep(0.25)
        if status["last_error"] or status["calibration"] is None:
            raise TrialError(f"the grating calibration failed: {status['last_error']}")
        self.result.gratings = status["calibration"]
        joints = self.result.gratings["joints"] if self.result.gratings else []
        return ", ".join(f"A{m['joint']} residual rms {m['residual_rms_deg']:.4f}°" for m in joints)

    async def iso_alone(self) -> str:
        """Phase 2: the ISO 9283 points by the robot program, with the set-up they are measured in."""
        iso, s = self.points.iso, self.sizes
        self.result.iso.update(
            {
                "points_mm": iso.points_mm.tolist(),
                "starts_mm": iso.starts_mm.tolist(),
                "abc_deg": iso.abc_deg.tolist(),
                "approach_mm": s.approach_mm,
                "cycles": s.iso_cycles,
                "warmup_cycles": s.iso_warmup_cycles,
                "repeatability_rated_mm": float(self.scenario.robot.repeatability_mm),
            }
        )
        await self.iso(feedback=False)
        return self._iso_note("without")

    async def sampling_alone(self) -> str:
        """Phase 3: the sampling points at their nominal axis values by the robot program."""
        sp = self.points.sampling
        self.result.sampling["open"] = await self.open_run(
            PointRun.empty(
                "sampling-open", "sampling, robot alone", "sampling", sp.wanted_mm, feedback=False
            ),
            sp.a_nominal_deg,
        )
        return ""

    async def targets_uncompensated(self) -> str:
        """Phase 4: the target points at their nominal axis values by the robot program."""
        tg = self.points.targets
        run = PointRun.empty("uncompensated", "uncompensated", "targets", tg.wanted_mm, feedback=False)
        self.result.runs["uncompensated"] = await self.open_run(run, tg.a_nominal_deg)
        return self.running_note(run)

    async def open_loop_fits(self) -> str:
        """Phases 3 + 4 as one data set; the nominal and kinematic models on it, and the Chebyshev
        model on its gratings' joint values when the loop does not sample."""
        r, sp, tg = self.result, self.points.sampling, self.points.targets
        runs = [(r.sampling["open"], sp, "fit"), (r.runs["uncompensated"], tg, "check")]
        open_id = await self.upload("trial-open-loop", runs)
        await self.fit("nominal", open_id, "nominal")
        await self.fit("kinematic", open_id, "kinematic")
        if (
            not self.sizes.loop_sampling
        ):  # the Chebyshev model in the loop's convention: A1..A3 from the gratings
            grat_id = await self.upload("trial-open-loop-gratings", runs, joints_from_gratings=True)
            await self.fit("chebyshev", grat_id, "chebyshev", self.sizes.chebyshev_order)
        return f"data set {open_id}; models {', '.join(str(m['id']) for m in r.models.values())}"

    async def targets_kinematic(self) -> str:
        """Phase 5: the target points compensated offline by the kinematic model's artifact, run by
        the robot program."""
        tg = self.points.targets
        kinematic_id = self.result.models["kinematic"]["id"]
        model = await self.fetch_model(kinematic_id)
        comp = compensate(
            model,
            tg.wanted_mm,
            tg.wanted_R,
            a_seed_deg=tg.a_nominal_deg,
            dir=tg.dir,
            payload_kg=self.plan.payload_kg,
            tol_mm=1e-6,
        )
        if not comp.converged:
            raise TrialError("the kinematic compensation of the target points did not converge")
        run = PointRun.empty(
            "kinematic",
            "kinematic calibration",
            "targets",
            tg.wanted_mm,
            feedback=False,
            model="kinematic",
            model_id=kinematic_id,
        )
        self.result.runs["kinematic"] = await self.open_run(run, comp.a_deg)
        return self.running_note(run)

    async def iso_with_feedback(self) -> str:
        """Phase 6: the ISO 9283 points as targets of the daemon under the nominal model."""
        await self.activate(self.result.models["nominal"]["id"])
        await self.iso(feedback=True)
        return self._iso_note("with")

    async def sampling_with_feedback(self) -> str:
        """Phase 7: the sampling points as targets of the daemon under the nominal model (already active)."""
        sp, nominal_id = self.points.sampling, self.result.models["nominal"]["id"]
        run = PointRun.empty(
            "sampling-closed",
            "sampling, joint feedback",
            "sampling",
            sp.wanted_mm,
            feedback=True,
            model="nominal",
            model_id=nominal_id,
        )
        self.result.sampling["closed"] = await self.loop_run(run, sp)
        return ""

    async def targets_feedback_only(self) -> str:
        """Phase 8: the target points through the loop under the nominal model (already active)."""
        return await self.targets_in_loop(
            "feedback", "joint feedback only", "nominal", "nominal", activate=False
        )

    async def closed_loop_fits(self) -> str:
        """Phases 7 + 8 as one data set; the Chebyshev and kinematic models on it."""
        r, sp, tg = self.result, self.points.sampling, self.points.targets
        runs = [(r.sampling["closed"], sp, "fit"), (r.runs["feedback"], tg, "check")]
        closed_id = await self.upload("trial-closed-loop", runs)
        await self.fit("chebyshev", closed_id, "chebyshev", self.sizes.chebyshev_order)
        await self.fit("kinematic (closed-loop data)", closed_id, "kinematic")
        return f"data set {closed_id}"

    async def targets_chebyshev(self) -> str:
        """Phase 9: seed 000's method, the Chebyshev model in the daemon with the joint loop."""
        order = self.sizes.chebyshev_order
        label = f"Chebyshev m={order} + joint feedback"
        return await self.targets_in_loop("chebyshev+feedback", label, f"chebyshev m={order}", "chebyshev")

    async def targets_chebyshev_seed000(self) -> str:
        """Phase 10: the same model with seed 000's joint mapping (:meth:`seed000_run`)."""
        models = self.result.models
        run = await self.seed000_run(models["chebyshev"]["id"], models["nominal"]["id"])
        self.result.runs["chebyshev-seed000+feedback"] = run
        return self.running_note(run)

    async def targets_kinematic_in_loop(self) -> str:
        """Phase 11: the closed-loop kinematic model in the daemon with the joint loop."""
        label = "kinematic + joint feedback"
        return await self.targets_in_loop(
            "kinematic+feedback", label, "kinematic", "kinematic (closed-loop data)"
        )

    async def targets_in_loop(
        self, key: str, label: str, model: str, fitted: str, *, activate: bool = True
    ) -> str:
        """The target points through the loop under the model fitted as ``fitted`` (activated first
        unless it is active already), kept as run ``key``."""
        tg, model_id = self.points.targets, self.result.models[fitted]["id"]
        if activate:
            await self.activate(model_id)
        run = PointRun.empty(
            key, label, "targets", tg.wanted_mm, feedback=True, model=model, model_id=model_id
        )
        self.result.runs[key] = await self.loop_run(run, tg)
        return self.running_note(run)

    def record_loop(self, status: dict[str, Any], controller: dict[str, Any]) -> None:
        """The daemon's loop counters and the robot controller's, as the trial ends."""
        kept = ("state", "stop_reason", "telegrams_sent", "replies_ok", "late_total", "overruns")
        self.result.loop = {
            "daemon": status["daemon"]["loop"],
            "controller": {k: v for k, v in controller.items() if k in kept},
            "targets": status.get("targets"),
        }

    async def run(self) -> None:
        """Every phase of :func:`trial_phases` in order, then the loop's counters."""
        for name, phase in trial_phases(self.sizes):
            self.begin(name)
            self.end(await phase(self))
        status = await self.cell.api("GET", "/api/status")
        self.record_loop(status, await self.cell.controller_status())

    async def seed000_run(self, model_id: int, nominal_id: int) -> PointRun:
        """The Chebyshev targets with seed 000's joint mapping (:mod:`comp_daemon.models.compensation`,
        ``mapping="three-axis"``): the model's artifact, fetched over HTTP, compensates the targets as the
        daemon would (seeded from the nominal axis values, the approach directions of the joints
        without gratings, the default limits), and the compensated commands go to the daemon as
        targets under the nominal model, which gives axis values back unchanged: the joint loop holds
        joints 1–3 at the mapped angles. A target the limits refuse is a failed target of the run."""
        tg = self.points.targets
        model = await self.fetch_model(model_id)
        direction = tg.dir.copy()
        direction[:, [j - 1 for j in self.scenario.cell.grating_joints]] = 0.0
        commands, reasons = await asyncio.to_thread(
            compensate_each, model, tg, direction, self.plan.payload_kg, "three-axis"
        )
        order = self.sizes.chebyshev_order
        run = PointRun.empty(
            "chebyshev-seed000+feedback",
            f"Chebyshev m={order} (seed 000 mapping) + joint feedback",
            "targets",
            tg.wanted_mm,
            feedback=True,
            model=f"chebyshev m={order}, seed 000 mapping",
            model_id=model_id,
        )
        for i, why in reasons.items():
            run.state[i] = "failed"
            run.reason[i] = f"compensation: {why}"
        await self.activate(nominal_id)
        return await self.loop_run(run, tg, commands)

    def _iso_note(self, key: str) -> str:
        stats = self.result.iso.get("runs", {}).get(key, {}).get("stats")
        if not stats:
            return ""
        return "vAP " + ", ".join(f"{v:.3f}" for v in stats["vap_mm"]) + " mm"

    def comparison(self) -> None:
        """Seed 001's comparison on the open-loop (and closed-loop) data, after the cell is down."""
        r, pts, s = self.result, self.points, self.sizes
        self.begin(COMPARISON_PHASE)
        sets = [
            ("open", r.sampling.get("open"), r.runs.get("uncompensated"), False),
            ("open-gratings", r.sampling.get("open"), r.runs.get("uncompensated"), True),
        ]
        if "closed" in r.sampling:
            sets.append(("closed", r.sampling.get("closed"), r.runs.get("feedback"), False))
        for key, fit_run, check_run, from_gratings in sets:
            if fit_run is None or check_run is None:
                continue
            fo, co = fit_run.ok, check_run.ok
            a_fit, a_check = fit_run.commanded_deg.copy(), check_run.commanded_deg.copy()
            if from_gratings:
                fo = fo & np.all(np.isfinite(fit_run.grating_deg), axis=1)
                co = co & np.all(np.isfinite(check_run.grating_deg), axis=1)
                a_fit[:, :3], a_check[:, :3] = fit_run.grating_deg, check_run.grating_deg
            data = ComparisonData(
                a_fit_deg=a_fit[fo],
                p_fit_mm=fit_run.measured_mm[fo],
                dir_fit=pts.sampling.dir[fo],
                a_check_deg=a_check[co],
                p_check_mm=check_run.measured_mm[co],
                dir_check=pts.targets.dir[co],
                payload_kg=self.plan.payload_kg,
            )
            r.comparison[key] = compare_models(
                self.scenario.robot,
                data,
                chebyshev_order=s.chebyshev_order,
                cross_validate=s.loop_sampling,
            )
            self.tell(len(r.comparison), len(sets))
        self.end()


COMPARISON_PHASE = "seed 001 model comparison"

#: A phase's step: it runs on the trial and returns the note its progress line ends with.
PhaseStep = Callable[[_Trial], Awaitable[str]]


def trial_phases(s: TrialSizes) -> list[tuple[str, PhaseStep]]:
    """The phases the trial runs with sizes ``s`` (module docstring), by name, in order; the model
    comparison (:data:`COMPARISON_PHASE`) follows them once the cell is down."""
    order = s.chebyshev_order
    phases: list[tuple[str, PhaseStep]] = [
        ("grating calibration", _Trial.calibrate_gratings),
        ("ISO 9283, robot alone", _Trial.iso_alone),
        ("sampling points, robot alone", _Trial.sampling_alone),
        ("target points, uncompensated", _Trial.targets_uncompensated),
        ("fits on the open-loop data (HTTP)", _Trial.open_loop_fits),
        ("target points, kinematic calibration", _Trial.targets_kinematic),
        ("ISO 9283, with joint feedback", _Trial.iso_with_feedback),
    ]
    if s.loop_sampling:
        phases += [
            ("sampling points, with joint feedback", _Trial.sampling_with_feedback),
            ("target points, joint feedback only", _Trial.targets_feedback_only),
            ("fits on the closed-loop data (HTTP)", _Trial.closed_loop_fits),
        ]
    phases.append((f"target points, Chebyshev m={order} + joint feedback", _Trial.targets_chebyshev))
    if s.seed000_mapping:
        name = f"target points, Chebyshev m={order} (seed 000 mapping) + joint feedback"
        phases.append((name, _Trial.targets_chebyshev_seed000))
    if s.loop_sampling and s.kinematic_with_loop:
        phases.append(("target points, kinematic + joint feedback", _Trial.targets_kinematic_in_loop))
    return phases


async def run_trial(
    plan: TrialPlan,
    workdir: Path,
    *,
    progress: Progress | None = None,
    cell_settings: CellSettings | None = None,
) -> TrialResult:
    """Run the trial (module docstring) in ``workdir`` (daemon data, logs); returns its result.

    A failure mid-way raises :class:`TrialError` with the partial result as ``exc.result``.
    """
    scenario = load_scenario(plan.scenario)
    points = plan_trial(scenario, plan)
    result = TrialResult(
        plan=plan.to_dict(),
        started_at=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        environment=environment(),
    )
    t0 = time.monotonic()
    cell = TrialCell(scenario, workdir, seed=plan.seed, payload_kg=plan.payload_kg, settings=cell_settings)
    names = [name for name, _ in trial_phases(plan.sizes)] + [COMPARISON_PHASE]
    trial = _Trial(scenario, plan, points, cell, result, names, progress or (lambda e: None))
    try:
        try:
            await cell.start()
            await trial.run()
        finally:
            await cell.close()
        result.loop["daemon_exit_code"] = cell.daemon_exit_code
        await asyncio.to_thread(trial.comparison)
        result.complete = True
    except TrialError as exc:
        result.error = str(exc)
        exc.result = result
        raise
    except CellError as exc:
        result.error = str(exc)
        raise TrialError(str(exc), result) from exc
    finally:
        result.duration_s = time.monotonic() - t0
    return result


def compensate_each(
    model: ErrorModel,
    pts: PlannedPoints,
    direction: NDArray[np.float64],
    payload_kg: float,
    mapping: JointMapping,
) -> tuple[NDArray[np.float64], dict[int, str]]:
    """Compensated commands (n, 6) of the points by ``model`` with ``mapping`` and the default
    limits; the rows the limits refuse are nan, with their reasons by index."""
    reasons: dict[int, str] = {}
    keep = np.arange(pts.n)
    while True:
        try:
            comp = compensate(
                model,
                pts.wanted_mm[keep],
                pts.wanted_R[keep],
                a_seed_deg=pts.a_nominal_deg[keep],
                dir=direction[keep],
                payload_kg=payload_kg,
                tol_mm=1e-6,
                mapping=mapping,
            )
        except CompensationRefused as exc:
            for refusal in exc.refusals:
                reasons[int(keep[refusal.index])] = refusal.reason
            keep = np.array([i for i in keep if int(i) not in reasons], dtype=int)
            if keep.size:
                continue
            return np.full((pts.n, 6), np.nan), reasons
        if not comp.converged:
            raise TrialError(f"the {mapping} compensation of the target points did not converge")
        commands = np.full((pts.n, 6), np.nan)
        commands[keep] = comp.a_deg
        return commands, reasons


def with_sizes(plan: TrialPlan, **changes: Any) -> TrialPlan:
    """``plan`` with some of its sizes replaced."""
    return replace(plan, sizes=replace(plan.sizes, **changes))
