"""The options that change a fit's result, stated once for every door.

:class:`FitSettings` holds what the user may choose about a fit: the frame, the cross-validation
folds and seed, whether approach directions are inferred, a 6-DOF probe's orientation σ, and for a
ballbar or cross-bar campaign :attr:`~FitSettings.fix_near_dependent` and :attr:`~FitSettings.ridge`.
Each is a pydantic field with its range and description; the HTTP fit job's request body
(``POST /api/fits``, :class:`comp_daemon.service.schemas.FitIn`) is this model with the data set and
the model name added, and ``comp-daemon fit`` / ``evaluate`` build their options from its fields
(:mod:`comp_daemon.commands.options`: ``probe_sigma_deg`` becomes ``--probe-sigma-deg``, a flag that
is on by default becomes ``--no-…``). A value out of range is refused by the same check, in the same
sentence, on both doors. The next option is a field here.

:class:`FitSettings` goes into the fit pipeline whole: in a
:class:`~comp_daemon.preparation.pipeline.FitRequest`, to
:func:`~comp_daemon.preparation.pipeline.prepare_for_models` (``evaluate``) and to
:func:`~comp_daemon.preparation.pipeline.calibrate_campaign` (a ballbar or cross-bar campaign).

The annotated types (:data:`FrameChoiceField`, :data:`Folds`, :data:`Seed`, :data:`ProbeSigmaDeg`)
are shared with the diagnosis's options (:mod:`comp_daemon.diagnosis.options`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, WrapValidator
from pydantic_core import PydanticCustomError

from comp_daemon.models.observations import DEFAULT_PROBE_SIGMA_DEG

__all__ = [
    "MAX_PROBE_SIGMA_DEG",
    "MAX_SEED",
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

    def changed(self) -> dict[str, object]:
        """The settings that differ from the defaults (what a job or a summary records)."""
        return self.model_dump(exclude_defaults=True)
