"""A diagnosis: its settings, the rungs of the ladder and its document (docs/diagnosis-output.md).

Units: mm for positions and errors, the effect parameters in the units of the effect catalogue
(:mod:`comp_daemon.models.effects`). Joints are numbered 1..6 in every output.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from comp_daemon.data.dataset import DEFAULT_SPLIT_SEED, Dataset
from comp_daemon.diagnosis.agreement import Agreement
from comp_daemon.diagnosis.comparison import ModelComparison, check_model_names
from comp_daemon.diagnosis.fitting import FitResult
from comp_daemon.diagnosis.remainder import RemainderModel
from comp_daemon.diagnosis.structure import StructureResult
from comp_daemon.models.effects import EFFECTS
from comp_daemon.models.rows import DEFAULT_PROBE_SIGMA_DEG, MeasuredRows
from comp_daemon.preparation.campaign import Directions
from comp_daemon.preparation.options import COMPARED_MODELS
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "DiagnoseOptions",
    "Diagnosis",
    "Frame",
    "Step",
    "final_step",
    "implicated_joints",
    "rounded",
    "significant_steps",
]

FloatArray = NDArray[np.float64]
Frame = Literal["auto", "base", "tracker"]


def rounded(value: float, digits: int = 6) -> float:
    """A float rounded to ``digits`` significant digits, for JSON."""
    if not math.isfinite(value) or value == 0.0:
        return float(value)
    return float(f"{value:.{digits}g}")


@dataclass(frozen=True)
class DiagnoseOptions:
    """Settings of a diagnosis; the defaults are the documented method."""

    frame: Frame = "auto"
    harmonics: int = 2  # K of the cyclic effect
    folds: int = 5  # k of the cross-validation inside the fit rows
    alpha: float = 0.002  # family-wise false-alarm level per selection round (calibrated, see docs)
    seed: int = DEFAULT_SPLIT_SEED  # folds, and the check rows when the data has no split column
    check_fraction: float = 0.3  # held out when the data has no split column
    t_ref_c: float = 20.0  # reference temperature of the thermal effect
    max_effects: int = 12  # at most this many (effect, joint) candidates are accepted
    tracker_sigma_mm: float | None = None  # declared tracker uncertainty (σ per axis), if known
    effects: tuple[str, ...] | None = None  # the effects to try (None: the whole catalogue)
    remainder_model: bool = True  # try the joint-space remainder model after the ladder
    infer_directions: bool = True  # without dir columns, approach directions from the pose order
    probe_sigma_deg: float = DEFAULT_PROBE_SIGMA_DEG  # a 6-DOF probe's orientation σ per axis
    # compensation models fitted on the same rows and compared with the ladder (empty: none)
    compare_models: tuple[str, ...] = COMPARED_MODELS

    def __post_init__(self) -> None:
        if self.frame not in ("auto", "base", "tracker"):
            raise ValueError(f"frame must be auto, base or tracker, got {self.frame!r}")
        if not 1 <= self.harmonics <= 8:
            raise ValueError(f"harmonics must be 1..8, got {self.harmonics}")
        if not 2 <= self.folds <= 20:
            raise ValueError(f"folds must be 2..20, got {self.folds}")
        if not 0.0 < self.alpha < 0.5:
            raise ValueError(f"alpha must be in (0, 0.5), got {self.alpha}")
        if not 0.0 < self.check_fraction < 1.0:
            raise ValueError(f"check_fraction must be in (0, 1), got {self.check_fraction}")
        if self.effects is not None:
            unknown = [e for e in self.effects if e not in EFFECTS]
            if unknown:
                raise ValueError(f"unknown effect(s) {', '.join(unknown)} (known: {', '.join(EFFECTS)})")
        object.__setattr__(self, "compare_models", check_model_names(self.compare_models))
        if self.tracker_sigma_mm is not None and not (
            math.isfinite(self.tracker_sigma_mm) and self.tracker_sigma_mm > 0.0
        ):
            raise ValueError(f"tracker_sigma_mm must be a number > 0, got {self.tracker_sigma_mm}")
        if not (math.isfinite(self.probe_sigma_deg) and self.probe_sigma_deg > 0.0):
            raise ValueError(f"probe_sigma_deg must be a number > 0, got {self.probe_sigma_deg}")


@dataclass(frozen=True)
class Step:
    """One rung of the ladder, as in the JSON output (plus what the report draws)."""

    effect: str
    joints: list[int]
    significant: bool
    check_rms_mm: float
    check_max_mm: float
    shrink_pct: float
    params: dict[str, Any]
    fit_rms_mm: float
    cv_rms_mm: float | None
    p_value: float | None
    n_params: int
    fit: FitResult = field(repr=False)
    names: tuple[str, ...] = ()

    def to_json(self) -> dict[str, Any]:
        return {
            "effect": self.effect,
            "joints": self.joints,
            "significant": self.significant,
            "check_rms_mm": rounded(self.check_rms_mm),
            "check_max_mm": rounded(self.check_max_mm),
            "shrink_pct": round(self.shrink_pct, 2),
            "params": self.params,
            "fit_rms_mm": rounded(self.fit_rms_mm),
            "cv_rms_mm": None if self.cv_rms_mm is None else rounded(self.cv_rms_mm),
            "p_value": None if self.p_value is None else float(f"{self.p_value:.3g}"),
            "n_params": self.n_params,
        }


def significant_steps(steps: Sequence[Step]) -> list[Step]:
    return [s for s in steps if s.significant]


def implicated_joints(steps: Sequence[Step]) -> list[int]:
    """The joints of the significant non-geometric steps."""
    out: set[int] = set()
    for s in significant_steps(steps):
        if s.effect != "geometric":
            out.update(s.joints)
    return sorted(out)


def final_step(steps: Sequence[Step]) -> Step:
    """The last significant step (the geometric step when none is)."""
    sig = significant_steps(steps)
    return sig[-1] if sig else steps[0]


@dataclass(frozen=True)
class Diagnosis:
    """The result: ``to_json()`` is the document of docs/diagnosis-output.md; the arrays feed the report."""

    robot: RobotDescription
    dataset: Dataset
    obs: MeasuredRows
    fit_rows: NDArray[np.int64]
    check_rows: NDArray[np.int64]
    split_message: str
    split_drawn: bool
    frame: str
    world_T_base: FloatArray
    options: DiagnoseOptions
    baseline_fit: FitResult
    baseline_check_rms_mm: float
    baseline_check_max_mm: float
    steps: list[Step]
    skipped: list[dict[str, Any]]
    selection: list[dict[str, Any]]
    unidentifiable: list[str]
    noise_floor_mm: float | None  # None: no independent evidence of the noise
    noise_floor_source: str | None  # repeats, targets, declared (None with no floor)
    where: dict[str, Any]
    residual_structure: list[StructureResult] = field(default_factory=list)
    remainder_rows: str = ""  # which rows' remainder residual_structure tested
    time_nuisance: bool = False  # the effects were tested with a time nuisance in their base
    remainder_model: RemainderModel | None = None  # joint-space model of the remainder (kept or not)
    directions: Directions | None = None  # where the approach directions come from (the preparation)
    stations: dict[str, Any] | None = None  # the tracker stations and how each was registered
    orientation: str | None = None  # how a 6-DOF probe's orientation entered the geometric step
    agreement: Agreement | None = None  # whether the fit and check rows tell the same story
    # errors an effect stood in for that a flexible alternative of its driver explains better
    unnamed: list[dict[str, Any]] = field(default_factory=list)
    # the ladder beside compensation models fitted on the same rows (None: none compared)
    model_comparison: ModelComparison | None = None

    @property
    def significant_steps(self) -> list[Step]:
        return significant_steps(self.steps)

    @property
    def unmodelled(self) -> list[str]:
        return [s.effect for s in self.significant_steps if s.effect != "geometric"]

    @property
    def implicated_joints(self) -> list[int]:
        return implicated_joints(self.steps)

    @property
    def final_step(self) -> Step:
        return final_step(self.steps)

    @property
    def unexplained_rms_mm(self) -> float:
        return self.final_step.check_rms_mm

    def to_json(self) -> dict[str, Any]:
        return {
            "robot": self.robot.name,
            "robot_sha256": self.robot.sha256,
            "data": {"source": self.dataset.source, "content_sha256": self.dataset.content_sha256},
            "rows": {"fit": len(self.fit_rows), "check": len(self.check_rows)},
            "split": {"drawn": self.split_drawn, "message": self.split_message},
            "frame": {
                "measured_in": self.frame,
                "world_T_base": [[rounded(v, 9) for v in row] for row in self.world_T_base],
                **({} if self.stations is None else {"stations": self.stations}),
                **({} if self.orientation is None else {"orientation": self.orientation}),
            },
            **({} if self.directions is None else {"directions": self.directions.to_json()}),
            "clock": {
                "from": self.obs.clock_name,
                "unit": "h since the first t_s" if self.obs.clock_name == "t_s" else "row",
            },
            "baseline": {
                "effect": "nominal",
                "check_rms_mm": rounded(self.baseline_check_rms_mm),
                "check_max_mm": rounded(self.baseline_check_max_mm),
            },
            "steps": [s.to_json() for s in self.steps],
            "unmodelled": self.unmodelled,
            "joints": self.implicated_joints,
            "where": self.where,
            "unexplained_rms_mm": rounded(self.unexplained_rms_mm),
            "noise_floor_mm": None if self.noise_floor_mm is None else rounded(self.noise_floor_mm),
            "noise_floor_source": self.noise_floor_source,
            "residual_structure": [r.to_json() for r in self.residual_structure],
            **({} if self.agreement is None else {"fit_check_agreement": self.agreement.to_json()}),
            "unnamed_errors": self.unnamed,
            "remainder_rows": self.remainder_rows,
            **({} if self.remainder_model is None else {"remainder_model": self.remainder_model.to_json()}),
            **(
                {} if self.model_comparison is None else {"model_comparison": self.model_comparison.to_json()}
            ),
            "unidentifiable": self.unidentifiable,
            "skipped": self.skipped,
            "selection": self.selection,
            "method": {
                "selection": "greedy forward selection by k-fold CV on fit rows (folds of pose groups)",
                "significance": "cluster-robust (CR3) Wald test, p < alpha / candidates, and lower CV error",
                "parsimony": "a runner-up with fewer parameters wins unless the best adds significantly",
                "alpha": self.options.alpha,
                "folds": self.options.folds,
                "cyclic_harmonics": self.options.harmonics,
                "t_ref_c": self.options.t_ref_c,
                "effects_tried": list(EFFECTS if self.options.effects is None else self.options.effects),
                "time_nuisance": self.time_nuisance,
                "noise_floor": "repeated poses, else the declared tracker uncertainty (option, else "
                "the sigma_mm column), else the spread of several targets' mutual distances; not the "
                "fit residual",
                "residual_structure": "binned means out of fold, permutation test, Holm over the variables",
                "remainder_model": "Gaussian process in the axis values (a length scale per joint), kept "
                "only if it lowers the k-fold CV error on the fit rows by 2 % or more at p < 0.01",
            },
        }
