"""What an entry of the effect catalogue declares, and the inputs its functions receive.

An :class:`Effect` is one non-geometric effect of the twin. It owns one or more parameter arrays
(:class:`ParamArray`: name stem, unit, per-joint layout) and enters the twin at one stage:

* ``axis``: it adds to the controller's axis value, ``A_eff_i += Σ value·basis`` (deg);
* ``joint``: it adds to the joint angle after the sign convention, ``q_i += Σ value·basis`` (rad);
* ``chain``: it changes the frames of the chain (a :class:`ChainStage` of three functions).

Axis and joint effects are linear in their parameters: the effect's ``basis`` function gives, for
each of its arrays, the factor that multiplies each parameter, shape (n, 6, w) with w = 1 for a
per-joint array, K for a per-joint-and-harmonic array, and 1 for a scalar (then one value for all
joints). The twin's Jacobian column of a parameter is that factor times ``∂TCP/∂θ_i``, so the
Jacobian of a linear effect needs no code of its own.

The rest of the entry is for the diagnosis and its report: the data columns the effect needs and
the words when they are missing, why the data cannot identify it (``data_reason``), the variable
its contribution is drawn against (``driver``) and what an engineer can do about it (``action``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.forward import Chain
from comp_daemon.kinematics.params import KinematicParams
from comp_daemon.models.rows import MeasuredRows

__all__ = [
    "N_JOINTS",
    "ChainStage",
    "Effect",
    "EffectData",
    "Layout",
    "ParamArray",
    "ParamRef",
    "Stage",
    "TwinInputs",
]

N_JOINTS = 6
FloatArray = NDArray[np.float64]
Layout = Literal["joint", "harmonic", "scalar"]
Stage = Literal["axis", "joint", "chain"]


@dataclass(frozen=True, slots=True)
class ParamArray:
    """One array of an effect's parameters.

    ``attr`` is its attribute of :class:`~comp_daemon.models.effects.params.EffectParams`;
    parameter names are ``{symbol}{j}`` (layout ``joint``, shape (6,)), ``{symbol}{j}_{k}``
    (``harmonic``, shape (6, K), k = 1..K) or ``{symbol}`` (``scalar``, one float);
    ``json_key`` names the fitted values in the diagnosis document; ``typical`` is a size (in
    ``unit``) the effect has on an industrial robot, a scale for tests and finite differences.
    """

    attr: str
    symbol: str
    unit: str
    layout: Layout
    json_key: str
    meaning: str
    typical: float

    def names(self, joint: int, n_harmonics: int) -> list[str]:
        """Parameter names of this array on ``joint`` (1-based; ignored for a scalar)."""
        if self.layout == "joint":
            return [f"{self.symbol}{joint}"]
        if self.layout == "harmonic":
            return [f"{self.symbol}{joint}_{k}" for k in range(1, n_harmonics + 1)]
        return [self.symbol]

    @property
    def pattern(self) -> str:
        """The name pattern in words, for error messages."""
        return {"joint": f"{self.symbol}<j>", "harmonic": f"{self.symbol}<j>_<k>", "scalar": self.symbol}[
            self.layout
        ]


@dataclass(frozen=True, slots=True)
class ParamRef:
    """Where one named parameter lives: its effect, array, joint (0-based) and harmonic (0-based)."""

    effect: Effect
    array: int
    joint: int | None
    harmonic: int | None


@dataclass(frozen=True, slots=True)
class TwinInputs:
    """The per-pose inputs of the effects (n poses; every array already checked): the poses'
    columns and what the twin derives from them (``delta_t_k``, ``tau_nm``). Built by
    :func:`~comp_daemon.models.effects.twin.twin_inputs` from arrays, and from measured rows by
    :func:`~comp_daemon.models.effects.twin.twin_inputs_of`."""

    a_deg: FloatArray  # (n, 6) commanded axis values
    dir: FloatArray  # (n, 6) approach directions −1 / +1 (0 = unknown)
    payload_kg: FloatArray  # (n,)
    temp_c: FloatArray | None  # (n,) or None without temperatures
    delta_t_k: FloatArray  # (n,) temp_c − t_ref_c (0 without temperatures)
    tau_nm: FloatArray | None  # (n, 6) gravity torques at the commanded configuration, if computed
    clock: FloatArray | None = None  # (n,) campaign clock (h; row number without times), or None
    step_at: float = float("inf")  # clock value from which the step effect acts


@dataclass(frozen=True, slots=True)
class EffectData:
    """What the fit rows of a campaign offer for identifying effects (the diagnosis's data check):
    the rows, and what the twin adds to them (built by
    :func:`~comp_daemon.models.effects.twin.effect_data`). A column the rows lack is None
    (``dir``, ``temp_c``, ``clock``)."""

    rows: MeasuredRows
    tau_nm: FloatArray  # (n, 6) gravity torques of the nominal twin at the commanded poses
    moves_tcp: NDArray[np.bool_]  # (6,) whether each joint moves the TCP in these poses

    @property
    def a_deg(self) -> FloatArray:
        return self.rows.a_deg

    @property
    def dir(self) -> FloatArray | None:
        return self.rows.dir

    @property
    def payload_kg(self) -> FloatArray:
        return self.rows.payload_kg

    @property
    def temp_c(self) -> FloatArray | None:
        return self.rows.temp_c

    @property
    def clock(self) -> FloatArray | None:
        return self.rows.clock

    @property
    def tau_scale_nm(self) -> float:
        return max(float(np.abs(self.tau_nm).max(initial=0.0)), 1e-300)


Values = tuple[FloatArray, ...]
Basis = Callable[[TwinInputs, int], tuple[FloatArray, ...]]


@dataclass(frozen=True, slots=True)
class ChainStage:
    """How a chain-stage effect changes the frames, and its derivatives.

    ``apply(values, inputs, params, chain)`` returns the changed chain; ``geometric(values, inputs,
    geo)`` applies the chain rule to the (n, 3, 39) geometric columns in place (the effect may scale
    the parameters the geometric columns belong to); ``column(values, inputs, params, geo, ref)``
    is the (n, 3) derivative of the TCP w.r.t. one of the effect's parameters, given the corrected
    geometric columns.
    """

    apply: Callable[[Values, TwinInputs, KinematicParams, Chain], Chain]
    geometric: Callable[[Values, TwinInputs, FloatArray], None]
    column: Callable[[Values, TwinInputs, KinematicParams, FloatArray, ParamRef], FloatArray]


def _no_reason(data: EffectData, joint: int | None) -> str | None:
    return None


def axis_driver(inputs: TwinInputs, joint: int | None) -> tuple[FloatArray, str]:
    """The axis value of the effect's (first) joint: the driver of the joint-angle effects."""
    j = joint or 1
    return inputs.a_deg[:, j - 1], f"A{j} (deg)"


@dataclass(frozen=True, slots=True)
class Effect:
    """One catalogue entry; see the module docstring for the meaning of each part."""

    name: str
    meaning: str
    formula: str  # how it changes the twin, in the notation of the effects package docstring
    arrays: tuple[ParamArray, ...]
    stage: Stage
    basis: Basis | None = None  # axis / joint stage
    chain: ChainStage | None = None  # chain stage
    needs_torques: bool = False  # the basis reads TwinInputs.tau_nm
    columns: tuple[str, ...] = ()  # data columns it reads
    required: Mapping[str, str] = field(default_factory=dict)  # column -> words when it is missing
    per_joint: bool = True  # diagnosis candidates per joint (else one for the whole robot)
    data_reason: Callable[[EffectData, int | None], str | None] = _no_reason
    driver: Callable[[TwinInputs, int | None], tuple[FloatArray, str]] = axis_driver
    smooth_driver: bool = False  # its contribution is a smooth function of the driver (drawn as a line)
    action: str = ""  # what to do about it; ``{axes}`` stands for the joints, e.g. "A2 and A3"
    settings: tuple[str, ...] = ()  # EffectParams settings reported with the fitted values
    # False: the effect belongs to one campaign (its clock), not to the robot, so a compensation model
    # cannot carry it to new targets; the diagnosis may name it, the model kinds refuse it
    of_the_robot: bool = True

    def __post_init__(self) -> None:
        if self.stage in ("axis", "joint") and self.basis is None:
            raise ValueError(f"effect {self.name}: an {self.stage}-stage effect needs a basis function")
        if self.stage == "chain" and self.chain is None:
            raise ValueError(f"effect {self.name}: a chain-stage effect needs its ChainStage functions")
        if not self.arrays:
            raise ValueError(f"effect {self.name}: no parameters")

    def names(self, joints: tuple[int, ...] | list[int], n_harmonics: int) -> list[str]:
        """Parameter names on ``joints``: scalars once, then per joint each array in order."""
        out = [n for arr in self.arrays if arr.layout == "scalar" for n in arr.names(0, n_harmonics)]
        for j in joints:
            for arr in self.arrays:
                if arr.layout != "scalar":
                    out += arr.names(j, n_harmonics)
        return out

    def unfit_reason(self, data: EffectData, joint: int | None) -> str | None:
        """Why ``data`` cannot identify this effect on ``joint`` (None: it can be tried)."""
        if self.per_joint and joint is not None and not data.moves_tcp[joint - 1]:
            return f"joint {joint} does not move the TCP in these poses (the TCP lies on its axis)"
        for column, words in self.required.items():
            if getattr(data, column) is None:
                return words
        return self.data_reason(data, joint)
