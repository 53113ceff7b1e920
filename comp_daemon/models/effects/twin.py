"""The twin with its effects: TCP of n poses, every intermediate, and the exact Jacobians.

The effects of :data:`~comp_daemon.models.effects.catalogue.EFFECT_CATALOGUE` compose by stage
(:mod:`comp_daemon.models.effects.base`): the axis-stage effects add to the commanded axis value,
the joint-stage effects to the joint angle, the chain-stage effects change the frames::

    A_eff_i = A_i + Σ_axis-effects Σ_p value_p·basis_p(inputs)_i                          [deg]
    q_i     = sign_i · A_eff_i in rad + Σ_joint-effects Σ_p value_p·basis_p(inputs)_i     [rad]
    theta_i = q_i + offset_i
    chain   = each chain-stage effect applied in catalogue order to the MDH chain of theta
    TCP     = the chain's TCP (base frame and tool unchanged, the drift's translation added)

The time effects (drift, step) read the campaign clock ``clock`` (h, or the row number where a
campaign has no times); without a clock they contribute nothing.

The gravity torques ``tau`` (N m, DH sign, links and payload at the TCP, masses from the robot
file), when an effect needs them, are :func:`comp_daemon.kinematics.forward.gravity_torques_nm` of
the twin's geometry *before* any chain-stage change at the *commanded* configuration
``q = sign·A``. The effects move the configuration by hundredths of a degree, which changes the
torque by far less than a per mille; fixing the configuration keeps every effect Jacobian exact.

All-zero parameters are no effect: :func:`twin_tcp_mm` then equals the plain forward kinematics.
:func:`effect_jacobian` gives the derivative of the TCP with respect to any list of effect parameter
names and :func:`twin_jacobian` stacks it behind the 39 geometric columns of
:data:`comp_daemon.kinematics.params.PARAM_NAMES`. The geometric columns are exact except for the
dependence of the gravity torque on the geometry (a term of size ``C·∂tau/∂x``, below 1e-3 of the
column for industrial stiffness), which is left out as in every Gauss–Newton calibration.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.forward import Chain, chain, gravity_torques_nm, identification_jacobian
from comp_daemon.kinematics.params import KinematicParams, as_six_columns
from comp_daemon.models.base import approach_directions
from comp_daemon.models.effects.base import N_JOINTS, Effect, EffectData, TwinInputs
from comp_daemon.models.effects.catalogue import EFFECT_CATALOGUE
from comp_daemon.models.effects.params import EffectParams, parse_param_name
from comp_daemon.models.rows import MeasuredRows

if TYPE_CHECKING:
    from comp_daemon.robot.description import RobotDescription

__all__ = [
    "MassModel",
    "TwinState",
    "effect_data",
    "effect_jacobian",
    "joint_output_axes_deg",
    "twin_inputs",
    "twin_inputs_of",
    "twin_jacobian",
    "twin_jacobian_targets",
    "twin_state",
    "twin_state_of",
    "twin_tcp_mm",
]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class MassModel:
    """Link masses (kg) and centres of mass (mm, link i's in frame i) for the gravity torques."""

    link_mass_kg: FloatArray  # (6,)
    link_com_mm: FloatArray  # (6, 3)

    @classmethod
    def from_robot(cls, robot: RobotDescription) -> MassModel:
        return cls(link_mass_kg=robot.link_mass_kg, link_com_mm=robot.link_com_mm)


def _mass_model(robot_or_arrays: RobotDescription | MassModel) -> MassModel:
    if isinstance(robot_or_arrays, MassModel):
        return robot_or_arrays
    return MassModel.from_robot(robot_or_arrays)


@dataclass(frozen=True, slots=True)
class TwinState:
    """Everything the effect model computed for n poses (kept for the Jacobians)."""

    a_deg: FloatArray  # (n, 6) commanded axis values
    dir: FloatArray  # (n, 6) approach directions (0 = unknown)
    delta_t_k: FloatArray  # (n,) temp_c − t_ref_c (0 without temperatures)
    a_eff_deg: FloatArray  # (n, 6) axis values after the axis-stage effects
    tau_nm: FloatArray  # (n, 6) gravity torques at the commanded configuration (0 if not needed)
    joint_delta_rad: FloatArray  # (n, 6) what the joint-stage effects added to q
    q_rad: FloatArray  # (n, 6) theta − offset, joint-stage effects included
    chain: Chain  # frames of the twin (chain-stage effects included)
    tcp_mm: FloatArray  # (n, 3)
    inputs: TwinInputs  # what the effects' functions were given


def _check_inputs(
    a_deg: FloatArray,
    dir: FloatArray | None,
    payload_kg: FloatArray | float,
    temp_c: FloatArray | None,
    clock: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray | None, FloatArray | None]:
    a = as_six_columns(a_deg, "a_deg")
    n = a.shape[0]
    d = approach_directions(dir, n)
    payload = np.asarray(payload_kg, dtype=float)
    if payload.ndim > 1 or (payload.ndim == 1 and payload.shape[0] != n):
        raise ValueError(f"payload_kg: expected a number or shape ({n},), got {payload.shape}")
    payload = np.broadcast_to(payload, (n,))
    temp = None
    if temp_c is not None:
        temp = np.broadcast_to(np.asarray(temp_c, dtype=float), (n,))
    clk = None
    if clock is not None:
        clk = np.asarray(clock, dtype=float)
        if clk.ndim > 1 or (clk.ndim == 1 and clk.shape[0] != n):
            raise ValueError(f"clock: expected a number or shape ({n},), got {clk.shape}")
        clk = np.broadcast_to(clk, (n,))
    checks = (("a_deg", a), ("dir", d), ("payload_kg", payload), ("temp_c", temp), ("clock", clk))
    for name, arr in checks:
        if arr is not None and not np.all(np.isfinite(arr)):
            raise ValueError(f"{name}: values must be finite")
    return a, d, payload, temp, clk


def twin_inputs(
    robot_or_arrays: RobotDescription | MassModel,
    params: KinematicParams,
    a_deg: FloatArray,
    dir: FloatArray | None = None,
    payload_kg: FloatArray | float = 0.0,
    temp_c: FloatArray | None = None,
    *,
    t_ref_c: float = 20.0,
    with_torques: bool = True,
    clock: FloatArray | None = None,
    step_at: float = float("inf"),
) -> TwinInputs:
    """The checked per-pose inputs of the effects (gravity torques of ``params`` if asked)."""
    a, d, payload, temp, clk = _check_inputs(a_deg, dir, payload_kg, temp_c, clock)
    tau = None
    if with_torques:
        mass = _mass_model(robot_or_arrays)
        q_cmd = params.sign * np.deg2rad(a)
        tau = gravity_torques_nm(params, q_cmd, mass.link_mass_kg, mass.link_com_mm, payload)
    delta_t = np.zeros(a.shape[0]) if temp is None else temp - t_ref_c
    return TwinInputs(
        a_deg=a,
        dir=d,
        payload_kg=payload,
        temp_c=temp,
        delta_t_k=delta_t,
        tau_nm=tau,
        clock=clk,
        step_at=float(step_at),
    )


def twin_inputs_of(
    mass: MassModel,
    params: KinematicParams,
    rows: MeasuredRows,
    *,
    t_ref_c: float = 20.0,
    with_torques: bool = True,
    step_at: float = float("inf"),
) -> TwinInputs:
    """:func:`twin_inputs` at measured rows: the one place their columns (axis values,
    directions, payload, temperature, clock) enter the twin."""
    return twin_inputs(
        mass,
        params,
        rows.a_deg,
        rows.dir,
        rows.payload_kg,
        rows.temp_c,
        t_ref_c=t_ref_c,
        with_torques=with_torques,
        clock=rows.clock,
        step_at=step_at,
    )


def effect_data(
    mass: MassModel, params: KinematicParams, rows: MeasuredRows, moves_tcp: NDArray[np.bool_]
) -> EffectData:
    """What ``rows`` offer for identifying effects: the rows, the gravity torques of ``params`` at
    their commanded poses and ``moves_tcp`` (6,), whether each joint moves the TCP there."""
    tau = twin_inputs_of(mass, params, rows).tau_nm
    assert tau is not None  # asked for
    return EffectData(rows, tau, moves_tcp)


def _stage_delta(effect: Effect, values: tuple[Any, ...], basis: tuple[FloatArray, ...]) -> FloatArray:
    """(n, 6) what a linear axis / joint effect adds: Σ over its arrays of value·basis."""
    out: FloatArray = np.zeros(basis[0].shape[:2])
    for arr, value, b in zip(effect.arrays, values, basis, strict=True):
        v = np.asarray(value, dtype=float)
        coeff = v[:, None] if arr.layout == "joint" else v  # (6, 1), (6, K) or a scalar
        out += (b * coeff).sum(axis=2)
    return out


def twin_state(
    robot_or_arrays: RobotDescription | MassModel,
    params: KinematicParams,
    effects: EffectParams,
    a_deg: FloatArray,
    dir: FloatArray | None = None,
    payload_kg: FloatArray | float = 0.0,
    temp_c: FloatArray | None = None,
    *,
    with_torques: bool = False,
    clock: FloatArray | None = None,
) -> TwinState:
    """The twin of n poses with every intermediate kept; see the module docstring for the model.

    Only the effects with a non-zero parameter are evaluated. Gravity torques are computed when an
    active effect needs them or ``with_torques`` asks for them (a Jacobian w.r.t. a compliance needs
    them even where every compliance is zero).
    """
    x = twin_inputs(
        robot_or_arrays,
        params,
        a_deg,
        dir,
        payload_kg,
        temp_c,
        t_ref_c=effects.t_ref_c,
        with_torques=with_torques or _torques_needed(effects),
        clock=clock,
        step_at=effects.step_at,
    )
    return _state_at(params, effects, x)


def twin_state_of(
    mass: MassModel,
    params: KinematicParams,
    effects: EffectParams,
    rows: MeasuredRows,
    *,
    with_torques: bool = False,
) -> TwinState:
    """:func:`twin_state` at measured rows (their inputs by :func:`twin_inputs_of`)."""
    x = twin_inputs_of(
        mass,
        params,
        rows,
        t_ref_c=effects.t_ref_c,
        with_torques=with_torques or _torques_needed(effects),
        step_at=effects.step_at,
    )
    return _state_at(params, effects, x)


def _active(effects: EffectParams) -> list[Effect]:
    """The catalogue's effects with a non-zero parameter: the only ones evaluated."""
    return [e for e in EFFECT_CATALOGUE if not effects.is_zero(e)]


def _torques_needed(effects: EffectParams) -> bool:
    return any(e.needs_torques for e in _active(effects))


def _state_at(params: KinematicParams, effects: EffectParams, x: TwinInputs) -> TwinState:
    """The twin's intermediates and TCP with ``effects`` at the checked inputs ``x``."""
    active = _active(effects)
    n = x.a_deg.shape[0]
    a_eff = x.a_deg
    joint_delta: FloatArray = np.zeros((n, N_JOINTS))
    for e in active:
        if e.basis is not None:
            delta = _stage_delta(e, effects.of(e), e.basis(x, effects.n_harmonics))
            if e.stage == "axis":
                a_eff = a_eff + delta
            else:
                joint_delta = joint_delta + delta
    q = params.sign * np.deg2rad(a_eff) + joint_delta
    ch = chain(params, q)
    for e in active:
        if e.chain is not None:
            ch = e.chain.apply(effects.of(e), x, params, ch)
    return TwinState(
        a_deg=x.a_deg,
        dir=x.dir,
        delta_t_k=x.delta_t_k,
        a_eff_deg=a_eff,
        tau_nm=x.tau_nm if x.tau_nm is not None else np.zeros((n, N_JOINTS)),
        joint_delta_rad=joint_delta,
        q_rad=q,
        chain=ch,
        tcp_mm=ch.tcp_mm,
        inputs=x,
    )


def twin_tcp_mm(
    robot_or_arrays: RobotDescription | MassModel,
    params: KinematicParams,
    effects: EffectParams,
    a_deg: FloatArray,
    dir: FloatArray | None = None,
    payload_kg: FloatArray | float = 0.0,
    temp_c: FloatArray | None = None,
    *,
    clock: FloatArray | None = None,
) -> FloatArray:
    """(n, 3) TCP (mm, world frame of ``params``) of the twin with ``effects`` at axis values ``a_deg``.

    ``dir`` (n, 6) of −1/+1 (0 or None: unknown, no backlash); ``payload_kg`` a number or (n,);
    ``temp_c`` (n,) or None (no thermal growth); ``clock`` (n,) the campaign clock (h) of the time
    effects (drift, step), or None (no time effect).
    """
    return twin_state(robot_or_arrays, params, effects, a_deg, dir, payload_kg, temp_c, clock=clock).tcp_mm


def joint_output_axes_deg(
    robot_or_arrays: RobotDescription | MassModel,
    params: KinematicParams,
    effects: EffectParams,
    a_deg: FloatArray,
    dir: FloatArray | None = None,
    payload_kg: FloatArray | float = 0.0,
) -> FloatArray:
    """(n, 6) true output angle of each joint in the controller's convention (deg).

    The axis value that the joint really sits at: after the axis- and joint-stage effects (ratio
    error, backlash, transmission error, gravity deflection: ``A_eff + sign·Δq`` in deg); what a
    grating on the joint reads.
    """
    st = twin_state(robot_or_arrays, params, effects, a_deg, dir, payload_kg, None)
    out: FloatArray = st.a_eff_deg + params.sign * np.rad2deg(st.joint_delta_rad)
    return out


def _geometric(params: KinematicParams, effects: EffectParams, st: TwinState) -> FloatArray:
    """(n, 3, 39) geometric columns with the chain-stage effects' chain rule applied."""
    geo = identification_jacobian(params, st.q_rad, st.chain)
    for e in EFFECT_CATALOGUE:
        if e.chain is not None:
            e.chain.geometric(effects.of(e), st.inputs, geo)
    return geo


def _effect_columns(
    params: KinematicParams,
    effects: EffectParams,
    st: TwinState,
    names: Sequence[str],
    geo: FloatArray,
) -> FloatArray:
    n = st.a_deg.shape[0]
    out = np.empty((n, 3, len(names)))
    j_theta = geo[:, :, 0:30:5]  # d TCP / d theta_i (theta columns are index 5·i)
    axis_scale = params.sign * (np.pi / 180.0)
    bases: dict[str, tuple[FloatArray, ...]] = {}
    for col, name in enumerate(names):
        ref = parse_param_name(name, effects.n_harmonics)
        e = ref.effect
        if e.chain is not None:
            out[:, :, col] = e.chain.column(effects.of(e), st.inputs, params, geo, ref)
            continue
        assert e.basis is not None
        if e.name not in bases:
            bases[e.name] = e.basis(st.inputs, effects.n_harmonics)
        b = bases[e.name][ref.array]  # (n, 6, w)
        dtheta = b[:, :, 0 if ref.harmonic is None else ref.harmonic]  # (n, 6)
        if e.stage == "axis":
            dtheta = dtheta * axis_scale
        if ref.joint is None:  # a scalar acts on every joint
            out[:, :, col] = np.einsum("nkj,nj->nk", j_theta, dtheta)
        else:
            out[:, :, col] = j_theta[:, :, ref.joint] * dtheta[:, ref.joint, None]
    return out


def _needs_torques(effects: EffectParams, names: Sequence[str]) -> bool:
    return any(parse_param_name(name, effects.n_harmonics).effect.needs_torques for name in names)


def _jacobian_parts(
    robot_or_arrays: RobotDescription | MassModel,
    params: KinematicParams,
    effects: EffectParams,
    names: Sequence[str],
    a_deg: FloatArray,
    dir: FloatArray | None,
    payload_kg: FloatArray | float,
    temp_c: FloatArray | None,
    clock: FloatArray | None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """TCP (n, 3), geometric columns (n, 3, 39) and the named effect columns (n, 3, len(names))."""
    torques = _needs_torques(effects, names)
    st = twin_state(
        robot_or_arrays, params, effects, a_deg, dir, payload_kg, temp_c, with_torques=torques, clock=clock
    )
    geo = _geometric(params, effects, st)
    return st.tcp_mm, geo, _effect_columns(params, effects, st, names, geo)


def effect_jacobian(
    robot_or_arrays: RobotDescription | MassModel,
    params: KinematicParams,
    effects: EffectParams,
    names: Sequence[str],
    a_deg: FloatArray,
    dir: FloatArray | None = None,
    payload_kg: FloatArray | float = 0.0,
    temp_c: FloatArray | None = None,
    *,
    clock: FloatArray | None = None,
) -> FloatArray:
    """(n, 3, len(names)) derivative of :func:`twin_tcp_mm` w.r.t. the named effect parameters.

    Columns are in mm per the parameter's unit (the catalogue's units); exact for every name.
    """
    return _jacobian_parts(robot_or_arrays, params, effects, names, a_deg, dir, payload_kg, temp_c, clock)[2]


def twin_jacobian(
    robot_or_arrays: RobotDescription | MassModel,
    params: KinematicParams,
    effects: EffectParams,
    names: Sequence[str],
    a_deg: FloatArray,
    dir: FloatArray | None = None,
    payload_kg: FloatArray | float = 0.0,
    temp_c: FloatArray | None = None,
    *,
    clock: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """TCP (n, 3) and the stacked Jacobian (n, 3, 39 + len(names)): [geometric 39 | named effects].

    The geometric block is the derivative w.r.t. :meth:`KinematicParams.apply`'s vector at the
    twin's effective configuration (the gravity torque held fixed, see the module docstring).
    """
    tcp, geo, eff = _jacobian_parts(
        robot_or_arrays, params, effects, names, a_deg, dir, payload_kg, temp_c, clock
    )
    return tcp, np.concatenate([geo, eff], axis=2)


def twin_jacobian_targets(
    mass: MassModel,
    params: KinematicParams,
    effects: EffectParams,
    names: Sequence[str],
    targets_mm: Sequence[FloatArray | None],
    rows: MeasuredRows,
) -> list[tuple[FloatArray, FloatArray]]:
    """:func:`twin_jacobian` of several points on the flange at the poses of ``rows``, from one twin.

    ``targets_mm`` holds each point's place in the flange frame (mm), None for the TCP (the tool
    of ``params``). The twin (its effects, frames and the gravity torques, whose payload sits at the
    TCP whichever point is measured) is evaluated once; each point's position and columns are then
    those of :func:`twin_jacobian` with the point as the tool. Returns (position (n, 3), Jacobian
    (n, 3, 39 + len(names))) per point, in the order given.
    """
    st = twin_state_of(mass, params, effects, rows, with_torques=_needs_torques(effects, names))
    flange = st.chain.world_T_frame[:, 6]
    out = []
    for place in targets_mm:
        at, p = st, params
        if place is not None:
            p = replace(params, tool_xyz_mm=np.asarray(place, dtype=float))
            tcp = flange[:, :3, :3] @ p.tool_xyz_mm + flange[:, :3, 3]
            at = replace(st, chain=replace(st.chain, tcp_mm=tcp), tcp_mm=tcp)
        geo = _geometric(p, effects, at)
        out.append((at.tcp_mm, np.concatenate([geo, _effect_columns(p, effects, at, names, geo)], axis=2)))
    return out
