"""Kinematic (MDH) calibration, seed 000 eqs 3–6, with the extended joint parameters of seed 001.

Model. The TCP is ``world_T_base · T_01 … T_56 · tool`` with MDH links (conventions in
:mod:`comp_daemon.kinematics.params`); optionally the joint angle carries the non-geometric effects
of :mod:`comp_daemon.models.effects` — per joint a reduction-ratio error ``eps{j}`` and a backlash
``h{j}`` (deg, signed by the approach direction ``dir``), the extended parameters of seed 001, or
any other entry of the effect catalogue (:data:`~comp_daemon.models.effects.EFFECTS`).

Identification. ``ΔP = J·Δx`` (seed 000 eq. 3) over the 39 parameters of :data:`PARAM_NAMES` (MDH
parameters of every joint, base frame 6, tool 3) and the chosen effect parameters, solved in the
least-squares sense (eq. 6) and iterated to convergence:

1. frame: if the data are not in the robot base frame (:func:`detect_frame`), the base frame is
   first registered in the tracker frame by a rigid fit of the nominal TCPs to the measured ones
   (:func:`comp_daemon.estimation.registration.rigid_registration`);
2. identifiability (seed 003) of the Jacobian at the start, on the data's own poses: zero and
   dependent columns are removed by name (:func:`analyze_identifiability`, MDH priority: base and
   tool kept, ``beta`` instead of ``d`` at parallel joints);
3. the identifiable parameters are iterated with the improved Levenberg–Marquardt method of
   seed 000 (:func:`comp_daemon.estimation.lm.improved_lm`, columns scaled); the Jacobian is exact,
   the base rotation being a rotation vector (its Jacobian through the SO(3) left Jacobian).

Several targets. When the flange carries further targets (reflectors ``x2, y2, z2`` … of the data
set), each one's position in the flange frame is three more parameters (``target2_x`` …, mm; the
first target is the tool, ``tool_x`` …), started from the registered nominal flange poses (the mean
of the measured points seen from the flange) and identified with the rest. The residual stacks every
target's position error (mm), target after target. Three or more non-collinear targets carry the
flange's orientation as well as its position, so this is a 6-DOF identification in which the
orientation is weighted by the targets' lever arms, in the same unit and with the same (isotropic)
tracker noise as the positions: the least-squares optimum of the measurements as they are, with no
choice of weight between millimetres and radians. A parameter that only the orientation sees (a
wrist twist the TCP hardly feels) becomes better determined; parameters that move every target
alike with an offset (``d6``, ``theta6`` against the targets' offsets) drop out as dependent.
The target positions are computed from the twin's flange frame (payload at the TCP); every
target's Jacobian comes from that one twin (:func:`~comp_daemon.models.effects.twin_jacobian_targets`),
target k's columns those of the twin with target k as the tool and the payload still at the TCP, so
that its compliance columns are the derivative of its residual (with the payload moved onto
target k they would be wrong by up to several times their size, and the steps near the optimum
rejected until the step tolerance stopped the iteration short of it).

Units: mm, rad for the geometry (``dx`` layout of :meth:`KinematicParams.apply`); effect units as in
:mod:`comp_daemon.models.effects` (the catalogue: deg for backlash, 1 for the ratio error …).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray

from comp_daemon.estimation.identifiability import (
    IdentifiabilityReport,
    analyze_identifiability,
    mdh_priority,
)
from comp_daemon.estimation.lm import LMResult, improved_lm
from comp_daemon.estimation.registration import detect_frame, rigid_registration
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import N_PARAMS, PARAM_NAMES, KinematicParams, axes_deg_to_q_rad
from comp_daemon.kinematics.so3 import left_jacobian, skew
from comp_daemon.models.base import (
    ErrorModel,
    Query,
    StoredModel,
    as_axes,
    finite_array,
    further_targets,
    measured_positions,
)
from comp_daemon.models.effects import (
    EFFECTS,
    EffectParams,
    MassModel,
    effect_param_names,
    twin_jacobian,
    twin_jacobian_targets,
    twin_state,
    twin_tcp_mm,
)
from comp_daemon.models.observations import (
    FrameObservations,
    ObservedProblem,
    angle_deg,
    mean_rotation,
)
from comp_daemon.models.rows import DEFAULT_PROBE_SIGMA_DEG, MeasuredRows
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "KinematicFit",
    "KinematicModel",
    "KinematicProblem",
    "calibrate_kinematic",
    "target_param_names",
]

FrameChoice = Literal["auto", "base", "tracker"]


class KinematicModel(ErrorModel):
    """Calibrated MDH geometry (and, optionally, the joint effects of seed 001)."""

    kind: ClassVar[str] = "kinematic"

    def __init__(
        self,
        robot: RobotDescription,
        params: KinematicParams,
        effects: EffectParams | None = None,
        registration: NDArray[np.float64] | None = None,
        more_targets_mm: NDArray[np.float64] | None = None,
    ):
        self.robot = robot
        self.params = params
        self.effects = effects
        # (K − 1, 3) further targets' positions in the flange frame (mm); None: the TCP only
        self.more_targets_mm = None if more_targets_mm is None else np.array(more_targets_mm, dtype=float)
        self.world_T_base = params.world_T_base
        self.registration = np.eye(4) if registration is None else np.array(registration, dtype=float)

    def tcp_mm(self, query: Query) -> NDArray[np.float64]:
        if self.effects is None:
            return tcp_position_mm(self.params, axes_deg_to_q_rad(query.a, self.params.sign))
        return twin_tcp_mm(
            self.robot, self.params, self.effects, query.a, query.dir, query.payload_kg, query.temp_c
        )

    def predict_targets_mm(
        self,
        a_deg: NDArray[np.float64],
        dir: NDArray[np.float64] | None = None,
        payload_kg: NDArray[np.float64] | float | None = None,
        temp_c: NDArray[np.float64] | None = None,
    ) -> NDArray[np.float64]:
        """(n, K, 3) every target's position (the TCP first, then the further targets), mm."""
        a = as_axes(a_deg)
        effects = self.effects if self.effects is not None else EffectParams.zeros()
        payload = 0.0 if payload_kg is None else payload_kg
        more = np.zeros((0, 3)) if self.more_targets_mm is None else self.more_targets_mm
        return targets_mm(self.robot, self.params, effects, more, a, dir, payload, temp_c)

    def ik_params(self) -> KinematicParams:
        return self.params

    def to_payload(self) -> dict[str, Any]:
        p = self.params
        out: dict[str, Any] = {
            **mdh_payload(p),
            "tool_xyz_mm": p.tool_xyz_mm.tolist(),
            "world_T_base": p.world_T_base.tolist(),
            "effects": None,
        }
        if self.more_targets_mm is not None:
            out["more_targets_mm"] = self.more_targets_mm.tolist()
        if self.effects is not None:
            names = self.effects.names()
            out["effects"] = {
                "n_harmonics": self.effects.n_harmonics,
                "t_ref_c": self.effects.t_ref_c,
                "names": names,
                "values": self.effects.get(names).tolist(),
            }
        return out

    def parameter_jacobian(
        self, names: Sequence[str], values: NDArray[np.float64], query: Query
    ) -> NDArray[np.float64]:
        """The calibration's own Jacobian (:class:`KinematicProblem`) at the query's poses: the
        geometric parameters (increments from the registered nominal start), then the effects'."""
        geo_idx = np.array([PARAM_NAMES.index(nm) for nm in names if nm in PARAM_NAMES], dtype=np.intp)
        eff_names = [nm for nm in names if nm not in PARAM_NAMES]
        if list(names) != [PARAM_NAMES[i] for i in geo_idx] + eff_names:
            raise ValueError("uncertainty: the geometric parameters must come before the effect parameters")
        eff0 = (
            EffectParams.zeros(self.effects.n_harmonics, self.effects.t_ref_c)
            if self.effects is not None
            else EffectParams.zeros()
        )
        start = KinematicParams.from_robot(self.robot).with_base(self.registration)
        n = query.a.shape[0]
        d = None if query.dir is None else np.asarray(query.dir, dtype=float)
        problem = KinematicProblem(
            self.robot,
            start,
            eff0,
            geo_idx,
            eff_names,
            query.a,
            np.zeros((n, 3)),
            d,
            query.payload_kg,
            query.temp_c,
        )
        return problem.jacobian(values).reshape(n, 3, len(names))

    @classmethod
    def from_stored(cls, stored: StoredModel) -> KinematicModel:
        robot, payload = stored.robot, stored.payload
        params = params_from_payload(robot, payload, payload["tool_xyz_mm"], payload["world_T_base"])
        effects = None
        eff = payload.get("effects")
        if eff is not None:
            names = [str(n) for n in eff["names"]]
            values = _floats(eff["values"], (len(names),), "effects.values")
            effects = EffectParams.zeros(int(eff["n_harmonics"]), float(eff["t_ref_c"])).with_values(
                names, values
            )
        more = payload.get("more_targets_mm")
        if more is not None:
            more = _floats(more, (len(more), 3), "more_targets_mm")
        return cls(robot, params, effects, stored.registration, more)


MDH_FIELDS = ("theta_offset_rad", "d_mm", "a_mm", "alpha_rad", "beta_rad")  # a model's MDH geometry


def mdh_payload(params: KinematicParams) -> dict[str, list[float]]:
    """The MDH geometry of ``params`` as an artifact stores it (:data:`MDH_FIELDS`, one list each)."""
    return {name: getattr(params, name).tolist() for name in MDH_FIELDS}


def params_from_payload(
    robot: RobotDescription, mdh: Mapping[str, Any], tool_xyz_mm: Any, world_T_base: Any, *, prefix: str = ""
) -> KinematicParams:
    """The :class:`KinematicParams` of an artifact's MDH geometry (:func:`mdh_payload`), tool and
    base frame, with the robot description's joint signs; a missing field is a ``KeyError``, a
    field of the wrong shape or not finite a ``ValueError`` naming it (``prefix`` + name)."""
    geometry = {name: _floats(mdh[name], (6,), prefix + name) for name in MDH_FIELDS}
    return KinematicParams(
        **geometry,
        sign=KinematicParams.from_robot(robot).sign,
        tool_xyz_mm=_floats(tool_xyz_mm, (3,), "tool_xyz_mm"),
        world_T_base=_floats(world_T_base, (4, 4), "world_T_base"),
    )


def _floats(value: Any, shape: tuple[int, ...], name: str) -> NDArray[np.float64]:
    """A stored model field as a finite float array (:func:`finite_array`, the error naming it)."""
    return finite_array(value, shape, f"model field '{name}'")


def target_param_names(n_more: int) -> list[str]:
    """The offset parameters of the further targets 2..K (flange frame, mm): ``target2_x`` …"""
    return [f"target{k}_{c}" for k in range(2, n_more + 2) for c in "xyz"]


def targets_mm(
    robot: RobotDescription,
    params: KinematicParams,
    effects: EffectParams,
    more_flange_mm: NDArray[np.float64],
    a_deg: NDArray[np.float64],
    dir: NDArray[np.float64] | None,
    payload_kg: NDArray[np.float64] | float,
    temp_c: NDArray[np.float64] | None,
) -> NDArray[np.float64]:
    """(n, K, 3): the twin's TCP and the points ``more_flange_mm`` (K − 1, 3) fixed to its flange."""
    st = twin_state(robot, params, effects, a_deg, dir, payload_kg, temp_c)
    flange = st.chain.world_T_frame[:, 6]
    more = np.einsum("nij,kj->nki", flange[:, :3, :3], more_flange_mm) + flange[:, None, :3, 3]
    return np.concatenate([st.tcp_mm[:, None, :], more], axis=1)


class KinematicProblem:
    """Residual and exact Jacobian of the calibration over a subset of parameters.

    ``x`` holds the increments of the geometric parameters ``geo_idx`` (indices into
    :data:`PARAM_NAMES`, the layout of :meth:`KinematicParams.apply` on ``start``) followed by the
    values of the effect parameters ``eff_names``, then, with further targets, the increments of
    their flange offsets ``more_idx`` (indices into the flattened (K − 1, 3) ``more_start_mm``).
    The residual is predicted − measured (mm): (3n,) for the TCP alone, (3nK,) with K targets,
    target after target (the TCP's n rows first).
    """

    def __init__(
        self,
        robot: RobotDescription,
        start: KinematicParams,
        eff0: EffectParams,
        geo_idx: NDArray[np.intp],
        eff_names: Sequence[str],
        a_deg: NDArray[np.float64],
        p_measured_mm: NDArray[np.float64],
        dir: NDArray[np.float64] | None,
        payload_kg: NDArray[np.float64] | float,
        temp_c: NDArray[np.float64] | None,
        *,
        more_measured_mm: NDArray[np.float64] | None = None,
        more_start_mm: NDArray[np.float64] | None = None,
        more_idx: NDArray[np.intp] | None = None,
        row_weights: NDArray[np.float64] | None = None,
    ) -> None:
        self.robot, self.start, self.eff0 = robot, start, eff0
        self.geo_idx = np.asarray(geo_idx, dtype=np.intp)
        self.eff_names = list(eff_names)
        self.a, self.p_meas, self.dir, self.payload, self.temp = a_deg, p_measured_mm, dir, payload_kg, temp_c
        self._rows: MeasuredRows | None = None  # the twin's inputs as rows, made on first use
        self._cols = np.concatenate([self.geo_idx, np.arange(N_PARAMS, N_PARAMS + len(self.eff_names))])
        self.more_meas = more_measured_mm  # (n, K − 1, 3) or None
        m = 0 if more_measured_mm is None else more_measured_mm.shape[1]
        self.more_start = (
            np.zeros((m, 3)) if more_start_mm is None else np.asarray(more_start_mm, dtype=float)
        )
        self.more_idx = np.arange(3 * m) if more_idx is None else np.asarray(more_idx, dtype=np.intp)
        # per residual entry (target after target, rows, x y z): the row's weight (None: all 1)
        self.weights = (
            None
            if row_weights is None
            else np.tile(np.repeat(np.asarray(row_weights, dtype=float), 3), 1 + m)
        )

    def unpack(self, x: NDArray[np.float64]) -> tuple[KinematicParams, EffectParams, NDArray[np.float64]]:
        n_geo = self.geo_idx.size
        n_eff = len(self.eff_names)
        dx = np.zeros(N_PARAMS)
        dx[self.geo_idx] = x[:n_geo]
        eff = self.eff0.with_values(self.eff_names, x[n_geo : n_geo + n_eff]) if self.eff_names else self.eff0
        return self.start.apply(dx), eff, dx

    def model(
        self, x: NDArray[np.float64], registration: NDArray[np.float64], *, with_effects: bool
    ) -> KinematicModel:
        """The model this problem's unknowns ``x`` describe (entries after them, an
        :class:`ObservedProblem`'s, are not the model's): the geometry, the effects (None when
        not ``with_effects``) and the further targets' offsets."""
        x_in = x[: self._cols.size + self.more_idx.size]
        params, eff, _ = self.unpack(x_in)
        more = None if self.more_meas is None else self.more_targets(x_in)
        return KinematicModel(self.robot, params, eff if with_effects else None, registration, more)

    def more_targets(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """(K − 1, 3) the further targets' flange offsets at ``x``."""
        flat = self.more_start.reshape(-1).copy()
        flat[self.more_idx] += x[self._cols.size :]
        return flat.reshape(-1, 3)

    def residual(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        raw = self._residual(x)
        return raw if self.weights is None else raw * self.weights

    def _residual(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        params, eff, _ = self.unpack(x)
        if self.more_meas is None:
            tcp = twin_tcp_mm(self.robot, params, eff, self.a, self.dir, self.payload, self.temp)
            return (tcp - self.p_meas).reshape(-1)
        pts = targets_mm(
            self.robot, params, eff, self.more_targets(x), self.a, self.dir, self.payload, self.temp
        )
        meas = np.concatenate([self.p_meas[:, None, :], self.more_meas], axis=1)
        return (pts - meas).transpose(1, 0, 2).reshape(-1)

    def _target_jacobian(
        self, params: KinematicParams, eff: EffectParams, dx: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        return self._targets_jacobians(params, eff, dx, [None])[0]

    def _targets_jacobians(
        self,
        params: KinematicParams,
        eff: EffectParams,
        dx: NDArray[np.float64],
        places: Sequence[NDArray[np.float64] | None],
    ) -> list[NDArray[np.float64]]:
        """(n, 3, 39 + effects) per point on the flange (None: the tool of ``params``), from one
        twin whose gravity torques carry the payload at the TCP, as the residual's do."""
        if self._rows is None:
            payload = np.asarray(self.payload, dtype=float)
            self._rows = MeasuredRows(self.a, self.p_meas, self.dir, payload, self.temp)
        mass = MassModel.from_robot(self.robot)
        parts = twin_jacobian_targets(mass, params, eff, self.eff_names, places, self._rows)
        out = []
        for tcp, jac in parts:
            # the base rotation is the rotation vector dx[33:36] applied on the left of the start frame
            jac[:, :, 33:36] = -skew(tcp - dx[30:33]) @ left_jacobian(dx[33:36])
            out.append(jac)
        return out

    def jacobian(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        raw = self._jacobian(x)
        return raw if self.weights is None else raw * self.weights[:, None]

    def _jacobian(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        params, eff, dx = self.unpack(x)
        if self.more_meas is None:
            jac = self._target_jacobian(params, eff, dx)
            return jac[:, :, self._cols].reshape(-1, self._cols.size)
        n = self.a.shape[0]
        more = self.more_targets(x)
        m = more.shape[0]
        jacs = self._targets_jacobians(params, eff, dx, [None, *more])
        blocks = [np.concatenate([jacs[0][:, :, self._cols], np.zeros((n, 3, self.more_idx.size))], axis=2)]
        for k in range(m):
            jk = jacs[k + 1]
            offset = np.zeros((n, 3, 3 * m))
            offset[:, :, 3 * k : 3 * k + 3] = jk[:, :, 36:39]  # ∂p_k/∂(its flange offset)
            jk[:, :, 36:39] = 0.0  # the tool is the first target's offset
            blocks.append(np.concatenate([jk[:, :, self._cols], offset[:, :, self.more_idx]], axis=2))
        return np.concatenate(blocks, axis=0).reshape(-1, self._cols.size + self.more_idx.size)


@dataclass(frozen=True, slots=True)
class KinematicFit:
    """The result of :func:`calibrate_kinematic`."""

    model: KinematicModel
    frame: Literal["base", "tracker"]
    registration: NDArray[np.float64]  # (4, 4) world_T_base the iteration started from
    report: IdentifiabilityReport
    identified: tuple[str, ...]  # names of the iterated parameters (geometric, then effects)
    values: NDArray[np.float64]  # their increments from the start (registered nominal, no effects)
    std: NDArray[np.float64]  # their 1-sigma standard errors from the residual (same units)
    lm: LMResult
    rms_mm: float  # 3-D RMS residual of the TCP (the first target) on the fitted rows
    n_rows: int
    targets: int = 1  # targets per row the fit used (K)
    targets_rms_mm: float | None = None  # 3-D RMS residual over every target (None: the TCP only)
    weighted: bool = False  # rows weighted by 1/sigma_mm (weighted least squares)
    #: per corrected station (its name): the (4, 4) rigid motion its measured points were moved by
    stations: dict[str, NDArray[np.float64]] | None = None
    orientation_rms_deg: float | None = None  # the probe's orientation residual (None: no probe)
    probe_mount: NDArray[np.float64] | None = None  # (3, 3) the probe's rotation on the flange
    orientation_weight: float | None = None  # mm/rad (observations module)

    def named_values(self) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.identified, self.values, strict=True)}


def calibrate_kinematic(
    robot: RobotDescription,
    a_deg: NDArray[np.float64],
    p_measured_mm: NDArray[np.float64],
    *,
    dir: NDArray[np.float64] | None = None,
    payload_kg: NDArray[np.float64] | float = 0.0,
    temp_c: NDArray[np.float64] | None = None,
    effects: Sequence[str] = (),
    effect_joints: Sequence[int] = (1, 2, 3, 4, 5, 6),
    n_harmonics: int = 0,
    frame: FrameChoice = "auto",
    fit_base: bool = True,
    fit_tool: bool = True,
    rtol: float = 1e-8,
    max_iter: int = 100,
    more_targets_mm: NDArray[np.float64] | None = None,
    sigma_mm: NDArray[np.float64] | None = None,
    report_ranks: bool = True,
    station: NDArray[np.intp] | None = None,
    station_names: Sequence[str] | None = None,
    probe_r: NDArray[np.float64] | None = None,
    probe_sigma_deg: float = DEFAULT_PROBE_SIGMA_DEG,
) -> KinematicFit:
    """Calibrate the robot's MDH parameters (and ``effects``) on measured TCP positions.

    ``a_deg`` (n, 6) commanded axis values, ``p_measured_mm`` (n, 3) measured TCPs (robot base frame
    or tracker frame, see ``frame``); ``effects`` from :data:`comp_daemon.models.effects.EFFECTS`
    (seed 001: ``("ratio", "backlash")``), on ``effect_joints``. ``more_targets_mm`` (n, K − 1, 3):
    further targets on the flange measured at the same poses, in the same frame; their flange
    offsets are identified with the rest (module docstring: 6-DOF with three or more targets).
    ``sigma_mm`` (n,): each row's declared position σ (the data set's column); the rows are then
    weighted by ``median(σ)/σ`` (weighted least squares; the RMS reported stays unweighted).
    ``station`` (n,) each row's station index (names ``station_names``): every station with enough
    rows but the largest gets its own rigid correction, estimated with the rest; ``probe_r``
    (n, 3, 3) a 6-DOF probe's measured rotations, fitted with its unknown rotation on the flange and
    weighted by ``probe_sigma_deg`` against the rows' position σ (:mod:`comp_daemon.models.observations`).
    ``report_ranks=False`` leaves the identifiability report's rank checks, condition number and
    the combinations that reproduce the dependent columns out (-1, NaN, empty), and the standard
    errors (NaN), and the solver's Jacobian is its last one rather than one at the solution; the
    identified parameters and their values are the same: for fits whose report nobody reads, the
    folds of a cross-validation.
    """
    a = as_axes(a_deg)
    n = a.shape[0]
    p_meas = measured_positions(p_measured_mm, n)
    more_meas = None
    if more_targets_mm is not None:
        more_meas = further_targets(more_targets_mm, n)
        more_meas = more_meas if more_meas.shape[1] else None
    unknown = [e for e in effects if e not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effect(s) {', '.join(unknown)} (known: {', '.join(EFFECTS)})")
    # step 1 (module docstring): the frame the data are in, and the start registered in it
    start, chosen, registration = registered_start(robot, a, p_meas, frame)
    eff_names = effect_param_names(list(effects), effect_joints, n_harmonics) if effects else []
    eff0 = EffectParams.zeros(n_harmonics)
    dir_arr = None if dir is None else np.asarray(dir, dtype=float)
    n_more = 0 if more_meas is None else more_meas.shape[1]
    weights = None if sigma_mm is None else _row_weights(sigma_mm, n)
    obs = FrameObservations.of(
        n,
        station,
        station_names,
        None if probe_r is None else _rotations(probe_r, n),
        sigma_mm,
        probe_sigma_deg,
    )
    layout = _Layout(
        tuple(eff_names), tuple(target_param_names(n_more)), tuple(obs.names if obs.active else ())
    )
    more_start, mount0 = _flange_starts(
        robot, start, eff0, a, dir_arr, payload_kg, temp_c, more_meas, obs.probe_r
    )

    def problem_of(
        geo: NDArray[np.intp],
        effs: Sequence[str],
        more_idx: NDArray[np.intp] | None,
        extra_idx: NDArray[np.intp] | None,
    ) -> KinematicProblem | ObservedProblem:
        inner = KinematicProblem(
            robot,
            start,
            eff0,
            geo,
            effs,
            a,
            p_meas,
            dir_arr,
            payload_kg,
            temp_c,
            more_measured_mm=more_meas,
            more_start_mm=more_start,
            more_idx=more_idx,
            row_weights=weights,
        )
        return ObservedProblem(inner, obs, extra_idx, mount0) if obs.active else inner

    # step 2: identifiability of the Jacobian at the start
    whole = None  # the Jacobian of the problem with every parameter, at the start (when it is made)
    if more_meas is None and not obs.active:
        _, jac0 = twin_jacobian(robot, start, eff0, eff_names, a, dir_arr, payload_kg, temp_c)
    else:
        whole = problem_of(np.arange(N_PARAMS), eff_names, None, None).jacobian(np.zeros(len(layout.names)))
        jac0 = whole
    report = analyze_identifiability(
        jac0,
        layout.names,
        candidates=layout.candidates(fit_base, fit_tool),
        priority=layout.priority(start),
        rtol=rtol,
        check_rank=report_ranks,
        check_condition=report_ranks,
        describe_dependent=report_ranks,
    )
    idx = report.identifiable_index
    problem = problem_of(*layout.split(idx))
    inner = problem.inner if isinstance(problem, ObservedProblem) else problem

    # step 3: the identifiable parameters iterated from the start
    x0 = np.zeros(idx.size)
    # the iteration's first Jacobian: the identified columns of the analysed one, where that is the
    # problem's own (each column is computed on its own: the same numbers)
    first = None if whole is None else whole[:, idx]
    result = improved_lm(
        problem.residual,
        problem.jacobian,
        x0,
        x_scale="jac",
        max_iter=max_iter,
        jacobian_x0=first,
        jacobian_at_solution=report_ranks,
    )
    model = inner.model(result.x, registration, with_effects=bool(effects))
    std = _standard_errors(result.jacobian, result.residual) if report_ranks else np.full(idx.size, np.nan)
    per_point = _squared_errors(result.residual, inner.weights, n, 1 + n_more)
    rms = float(np.sqrt(np.mean(per_point[0])))
    observed = _observed_fit(problem, obs, result.x) if isinstance(problem, ObservedProblem) else {}
    return KinematicFit(
        model=model,
        frame=chosen,
        registration=registration,
        report=report,
        identified=tuple(layout.names[i] for i in idx),
        values=result.x.copy(),
        std=std,
        lm=result,
        rms_mm=rms,
        n_rows=n,
        targets=1 + n_more,
        targets_rms_mm=None if more_meas is None else float(np.sqrt(np.mean(per_point))),
        weighted=sigma_mm is not None,
        **observed,
    )


def registered_start(
    robot: RobotDescription, a_deg: NDArray[np.float64], p_meas_mm: NDArray[np.float64], frame: FrameChoice
) -> tuple[KinematicParams, Literal["base", "tracker"], NDArray[np.float64]]:
    """The calibration's start: the nominal geometry with its base frame registered in the frame
    the measured points are in (``frame``, or detected from the nominal TCPs of ``a_deg``), that
    frame, and the (4, 4) registration (the identity in the robot's base frame)."""
    nominal = KinematicParams.from_robot(robot)
    p_nominal = tcp_position_mm(nominal, axes_deg_to_q_rad(a_deg, nominal.sign))
    chosen: Literal["base", "tracker"] = detect_frame(p_nominal, p_meas_mm) if frame == "auto" else frame
    registration = rigid_registration(p_nominal, p_meas_mm) if chosen == "tracker" else np.eye(4)
    return nominal.with_base(registration), chosen, registration


@dataclass(frozen=True, slots=True)
class _Layout:
    """The columns of the calibration's Jacobian, in order: the 39 geometric parameters
    (:data:`PARAM_NAMES`), the effects', the further targets' flange offsets, then the frame
    observations' (the stations' corrections, the probe's rotation on the flange)."""

    effects: tuple[str, ...]
    targets: tuple[str, ...]
    observed: tuple[str, ...]

    @property
    def names(self) -> tuple[str, ...]:
        return (*PARAM_NAMES, *self.effects, *self.targets, *self.observed)

    def candidates(self, fit_base: bool, fit_tool: bool) -> list[str]:
        """Every column but the base frame's (``fit_base=False``) and the tool's (``fit_tool=False``)."""
        geometry = [
            name
            for name in PARAM_NAMES
            if (fit_base or not name.startswith("base_")) and (fit_tool or not name.startswith("tool_"))
        ]
        return [*geometry, *self.effects, *self.targets, *self.observed]

    def priority(self, start: KinematicParams) -> tuple[str, ...]:
        """MDH priority with the further targets' offsets (and the probe's rotation on the flange)
        offered right after the tool (the first target's), and the stations' corrections first: a
        station's frame is not the robot's, and nothing of the robot stands in for it."""
        order = list(mdh_priority(start, extra=self.effects))
        at = max(i for i, name in enumerate(order) if name.startswith("tool_")) + 1
        stations = [name for name in self.observed if name.startswith("station_")]
        mount = [name for name in self.observed if not name.startswith("station_")]
        return tuple(stations + order[:at] + list(self.targets) + mount + order[at:])

    def split(
        self, idx: NDArray[np.intp]
    ) -> tuple[NDArray[np.intp], list[str], NDArray[np.intp], NDArray[np.intp]]:
        """The kept columns ``idx`` block by block, as :class:`KinematicProblem` and
        :class:`ObservedProblem` take them: geometric indices into :data:`PARAM_NAMES`, effect
        names, then indices into the flattened target offsets and into the observations' names."""
        n_geo_eff = N_PARAMS + len(self.effects)
        n_in = n_geo_eff + len(self.targets)
        names = self.names
        geo_idx = idx[idx < N_PARAMS]
        eff_sel = [names[i] for i in idx[(idx >= N_PARAMS) & (idx < n_geo_eff)]]
        more_idx = idx[(idx >= n_geo_eff) & (idx < n_in)] - n_geo_eff
        return geo_idx, eff_sel, more_idx, idx[idx >= n_in] - n_in


def _squared_errors(
    residual: NDArray[np.float64], weights: NDArray[np.float64] | None, n: int, targets: int
) -> NDArray[np.float64]:
    """(K, n) every target's squared 3-D position error (mm²) in each row, from the solver's
    residual (the position errors target after target, weighted by ``weights``, then any other)."""
    position = residual[: 3 * n * targets]
    unweighted = position if weights is None else position / weights
    return np.sum(unweighted.reshape(-1, n, 3) ** 2, axis=2)


def _observed_fit(problem: ObservedProblem, obs: FrameObservations, x: NDArray[np.float64]) -> dict[str, Any]:
    """The frame observations' part of a :class:`KinematicFit` at the solution ``x``: every
    corrected station's rigid motion, and the probe's orientation residual, mount and weight."""
    motions = problem.station_motion(x)
    out: dict[str, Any] = {
        "stations": {name: _rigid(rot, t) for name, (rot, t) in zip(obs.labels, motions, strict=True)}
    }
    if obs.probe_r is not None:
        ang = angle_deg(problem.predicted_rotations(x), problem.measured_rotations(x))
        out["orientation_rms_deg"] = float(np.sqrt(np.mean(ang**2)))
        out["probe_mount"] = problem.mount(x)
        out["orientation_weight"] = obs.orientation_weight
    return out


def _rigid(rot: NDArray[np.float64], t: NDArray[np.float64]) -> NDArray[np.float64]:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, t
    return out


def _rotations(probe_r: NDArray[np.float64], n: int) -> NDArray[np.float64]:
    rot = np.asarray(probe_r, dtype=float)
    if rot.shape != (n, 3, 3):
        raise ValueError(f"probe rotations must have shape ({n}, 3, 3), got {rot.shape}")
    return rot


def _row_weights(sigma_mm: NDArray[np.float64], n: int) -> NDArray[np.float64]:
    """``median(σ)/σ`` per row: weighted least squares with residuals kept in mm."""
    sigma = np.asarray(sigma_mm, dtype=float)
    if sigma.shape != (n,) or not np.all(np.isfinite(sigma)) or (sigma <= 0).any():
        raise ValueError(f"sigma_mm must be ({n},) finite numbers > 0")
    return float(np.median(sigma)) / sigma


def _flange_starts(
    robot: RobotDescription,
    start: KinematicParams,
    eff0: EffectParams,
    a: NDArray[np.float64],
    dir: NDArray[np.float64] | None,
    payload_kg: NDArray[np.float64] | float,
    temp_c: NDArray[np.float64] | None,
    more_meas: NDArray[np.float64] | None,
    probe_r: NDArray[np.float64] | None,
) -> tuple[NDArray[np.float64] | None, NDArray[np.float64] | None]:
    """The start values of what sits on the flange, seen from the start twin's flange: the further
    targets' (K − 1, 3) offsets, the mean of each measured point (off by about the nominal twin's
    error, which the iteration removes), and the probe's (3, 3) rotation on the flange, the mean
    of the measured rotations; None for what was not measured."""
    if more_meas is None and probe_r is None:
        return None, None
    flange = twin_state(robot, start, eff0, a, dir, payload_kg, temp_c).chain.world_T_frame[:, 6]
    more_start = None
    if more_meas is not None:
        local = np.einsum("nji,nkj->nki", flange[:, :3, :3], more_meas - flange[:, None, :3, 3])
        more_start = np.asarray(local.mean(axis=0))
    mount0 = None if probe_r is None else mean_rotation(np.swapaxes(flange[:, :3, :3], 1, 2) @ probe_r)
    return more_start, mount0


def _standard_errors(jac: NDArray[np.float64], residual: NDArray[np.float64]) -> NDArray[np.float64]:
    """1-sigma parameter errors ``sqrt(diag(s²·(JᵀJ)⁻¹))`` with ``s² = |F|² / (m − p)``."""
    m, p = jac.shape
    if m <= p:
        return np.full(p, np.nan)
    s2 = float(residual @ residual) / (m - p)
    norms = np.linalg.norm(jac, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    _, sv, vt = np.linalg.svd(jac / norms, full_matrices=False)
    inv_diag = np.sum((vt / sv[:, None]) ** 2, axis=0)
    return np.sqrt(s2 * inv_diag) / norms
