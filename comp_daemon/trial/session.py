"""One trial against the running cell: progress by phase, and the operations every phase uses.

:class:`TrialSession` holds the scenario, the plan and its points, the cell (:mod:`comp_daemon.trial.cell`)
and the result being filled, and offers what the phases (:mod:`comp_daemon.trial.runner`) are made
of: tracker readings after a dwell, the gratings as the daemon reports them, targets of the daemon
(posted again when they failed for a reason of the machine), fit jobs, model artifacts, model
activation and data set uploads — all over the daemon's HTTP API, the robot program's motion port
and the tracker.
"""

from __future__ import annotations

import asyncio
import secrets
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.common.atomic import write_json_atomic
from comp_daemon.data.dataset import Dataset, dataset_to_csv
from comp_daemon.models.artifact import ModelArtifactError, load_model
from comp_daemon.models.base import ErrorModel
from comp_daemon.sim.scenario import Scenario
from comp_daemon.trial.cell import TrialCell
from comp_daemon.trial.plan import PlannedPoints, TrialPlan, TrialPoints
from comp_daemon.trial.result import PointRun, TrialResult

__all__ = ["FINAL_STATES", "RETRIES", "TRANSIENT", "Progress", "ProgressEvent", "TrialError", "TrialSession"]

FINAL_STATES = ("done", "failed", "cancelled", "interrupted")
#: target failures that say the computer was busy (docs/daemon.md, Safety): such a target is posted again
TRANSIENT = ("feedback_stale", "rsi_lost")
RETRIES = 2


class TrialError(RuntimeError):
    """The trial could not go on; the message says where and why. ``result``: what was measured."""

    def __init__(self, message: str, result: TrialResult | None = None) -> None:
        super().__init__(message)
        self.result = result


@dataclass(frozen=True, slots=True)
class ProgressEvent:
    step: int  # 1-based phase number
    steps: int
    phase: str
    done: int  # units done in this phase
    total: int  # 0: no countable units
    note: str = ""
    finished: bool = False


Progress = Callable[[ProgressEvent], None]


class TrialSession:
    """The state of one trial and the operations of its phases (module docstring)."""

    def __init__(
        self,
        scenario: Scenario,
        plan: TrialPlan,
        points: TrialPoints,
        cell: TrialCell,
        result: TrialResult,
        names: Sequence[str],
        progress: Progress,
    ) -> None:
        self.scenario = scenario
        self.plan = plan
        self.sizes = plan.sizes
        self.points = points
        self.cell = cell
        self.result = result
        self.progress = progress
        self.names = list(names)  # the phases, in order: progress counts by them
        self.step = 0
        self.t0 = time.monotonic()
        self.phase_t0 = self.t0
        self.key_prefix = f"trial-{secrets.token_hex(4)}"
        self.target_counter = 0

    # ------------------------------------------------------------------------------ progress

    def begin(self, name: str) -> None:
        self.step = self.names.index(name) + 1
        self.phase = name
        self.phase_t0 = time.monotonic()
        self.tell(0, 0)

    def tell(self, done: int, total: int, note: str = "") -> None:
        self.progress(ProgressEvent(self.step, len(self.names), self.phase, done, total, note))

    def end(self, note: str = "") -> None:
        dt = time.monotonic() - self.phase_t0
        self.result.phases.append({"name": self.phase, "duration_s": round(dt, 1)})
        self.progress(ProgressEvent(self.step, len(self.names), self.phase, 0, 0, note, finished=True))

    @staticmethod
    def running_note(run: PointRun) -> str:
        err = run.errors_mm()
        if len(err) == 0:
            return ""
        d = np.linalg.norm(err, axis=1)
        return f"3-D error so far: mean {d.mean():.3f}, max {d.max():.3f} mm"

    # ------------------------------------------------------------------------------ primitives

    async def settle_and_measure(self) -> NDArray[np.float64]:
        if self.sizes.dwell_s > 0.0:
            await asyncio.sleep(self.sizes.dwell_s)
        return await self.cell.measure_mm()

    async def gratings_now(self, wait_s: float = 2.0, every_s: float = 0.05) -> NDArray[np.float64]:
        """A1..A3 as the daemon's gratings read them now (NaN where it has none). The robot stands
        still here, so a reading that is stale for a moment (a busy computer) is asked for again for
        up to ``wait_s`` before the point goes without it."""
        deadline = time.monotonic() + wait_s
        # /api/status is a snapshot (built every http.status_interval_s): the first answer may have
        # been built before the robot came to stand; one built after it was served is not
        first = (await self.cell.api("GET", "/api/status"))["built_at"]
        while True:
            status = await self.cell.api("GET", "/api/status")
            if status["built_at"] <= first and time.monotonic() < deadline:
                await asyncio.sleep(every_s)
                continue
            out = np.full(3, np.nan)
            for joint in status["daemon"]["joints"]:
                j, g = int(joint["joint"]), joint.get("grating_deg")
                if j <= 3 and g is not None:
                    out[j - 1] = float(g)
            if np.all(np.isfinite(out)) or time.monotonic() >= deadline:
                return out
            await asyncio.sleep(every_s)

    async def target(self, axes_deg: NDArray[np.float64], pose_id: str) -> tuple[dict[str, Any], list[str]]:
        """A target of the daemon, posted again (up to :data:`RETRIES` times) when it failed for a
        reason of the machine rather than of the method (:data:`TRANSIENT`: a grating reading or
        the RSI telegrams late on a busy computer); returns the last target and the reasons retried."""
        retried: list[str] = []
        while True:
            doc = await self._target_once(axes_deg, pose_id)
            reason = str(doc.get("reason") or "")
            if doc["state"] != "failed" or not reason.startswith(TRANSIENT) or len(retried) >= RETRIES:
                return doc, retried
            retried.append(reason)

    async def _target_once(self, axes_deg: NDArray[np.float64], pose_id: str) -> dict[str, Any]:
        """One target of the daemon (a batch of one), followed until it ends."""
        ctl = await self.cell.controller_status()
        if ctl["state"] != "running":
            raise TrialError(
                f"RSI is not running on the robot controller ({ctl['state']}: {ctl['stop_reason']})"
            )
        self.target_counter += 1
        key = f"{self.key_prefix}-{self.target_counter}"
        request = {f"a{k + 1}": round(float(v), 9) for k, v in enumerate(axes_deg)}
        request["pose_id"] = pose_id  # type: ignore[assignment]
        if self.plan.payload_kg:
            request["payload_kg"] = float(self.plan.payload_kg)
        batch = await self.cell.api(
            "POST", "/api/batches", json={"targets": [request]}, headers={"Idempotency-Key": key}
        )
        tid = int(batch["targets"][0]["id"])
        deadline = time.monotonic() + 120.0
        while True:
            doc: dict[str, Any] = await self.cell.api("GET", f"/api/targets/{tid}")
            if doc["state"] in FINAL_STATES:
                return doc
            if not self.cell.daemon_alive():
                raise TrialError(f"the daemon exited during target {tid}; see {self.cell.daemon_log}")
            if time.monotonic() > deadline:
                ready = await self.cell.http.get("/ready") if self.cell.http is not None else None
                why = ready.json().get("reasons") if ready is not None else "?"
                raise TrialError(f"target {tid} did not finish within 120 s (state {doc['state']}; {why})")
            await asyncio.sleep(0.02)

    async def wait_job(self, job_id: int) -> dict[str, Any]:
        while True:
            job: dict[str, Any] = await self.cell.api("GET", f"/api/jobs/{job_id}")
            if job["state"] in ("done", "failed", "cancelled"):
                if job["state"] != "done":
                    raise TrialError(f"fit job {job_id} {job['state']}: {job.get('error')}")
                return job
            await asyncio.sleep(0.2)

    async def fit(self, label: str, dataset_id: int, model: str, order: int | None = None) -> dict[str, Any]:
        body: dict[str, Any] = {"dataset_id": dataset_id, "model": model}
        if order is not None:
            body["order"] = order
        job = await self.cell.api("POST", "/api/fits", json=body)
        job = await self.wait_job(int(job["id"]))
        models = await self.cell.api("GET", "/api/models", params={"limit": 50})
        record = next((m for m in models if m.get("job_id") == job["id"]), None)
        if record is None:
            raise TrialError(f"fit job {job['id']} finished without a model")
        stats = record["stats"]
        entry = {
            "id": record["id"],
            "model": model,
            "kind": record["kind"],
            "order": record["order"],
            "dataset_id": dataset_id,
            "fit_rows": stats.get("rows", {}).get("fit"),
            "server_table2": stats.get("table2", {}),
            "fit": {k: stats.get("fit", {}).get(k) for k in ("rms_mm", "rtol", "order")},
        }
        self.result.models[label] = entry
        return entry

    async def fetch_model(self, model_id: int) -> ErrorModel:
        """A model's artifact over HTTP, kept in the working directory and loaded from there."""
        artifact = await self.cell.api("GET", f"/api/models/{model_id}/artifact")
        folder = self.cell.workdir / "models"
        folder.mkdir(parents=True, exist_ok=True)
        path = write_json_atomic(folder / f"model-{model_id}.json", artifact)
        try:
            return load_model(path, self.scenario.robot).model
        except ModelArtifactError as exc:
            raise TrialError(f"the artifact of model {model_id}: {exc}") from None

    async def activate(self, model_id: int) -> None:
        await self.cell.api("POST", f"/api/models/{model_id}/activate")

    async def upload(
        self,
        name: str,
        runs: list[tuple[PointRun, PlannedPoints, str]],
        *,
        joints_from_gratings: bool = False,
    ) -> int:
        """One data set of several runs (commanded axes, tracker, dir, gratings, split).

        ``joints_from_gratings``: A1..A3 are the grating readings instead of the commands — the joint
        angles the robot really had, in the convention the joint loop holds them to.
        """
        a, p, dirs, g = [], [], [], []
        split: list[str] = []
        ids: list[str] = []
        for run, pts, sp in runs:
            ok = run.ok
            if joints_from_gratings:
                ok = ok & np.all(np.isfinite(run.grating_deg), axis=1)
                a.append(np.concatenate([run.grating_deg[ok], run.commanded_deg[ok, 3:]], axis=1))
            else:
                a.append(run.commanded_deg[ok])
            p.append(run.measured_mm[ok])
            dirs.append(pts.dir[ok])
            g6 = np.full((int(ok.sum()), 6), np.nan)
            g6[:, :3] = run.grating_deg[ok]
            g.append(g6)
            split += [sp] * int(ok.sum())
            ids += [f"{pts.name[0]}{i + 1:03d}" for i in np.flatnonzero(ok)]
        all_g = np.concatenate(g)
        have_g = np.all(np.isfinite(all_g[:, :3]))
        ds = Dataset(
            a_deg=np.concatenate(a),
            xyz_mm=np.concatenate(p),
            dir=np.concatenate(dirs).astype(np.int8),
            g_deg=all_g if have_g else None,
            g_present=np.array([True] * 3 + [False] * 3) if have_g else np.zeros(0, bool),
            payload_kg=np.full(len(split), float(self.plan.payload_kg)),
            split=np.array(split),
            pose_id=tuple(ids),
            source=f"comp-daemon trial {self.key_prefix}",
        )
        doc = await self.cell.api(
            "POST",
            "/api/datasets",
            params={"name": name},
            content=dataset_to_csv(ds),
            headers={"Content-Type": "text/csv"},
        )
        self.result.datasets[name] = {
            "id": doc["id"],
            "rows": doc["rows"],
            "sha256": doc["sha256"],
            "fit_rows": split.count("fit"),
            "check_rows": split.count("check"),
        }
        return int(doc["id"])

    # ------------------------------------------------------------------------------ runs
