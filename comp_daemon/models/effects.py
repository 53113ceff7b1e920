"""Non-geometric effects of the twin (``shared/spec/diagnose.md``), their TCP model and Jacobians.

One batch numerics module shared by the simulated plant, the calibration core and the diagnosis.
For pose r and joint i (1..6), with the controller's axis value ``A_i`` (deg), the approach
direction ``dir_i`` (−1 / +1, 0 = unknown), the payload (kg) and the temperature ``temp_c`` (°C),
the effects compose in this order::

    A_eff_i = A_i·(1 + eps_i) + h_i·dir_i + Σ_k (c_ik·sin(k·a_i) + s_ik·cos(k·a_i))     [deg]
              with a_i = A_i in rad (the commanded axis value converted to radians), k = 1..K
    q_i     = sign_i · A_eff_i in rad                                                     [rad]
    theta_i = q_i + offset_i + C_i·tau_i                                                  [rad]
    a_i, d_i  ← a_i·(1 + kappa·(temp_c − t_ref_c)),  d_i·(1 + kappa·(temp_c − t_ref_c))
    TCP     = forward kinematics of theta with the grown a, d (base frame and tool unchanged)

``tau`` (N m, DH sign, links and payload at the TCP, masses from the robot file) is
:func:`comp_daemon.kinematics.forward.gravity_torques_nm` of the twin's geometry *before* thermal
growth at the *commanded* configuration ``q = sign·A``. The effects move the configuration by
hundredths of a degree, which changes the torque by far less than a per mille; fixing the
configuration keeps every effect Jacobian exact.

Units of the parameters (and so of the Jacobian columns, mm per unit):

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

All-zero parameters are no effect: :func:`twin_tcp_mm` then equals the plain forward kinematics.
:func:`effect_jacobian` gives the derivative of the TCP with respect to any list of these names and
:func:`twin_jacobian` stacks it behind the 39 geometric columns of
:data:`comp_daemon.kinematics.params.PARAM_NAMES`. The geometric columns are exact except for the
dependence of the gravity torque on the geometry (a term of size ``C·∂tau/∂x``, below 1e-3 of the
column for industrial stiffness), which is left out as in every Gauss–Newton calibration.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.forward import Chain, chain, gravity_torques_nm, identification_jacobian
from comp_daemon.kinematics.params import KinematicParams

if TYPE_CHECKING:
    from comp_daemon.robot.description import RobotDescription

__all__ = [
    "EFFECTS",
    "EffectParams",
    "MassModel",
    "TwinState",
    "effect_jacobian",
    "effect_param_names",
    "joint_output_axes_deg",
    "twin_jacobian",
    "twin_state",
    "twin_tcp_mm",
]

N_JOINTS = 6
EFFECTS: tuple[str, ...] = ("backlash", "ratio", "cyclic", "compliance", "thermal")
_NAME_RE = re.compile(r"^(?:(h|eps|C)([1-6])|([cs])([1-6])_([1-9][0-9]*)|(kappa))$")


@dataclass(frozen=True, slots=True)
class MassModel:
    """Link masses (kg) and centres of mass (mm, link i's in frame i) for the gravity torques."""

    link_mass_kg: NDArray[np.float64]  # (6,)
    link_com_mm: NDArray[np.float64]  # (6, 3)

    @classmethod
    def from_robot(cls, robot: RobotDescription) -> MassModel:
        return cls(link_mass_kg=robot.link_mass_kg, link_com_mm=robot.link_com_mm)


def _mass_model(robot_or_arrays: RobotDescription | MassModel) -> MassModel:
    if isinstance(robot_or_arrays, MassModel):
        return robot_or_arrays
    return MassModel.from_robot(robot_or_arrays)


def _vec6(value: object, name: str) -> NDArray[np.float64]:
    out = np.array(value, dtype=float)
    if out.shape == ():
        out = np.full(N_JOINTS, float(out))
    if out.shape != (N_JOINTS,):
        raise ValueError(f"EffectParams.{name}: expected 6 values (one per joint), got shape {out.shape}")
    if not np.all(np.isfinite(out)):
        raise ValueError(f"EffectParams.{name}: values must be finite")
    return out


@dataclass(frozen=True, slots=True)
class EffectParams:
    """Sizes of the non-geometric effects, per joint (index 0 = joint 1). Zeros are no effect.

    ``cyclic_sin_deg[i, k-1]`` is c_ik and ``cyclic_cos_deg[i, k-1]`` is s_ik of harmonic k; the
    number of harmonics K is their second dimension (0 allowed).
    """

    backlash_deg: NDArray[np.float64] = field(default_factory=lambda: np.zeros(N_JOINTS))
    ratio: NDArray[np.float64] = field(default_factory=lambda: np.zeros(N_JOINTS))
    cyclic_sin_deg: NDArray[np.float64] = field(default_factory=lambda: np.zeros((N_JOINTS, 0)))
    cyclic_cos_deg: NDArray[np.float64] = field(default_factory=lambda: np.zeros((N_JOINTS, 0)))
    compliance_rad_per_nm: NDArray[np.float64] = field(default_factory=lambda: np.zeros(N_JOINTS))
    thermal_per_k: float = 0.0
    t_ref_c: float = 20.0

    def __post_init__(self) -> None:
        for name in ("backlash_deg", "ratio", "compliance_rad_per_nm"):
            object.__setattr__(self, name, _vec6(getattr(self, name), name))
        sin = np.array(self.cyclic_sin_deg, dtype=float)
        cos = np.array(self.cyclic_cos_deg, dtype=float)
        if sin.ndim != 2 or sin.shape[0] != N_JOINTS or sin.shape != cos.shape:
            raise ValueError(
                "EffectParams.cyclic_sin_deg / cyclic_cos_deg: expected two arrays of shape (6, K), "
                f"got {sin.shape} and {cos.shape}"
            )
        if not (np.all(np.isfinite(sin)) and np.all(np.isfinite(cos))):
            raise ValueError("EffectParams.cyclic_sin_deg / cyclic_cos_deg: values must be finite")
        object.__setattr__(self, "cyclic_sin_deg", sin)
        object.__setattr__(self, "cyclic_cos_deg", cos)
        for name in ("thermal_per_k", "t_ref_c"):
            value = float(getattr(self, name))
            if not np.isfinite(value):
                raise ValueError(f"EffectParams.{name}: must be finite, got {value}")
            object.__setattr__(self, name, value)

    @classmethod
    def zeros(cls, n_harmonics: int = 0, t_ref_c: float = 20.0) -> EffectParams:
        """No effect at all, with room for ``n_harmonics`` cyclic harmonics."""
        if n_harmonics < 0:
            raise ValueError(f"n_harmonics must be >= 0, got {n_harmonics}")
        k = np.zeros((N_JOINTS, n_harmonics))
        return cls(cyclic_sin_deg=k, cyclic_cos_deg=k.copy(), t_ref_c=t_ref_c)

    @property
    def n_harmonics(self) -> int:
        return int(self.cyclic_sin_deg.shape[1])

    def names(
        self, effects: Sequence[str] = EFFECTS, joints: Sequence[int] = (1, 2, 3, 4, 5, 6)
    ) -> list[str]:
        """Parameter names of ``effects`` on ``joints`` with this object's number of harmonics."""
        return effect_param_names(effects, joints, self.n_harmonics)

    def _check_name(self, name: str) -> re.Match[str]:
        m = _NAME_RE.match(name)
        if m is None:
            raise ValueError(
                f"unknown effect parameter '{name}' (expected h<j>, eps<j>, c<j>_<k>, s<j>_<k>, C<j>, kappa)"
            )
        if m.group(3) is not None and int(m.group(5)) > self.n_harmonics:
            raise ValueError(
                f"effect parameter '{name}': harmonic {m.group(5)} exceeds the {self.n_harmonics} "
                "harmonics of these effect parameters"
            )
        return m

    def get(self, names: Sequence[str]) -> NDArray[np.float64]:
        """Values of the named parameters (units as in the module docstring)."""
        out = np.empty(len(names))
        for index, name in enumerate(names):
            m = self._check_name(name)
            if m.group(6):
                out[index] = self.thermal_per_k
            elif m.group(1):
                arr = {"h": self.backlash_deg, "eps": self.ratio, "C": self.compliance_rad_per_nm}[m.group(1)]
                out[index] = arr[int(m.group(2)) - 1]
            else:
                arr = self.cyclic_sin_deg if m.group(3) == "c" else self.cyclic_cos_deg
                out[index] = arr[int(m.group(4)) - 1, int(m.group(5)) - 1]
        return out

    def with_values(
        self, names: Sequence[str], values: NDArray[np.float64] | Sequence[float]
    ) -> EffectParams:
        """A copy with the named parameters set to ``values``."""
        values = np.asarray(values, dtype=float)
        if values.shape != (len(names),):
            raise ValueError(f"{len(names)} names but values of shape {values.shape}")
        arrays = {
            "h": self.backlash_deg.copy(),
            "eps": self.ratio.copy(),
            "C": self.compliance_rad_per_nm.copy(),
            "c": self.cyclic_sin_deg.copy(),
            "s": self.cyclic_cos_deg.copy(),
        }
        kappa = self.thermal_per_k
        for name, value in zip(names, values, strict=True):
            m = self._check_name(name)
            if m.group(6):
                kappa = float(value)
            elif m.group(1):
                arrays[m.group(1)][int(m.group(2)) - 1] = value
            else:
                arrays[m.group(3)][int(m.group(4)) - 1, int(m.group(5)) - 1] = value
        return replace(
            self,
            backlash_deg=arrays["h"],
            ratio=arrays["eps"],
            compliance_rad_per_nm=arrays["C"],
            cyclic_sin_deg=arrays["c"],
            cyclic_cos_deg=arrays["s"],
            thermal_per_k=kappa,
        )

    def add(self, names: Sequence[str], delta: NDArray[np.float64] | Sequence[float]) -> EffectParams:
        """A copy with ``delta`` added to the named parameters (an identification step)."""
        return self.with_values(names, self.get(names) + np.asarray(delta, dtype=float))


def effect_param_names(
    effects: str | Sequence[str], joints: Sequence[int] = (1, 2, 3, 4, 5, 6), n_harmonics: int = 0
) -> list[str]:
    """Parameter names of the given effect(s) (diagnose.md vocabulary) on the given joints (1-based).

    ``thermal`` has the single name ``kappa`` whatever the joints; ``cyclic`` gives, per joint,
    ``c{j}_{k}`` then ``s{j}_{k}`` for k = 1..n_harmonics.
    """
    if isinstance(effects, str):
        effects = (effects,)
    for j in joints:
        if not 1 <= int(j) <= N_JOINTS:
            raise ValueError(f"joint {j}: joints are numbered 1..6")
    names: list[str] = []
    for effect in effects:
        if effect == "backlash":
            names += [f"h{j}" for j in joints]
        elif effect == "ratio":
            names += [f"eps{j}" for j in joints]
        elif effect == "cyclic":
            for j in joints:
                names += [f"c{j}_{k}" for k in range(1, n_harmonics + 1)]
                names += [f"s{j}_{k}" for k in range(1, n_harmonics + 1)]
        elif effect == "compliance":
            names += [f"C{j}" for j in joints]
        elif effect == "thermal":
            names.append("kappa")
        else:
            raise ValueError(f"unknown effect '{effect}' (known: {', '.join(EFFECTS)})")
    return names


@dataclass(frozen=True, slots=True)
class TwinState:
    """Everything the effect model computed for n poses (kept for the Jacobians)."""

    a_deg: NDArray[np.float64]  # (n, 6) commanded axis values
    dir: NDArray[np.float64]  # (n, 6) approach directions (0 = unknown)
    delta_t_k: NDArray[np.float64]  # (n,) temp_c − t_ref_c (0 without temperatures)
    a_eff_deg: NDArray[np.float64]  # (n, 6) axis values after ratio, backlash, cyclic error
    tau_nm: NDArray[np.float64]  # (n, 6) gravity torques at the commanded configuration
    q_rad: NDArray[np.float64]  # (n, 6) theta − offset, compliance included
    chain: Chain  # frames of the twin (thermal growth included)
    tcp_mm: NDArray[np.float64]  # (n, 3)


def _check_inputs(
    a_deg: NDArray[np.float64],
    dir: NDArray[np.float64] | None,
    payload_kg: NDArray[np.float64] | float,
    temp_c: NDArray[np.float64] | None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64] | None]:
    a = np.asarray(a_deg, dtype=float)
    if a.ndim == 1:
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != N_JOINTS:
        raise ValueError(f"a_deg: expected shape (n, 6), got {a.shape}")
    n = a.shape[0]
    d = np.zeros((n, N_JOINTS)) if dir is None else np.asarray(dir, dtype=float)
    if d.ndim == 1:
        d = d[None, :]
    if d.shape != (n, N_JOINTS):
        raise ValueError(f"dir: expected shape ({n}, 6) like a_deg, got {d.shape}")
    payload = np.asarray(payload_kg, dtype=float)
    if payload.ndim > 1 or (payload.ndim == 1 and payload.shape[0] != n):
        raise ValueError(f"payload_kg: expected a number or shape ({n},), got {payload.shape}")
    payload = np.broadcast_to(payload, (n,))
    temp = None
    if temp_c is not None:
        temp = np.broadcast_to(np.asarray(temp_c, dtype=float), (n,))
    for name, arr in (("a_deg", a), ("dir", d), ("payload_kg", payload), ("temp_c", temp)):
        if arr is not None and not np.all(np.isfinite(arr)):
            raise ValueError(f"{name}: values must be finite")
    return a, d, payload, temp


def _cyclic_deg(effects: EffectParams, a_deg: NDArray[np.float64]) -> NDArray[np.float64]:
    k = np.arange(1, effects.n_harmonics + 1)
    arg = np.deg2rad(a_deg)[:, :, None] * k  # (n, 6, K)
    return (np.sin(arg) * effects.cyclic_sin_deg + np.cos(arg) * effects.cyclic_cos_deg).sum(axis=2)


def _grow_chain(ch: Chain, scale: NDArray[np.float64], tool_xyz_mm: NDArray[np.float64]) -> Chain:
    """The chain with every a_i, d_i multiplied by ``scale`` (n,), exactly.

    Link rotations do not depend on a, d and each link's translation is linear in them, so the frame
    origins move to ``o_0 + scale·(o_i − o_0)`` while the base frame and the tool offset stay.
    """
    if np.all(scale == 1.0):
        return ch
    frames = ch.world_T_frame.copy()
    o0 = frames[:, 0, None, :3, 3]
    frames[:, 1:, :3, 3] = o0 + scale[:, None, None] * (frames[:, 1:, :3, 3] - o0)
    tcp = frames[:, 6, :3, :3] @ tool_xyz_mm + frames[:, 6, :3, 3]
    return Chain(world_T_frame=frames, x_prime=ch.x_prime, y_beta=ch.y_beta, tcp_mm=tcp)


def twin_state(
    robot_or_arrays: RobotDescription | MassModel,
    params: KinematicParams,
    effects: EffectParams,
    a_deg: NDArray[np.float64],
    dir: NDArray[np.float64] | None = None,
    payload_kg: NDArray[np.float64] | float = 0.0,
    temp_c: NDArray[np.float64] | None = None,
    *,
    with_torques: bool = False,
) -> TwinState:
    """The twin of n poses with every intermediate kept; see the module docstring for the model.

    Gravity torques are computed when some compliance is non-zero or ``with_torques`` asks for them
    (a Jacobian w.r.t. a compliance needs them even where every compliance is zero).
    """
    mass = _mass_model(robot_or_arrays)
    a, d, payload, temp = _check_inputs(a_deg, dir, payload_kg, temp_c)
    n = a.shape[0]
    a_eff = a * (1.0 + effects.ratio) + effects.backlash_deg * d
    if effects.n_harmonics:
        a_eff = a_eff + _cyclic_deg(effects, a)
    q = params.sign * np.deg2rad(a_eff)
    if with_torques or np.any(effects.compliance_rad_per_nm != 0.0):
        q_cmd = params.sign * np.deg2rad(a)
        tau = gravity_torques_nm(params, q_cmd, mass.link_mass_kg, mass.link_com_mm, payload)
        q = q + effects.compliance_rad_per_nm * tau
    else:
        tau = np.zeros((n, N_JOINTS))
    delta_t = np.zeros(n) if temp is None else temp - effects.t_ref_c
    ch = _grow_chain(chain(params, q), 1.0 + effects.thermal_per_k * delta_t, params.tool_xyz_mm)
    return TwinState(
        a_deg=a,
        dir=d,
        delta_t_k=delta_t,
        a_eff_deg=a_eff,
        tau_nm=tau,
        q_rad=q,
        chain=ch,
        tcp_mm=ch.tcp_mm,
    )


def twin_tcp_mm(
    robot_or_arrays: RobotDescription | MassModel,
    params: KinematicParams,
    effects: EffectParams,
    a_deg: NDArray[np.float64],
    dir: NDArray[np.float64] | None = None,
    payload_kg: NDArray[np.float64] | float = 0.0,
    temp_c: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """(n, 3) TCP (mm, world frame of ``params``) of the twin with ``effects`` at axis values ``a_deg``.

    ``dir`` (n, 6) of −1/+1 (0 or None: unknown, no backlash); ``payload_kg`` a number or (n,);
    ``temp_c`` (n,) or None (no thermal growth).
    """
    return twin_state(robot_or_arrays, params, effects, a_deg, dir, payload_kg, temp_c).tcp_mm


def joint_output_axes_deg(
    robot_or_arrays: RobotDescription | MassModel,
    params: KinematicParams,
    effects: EffectParams,
    a_deg: NDArray[np.float64],
    dir: NDArray[np.float64] | None = None,
    payload_kg: NDArray[np.float64] | float = 0.0,
) -> NDArray[np.float64]:
    """(n, 6) true output angle of each joint in the controller's convention (deg).

    The axis value that the joint really sits at: after ratio error, backlash, transmission error
    and gravity deflection (``A_eff + sign·C·tau`` in deg); what a grating on the joint reads.
    """
    st = twin_state(robot_or_arrays, params, effects, a_deg, dir, payload_kg, None)
    return st.a_eff_deg + params.sign * np.rad2deg(effects.compliance_rad_per_nm * st.tau_nm)


def _jacobians(
    params: KinematicParams, effects: EffectParams, st: TwinState
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(n, 3, 39) geometric and (n, 3, 6) d TCP / d theta Jacobians over all rows."""
    scale = 1.0 + effects.thermal_per_k * st.delta_t_k
    geo = identification_jacobian(params, st.q_rad, st.chain)
    # columns of the grown a, d → columns of the parameters a, d themselves
    da = np.r_[1:30:5, 2:30:5]
    geo[:, :, da] *= scale[:, None, None]
    # theta columns (index 5·i) are d TCP / d theta_i
    return geo, geo[:, :, 0:30:5].copy()


def _effect_columns(
    params: KinematicParams,
    effects: EffectParams,
    st: TwinState,
    names: Sequence[str],
    geo: NDArray[np.float64],
    j_theta: NDArray[np.float64],
) -> NDArray[np.float64]:
    n = st.a_deg.shape[0]
    out = np.empty((n, 3, len(names)))
    deg = np.pi / 180.0
    a_rad = np.deg2rad(st.a_deg)
    for col, name in enumerate(names):
        m = effects._check_name(name)
        if m.group(6):  # kappa: d a_i/d kappa = a_i·ΔT (same for d); geo's a,d columns are per unit a,d
            unscaled = geo[:, :, 1:30:5] * params.d_mm + geo[:, :, 2:30:5] * params.a_mm
            scale = 1.0 + effects.thermal_per_k * st.delta_t_k
            out[:, :, col] = unscaled.sum(axis=2) / scale[:, None] * st.delta_t_k[:, None]
            continue
        if m.group(1):
            kind, i = m.group(1), int(m.group(2)) - 1
            if kind == "h":
                dtheta = params.sign[i] * deg * st.dir[:, i]
            elif kind == "eps":
                dtheta = params.sign[i] * a_rad[:, i]
            else:
                dtheta = st.tau_nm[:, i]
        else:
            i, k = int(m.group(4)) - 1, int(m.group(5))
            trig = np.sin if m.group(3) == "c" else np.cos
            dtheta = params.sign[i] * deg * trig(k * a_rad[:, i])
        out[:, :, col] = j_theta[:, :, i] * dtheta[:, None]
    return out


def _needs_torques(names: Sequence[str]) -> bool:
    return any(name.startswith("C") for name in names)


def effect_jacobian(
    robot_or_arrays: RobotDescription | MassModel,
    params: KinematicParams,
    effects: EffectParams,
    names: Sequence[str],
    a_deg: NDArray[np.float64],
    dir: NDArray[np.float64] | None = None,
    payload_kg: NDArray[np.float64] | float = 0.0,
    temp_c: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """(n, 3, len(names)) derivative of :func:`twin_tcp_mm` w.r.t. the named effect parameters.

    Columns are in mm per the parameter's unit (module docstring); exact for every name.
    """
    st = twin_state(
        robot_or_arrays, params, effects, a_deg, dir, payload_kg, temp_c, with_torques=_needs_torques(names)
    )
    geo, j_theta = _jacobians(params, effects, st)
    return _effect_columns(params, effects, st, names, geo, j_theta)


def twin_jacobian(
    robot_or_arrays: RobotDescription | MassModel,
    params: KinematicParams,
    effects: EffectParams,
    names: Sequence[str],
    a_deg: NDArray[np.float64],
    dir: NDArray[np.float64] | None = None,
    payload_kg: NDArray[np.float64] | float = 0.0,
    temp_c: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """TCP (n, 3) and the stacked Jacobian (n, 3, 39 + len(names)): [geometric 39 | named effects].

    The geometric block is the derivative w.r.t. :meth:`KinematicParams.apply`'s vector at the
    twin's effective configuration (the gravity torque held fixed, see the module docstring).
    """
    st = twin_state(
        robot_or_arrays, params, effects, a_deg, dir, payload_kg, temp_c, with_torques=_needs_torques(names)
    )
    geo, j_theta = _jacobians(params, effects, st)
    eff = _effect_columns(params, effects, st, names, geo, j_theta)
    return st.tcp_mm, np.concatenate([geo, eff], axis=2)
