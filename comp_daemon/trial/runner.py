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
from comp_daemon.trial.plan import PlannedPoints, TrialPlan, plan_trial
from comp_daemon.trial.result import PointRun, TrialResult
from comp_daemon.trial.session import Progress, ProgressEvent, TrialError, TrialSession
from comp_daemon.trial.stats import iso9283_statistics

__all__ = ["ProgressEvent", "TrialError", "run_trial", "with_sizes"]


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

    # ------------------------------------------------------------------------------ the trial

    async def run(self) -> None:
        r = self.result
        s = self.sizes
        pts = self.points
        tg = pts.targets
        order = s.chebyshev_order

        self.begin("grating calibration")
        body = None
        if s.calibration_poses != 6:  # 6: the daemon's own poses
            poses = default_calibration_poses(
                list(pts.home_deg), self.scenario.cell.grating_joints, self.scenario.robot.axis_limits_deg,
                n=s.calibration_poses,
            )  # fmt: skip
            body = {"poses": [list(p) for p in poses]}
        await self.cell.api("POST", "/api/gratings/calibrate", json=body)
        while (status := await self.cell.api("GET", "/api/gratings"))["calibrating"]:
            self.tell(0, 0, f"{time.monotonic() - self.phase_t0:.0f} s")
            await asyncio.sleep(0.25)
        if status["last_error"] or status["calibration"] is None:
            raise TrialError(f"the grating calibration failed: {status['last_error']}")
        r.gratings = status["calibration"]
        joints = r.gratings["joints"] if r.gratings else []
        self.end(", ".join(f"A{m['joint']} residual rms {m['residual_rms_deg']:.4f}°" for m in joints))

        self.begin("ISO 9283, robot alone")
        r.iso.update(
            {
                "points_mm": pts.iso.points_mm.tolist(),
                "starts_mm": pts.iso.starts_mm.tolist(),
                "abc_deg": pts.iso.abc_deg.tolist(),
                "approach_mm": s.approach_mm,
                "cycles": s.iso_cycles,
                "warmup_cycles": s.iso_warmup_cycles,
                "repeatability_rated_mm": float(self.scenario.robot.repeatability_mm),
            }
        )
        await self.iso(feedback=False)
        self.end(self._iso_note("without"))

        self.begin("sampling points, robot alone")
        sp = pts.sampling
        r.sampling["open"] = await self.open_run(
            PointRun.empty(
                "sampling-open", "sampling, robot alone", "sampling", sp.wanted_mm, feedback=False
            ),
            sp.a_nominal_deg,
        )
        self.end()

        self.begin("target points, uncompensated")
        r.runs["uncompensated"] = await self.open_run(
            PointRun.empty("uncompensated", "uncompensated", "targets", tg.wanted_mm, feedback=False),
            tg.a_nominal_deg,
        )
        self.end(self.running_note(r.runs["uncompensated"]))

        self.begin("fits on the open-loop data (HTTP)")
        open_id = await self.upload(
            "trial-open-loop", [(r.sampling["open"], sp, "fit"), (r.runs["uncompensated"], tg, "check")]
        )
        nominal = await self.fit("nominal", open_id, "nominal")
        kinematic = await self.fit("kinematic", open_id, "kinematic")
        if not s.loop_sampling:  # the Chebyshev model in the loop's convention: A1..A3 from the gratings
            runs = [(r.sampling["open"], sp, "fit"), (r.runs["uncompensated"], tg, "check")]
            grat_id = await self.upload("trial-open-loop-gratings", runs, joints_from_gratings=True)
            await self.fit("chebyshev", grat_id, "chebyshev", order)
        self.end(f"data set {open_id}; models {', '.join(str(m['id']) for m in r.models.values())}")

        self.begin("target points, kinematic calibration")
        model = await self.fetch_model(kinematic["id"])
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
        r.runs["kinematic"] = await self.open_run(
            PointRun.empty(
                "kinematic",
                "kinematic calibration",
                "targets",
                tg.wanted_mm,
                feedback=False,
                model="kinematic",
                model_id=kinematic["id"],
            ),
            comp.a_deg,
        )
        self.end(self.running_note(r.runs["kinematic"]))

        self.begin("ISO 9283, with joint feedback")
        await self.activate(nominal["id"])
        await self.iso(feedback=True)
        self.end(self._iso_note("with"))

        if s.loop_sampling:
            self.begin("sampling points, with joint feedback")
            r.sampling["closed"] = await self.loop_run(
                PointRun.empty(
                    "sampling-closed",
                    "sampling, joint feedback",
                    "sampling",
                    sp.wanted_mm,
                    feedback=True,
                    model="nominal",
                    model_id=nominal["id"],
                ),
                sp,
            )
            self.end()
            self.begin("target points, joint feedback only")
            r.runs["feedback"] = await self.loop_run(
                PointRun.empty(
                    "feedback",
                    "joint feedback only",
                    "targets",
                    tg.wanted_mm,
                    feedback=True,
                    model="nominal",
                    model_id=nominal["id"],
                ),
                tg,
            )
            self.end(self.running_note(r.runs["feedback"]))
            self.begin("fits on the closed-loop data (HTTP)")
            closed_id = await self.upload(
                "trial-closed-loop", [(r.sampling["closed"], sp, "fit"), (r.runs["feedback"], tg, "check")]
            )
            await self.fit("chebyshev", closed_id, "chebyshev", order)
            await self.fit("kinematic (closed-loop data)", closed_id, "kinematic")
            self.end(f"data set {closed_id}")

        cheb = r.models["chebyshev"]
        self.begin(f"target points, Chebyshev m={order} + joint feedback")
        await self.activate(cheb["id"])
        r.runs["chebyshev+feedback"] = await self.loop_run(
            PointRun.empty(
                "chebyshev+feedback",
                f"Chebyshev m={order} + joint feedback",
                "targets",
                tg.wanted_mm,
                feedback=True,
                model=f"chebyshev m={order}",
                model_id=cheb["id"],
            ),
            tg,
        )
        self.end(self.running_note(r.runs["chebyshev+feedback"]))

        if s.seed000_mapping:
            self.begin(f"target points, Chebyshev m={order} (seed 000 mapping) + joint feedback")
            r.runs["chebyshev-seed000+feedback"] = await self.seed000_run(cheb["id"], nominal["id"])
            self.end(self.running_note(r.runs["chebyshev-seed000+feedback"]))

        if s.loop_sampling and s.kinematic_with_loop:
            kin_loop = r.models["kinematic (closed-loop data)"]
            self.begin("target points, kinematic + joint feedback")
            await self.activate(kin_loop["id"])
            r.runs["kinematic+feedback"] = await self.loop_run(
                PointRun.empty(
                    "kinematic+feedback",
                    "kinematic + joint feedback",
                    "targets",
                    tg.wanted_mm,
                    feedback=True,
                    model="kinematic",
                    model_id=kin_loop["id"],
                ),
                tg,
            )
            self.end(self.running_note(r.runs["kinematic+feedback"]))

        status = await self.cell.api("GET", "/api/status")
        r.loop = {
            "daemon": status["daemon"]["loop"],
            "controller": {
                k: v
                for k, v in (await self.cell.controller_status()).items()
                if k in ("state", "stop_reason", "telegrams_sent", "replies_ok", "late_total", "overruns")
            },
            "targets": status.get("targets"),
        }

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
        self.begin("seed 001 model comparison")
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
    trial = _Trial(scenario, plan, points, cell, result, progress or (lambda e: None))
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
