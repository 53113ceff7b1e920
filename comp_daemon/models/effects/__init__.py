"""Non-geometric effects of the twin (``docs/diagnosis-output.md``): catalogue, sizes, TCP and Jacobians.

One batch numerics package shared by the simulated plant, the calibration core and the diagnosis.

* :mod:`~comp_daemon.models.effects.base`: what a catalogue entry declares (:class:`Effect`,
  :class:`ParamArray`) and the inputs its functions receive;
* :mod:`~comp_daemon.models.effects.catalogue`: :data:`EFFECT_CATALOGUE`, every effect defined once
  (name, parameters with units and layout, how it changes the twin, the data it needs, its words);
* :mod:`~comp_daemon.models.effects.params`: :class:`EffectParams`, the sizes of all effects, and
  the parameter names (:func:`effect_param_names`);
* :mod:`~comp_daemon.models.effects.twin`: the twin's TCP (:func:`twin_tcp_mm`), its intermediates
  (:func:`twin_state`, or :func:`twin_state_of` at measured rows) and the exact Jacobians
  (:func:`effect_jacobian`, :func:`twin_jacobian`); what the effects derive from measured rows
  (:func:`twin_inputs_of`, :func:`effect_data`).

The effects, their composition and the table of their parameters and units are in the docstring
of :mod:`~comp_daemon.models.effects.catalogue`; how the twin composes them by stage in that of
:mod:`~comp_daemon.models.effects.twin`.
"""

from comp_daemon.models.effects.base import Effect, EffectData, ParamArray, TwinInputs
from comp_daemon.models.effects.catalogue import (
    EFFECT_CATALOGUE,
    EFFECTS,
    TIME_EFFECTS,
    TRANSMISSION_EFFECTS,
    effect_by_name,
)
from comp_daemon.models.effects.params import EffectParams, effect_param_names
from comp_daemon.models.effects.twin import (
    MassModel,
    TwinState,
    effect_data,
    effect_jacobian,
    joint_output_axes_deg,
    twin_inputs,
    twin_inputs_of,
    twin_jacobian,
    twin_jacobian_targets,
    twin_state,
    twin_state_of,
    twin_tcp_mm,
)

__all__ = [
    "EFFECTS",
    "EFFECT_CATALOGUE",
    "TIME_EFFECTS",
    "TRANSMISSION_EFFECTS",
    "Effect",
    "EffectData",
    "EffectParams",
    "MassModel",
    "ParamArray",
    "TwinInputs",
    "TwinState",
    "effect_by_name",
    "effect_data",
    "effect_jacobian",
    "effect_param_names",
    "joint_output_axes_deg",
    "twin_inputs",
    "twin_inputs_of",
    "twin_jacobian",
    "twin_jacobian_targets",
    "twin_state",
    "twin_state_of",
    "twin_tcp_mm",
]
