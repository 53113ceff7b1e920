"""The diagnosis beside the compensation models: does the ladder explain what the models explain?

The ladder names effects of a closed vocabulary; a compensation model of the registry
(:mod:`comp_daemon.models.registry`, what ``comp-daemon evaluate`` compares) has no names to give
and may fit what the vocabulary lacks: an error smooth in the axis values (kriging, Chebyshev
polynomials), one that also follows the approach directions (``kriging-backlash``), or the
vocabulary's own effects on every joint at once (``kinematic+ratio+backlash``). Each model of a
small set is fitted on the diagnosis's fit rows of the same prepared campaign (the same split,
frame detection and approach directions as ``evaluate``) and predicts its check rows; their check
RMS stands beside the ladder's last significant step's (the TCP's rows, the figure ``evaluate``
reports). When the best model is more than :data:`AGREE_PCT` % below the ladder, the diagnosis says
which and what that model has that the ladder lacks.

The default set (:data:`comp_daemon.preparation.options.COMPARED_MODELS`, the one default of both
doors) is chosen for cost: a kinematic model with ratio and backlash on every joint, and isotropic
kriging of the kinematic remainder, about 1–2 s together on 1 000 poses on one core.
``kriging:aniso`` (per-joint ranges, 1.4–1.9 s) and the stacks cost more each; they are named with
``DiagnoseOptions(compare_models=...)`` (``--compare-models``).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.diagnosis.remainder import RemainderModel
from comp_daemon.models.fitting import FitOptions, ModelSpec
from comp_daemon.models.registry import (
    MissingColumnError,
    UndeterminedModelError,
    UnknownModelError,
    fit_spec,
    parse_model_name,
    undetermined_reason,
)
from comp_daemon.preparation.campaign import PreparedCampaign
from comp_daemon.robot.description import RobotDescription

__all__ = ["AGREE_PCT", "ModelComparison", "check_model_names", "compare_models"]

#: the ladder agrees with the models when the best of them is at most this much lower (%)
AGREE_PCT = 5.0
#: the models compared by default: cheap, and between them what the vocabulary lacks
#: a remainder length scale below this (deg) says the error varies along that joint
SHORT_SCALE_DEG = 180.0


def check_model_names(names: Sequence[str]) -> tuple[str, ...]:
    """The model names, each parsed by the registry (ValueError naming an unknown one)."""
    out = []
    for name in names:
        try:
            out.append(parse_model_name(name).name)
        except UnknownModelError as exc:
            raise ValueError(f"compare_models: {exc}") from None
    return tuple(out)


def what_it_has(spec: ModelSpec, unnamed: Sequence[dict[str, Any]] = ()) -> str:
    """What a model of this kind has that the ladder lacks, in words; ``unnamed`` the errors the
    diagnosis found that no effect of the vocabulary names (``unnamed_errors``)."""
    if spec.kind == "kriging-backlash":
        return (
            "an error smooth in the axis values and the approach directions that no effect of the "
            "vocabulary names"
        )
    if spec.kind in ("kriging", "chebyshev"):
        return "an error smooth in the axis values that no effect of the vocabulary names"
    if spec.kind == "kinematic" and spec.effects and unnamed:
        first = unnamed[0]
        return (
            f"the vocabulary's own {', '.join(spec.effects)} on every joint at once, which take part of "
            f"the error of axes {', '.join(str(a) for a in first['axes'])} that the diagnosis does not "
            f"name: {first['instead_of']} does not explain it (a smooth function of "
            f"A{first['driver_axis']} does better out of fold), so the ladder leaves it out; it can be "
            "compensated, not named"
        )
    if spec.kind == "kinematic" and spec.effects:
        return (
            f"the vocabulary's own {', '.join(spec.effects)} on every joint at once: the ladder left out "
            "an effect it tried, or named it on fewer joints"
        )
    return f"another form of the robot's geometry ({spec.name}) than the ladder's twin"


def _kind_words(spec: ModelSpec) -> str:
    if spec.kind.startswith("kriging") or spec.kind == "chebyshev":
        return f"a joint-space error model ({spec.name})"
    return f"the model {spec.name}"


@dataclass(frozen=True)
class ModelComparison:
    """The ``model_comparison`` field: the ladder's check RMS beside the models' on the same rows."""

    ladder_check_rms_mm: float
    check_rows: int
    models: list[dict[str, Any]] = field(default_factory=list)  # model, check_rms_mm, cpu_s
    skipped: list[dict[str, str]] = field(default_factory=list)  # model, reason
    best: str | None = None
    best_check_rms_mm: float | None = None
    lacks: str | None = None
    remainder_check_rms_mm: float | None = None  # the diagnosis's own remainder model, when kept
    where: str | None = None  # the remainder model's shortest length scales, when it was tried

    @property
    def better_pct(self) -> float | None:
        """How much lower the best model's check RMS is than the ladder's (%; negative: higher)."""
        if self.best_check_rms_mm is None or self.ladder_check_rms_mm <= 0:
            return None
        return 100.0 * (1.0 - self.best_check_rms_mm / self.ladder_check_rms_mm)

    @property
    def agree(self) -> bool | None:
        better = self.better_pct
        return None if better is None else better <= AGREE_PCT

    def describe(self) -> str:
        """The comparison in words."""
        if self.best is None:
            reasons = "; ".join(f"{s['model']}: {s['reason']}" for s in self.skipped) or "none asked"
            return f"No compensation model could be compared with the ladder ({reasons})."
        assert self.best_check_rms_mm is not None
        better = self.better_pct or 0.0
        others = ", ".join(f"{m['model']} {m['check_rms_mm']:.4f}" for m in self.models)
        rows = f"the same {self.check_rows} check rows"
        if self.agree:
            if better <= 0:
                head = (
                    f"The ladder ({self.ladder_check_rms_mm:.4f} mm) does as well as or better than every "
                    f"compensation model compared on {rows} ({others} mm)."
                )
            else:
                head = (
                    f"The ladder ({self.ladder_check_rms_mm:.4f} mm) is within {AGREE_PCT:g} % of the best "
                    f"compensation model compared on {rows} ({others} mm)."
                )
        else:
            spec = parse_model_name(self.best)
            head = (
                f"{_kind_words(spec)[0].upper()}{_kind_words(spec)[1:]} explains {better:.0f} % more than "
                f"the ladder on {rows} ({self.best_check_rms_mm:.4f} against {self.ladder_check_rms_mm:.4f} "
                f"mm): {self.lacks}"
            )
            if self.where and (spec.kind.startswith("kriging") or spec.kind == "chebyshev"):
                head += f"; {self.where}"
            head += "."
        if self.remainder_check_rms_mm is not None:
            below = self.remainder_check_rms_mm < self.best_check_rms_mm
            head += (
                " With its joint-space remainder model the diagnosis reaches "
                f"{self.remainder_check_rms_mm:.4f} mm" + (", below every model compared." if below else ".")
            )
        return head

    def to_json(self) -> dict[str, Any]:
        def r(v: float | None) -> float | None:
            return None if v is None else float(f"{v:.6g}")

        better = self.better_pct
        return {
            "rows": "check",
            "check_rows": self.check_rows,
            "ladder_check_rms_mm": r(self.ladder_check_rms_mm),
            "models": [
                {"model": m["model"], "check_rms_mm": r(m["check_rms_mm"]), "cpu_s": round(m["cpu_s"], 2)}
                for m in self.models
            ],
            "skipped": self.skipped,
            "best": self.best,
            "best_check_rms_mm": r(self.best_check_rms_mm),
            "better_pct": None if better is None else round(better, 2),
            "agree": self.agree,
            "agree_within_pct": AGREE_PCT,
            "lacks": None if self.agree else self.lacks,
            "remainder_model_check_rms_mm": r(self.remainder_check_rms_mm),
            "summary": self.describe(),
        }


def _rms(err: NDArray[np.float64]) -> float:
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def compare_models(
    prepared: PreparedCampaign,
    robot: RobotDescription,
    names: Sequence[str],
    ladder_check_rms_mm: float,
    remainder: RemainderModel | None,
    unnamed: Sequence[dict[str, Any]] = (),
    *,
    folds: int,
    seed: int,
) -> ModelComparison:
    """Fit each model of ``names`` on the prepared campaign's fit rows and judge it on its check rows.

    A model the rows cannot carry (no directions, too few rows, a fit that fails) is skipped with
    the reason; the comparison never stops the diagnosis.
    """
    fit_rows, check_rows = prepared.fit_rows, prepared.check_rows
    dataset = prepared.dataset
    assert dataset.xyz_mm is not None
    check = prepared.rows(check_rows)
    options = FitOptions(frame=prepared.frame, cv_folds=folds, seed=seed)
    models: list[dict[str, Any]] = []
    skipped: list[dict[str, str]] = []
    best: tuple[float, str, ModelSpec] | None = None
    for name in names:
        spec = parse_model_name(name)
        reason = undetermined_reason(spec, robot, len(fit_rows), dataset.payload_kg)
        if reason is None:
            t0 = time.process_time()
            try:
                fitted = fit_spec(spec, robot, prepared.rows(fit_rows), options)
                pred = fitted.model.predict_tcp_mm(check.a_deg, check.dir, check.payload_kg, check.temp_c)
            except (MissingColumnError, UndeterminedModelError, np.linalg.LinAlgError, ValueError) as exc:
                reason = str(exc)
            else:
                rms = _rms(dataset.xyz_mm[check_rows] - pred)
                models.append({"model": spec.name, "check_rms_mm": rms, "cpu_s": time.process_time() - t0})
                if best is None or rms < best[0]:
                    best = (rms, spec.name, spec)
        if reason is not None:
            skipped.append({"model": spec.name, "reason": reason})
    models.sort(key=lambda m: m["check_rms_mm"])
    kept = remainder is not None and remainder.kept and remainder.check_rms_mm_after is not None
    where = None
    if remainder is not None and remainder.tried:
        short = sorted(
            (kv for kv in remainder.length_scales_deg.items() if kv[1] < SHORT_SCALE_DEG),
            key=lambda kv: kv[1],
        )
        if short:
            where = (
                "it varies along "
                + ", ".join(f"A{j}" for j, _ in short)
                + (
                    " (the joint-space remainder model's length scales: "
                    + ", ".join(f"A{j} {v:.3g}°" for j, v in short)
                    + ")"
                )
            )
    return ModelComparison(
        ladder_check_rms_mm=ladder_check_rms_mm,
        check_rows=len(check_rows),
        models=models,
        skipped=skipped,
        best=None if best is None else best[1],
        best_check_rms_mm=None if best is None else best[0],
        lacks=None if best is None else what_it_has(best[2], unnamed),
        remainder_check_rms_mm=remainder.check_rms_mm_after if kept and remainder is not None else None,
        where=where,
    )
