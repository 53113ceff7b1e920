"""The options that change a fit's or a diagnosis's result, stated once for every door.

:class:`FitSettings` holds what the user may choose about a fit: the frame, the cross-validation
folds and seed, whether approach directions are inferred, a 6-DOF probe's orientation σ, and for a
ballbar or cross-bar campaign :attr:`~FitSettings.fix_near_dependent` and :attr:`~FitSettings.ridge`.
:class:`DiagnosisSettings` holds what the user may choose about a diagnosis (its defaults are those
of :class:`comp_daemon.diagnosis.result.DiagnoseOptions`, the documented method; a test holds them
equal). Each is a pydantic field with its range, its refusal sentence (:func:`refusal`) and its
description. The HTTP request bodies (``POST /api/fits``, ``POST /api/diagnoses``:
:class:`comp_daemon.service.schemas.FitIn`, :class:`~comp_daemon.service.schemas.DiagnosisIn`) are
these models with the data set (and the model name) added, and ``comp-daemon fit`` / ``evaluate`` /
``diagnose`` build their options from the same fields (:mod:`comp_daemon.commands.options`:
``probe_sigma_deg`` becomes ``--probe-sigma-deg``, a flag that is on by default becomes ``--no-…``).
A bad value is refused by the same check, in the same sentence, on both doors. The next option is a
field here.

:class:`FitSettings` goes into the fit pipeline whole: in a
:class:`~comp_daemon.preparation.pipeline.FitRequest`, to
:func:`~comp_daemon.preparation.pipeline.prepare_for_models` (``evaluate``) and to
:func:`~comp_daemon.preparation.pipeline.calibrate_campaign` (a ballbar or cross-bar campaign).
:class:`DiagnosisSettings` becomes the diagnosis's options by
:func:`comp_daemon.diagnosis.options.diagnose_options`. The module imports nothing of the diagnosis:
the service validates requests with it without loading the diagnosis's numerics.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    WrapValidator,
)
from pydantic_core import PydanticCustomError

from comp_daemon.data.dataset import DEFAULT_SPLIT_SEED
from comp_daemon.models.effects import EFFECTS
from comp_daemon.models.registry import UnknownModelError, parse_model_name
from comp_daemon.models.rows import DEFAULT_PROBE_SIGMA_DEG

__all__ = [
    "COMPARED_MODELS",
    "MAX_PROBE_SIGMA_DEG",
    "MAX_SEED",
    "MAX_TRACKER_SIGMA_MM",
    "DiagnosisSettings",
    "FitSettings",
    "Folds",
    "FrameChoiceField",
    "ProbeSigmaDeg",
    "Seed",
    "refusal",
]

#: the largest seed numpy's generators take from one 32-bit word
MAX_SEED = 2**32 - 1
#: a probe orientation σ above this says nothing about the orientation at all
MAX_PROBE_SIGMA_DEG = 45.0
#: a declared tracker σ above this (mm) is not a tracker's
MAX_TRACKER_SIGMA_MM = 10.0
#: the compensation models a diagnosis compares with its ladder unless told otherwise
COMPARED_MODELS: tuple[str, ...] = ("kinematic+ratio+backlash", "kriging")


def refusal(sentence: str) -> WrapValidator:
    """A field's refusal of any bad value (wrong type, out of range) in ``sentence``: one sentence of
    ours, the same on the command line and over HTTP, instead of pydantic's."""

    def check(value: Any, handler: Callable[[Any], Any]) -> Any:
        try:
            return handler(value)
        except ValidationError:
            raise PydanticCustomError("invalid_option", sentence) from None

    return WrapValidator(check)


FrameChoiceField = Annotated[
    Literal["auto", "base", "tracker"],
    Field(description="frame of x, y, z: robot base, tracker (registered first), or auto"),
]
Folds = Annotated[
    int,
    Field(ge=2, le=20, description="cross-validation folds inside the fit rows, 2..20"),
    refusal("expected 2..20 folds"),
]
Seed = Annotated[
    int,
    Field(ge=0, le=MAX_SEED, description="seed of the cross-validation folds"),
    refusal(f"expected a seed 0..{MAX_SEED}"),
]
ProbeSigmaDeg = Annotated[
    float,
    Field(
        gt=0.0,
        le=MAX_PROBE_SIGMA_DEG,
        description="a 6-DOF probe's orientation uncertainty (σ per axis, deg): weighs its qw..qz against "
        "the positions in the kinematic calibration",
    ),
    refusal(f"expected an angle in degrees > 0 and <= {MAX_PROBE_SIGMA_DEG:g}"),
]
InferDirections = Annotated[
    bool,
    Field(
        description="derive the approach directions from the pose order when the data set has no "
        "dir1..dir6 columns and a model needs them (backlash); turned off (--no-infer-dir, over HTTP "
        '"infer_dir": false), such models refuse the data',
    ),
]


class FitSettings(BaseModel):
    """What the user chooses about a fit (module docstring); the defaults are the documented method."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    frame: FrameChoiceField = "auto"
    folds: Folds = 5
    seed: Seed = 0
    infer_dir: InferDirections = True
    probe_sigma_deg: ProbeSigmaDeg = DEFAULT_PROBE_SIGMA_DEG
    fix_near_dependent: bool = Field(
        default=False,
        description="ballbar campaigns: hold the weaker parameter of each near-dependent pair "
        "(|correlation| > 0.9) at zero and fit again (never a pivot offset); the pairs are named either way",
    )
    ridge: bool = Field(
        default=False,
        description="ballbar campaigns: pull every POE error toward zero (5 mm of dl or 2 deg of dtheta cost "
        "as much as 1 mm of length residual on one reading); docs/seeds-002-003.md measures it",
    )


def _words(value: Any) -> Any:
    """A comma-separated string as its words (blanks dropped); anything else as it is."""
    if isinstance(value, str):
        return tuple(w.strip() for w in value.split(",") if w.strip())
    return value


def _effects(names: tuple[str, ...]) -> tuple[str, ...]:
    """Effects of the catalogue, at least one."""
    known = ", ".join(EFFECTS)
    if not names:
        raise ValueError(f"names no effect; give one or more of {known}, or leave it out to try all")
    unknown = [e for e in names if e not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effect(s) {', '.join(unknown)} (known: {known})")
    return names


def _models(names: tuple[str, ...]) -> tuple[str, ...]:
    """Model names of the registry, each as the registry writes it; ``none`` alone: none."""
    if names == ("none",):
        return ()
    try:
        return tuple(parse_model_name(name).name for name in names)
    except UnknownModelError as exc:
        raise ValueError(str(exc)) from None


TrackerSigmaMm = Annotated[
    float,
    Field(gt=0.0, le=MAX_TRACKER_SIGMA_MM),
    refusal(f"expected a length in mm > 0 and <= {MAX_TRACKER_SIGMA_MM:g}"),
]
Effects = Annotated[tuple[str, ...], BeforeValidator(_words), AfterValidator(_effects)]
ModelNames = Annotated[tuple[str, ...], BeforeValidator(_words), AfterValidator(_models)]


class DiagnosisSettings(BaseModel):
    """What the user chooses about a diagnosis (module docstring). ``effects`` and
    ``compare_models`` are lists over HTTP and comma-separated words on the command line (a string
    is split at commas on both doors; ``compare_models`` ``none``: no comparison)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    frame: FrameChoiceField = "auto"
    harmonics: Annotated[int, Field(ge=1, le=8), refusal("expected 1..8 harmonics")] = Field(
        default=2, description="harmonics K of the cyclic effect"
    )
    folds: Folds = 5
    alpha: Annotated[float, Field(gt=0.0, lt=0.5), refusal("expected a level between 0 and 0.5")] = Field(
        default=0.002, description="false-alarm level of the significance test per selection round"
    )
    seed: Seed = Field(default=DEFAULT_SPLIT_SEED, description="seed of the folds and of drawn check rows")
    tracker_sigma_mm: TrackerSigmaMm | None = Field(
        default=None,
        description="the tracker's declared uncertainty (σ per axis, mm): the noise floor (√3·σ, 3-D) "
        "when the data have no repeated poses (over a sigma_mm column and over the spread of several "
        "targets); omitted and without any, no noise floor is claimed",
    )
    probe_sigma_deg: ProbeSigmaDeg = DEFAULT_PROBE_SIGMA_DEG
    effects: Effects | None = Field(
        default=None,
        description=f"try only these effects (of {', '.join(EFFECTS)}; a list, or comma-separated words); "
        "omitted: all",
    )
    infer_dir: InferDirections = True
    compare_models: ModelNames = Field(
        default=COMPARED_MODELS,
        description="compensation models (names as for evaluate --models and POST /api/fits) fitted on the "
        "same fit rows and compared with the ladder on the check rows; none (or an empty list) to leave "
        "the comparison out",
    )
