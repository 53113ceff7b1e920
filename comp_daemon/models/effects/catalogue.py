"""The effect catalogue: every non-geometric effect of the twin, each defined once.

Each entry is an :class:`~comp_daemon.models.effects.base.Effect` next to its physics function(s).
The parameter store (:class:`~comp_daemon.models.effects.params.EffectParams`), the twin and its
Jacobians (:mod:`comp_daemon.models.effects.twin`), the diagnosis's candidates, data checks and
fitted-value JSON, and the report's drivers and advice all iterate :data:`EFFECT_CATALOGUE`;
none of them names an effect. The order of the catalogue is the order of the vocabulary of
``docs/diagnosis-output.md`` (and of the diagnosis's candidates and skip list).

The effects, for pose r and joint i (1..6), with the controller's axis value ``A_i`` (deg), the
approach direction ``dir_i`` (−1 / +1, 0 = unknown), the payload (kg), the temperature
``temp_c`` (°C) and the campaign clock ``t`` (h from ``t_s`` = 0; the row number where a campaign
has no times), composed by stage (:mod:`comp_daemon.models.effects.twin`)::

    A_eff_i = A_i·(1 + eps_i) + h_i·dir_i + Σ_k (c_ik·sin(k·a_i) + s_ik·cos(k·a_i))
              + sz_i·[t >= step_at]                                                       [deg]
              with a_i = A_i in rad (the commanded axis value converted to radians), k = 1..K
    q_i     = sign_i · A_eff_i in rad                                                     [rad]
    theta_i = q_i + offset_i + C_i·tau_i                                                  [rad]
    a_i, d_i  ← a_i·(1 + kappa·(temp_c − t_ref_c)),  d_i·(1 + kappa·(temp_c − t_ref_c))
    TCP     = forward kinematics of theta with the grown a, d (base frame and tool unchanged)
              + (vx, vy, vz)·t + (wx, wy, wz)·t²                   (drift, measurement frame)

``drift`` and ``step`` extend the vocabulary of ``docs/diagnosis-output.md``: effects that real
campaigns show and that no column names (thermal growth without a temperature sensor, a base or
tracker settling; a joint re-mastered or knocked mid-campaign). ``step_at`` (a setting, in clock
units) is the moment of the step; the diagnosis searches it on the fit rows.

=============  ==========================  ==========================================
name           parameter                   unit
=============  ==========================  ==========================================
``h{i}``       backlash of joint i         deg (half the play: ±h around the command)
``eps{i}``     reduction-ratio error       1
``c{i}_{k}``   sine coefficient c_ik       deg (joint i, harmonic k)
``s{i}_{k}``   cosine coefficient s_ik     deg (joint i, harmonic k)
``C{i}``       compliance                  rad / (N m)
``kappa``      thermal expansion           1 / K
``vx``         drift rate along x          mm / h (mm per row without t_s)
``vy``         drift rate along y          mm / h (mm per row without t_s)
``vz``         drift rate along z          mm / h (mm per row without t_s)
``wx``         drift curvature along x     mm / h² (mm per row² without t_s)
``wy``         drift curvature along y     mm / h² (mm per row² without t_s)
``wz``         drift curvature along z     mm / h² (mm per row² without t_s)
``sz{i}``      step of joint i's zero      deg (from step_at on)
=============  ==========================  ==========================================

The entries below are the definition; this table is their summary (a test keeps them in step).
"""

from __future__ import annotations

import numpy as np

from comp_daemon.kinematics.forward import Chain
from comp_daemon.kinematics.params import BASE_SLICE, KinematicParams
from comp_daemon.models.effects.base import (
    ChainStage,
    Effect,
    EffectData,
    FloatArray,
    ParamArray,
    ParamRef,
    TwinInputs,
    Values,
)

__all__ = ["EFFECTS", "EFFECT_CATALOGUE", "MIN_CLOCK_VALUES", "MIN_TEMP_SPREAD_K", "effect_by_name"]


# ------------------------------------------------------------------------------------- backlash
def _backlash_basis(x: TwinInputs, n_harmonics: int) -> tuple[FloatArray, ...]:
    return (x.dir[:, :, None],)


def _backlash_data(data: EffectData, joint: int | None) -> str | None:
    j = int(joint or 1)
    assert data.dir is not None  # required column, checked first
    if np.ptp(data.dir[:, j - 1]) == 0:
        return f"dir{j} is {int(data.dir[0, j - 1]):+d} on every fit row (play looks like an offset)"
    return None


BACKLASH = Effect(
    name="backlash",
    meaning="play in the gear train: the joint lags the command by h on the side it came from",
    formula="A_eff_i += h_i·dir_i",
    arrays=(
        ParamArray(
            attr="backlash_deg",
            symbol="h",
            unit="deg",
            layout="joint",
            json_key="h_deg",
            meaning="backlash, half the play (±h)",
            typical=0.01,
        ),
    ),
    stage="axis",
    basis=_backlash_basis,
    columns=("dir",),
    required={"dir": "no dir1..dir6 columns: the approach direction is unknown"},
    data_reason=_backlash_data,
    action="approach drilling targets on {axes} from one direction, or compensate the play by "
    "approach direction (h per joint); a grating on the joint measures the output side directly",
)


# ---------------------------------------------------------------------------------------- ratio
def _ratio_basis(x: TwinInputs, n_harmonics: int) -> tuple[FloatArray, ...]:
    return (x.a_deg[:, :, None],)


def _axis_moves(data: EffectData, joint: int | None) -> str | None:
    j = int(joint or 1)
    if np.ptp(data.a_deg[:, j - 1]) < 1e-6:
        return f"A{j} does not move on the fit rows"
    return None


RATIO = Effect(
    name="ratio",
    meaning="reduction-ratio error: the joint turns (1 + eps) times the commanded angle",
    formula="A_eff_i += eps_i·A_i",
    arrays=(
        ParamArray(
            attr="ratio",
            symbol="eps",
            unit="1",
            layout="joint",
            json_key="eps",
            meaning="reduction-ratio error",
            typical=2e-4,
        ),
    ),
    stage="axis",
    basis=_ratio_basis,
    data_reason=_axis_moves,
    smooth_driver=True,
    action="correct the reduction ratio of {axes} in the controller's machine data, or add the ratio "
    "error to the compensation model",
)


# --------------------------------------------------------------------------------------- cyclic
def _cyclic_basis(x: TwinInputs, n_harmonics: int) -> tuple[FloatArray, ...]:
    arg = np.deg2rad(x.a_deg)[:, :, None] * np.arange(1, n_harmonics + 1)  # (n, 6, K)
    return np.sin(arg), np.cos(arg)


CYCLIC = Effect(
    name="cyclic",
    meaning="transmission error periodic in the axis angle, K harmonics",
    formula="A_eff_i += Σ_k (c_ik·sin(k·a_i) + s_ik·cos(k·a_i)),  a_i = A_i in rad",
    arrays=(
        ParamArray(
            attr="cyclic_sin_deg",
            symbol="c",
            unit="deg",
            layout="harmonic",
            json_key="c_deg",
            meaning="sine coefficient of harmonic k",
            typical=0.01,
        ),
        ParamArray(
            attr="cyclic_cos_deg",
            symbol="s",
            unit="deg",
            layout="harmonic",
            json_key="s_deg",
            meaning="cosine coefficient of harmonic k",
            typical=0.01,
        ),
    ),
    stage="axis",
    basis=_cyclic_basis,
    data_reason=_axis_moves,
    smooth_driver=True,
    action="model the transmission error of {axes} as a function of the axis angle (Chebyshev / "
    "harmonic terms), or close the loop on a grating for that joint",
)


# ----------------------------------------------------------------------------------- compliance
def _compliance_basis(x: TwinInputs, n_harmonics: int) -> tuple[FloatArray, ...]:
    assert x.tau_nm is not None  # needs_torques
    return (x.tau_nm[:, :, None],)


def _compliance_data(data: EffectData, joint: int | None) -> str | None:
    j = int(joint or 1)
    tau_j = data.tau_nm[:, j - 1]
    if not np.any(data.tau_nm):
        return (
            "no gravity torque on any joint: the robot description has no link masses and no row "
            "carries a payload (payload_kg)"
        )
    if np.abs(tau_j).max() < 1e-9 * data.tau_scale_nm:
        return f"no gravity torque on joint {j} in these poses (its axis is vertical)"
    if np.ptp(tau_j) < 1e-6 * data.tau_scale_nm:
        load = "payload" if len(np.unique(data.payload_kg)) == 1 else "payloads"
        return f"the gravity torque on joint {j} does not vary over these poses and {load}"
    return None


def _torque_driver(x: TwinInputs, joint: int | None) -> tuple[FloatArray, str]:
    j = joint or 1
    assert x.tau_nm is not None
    return x.tau_nm[:, j - 1], f"gravity torque on joint {j} (N m)"


COMPLIANCE = Effect(
    name="compliance",
    meaning="joint stiffness: the joint deflects by C times the gravity torque (links and payload)",
    formula="q_i += C_i·tau_i  (tau: gravity torque, DH sign, at the commanded configuration)",
    arrays=(
        ParamArray(
            attr="compliance_rad_per_nm",
            symbol="C",
            unit="rad / (N m)",
            layout="joint",
            json_key="C_rad_per_nm",
            meaning="compliance",
            typical=2e-7,
        ),
    ),
    stage="joint",
    basis=_compliance_basis,
    needs_torques=True,
    columns=("payload_kg",),
    data_reason=_compliance_data,
    driver=_torque_driver,
    action="add gravity compliance of {axes} to the compensation, with the payload declared "
    "correctly for every job",
)


# -------------------------------------------------------------------------------------- thermal
#: thermal needs at least this spread of ``temp_c`` on the fit rows (K)
MIN_TEMP_SPREAD_K = 0.5
#: indices of the a and d columns in the 39 geometric columns (5 per joint: theta, d, a, alpha, beta)
_AD_COLUMNS = np.r_[1:30:5, 2:30:5]
BASE_ROTATION_COLUMNS = slice(BASE_SLICE.start + 3, BASE_SLICE.stop)  # the base frame's rotation vector


def _growth(values: Values, x: TwinInputs) -> FloatArray:
    return 1.0 + float(values[0]) * x.delta_t_k


def _thermal_apply(values: Values, x: TwinInputs, params: KinematicParams, ch: Chain) -> Chain:
    """The chain with every a_i, d_i multiplied by ``1 + kappa·ΔT``, exactly.

    Link rotations do not depend on a, d and each link's translation is linear in them, so the frame
    origins move to ``o_0 + scale·(o_i − o_0)`` while the base frame and the tool offset stay.
    """
    scale = _growth(values, x)
    if np.all(scale == 1.0):
        return ch
    frames = ch.world_T_frame.copy()
    o0 = frames[:, 0, None, :3, 3]
    frames[:, 1:, :3, 3] = o0 + scale[:, None, None] * (frames[:, 1:, :3, 3] - o0)
    tcp = frames[:, 6, :3, :3] @ params.tool_xyz_mm + frames[:, 6, :3, 3]
    return Chain(world_T_frame=frames, x_prime=ch.x_prime, y_beta=ch.y_beta, tcp_mm=tcp)


def _thermal_geometric(values: Values, x: TwinInputs, geo: FloatArray) -> None:
    # columns of the grown a, d → columns of the parameters a, d themselves
    geo[:, :, _AD_COLUMNS] *= _growth(values, x)[:, None, None]


def _thermal_column(
    values: Values, x: TwinInputs, params: KinematicParams, geo: FloatArray, ref: ParamRef
) -> FloatArray:
    # d a_i / d kappa = a_i·ΔT (same for d); geo's a, d columns are per unit a, d (already scaled)
    unscaled = geo[:, :, 1:30:5] * params.d_mm + geo[:, :, 2:30:5] * params.a_mm
    out: FloatArray = unscaled.sum(axis=2) / _growth(values, x)[:, None] * x.delta_t_k[:, None]
    return out


def _thermal_data(data: EffectData, joint: int | None) -> str | None:
    assert data.temp_c is not None  # required column, checked first
    spread = float(np.ptp(data.temp_c))
    if spread < MIN_TEMP_SPREAD_K:
        return (
            f"temp_c spans only {spread:.2f} K on the fit rows "
            f"(needs at least {MIN_TEMP_SPREAD_K} K to separate growth from constant lengths)"
        )
    return None


def _row_driver(x: TwinInputs) -> tuple[FloatArray, str]:
    """The driver of a time-like effect whose campaign lacks its column: the row number."""
    return np.arange(x.a_deg.shape[0], dtype=float), "row"


def _temperature_driver(x: TwinInputs, joint: int | None) -> tuple[FloatArray, str]:
    if x.temp_c is not None:
        return x.temp_c, "temp_c (°C)"
    return _row_driver(x)


THERMAL = Effect(
    name="thermal",
    meaning="thermal growth of the links: every a_i, d_i grows by kappa per kelvin from t_ref_c",
    formula="a_i, d_i ← a_i·(1 + kappa·(temp_c − t_ref_c)), d_i·(1 + kappa·(temp_c − t_ref_c))",
    arrays=(
        ParamArray(
            attr="thermal_per_k",
            symbol="kappa",
            unit="1 / K",
            layout="scalar",
            json_key="kappa_per_k",
            meaning="thermal expansion",
            typical=1.2e-5,
        ),
    ),
    stage="chain",
    chain=ChainStage(apply=_thermal_apply, geometric=_thermal_geometric, column=_thermal_column),
    columns=("temp_c",),
    required={"temp_c": "no temp_c column: the temperature is unknown"},
    per_joint=False,
    data_reason=_thermal_data,
    driver=_temperature_driver,
    action="calibrate at working temperature, or add thermal growth (κ with the temperature "
    "input) to the compensation",
    settings=("t_ref_c",),
)


# ---------------------------------------------------------------------------------------- drift
_DRIFT_AXES = ("x", "y", "z")


def _drift_mm(values: Values, x: TwinInputs) -> FloatArray:
    """(n, 3) translation of the drift at each pose's clock (zero without a clock)."""
    n = x.a_deg.shape[0]
    if x.clock is None:
        return np.zeros((n, 3))
    v = np.asarray(values[:3], dtype=float)
    w = np.asarray(values[3:], dtype=float)
    t = x.clock[:, None]
    out: FloatArray = t * v + t * t * w
    return out


def _drift_apply(values: Values, x: TwinInputs, params: KinematicParams, ch: Chain) -> Chain:
    """The chain translated as a whole by the drift (every frame origin and the TCP)."""
    shift = _drift_mm(values, x)
    if not np.any(shift):
        return ch
    frames = ch.world_T_frame.copy()
    frames[:, :, :3, 3] += shift[:, None, :]
    return Chain(world_T_frame=frames, x_prime=ch.x_prime, y_beta=ch.y_beta, tcp_mm=ch.tcp_mm + shift)


def _drift_geometric(values: Values, x: TwinInputs, geo: FloatArray) -> None:
    # the drift translates the chain after the base frame: a rotation of the base turns the TCP
    # about the base origin but not the drift, so the base-rotation columns (taken at the drifted
    # TCP) lose e_k × shift; the other columns do not see a translation of the whole chain
    shift = _drift_mm(values, x)
    if np.any(shift):
        turned = np.cross(np.eye(3)[None, :, :], shift[:, None, :])  # [i, k] = e_k × shift_i
        geo[:, :, BASE_ROTATION_COLUMNS] -= turned.transpose(0, 2, 1)


def _drift_column(
    values: Values, x: TwinInputs, params: KinematicParams, geo: FloatArray, ref: ParamRef
) -> FloatArray:
    n = x.a_deg.shape[0]
    out: FloatArray = np.zeros((n, 3))
    if x.clock is not None:
        power = 1 if ref.array < 3 else 2
        out[:, ref.array % 3] = x.clock**power
    return out


def _clock_driver(x: TwinInputs, joint: int | None) -> tuple[FloatArray, str]:
    if x.clock is not None:
        return x.clock, "campaign clock (h, or row number without t_s)"
    return _row_driver(x)


#: the time effects need at least this many distinct clock values on the fit rows
MIN_CLOCK_VALUES = 8


#: the words when a campaign has no clock
_NO_CLOCK = "no campaign clock (neither t_s nor a row order)"


def _clock_data(data: EffectData, joint: int | None) -> str | None:
    assert data.clock is not None  # required column, checked first
    if len(np.unique(data.clock)) < MIN_CLOCK_VALUES:
        return f"fewer than {MIN_CLOCK_VALUES} distinct times on the fit rows"
    return None


def _drift_array(power: int, axis: str) -> ParamArray:
    unit = "mm / h" if power == 1 else "mm / h²"
    return ParamArray(
        attr=f"drift_{axis}_mm_per_h{power}",
        symbol=f"{'v' if power == 1 else 'w'}{axis}",
        unit=unit,
        layout="scalar",
        json_key=f"{'v' if power == 1 else 'w'}{axis}_{'mm_per_h' if power == 1 else 'mm_per_h2'}",
        meaning=f"{'rate' if power == 1 else 'curvature'} of the drift along {axis} (per row without t_s)",
        typical=0.01 if power == 1 else 0.002,
    )


DRIFT = Effect(
    name="drift",
    meaning="a smooth drift over time: the measured TCP translates by a quadratic in the campaign "
    "clock (thermal growth without a temperature sensor, a settling base or tracker)",
    formula="TCP += v·t + w·t²  (t: campaign clock, h from t_s = 0, or the row number; v, w per x, y, z "
    "of the measurement frame)",
    arrays=tuple(_drift_array(p, a) for p in (1, 2) for a in _DRIFT_AXES),
    stage="chain",
    chain=ChainStage(apply=_drift_apply, geometric=_drift_geometric, column=_drift_column),
    per_joint=False,
    columns=("clock",),
    required={"clock": _NO_CLOCK},
    data_reason=_clock_data,
    driver=_clock_driver,
    smooth_driver=True,
    action="re-measure the reference (or the base) periodically during the campaign and the job, "
    "add a temperature sensor where the drift is thermal, or let the structure settle before measuring",
    of_the_robot=False,
)


# ----------------------------------------------------------------------------------------- step
def _step_basis(x: TwinInputs, n_harmonics: int) -> tuple[FloatArray, ...]:
    n = x.a_deg.shape[0]
    if x.clock is None:
        return (np.zeros((n, 6, 1)),)
    on = (x.clock >= x.step_at).astype(float)
    return (np.broadcast_to(on[:, None, None], (n, 6, 1)).copy(),)


STEP = Effect(
    name="step",
    meaning="a joint's zero changes at one moment of the campaign (re-mastering, a collision)",
    formula="A_eff_i += s_i·[t >= step_at]  (t: campaign clock, step_at: the moment of the change)",
    arrays=(
        ParamArray(
            attr="step_deg",
            symbol="sz",
            unit="deg",
            layout="joint",
            json_key="step_deg",
            meaning="change of the joint's zero from step_at on",
            typical=0.01,
        ),
    ),
    stage="axis",
    basis=_step_basis,
    columns=("clock",),
    required={"clock": _NO_CLOCK},
    data_reason=_clock_data,
    driver=_clock_driver,
    action="re-master {axes} and check the campaign log for a collision or a mastering at that moment; "
    "calibrate again from the data after the change",
    settings=("step_at",),
    of_the_robot=False,
)


# ------------------------------------------------------------------------------------ catalogue
EFFECT_CATALOGUE: tuple[Effect, ...] = (BACKLASH, RATIO, CYCLIC, COMPLIANCE, THERMAL, DRIFT, STEP)
#: the effect names (the vocabulary of docs/diagnosis-output.md), in catalogue order
EFFECTS: tuple[str, ...] = tuple(e.name for e in EFFECT_CATALOGUE)
#: the effects that are functions of the campaign clock (they need it: ``required`` names ``clock``)
TIME_EFFECTS: tuple[str, ...] = tuple(e.name for e in EFFECT_CATALOGUE if "clock" in e.required)
#: the transmission's effects, ratio and backlash (seed 001 §1): the base of the kriging-backlash kind
TRANSMISSION_EFFECTS: tuple[str, ...] = (RATIO.name, BACKLASH.name)
_BY_NAME = {e.name: e for e in EFFECT_CATALOGUE}


def effect_by_name(name: str) -> Effect:
    """The catalogue entry called ``name``; ValueError naming the known ones otherwise."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise ValueError(f"unknown effect '{name}' (known: {', '.join(EFFECTS)})") from None
