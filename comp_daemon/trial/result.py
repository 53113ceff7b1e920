"""What a trial produced: the runs over the points, the ISO 9283 positions, models, and statistics.

A :class:`PointRun` is one pass of the robot over a list of points (sampling or target points), by
the robot program alone (``feedback`` False: open loop, state ``open``) or as targets of the daemon
(``feedback`` True: the closed joint loop; state ``done``/``failed``…). Positions are tracker
readings in the robot base frame (mm); ``wanted_mm`` is the nominal TCP of the planned point; the
error of a point is ``measured − wanted`` (seed 000: ΔP = P_actual − P_theoretical).

:class:`TrialResult` is a JSON document (``format`` ``comp-daemon-trial``, ``version`` 1) so a
report can be rendered again from it (``comp-daemon trial --from-json``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.models.evaluation import error_statistics

__all__ = ["FORMAT", "VERSION", "PointRun", "TrialResult"]

FORMAT = "comp-daemon-trial"
VERSION = 1
OK_STATES = ("open", "done")


@dataclass
class PointRun:
    key: str
    label: str
    points: str  # "sampling" | "targets"
    feedback: bool
    model: str | None  # what compensated the commands ("nominal", "kinematic", "chebyshev m=3", …)
    model_id: int | None
    wanted_mm: NDArray[np.float64]  # (n, 3)
    commanded_deg: NDArray[np.float64]  # (n, 6) what the robot was commanded (NaN: never)
    measured_mm: NDArray[np.float64]  # (n, 3) tracker, base frame (NaN: not measured)
    grating_deg: NDArray[np.float64]  # (n, 3) gratings A1..A3 as the daemon read them (NaN: none)
    state: list[str]
    reason: list[str | None]
    duration_s: float = 0.0
    retried: list[dict[str, Any]] = field(default_factory=list)  # {index, reason} of attempts posted again

    @classmethod
    def empty(
        cls,
        key: str,
        label: str,
        points: str,
        wanted_mm: NDArray[np.float64],
        *,
        feedback: bool,
        model: str | None = None,
        model_id: int | None = None,
    ) -> PointRun:
        n = len(wanted_mm)
        return cls(
            key=key,
            label=label,
            points=points,
            feedback=feedback,
            model=model,
            model_id=model_id,
            wanted_mm=np.asarray(wanted_mm, dtype=float).copy(),
            commanded_deg=np.full((n, 6), np.nan),
            measured_mm=np.full((n, 3), np.nan),
            grating_deg=np.full((n, 3), np.nan),
            state=["pending"] * n,
            reason=[None] * n,
        )

    @property
    def n(self) -> int:
        return len(self.state)

    @property
    def ok(self) -> NDArray[np.bool_]:
        """Points reached and measured (robot program: arrived; daemon: target done)."""
        return np.array([s in OK_STATES for s in self.state]) & np.all(np.isfinite(self.measured_mm), axis=1)

    def errors_mm(self) -> NDArray[np.float64]:
        """(m, 3) measured − wanted of the points in :attr:`ok`."""
        ok = self.ok
        out: NDArray[np.float64] = self.measured_mm[ok] - self.wanted_mm[ok]
        return out

    def table2(self) -> dict[str, Any]:
        ok = self.ok
        if not ok.any():
            raise ValueError(f"run '{self.key}': no point was reached and measured")
        return error_statistics(self.measured_mm[ok], self.wanted_mm[ok])

    def failures(self) -> list[dict[str, Any]]:
        return [
            {"index": i, "state": s, "reason": r}
            for i, (s, r) in enumerate(zip(self.state, self.reason, strict=True))
            if s not in OK_STATES
        ]

    def to_dict(self) -> dict[str, Any]:
        def arr(a: NDArray[np.float64]) -> list[Any]:
            return [[None if not np.isfinite(v) else round(float(v), 9) for v in row] for row in a]

        return {
            "key": self.key,
            "label": self.label,
            "points": self.points,
            "feedback": self.feedback,
            "model": self.model,
            "model_id": self.model_id,
            "duration_s": round(self.duration_s, 3),
            "wanted_mm": arr(self.wanted_mm),
            "commanded_deg": arr(self.commanded_deg),
            "measured_mm": arr(self.measured_mm),
            "grating_deg": arr(self.grating_deg),
            "state": list(self.state),
            "reason": list(self.reason),
            "retried": list(self.retried),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PointRun:
        def arr(v: Any, width: int) -> NDArray[np.float64]:
            a = np.array([[np.nan if x is None else float(x) for x in row] for row in v], dtype=float)
            return a.reshape(len(v), width)

        return cls(
            key=str(d["key"]),
            label=str(d["label"]),
            points=str(d["points"]),
            feedback=bool(d["feedback"]),
            model=d.get("model"),
            model_id=d.get("model_id"),
            wanted_mm=arr(d["wanted_mm"], 3),
            commanded_deg=arr(d["commanded_deg"], 6),
            measured_mm=arr(d["measured_mm"], 3),
            grating_deg=arr(d["grating_deg"], 3),
            state=[str(s) for s in d["state"]],
            reason=list(d["reason"]),
            duration_s=float(d.get("duration_s", 0.0)),
            retried=list(d.get("retried", [])),
        )


@dataclass
class TrialResult:
    plan: dict[str, Any]
    started_at: str
    environment: dict[str, str]
    duration_s: float = 0.0
    phases: list[dict[str, Any]] = field(default_factory=list)  # name, duration_s
    gratings: dict[str, Any] | None = None
    iso: dict[str, Any] = field(default_factory=dict)  # points_mm, abc_deg, runs {without|with: positions}
    runs: dict[str, PointRun] = field(default_factory=dict)  # target runs, in execution order
    sampling: dict[str, PointRun] = field(default_factory=dict)  # "open" / "closed"
    datasets: dict[str, Any] = field(default_factory=dict)
    models: dict[str, Any] = field(default_factory=dict)
    comparison: dict[str, Any] = field(default_factory=dict)
    loop: dict[str, Any] = field(default_factory=dict)
    complete: bool = False
    error: str | None = None

    def table2(self) -> dict[str, dict[str, Any]]:
        return {key: run.table2() for key, run in self.runs.items() if run.ok.any()}

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "version": VERSION,
            "plan": self.plan,
            "started_at": self.started_at,
            "duration_s": round(self.duration_s, 1),
            "environment": self.environment,
            "complete": self.complete,
            "error": self.error,
            "phases": self.phases,
            "gratings": self.gratings,
            "iso9283": self.iso,
            "table2": self.table2(),
            "runs": {k: r.to_dict() for k, r in self.runs.items()},
            "sampling": {k: r.to_dict() for k, r in self.sampling.items()},
            "datasets": self.datasets,
            "models": self.models,
            "comparison": self.comparison,
            "loop": self.loop,
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1, allow_nan=False)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrialResult:
        if d.get("format") != FORMAT or d.get("version") != VERSION:
            raise ValueError(f"not a {FORMAT} v{VERSION} document (fields 'format', 'version')")
        return cls(
            plan=d["plan"],
            started_at=d["started_at"],
            environment=d.get("environment", {}),
            duration_s=float(d.get("duration_s", 0.0)),
            phases=list(d.get("phases", [])),
            gratings=d.get("gratings"),
            iso=d.get("iso9283", {}),
            runs={k: PointRun.from_dict(v) for k, v in d.get("runs", {}).items()},
            sampling={k: PointRun.from_dict(v) for k, v in d.get("sampling", {}).items()},
            datasets=d.get("datasets", {}),
            models=d.get("models", {}),
            comparison=d.get("comparison", {}),
            loop=d.get("loop", {}),
            complete=bool(d.get("complete", False)),
            error=d.get("error"),
        )

    @classmethod
    def load(cls, path: str | Path) -> TrialResult:
        try:
            doc = json.loads(Path(path).read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: not JSON ({exc})") from None
        if not isinstance(doc, dict):
            raise ValueError(f"{path}: not a trial result")
        try:
            return cls.from_dict(doc)
        except (KeyError, TypeError) as exc:
            raise ValueError(f"{path}: a trial result without field {exc}") from None
