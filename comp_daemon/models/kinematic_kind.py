"""The ``kinematic`` kind: MDH calibration (seed 000), with the joint effects named after ``+``.

The model class and the calibration are :mod:`comp_daemon.models.kinematic`'s; this module holds
the kind's fit and its registry entry. They sit beside the calibration rather than in it because
the shared fitting module (:mod:`comp_daemon.models.fitting`: the effect selection and the base
calibration the kriging kinds share) calls the calibration, and the kind's fit calls them.

``kinematic+ratio+backlash`` adds seed 001 §1's joint effects (any effect of
:data:`comp_daemon.models.effects.EFFECTS` that belongs to the robot), each kept only if it earns
its place out of fold; ``kinematic:all+…`` keeps every one, as the papers do.
"""

from __future__ import annotations

from comp_daemon.models.effects import effect_param_names
from comp_daemon.models.fitting import (
    FitOptions,
    FittedModel,
    ModelSpec,
    attach_tcp_covariance,
    kinematic_info,
    selected_base,
)
from comp_daemon.models.kind import ModelKind
from comp_daemon.models.kinematic import KinematicModel
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.robot.description import RobotDescription

__all__ = ["KIND", "KINEMATIC_PARAMETERS", "fit_kinematic_kind", "kinematic_parameters"]

KINEMATIC_PARAMETERS = 39  # 30 MDH + 6 base + 3 tool


def kinematic_parameters(spec: ModelSpec) -> int:
    """The geometry's parameters and those of the spec's joint effects."""
    return KINEMATIC_PARAMETERS + (len(effect_param_names(spec.effects)) if spec.effects else 0)


def fit_kinematic_kind(
    robot: RobotDescription, rows: MeasuredRows, spec: ModelSpec, options: FitOptions
) -> FittedModel:
    """MDH calibration with those of the spec's joint effects that earn their place (all of them
    with ``:all``)."""
    effects, selection, kf = selected_base(robot, rows, spec, options, spec.effects)
    attach_tcp_covariance(kf)
    info = {
        "kind": spec.kind,
        "rows": rows.n,
        **kinematic_info(kf, effects),
        "selection": selection.to_info(),
    }
    return FittedModel(kf.model, kf.frame, info)


KIND = ModelKind(
    "kinematic",
    "MDH calibration (seed 000); joint effects with +, e.g. kinematic+ratio+backlash (seed 001 §1)",
    KinematicModel,
    fit_kinematic_kind,
    kinematic_parameters,
    takes_effects=True,
    option_words=("all",),
    uses=("dir", "payload_kg", "temp_c"),
)
