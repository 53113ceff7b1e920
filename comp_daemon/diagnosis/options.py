"""The options that change a diagnosis's result, stated once for every door.

:class:`DiagnosisSettings` is what the user may choose about a diagnosis; its defaults are
:class:`~comp_daemon.diagnosis.result.DiagnoseOptions`'s (the documented method). The HTTP
diagnosis job's request body (``POST /api/diagnoses``, :class:`comp_daemon.service.schemas.DiagnosisIn`)
is this model with the data set added, and ``comp-daemon diagnose`` builds its options from its
fields (:mod:`comp_daemon.commands.options`), so a value out of range is refused by the same check,
in the same sentence, on both doors. ``effects`` and ``compare_models`` are lists over HTTP and
comma-separated words on the command line (a string is split at commas on both doors;
``compare_models`` ``none``: no comparison); their names are checked by
:class:`~comp_daemon.diagnosis.result.DiagnoseOptions` itself. :meth:`DiagnosisSettings.options`
gives the options :func:`~comp_daemon.diagnosis.ladder.diagnose` takes.
"""

from __future__ import annotations

from dataclasses import fields
from typing import Annotated, Any

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationInfo, field_validator

from comp_daemon.diagnosis.result import DiagnoseOptions
from comp_daemon.models.effects import EFFECTS
from comp_daemon.preparation.options import (
    Folds,
    FrameChoiceField,
    InferDirections,
    ProbeSigmaDeg,
    Seed,
    refusal,
)

__all__ = ["DiagnosisSettings"]

_METHOD = DiagnoseOptions()
#: a declared tracker σ above this (mm) is not a tracker's
MAX_TRACKER_SIGMA_MM = 10.0


def _words(value: Any) -> Any:
    """A comma-separated string as its words (blanks dropped); anything else as it is."""
    if isinstance(value, str):
        return tuple(w.strip() for w in value.split(",") if w.strip())
    return value


Words = Annotated[tuple[str, ...], BeforeValidator(_words)]
TrackerSigmaMm = Annotated[
    float,
    Field(gt=0.0, le=MAX_TRACKER_SIGMA_MM),
    refusal(f"expected a length in mm > 0 and <= {MAX_TRACKER_SIGMA_MM:g}"),
]


class DiagnosisSettings(BaseModel):
    """What the user chooses about a diagnosis (module docstring)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    frame: FrameChoiceField = _METHOD.frame
    harmonics: Annotated[int, Field(ge=1, le=8), refusal("expected 1..8 harmonics")] = Field(
        default=_METHOD.harmonics, description="harmonics K of the cyclic effect"
    )
    folds: Folds = _METHOD.folds
    alpha: Annotated[float, Field(gt=0.0, lt=0.5), refusal("expected a level between 0 and 0.5")] = Field(
        default=_METHOD.alpha, description="false-alarm level of the significance test per selection round"
    )
    seed: Seed = Field(default=_METHOD.seed, description="seed of the folds and of drawn check rows")
    tracker_sigma_mm: TrackerSigmaMm | None = Field(
        default=_METHOD.tracker_sigma_mm,
        description="the tracker's declared uncertainty (σ per axis, mm): the noise floor (√3·σ, 3-D) "
        "when the data have no repeated poses (over a sigma_mm column and over the spread of several "
        "targets); omitted and without any, no noise floor is claimed",
    )
    probe_sigma_deg: ProbeSigmaDeg = _METHOD.probe_sigma_deg
    effects: Words | None = Field(
        default=_METHOD.effects,
        description=f"try only these effects (of {', '.join(EFFECTS)}; a list, or comma-separated words); "
        "omitted: all",
    )
    infer_dir: InferDirections = _METHOD.infer_directions
    compare_models: Words = Field(
        default=_METHOD.compare_models,
        description="compensation models (names as for evaluate --models and POST /api/fits) fitted on the "
        "same fit rows and compared with the ladder on the check rows; none (or an empty list) to leave "
        "the comparison out",
    )

    @field_validator("effects", "compare_models", mode="after")
    @classmethod
    def _names(cls, value: tuple[str, ...] | None, info: ValidationInfo) -> tuple[str, ...] | None:
        """The diagnosis's own check of the names (:class:`DiagnoseOptions`)."""
        if info.field_name == "effects" and value == ():
            raise ValueError(
                f"names no effect; give one or more of {', '.join(EFFECTS)}, or leave it out to try all"
            )
        if info.field_name == "compare_models":
            value = () if value == ("none",) else value
        assert info.field_name is not None
        given: dict[str, Any] = {info.field_name: value}
        checked: tuple[str, ...] | None = getattr(DiagnoseOptions(**given), info.field_name)
        return checked

    def options(self) -> DiagnoseOptions:
        """The options :func:`~comp_daemon.diagnosis.ladder.diagnose` takes."""
        values = self.model_dump()
        values["infer_directions"] = values.pop("infer_dir")
        known = {f.name for f in fields(DiagnoseOptions)}
        assert set(values) <= known, set(values) - known
        return DiagnoseOptions(**values)

    def changed(self) -> dict[str, object]:
        """The settings that differ from the method's (what a job records)."""
        return self.model_dump(exclude_defaults=True)
