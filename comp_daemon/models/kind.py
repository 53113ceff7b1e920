"""What a model kind is: the :class:`ModelKind` entry each kind's module declares beside its model.

A kind's module holds its :class:`~comp_daemon.models.base.ErrorModel` subclass, its fit function
(``fit(robot, rows, spec, options) -> FittedModel``, :mod:`comp_daemon.models.fitting`) and a
module-level ``KIND = ModelKind(...)`` naming both; :mod:`comp_daemon.models.registry` lists the
entries once and every door reads them there. This module sits below the kinds' modules (they
import it) and above the shared fitting module, so that no kind imports the registry.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from comp_daemon.models.base import ErrorModel
from comp_daemon.models.effects import effect_by_name
from comp_daemon.models.fitting import FitOptions, FittedModel, ModelSpec
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.robot.description import RobotDescription

__all__ = ["FitFunction", "ModelKind"]

FitFunction = Callable[[RobotDescription, MeasuredRows, ModelSpec, FitOptions], FittedModel]


@dataclass(frozen=True, slots=True)
class ModelKind:
    """One kind: its name and summary, the class that predicts with it and rebuilds it from an
    artifact, the function that fits it, its parameter count before the identifiability analysis
    (the floor on the rows of a data set), the options its name takes (joint effects, a Chebyshev
    order, ``:option`` words), the data columns it needs and those it uses when present."""

    name: str
    summary: str
    model_class: type[ErrorModel]
    fit: FitFunction
    parameters: Callable[[ModelSpec], int]  # before identifiability analysis
    takes_effects: bool = False  # "+ratio+backlash"
    takes_order: bool = False  # ":3", ":cv"
    option_words: tuple[str, ...] = ()  # the ":option" words it takes: "k=N", "aniso", "all", "paper"
    needs: tuple[str, ...] = ()  # data columns without which the fit is refused
    uses: tuple[str, ...] = ()  # optional columns the fit takes when the data have them

    @property
    def takes_options(self) -> bool:
        return bool(self.option_words)

    def needed_columns(self, spec: ModelSpec) -> tuple[str, ...]:
        """The columns this spec cannot be fitted without (the kind's, and its effects')."""
        extra = tuple(column for e in spec.effects for column in effect_by_name(e).required)
        return tuple(dict.fromkeys((*self.needs, *extra)))
