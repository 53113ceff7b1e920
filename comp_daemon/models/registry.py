"""The one list of model kinds, read by every door that fits, loads or names a model.

Each kind's module declares its :class:`~comp_daemon.models.kind.ModelKind` beside its model class
and its fit function (``KIND``: name and summary, the fit, the
:class:`~comp_daemon.models.base.ErrorModel` class that predicts with it and rebuilds it from an
artifact, the options its name takes, the data columns it needs and uses, its parameter count before
the identifiability analysis); :data:`KINDS` lists them, once. ``comp-daemon fit | evaluate |
compensate``, the HTTP fit jobs, the artifact loader and the daemon's model activation all read it;
adding a model kind is one module with its model class, its fit function and its ``KIND``, and one
line in :data:`KINDS`. This module parses model names, applies the checks every fit shares
(:func:`fit_spec`) and rebuilds stored models (:func:`model_from_payload`).

Model names (:func:`parse_model_name`)::

    kind[:order|:option…][+effect…]   nominal, kinematic, kinematic+ratio+backlash,
                                      kinematic:all+ratio+backlash, chebyshev, chebyshev:3,
                                      chebyshev:cv, kriging, kriging:k=64:aniso, kriging-backlash,
                                      kriging-backlash+compliance, compliance, compliance:paper,
                                      poe, poe:paper

``:order`` is the Chebyshev order (0..8; ``cv``: chosen by cross-validation; default 3, seed 000's);
the kriging kinds take the options ``:k=N`` (local neighbourhoods of N nearest samples, N ≥ 4) and
``:aniso`` (per-joint ranges); the kinematic, kriging and compliance kinds ``:all`` (every effect
kept, no out-of-fold selection: :mod:`comp_daemon.models.fitting`); ``compliance:paper`` and
``poe:paper`` are seed 004's and seed 002's own forms; ``+effect`` adds a joint effect of
:data:`comp_daemon.models.effects.EFFECTS` to the kinematic model, or to a kriging model's
kinematic base (a stack: ``kriging-backlash+compliance`` krigs the residual of
kinematic + ratio + backlash + compliance).

Artifacts store the model class's ``kind`` (``kriging-backlash`` is a ``kriging`` model whose base
has ratio and backlash and whose distance sees approach directions); :func:`model_from_payload`
rebuilds any of them, a kriging model's base included.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from comp_daemon.estimation.registration import BASE_FRAME_MAX_RMS_MM, detect_frame
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import KinematicParams, axes_deg_to_q_rad
from comp_daemon.models import chebyshev, compliance, kinematic_kind, kriging, nominal
from comp_daemon.models.base import ErrorModel, StoredModel
from comp_daemon.models.effects import EFFECTS, effect_by_name
from comp_daemon.models.fitting import FitOptions, FittedModel, ModelSpec
from comp_daemon.models.kind import ModelKind
from comp_daemon.models.poe import model as poe
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.models.units import millimetre_problem
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "ALL_MODELS",
    "ARTIFACT_KINDS",
    "KINDS",
    "MAX_ORDER",
    "FittedModel",
    "MissingColumnError",
    "ModelSpec",
    "UndeterminedModelError",
    "UnknownModelError",
    "fit_model",
    "fit_spec",
    "get_kind",
    "kind_names",
    "max_parameters",
    "model_from_payload",
    "parse_model_name",
    "too_few_rows_reason",
    "undetermined_reason",
    "unloaded_reason",
    "uses_directions",
    "with_order",
]

MAX_ORDER = 8
MIN_POSES = 3  # distinct axis-value rows below which no model but the nominal one is fitted
OPTION_ORDER = ("aniso", "all", "paper")  # canonical order of the option words after k=N


class UnknownModelError(ValueError):
    """A model name the registry does not know, or options its kind does not take."""


class MissingColumnError(ValueError):
    """The data lack a column the model needs (``dir`` for backlash, …)."""


class UndeterminedModelError(ValueError):
    """The rows (with the robot description) cannot determine the model: too few rows for its
    parameters, or a compliance with nothing that loads the joints."""


#: every kind, each declared in its own module; the order is the one the doors list them in
KINDS: dict[str, ModelKind] = {
    k.name: k
    for k in (
        nominal.KIND,
        kinematic_kind.KIND,
        chebyshev.KIND,
        kriging.KIND,
        kriging.BACKLASH_KIND,
        compliance.KIND,
        poe.KIND,
    )
}


# what ``evaluate --models all`` compares: every kind, and the stacks of the seeds
ALL_MODELS: tuple[str, ...] = (
    "nominal",
    "kinematic",
    "kinematic+ratio+backlash",
    "kinematic+compliance",
    "kinematic+ratio+backlash+compliance",
    "chebyshev",
    "chebyshev:cv",
    "kriging",
    "kriging:aniso",
    "kriging-backlash",
    "kriging-backlash+compliance",
    "compliance",
    "compliance:paper",
    "poe",
    "poe:paper",
)


def uses_directions(spec: ModelSpec) -> bool:
    """Whether the model ``spec`` needs the approach directions (``dir``: backlash)."""
    return "dir" in get_kind(spec.kind).needed_columns(spec)


def kind_names() -> tuple[str, ...]:
    return tuple(KINDS)


def _known() -> str:
    return ", ".join(KINDS)


def get_kind(name: str) -> ModelKind:
    """The table's entry for ``name`` (a kind, not a full model name)."""
    try:
        return KINDS[name]
    except KeyError:
        raise UnknownModelError(f"unknown model '{name}' (known: {_known()})") from None


def parse_model_name(name: str) -> ModelSpec:
    """``kinematic+ratio+backlash``, ``chebyshev:3``, … as a :class:`ModelSpec` (UnknownModelError)."""
    parts = [p.strip() for p in name.split("+")]
    head, effects = parts[0], tuple(parts[1:])
    if not head:
        raise UnknownModelError(f"empty model name (known: {_known()})")
    kind_name, sep, order_text = head.partition(":")
    kind = get_kind(kind_name.strip())
    order: int | None = None
    by_cv = False
    options: tuple[str, ...] = ()
    if sep and kind.takes_options:
        options = _parse_options(name, kind, order_text)
    elif sep:
        if not kind.takes_order:
            raise UnknownModelError(f"model '{name}': the {kind.name} model takes no order")
        order_text = order_text.strip()
        if order_text == "cv":
            by_cv = True
        elif order_text.isdigit() and 0 <= int(order_text) <= MAX_ORDER:
            order = int(order_text)
        else:
            raise UnknownModelError(
                f"model '{name}': the order must be 0..{MAX_ORDER} or 'cv', got {order_text!r}"
            )
    if effects:
        if not kind.takes_effects:
            takers = ", ".join(k.name for k in KINDS.values() if k.takes_effects)
            raise UnknownModelError(f"model '{name}': joint effects are offered by the {takers} models only")
        known = [e for e in EFFECTS if effect_by_name(e).of_the_robot]
        bad = [e or "(empty)" for e in effects if e not in EFFECTS]
        if bad:
            raise UnknownModelError(
                f"model '{name}': unknown effect(s) {', '.join(bad)} (known: {', '.join(known)})"
            )
        of_a_campaign = [e for e in effects if not effect_by_name(e).of_the_robot]
        if of_a_campaign:
            raise UnknownModelError(
                f"model '{name}': {', '.join(of_a_campaign)} belongs to one campaign's clock, not to the "
                f"robot, so a model cannot carry it to new targets (diagnose names it; model effects: "
                f"{', '.join(known)})"
            )
        if len(set(effects)) != len(effects):
            raise UnknownModelError(f"model '{name}': an effect is named twice")
    return ModelSpec(kind.name, effects, order, by_cv, options)


MAX_NEIGHBOURS = 100_000


def _neighbours_ok(text: str) -> bool:
    return text.isdigit() and 4 <= int(text) <= MAX_NEIGHBOURS


def _parse_options(name: str, kind: ModelKind, text: str) -> tuple[str, ...]:
    """The ``:option`` words of a kind (``k=N``, ``aniso``, ``all``, ``paper``), canonical (k first,
    each once)."""
    k: int | None = None
    words: set[str] = set()
    for part in (p.strip() for p in text.split(":")):
        if part in kind.option_words and part not in words and part != "k=N":
            words.add(part)
        elif "k=N" in kind.option_words and part.startswith("k=") and k is None and _neighbours_ok(part[2:]):
            k = int(part[2:])
        else:
            offered = ", ".join(
                f"k=N (N 4..{MAX_NEIGHBOURS}, local neighbourhoods)"
                if w == "k=N"
                else f"{w} ({OPTION_MEANING[w]})"
                for w in kind.option_words
            )
            no_order = "takes no order; it " if part == "cv" or part.isdigit() else ""
            raise UnknownModelError(
                f"model '{name}': the {kind.name} model {no_order}takes the options {offered}, each once; "
                f"got {part!r}"
            )
    return (*(() if k is None else (f"k={k}",)), *(w for w in OPTION_ORDER if w in words))


OPTION_MEANING = {
    "aniso": "per-joint ranges",
    "all": "every effect kept, no selection",
    "paper": "the paper's own form",
}


def with_order(spec: ModelSpec, order: int | Literal["cv"] | None) -> ModelSpec:
    """``spec`` with an order given apart from the name (``--order``, the HTTP ``order`` field)."""
    if order is None:
        return spec
    if not get_kind(spec.kind).takes_order:
        raise UnknownModelError(f"model '{spec.name}': the {spec.kind} model takes no order")
    if order == "cv":
        new = ModelSpec(spec.kind, spec.effects, None, True, spec.options)
    elif isinstance(order, int) and not isinstance(order, bool) and 0 <= order <= MAX_ORDER:
        new = ModelSpec(spec.kind, spec.effects, order, False, spec.options)
    else:
        raise UnknownModelError(f"the order must be 0..{MAX_ORDER} or 'cv', got {order!r}")
    if (spec.order is not None or spec.order_by_cv) and new != spec:
        raise UnknownModelError(f"model '{spec.name}' names an order; the order {order!r} contradicts it")
    return new


def max_parameters(spec: ModelSpec) -> int:
    """Parameters of the model before the identifiability analysis (a row-count floor)."""
    return get_kind(spec.kind).parameters(spec)


def uses_compliance(spec: ModelSpec) -> bool:
    """Whether the model ``spec`` fits a joint compliance (it needs gravity or payload torques)."""
    return spec.kind == "compliance" or "compliance" in spec.effects


def too_few_rows_reason(spec: ModelSpec, n_rows: int) -> str | None:
    """Why ``n_rows`` rows cannot determine ``spec``: fewer rows than the model has parameters
    before the identifiability analysis (:func:`max_parameters`, the campaign format's floor),
    as a sentence naming the model; None when they are enough."""
    needed = max_parameters(spec)
    if n_rows < needed:
        return (
            f"the {spec.name} model has {needed} parameters; {n_rows} rows leave it undetermined "
            f"(it needs at least {needed} rows)"
        )
    return None


def unloaded_reason(spec: ModelSpec, robot: RobotDescription, payload_kg: Any = 0.0) -> str | None:
    """Why a compliance (``compliance``, ``+compliance``) is not determined on ``robot`` with these
    payloads: no link masses in the description and no row with a payload, so no torque loads the
    joints and C2, C3 would be fitted on nothing; None when something loads them (or no compliance)."""
    if (
        uses_compliance(spec)
        and not np.any(robot.link_mass_kg > 0)
        and not np.any(np.asarray(payload_kg) > 0)
    ):
        return (
            f"the {spec.name} model needs link masses in the robot description ({robot.name} has none) "
            "or rows measured with a payload (payload_kg > 0): nothing loads the joints, so the "
            "compliance is not determined"
        )
    return None


def undetermined_reason(
    spec: ModelSpec, robot: RobotDescription, n_rows: int, payload_kg: Any = 0.0
) -> str | None:
    """Why ``n_rows`` rows with these payloads cannot determine ``spec`` on ``robot``, as a sentence
    naming the model (:func:`too_few_rows_reason`, then :func:`unloaded_reason`); None when they can."""
    return too_few_rows_reason(spec, n_rows) or unloaded_reason(spec, robot, payload_kg)


def fit_spec(
    spec: ModelSpec, robot: RobotDescription, rows: MeasuredRows, options: FitOptions | None = None
) -> FittedModel:
    """Fit ``spec`` on ``rows``; :class:`MissingColumnError` naming a needed column the rows lack,
    :class:`UndeterminedModelError` when a compliance has no masses and no payload to load the joints
    (:func:`unloaded_reason`; the row floor is the doors' to apply, on the data set), or when the
    measured positions are not millimetres of this robot
    (:func:`comp_daemon.models.units.millimetre_problem`, the rule ``data check`` applies too)."""
    kind = get_kind(spec.kind)
    for column in kind.needed_columns(spec):
        if getattr(rows, column) is None:
            raise MissingColumnError(f"the {spec.name} model needs the {_column_label(column)} column(s)")
    reason = unloaded_reason(spec, robot, rows.payload_kg)
    if reason is not None:
        raise UndeterminedModelError(reason)
    scale = millimetre_problem(robot, rows.a_deg, rows.xyz_mm)
    if scale is not None:
        raise UndeterminedModelError(scale)
    nominal = KinematicParams.from_robot(robot)
    p_nominal = tcp_position_mm(nominal, axes_deg_to_q_rad(rows.a_deg, nominal.sign))
    poses = len(np.unique(rows.a_deg, axis=0))
    if poses < MIN_POSES and spec.kind != "nominal":
        raise UndeterminedModelError(
            f"the fit rows hold {poses} distinct pose(s) (repeats of one pose add no geometry); "
            f"the {spec.name} model needs at least {MIN_POSES} poses spread over the workspace"
        )
    options = options or FitOptions()
    fitted = kind.fit(robot, rows, spec, options)
    if uses_compliance(spec) and not np.any(robot.link_mass_kg > 0):
        fitted.info["mass_warning"] = (
            f"{robot.name} has no link masses: the compliance sees the payload's torque only, not the "
            "links' own weight"
        )
    if options.frame == "base" and detect_frame(p_nominal, rows.xyz_mm) == "tracker":
        off = float(np.sqrt(np.mean(np.sum((rows.xyz_mm - p_nominal) ** 2, axis=1))))
        fitted.info["frame_warning"] = (
            f"--frame base, but the measured positions lie {off:.1f} mm RMS from the nominal TCPs "
            f"(more than {BASE_FRAME_MAX_RMS_MM:g} mm): they look like a tracker's frame; --frame auto "
            "or tracker registers it first"
        )
    return fitted


def _column_label(column: str) -> str:
    return "dir1..dir6" if column == "dir" else column


def fit_model(
    name: str,
    robot: RobotDescription,
    a_deg: NDArray[np.float64],
    xyz_mm: NDArray[np.float64],
    *,
    dir: NDArray[np.float64] | None = None,
    payload_kg: NDArray[np.float64] | float = 0.0,
    temp_c: NDArray[np.float64] | None = None,
    order: int | Literal["cv"] | None = None,
    effects: Sequence[str] = (),
    frame: Literal["auto", "base", "tracker"] = "auto",
    cv_folds: int = 5,
    seed: int = 0,
) -> FittedModel:
    """Fit the model ``name`` (a model name; ``effects`` and ``order`` may also be given apart)."""
    spec = parse_model_name("+".join([name, *effects]))
    spec = with_order(spec, order)
    rows = MeasuredRows(a_deg, xyz_mm, dir, np.asarray(payload_kg, dtype=float), temp_c)
    return fit_spec(spec, robot, rows, FitOptions(frame, cv_folds, seed))


#: the model class of each kind an artifact stores (``kriging-backlash`` is stored as a ``kriging`` model)
ARTIFACT_KINDS: dict[str, type[ErrorModel]] = {}
for _kind in KINDS.values():
    ARTIFACT_KINDS.setdefault(_kind.model_class.kind, _kind.model_class)


def model_from_payload(
    kind: str,
    robot: RobotDescription,
    payload: dict[str, Any],
    order: int | None,
    registration: NDArray[np.float64],
) -> ErrorModel:
    """The model of an artifact's ``kind`` and content (ValueError when either is not usable); a
    stacked model's stored base is rebuilt through here too."""
    model_class = ARTIFACT_KINDS.get(kind)
    if model_class is None:
        raise UnknownModelError(f"unknown model kind '{kind}' (known: {', '.join(ARTIFACT_KINDS)})")
    return model_class.from_stored(StoredModel(robot, payload, order, registration, model_from_payload))
