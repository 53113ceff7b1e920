"""Non-geometric effects of the twin (``shared/spec/diagnose.md``): catalogue, sizes, TCP and Jacobians.

One batch numerics package shared by the simulated plant, the calibration core and the diagnosis.

* :mod:`~comp_daemon.models.effects.base`: what a catalogue entry declares (:class:`Effect`,
  :class:`ParamArray`) and the inputs its functions receive;
* :mod:`~comp_daemon.models.effects.catalogue`: :data:`EFFECT_CATALOGUE`, every effect defined once
  (name, parameters with units and layout, how it changes the twin, the data it needs, its words);
* :mod:`~comp_daemon.models.effects.params`: :class:`EffectParams`, the sizes of all effects, and
  the parameter names (:func:`effect_param_names`);
* :mod:`~comp_daemon.models.effects.twin`: the twin's TCP (:func:`twin_tcp_mm`), its intermediates
  (:func:`twin_state`) and the exact Jacobians (:func:`effect_jacobian`, :func:`twin_jacobian`).

The effects today, for pose r and joint i (1..6), with the controller's axis value ``A_i`` (deg),
the approach direction ``dir_i`` (−1 / +1, 0 = unknown), the payload (kg) and the temperature
``temp_c`` (°C)::

    A_eff_i = A_i·(1 + eps_i) + h_i·dir_i + Σ_k (c_ik·sin(k·a_i) + s_ik·cos(k·a_i))     [deg]
              with a_i = A_i in rad (the commanded axis value converted to radians), k = 1..K
    q_i     = sign_i · A_eff_i in rad                                                     [rad]
    theta_i = q_i + offset_i + C_i·tau_i                                                  [rad]
    a_i, d_i  ← a_i·(1 + kappa·(temp_c − t_ref_c)),  d_i·(1 + kappa·(temp_c − t_ref_c))
    TCP     = forward kinematics of theta with the grown a, d (base frame and tool unchanged)

=============  ==========================  ==========================================
name           parameter                   unit
=============  ==========================  ==========================================
``h{i}``       backlash of joint i         deg (half the play: ±h around the command)
``eps{i}``     reduction-ratio error       1
``c{i}_{k}``   sine coefficient c_ik       deg (joint i, harmonic k)
``s{i}_{k}``   cosine coefficient s_ik     deg (joint i, harmonic k)
``C{i}``       compliance                  rad / (N m)
``kappa``      thermal expansion           1 / K
=============  ==========================  ==========================================

The catalogue is the definition; this table is its summary (a test keeps them in step).
"""

from comp_daemon.models.effects.base import Effect, EffectData, ParamArray, TwinInputs
from comp_daemon.models.effects.catalogue import EFFECT_CATALOGUE, EFFECTS, effect_by_name
from comp_daemon.models.effects.params import EffectParams, effect_param_names
from comp_daemon.models.effects.twin import (
    MassModel,
    TwinState,
    effect_jacobian,
    joint_output_axes_deg,
    twin_inputs,
    twin_jacobian,
    twin_state,
    twin_tcp_mm,
)

__all__ = [
    "EFFECTS",
    "EFFECT_CATALOGUE",
    "Effect",
    "EffectData",
    "EffectParams",
    "MassModel",
    "ParamArray",
    "TwinInputs",
    "TwinState",
    "effect_by_name",
    "effect_jacobian",
    "effect_param_names",
    "joint_output_axes_deg",
    "twin_inputs",
    "twin_jacobian",
    "twin_state",
    "twin_tcp_mm",
]
