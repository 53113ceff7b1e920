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
   (:func:`comp_daemon.models.registration.rigid_registration`);
2. identifiability (seed 003) of the Jacobian at the start, on the data's own poses: zero and
   dependent columns are removed by name (:func:`analyze_identifiability`, MDH priority: base and
   tool kept, ``beta`` instead of ``d`` at parallel joints);
3. the identifiable parameters are iterated with the improved Levenberg–Marquardt method of
   seed 000 (:func:`comp_daemon.models.lm.improved_lm`, columns scaled); the Jacobian is exact,
   the base rotation being a rotation vector (its Jacobian through the SO(3) left Jacobian).

Units: mm, rad for the geometry (``dx`` layout of :meth:`KinematicParams.apply`); effect units as in
:mod:`comp_daemon.models.effects` (the catalogue: deg for backlash, 1 for the ratio error …).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import N_PARAMS, PARAM_NAMES, KinematicParams, axes_deg_to_q_rad
from comp_daemon.kinematics.so3 import left_jacobian, skew
from comp_daemon.models.base import ErrorModel, as_axes
from comp_daemon.models.effects import EFFECTS, EffectParams, effect_param_names, twin_jacobian, twin_tcp_mm
from comp_daemon.models.identifiability import IdentifiabilityReport, analyze_identifiability, mdh_priority
from comp_daemon.models.lm import LMResult, improved_lm
from comp_daemon.models.registration import detect_frame, rigid_registration
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "SEED001_EFFECTS",
    "KinematicFit",
    "KinematicModel",
    "KinematicProblem",
    "calibrate_kinematic",
]

SEED001_EFFECTS: tuple[str, ...] = ("ratio", "backlash")
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
    ):
        self.robot = robot
        self.params = params
        self.effects = effects
        self.world_T_base = params.world_T_base
        self.registration = np.eye(4) if registration is None else np.array(registration, dtype=float)

    def predict_tcp_mm(
        self,
        a_deg: NDArray[np.float64],
        dir: NDArray[np.float64] | None = None,
        payload_kg: NDArray[np.float64] | float | None = None,
        temp_c: NDArray[np.float64] | None = None,
    ) -> NDArray[np.float64]:
        a = as_axes(a_deg)
        if self.effects is None:
            return tcp_position_mm(self.params, axes_deg_to_q_rad(a, self.params.sign))
        payload = 0.0 if payload_kg is None else payload_kg
        return twin_tcp_mm(self.robot, self.params, self.effects, a, dir, payload, temp_c)

    def ik_params(self) -> KinematicParams:
        return self.params

    def to_payload(self) -> dict[str, Any]:
        p = self.params
        out: dict[str, Any] = {
            "theta_offset_rad": p.theta_offset_rad.tolist(),
            "d_mm": p.d_mm.tolist(),
            "a_mm": p.a_mm.tolist(),
            "alpha_rad": p.alpha_rad.tolist(),
            "beta_rad": p.beta_rad.tolist(),
            "tool_xyz_mm": p.tool_xyz_mm.tolist(),
            "world_T_base": p.world_T_base.tolist(),
            "effects": None,
        }
        if self.effects is not None:
            names = self.effects.names()
            out["effects"] = {
                "n_harmonics": self.effects.n_harmonics,
                "t_ref_c": self.effects.t_ref_c,
                "names": names,
                "values": self.effects.get(names).tolist(),
            }
        return out

    @classmethod
    def from_payload(
        cls,
        robot: RobotDescription,
        payload: dict[str, Any],
        order: int | None,
        registration: NDArray[np.float64],
    ) -> KinematicModel:
        nominal = KinematicParams.from_robot(robot)
        params = KinematicParams(
            theta_offset_rad=_floats(payload["theta_offset_rad"], (6,), "theta_offset_rad"),
            d_mm=_floats(payload["d_mm"], (6,), "d_mm"),
            a_mm=_floats(payload["a_mm"], (6,), "a_mm"),
            alpha_rad=_floats(payload["alpha_rad"], (6,), "alpha_rad"),
            beta_rad=_floats(payload["beta_rad"], (6,), "beta_rad"),
            sign=nominal.sign,
            tool_xyz_mm=_floats(payload["tool_xyz_mm"], (3,), "tool_xyz_mm"),
            world_T_base=_floats(payload["world_T_base"], (4, 4), "world_T_base"),
        )
        effects = None
        eff = payload.get("effects")
        if eff is not None:
            names = [str(n) for n in eff["names"]]
            values = _floats(eff["values"], (len(names),), "effects.values")
            effects = EffectParams.zeros(int(eff["n_harmonics"]), float(eff["t_ref_c"])).with_values(
                names, values
            )
        return cls(robot, params, effects, registration)


def _floats(value: Any, shape: tuple[int, ...], name: str) -> NDArray[np.float64]:
    out = np.array(value, dtype=float)
    if out.shape != shape:
        raise ValueError(f"model field '{name}': expected shape {shape}, got {out.shape}")
    if not np.all(np.isfinite(out)):
        raise ValueError(f"model field '{name}': values must be finite")
    return out


class KinematicProblem:
    """Residual and exact Jacobian of the calibration over a subset of parameters.

    ``x`` holds the increments of the geometric parameters ``geo_idx`` (indices into
    :data:`PARAM_NAMES`, the layout of :meth:`KinematicParams.apply` on ``start``) followed by the
    values of the effect parameters ``eff_names``. The residual is predicted − measured (mm, (3n,)).
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
    ) -> None:
        self.robot, self.start, self.eff0 = robot, start, eff0
        self.geo_idx = np.asarray(geo_idx, dtype=np.intp)
        self.eff_names = list(eff_names)
        self.a, self.p_meas, self.dir, self.payload, self.temp = a_deg, p_measured_mm, dir, payload_kg, temp_c
        self._cols = np.concatenate([self.geo_idx, np.arange(N_PARAMS, N_PARAMS + len(self.eff_names))])

    def unpack(self, x: NDArray[np.float64]) -> tuple[KinematicParams, EffectParams, NDArray[np.float64]]:
        n_geo = self.geo_idx.size
        dx = np.zeros(N_PARAMS)
        dx[self.geo_idx] = x[:n_geo]
        eff = self.eff0.with_values(self.eff_names, x[n_geo:]) if self.eff_names else self.eff0
        return self.start.apply(dx), eff, dx

    def residual(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        params, eff, _ = self.unpack(x)
        tcp = twin_tcp_mm(self.robot, params, eff, self.a, self.dir, self.payload, self.temp)
        return (tcp - self.p_meas).reshape(-1)

    def jacobian(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        params, eff, dx = self.unpack(x)
        tcp, jac = twin_jacobian(
            self.robot, params, eff, self.eff_names, self.a, self.dir, self.payload, self.temp
        )
        # the base rotation is the rotation vector dx[33:36] applied on the left of the start frame
        jac[:, :, 33:36] = -skew(tcp - dx[30:33]) @ left_jacobian(dx[33:36])
        return jac[:, :, self._cols].reshape(-1, self._cols.size)


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
    rms_mm: float  # 3-D RMS residual on the fitted rows
    n_rows: int

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
) -> KinematicFit:
    """Calibrate the robot's MDH parameters (and ``effects``) on measured TCP positions.

    ``a_deg`` (n, 6) commanded axis values, ``p_measured_mm`` (n, 3) measured TCPs (robot base frame
    or tracker frame, see ``frame``); ``effects`` from :data:`comp_daemon.models.effects.EFFECTS`
    (seed 001: ``("ratio", "backlash")``), on ``effect_joints``.
    """
    a = as_axes(a_deg)
    p_meas = np.asarray(p_measured_mm, dtype=float)
    n = a.shape[0]
    if p_meas.shape != (n, 3):
        raise ValueError(f"measured positions must have shape ({n}, 3), got {p_meas.shape}")
    unknown = [e for e in effects if e not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effect(s) {', '.join(unknown)} (known: {', '.join(EFFECTS)})")
    nominal = KinematicParams.from_robot(robot)
    p_nominal = tcp_position_mm(nominal, axes_deg_to_q_rad(a, nominal.sign))
    chosen = detect_frame(p_nominal, p_meas) if frame == "auto" else frame
    registration = rigid_registration(p_nominal, p_meas) if chosen == "tracker" else np.eye(4)
    start = nominal.with_base(registration)
    eff_names = effect_param_names(list(effects), effect_joints, n_harmonics) if effects else []
    eff0 = EffectParams.zeros(n_harmonics)
    dir_arr = None if dir is None else np.asarray(dir, dtype=float)

    geo_candidates = [
        name
        for name in PARAM_NAMES
        if (fit_base or not name.startswith("base_")) and (fit_tool or not name.startswith("tool_"))
    ]
    all_names = (*PARAM_NAMES, *eff_names)
    _, jac0 = twin_jacobian(robot, start, eff0, eff_names, a, dir_arr, payload_kg, temp_c)
    report = analyze_identifiability(
        jac0,
        all_names,
        candidates=[*geo_candidates, *eff_names],
        priority=mdh_priority(start, extra=eff_names),
        rtol=rtol,
    )
    idx = report.identifiable_index
    geo_idx = idx[idx < N_PARAMS]
    eff_sel = [all_names[i] for i in idx[idx >= N_PARAMS]]
    problem = KinematicProblem(robot, start, eff0, geo_idx, eff_sel, a, p_meas, dir_arr, payload_kg, temp_c)

    x0 = np.zeros(idx.size)
    result = improved_lm(problem.residual, problem.jacobian, x0, x_scale="jac", max_iter=max_iter)
    params, eff, _ = problem.unpack(result.x)
    model = KinematicModel(robot, params, eff if effects else None, registration)
    std = _standard_errors(result.jacobian, result.residual)
    rms = float(np.sqrt(np.mean(np.sum(result.residual.reshape(n, 3) ** 2, axis=1))))
    return KinematicFit(
        model=model,
        frame=chosen,
        registration=registration,
        report=report,
        identified=tuple(all_names[i] for i in idx),
        values=result.x.copy(),
        std=std,
        lm=result,
        rms_mm=rms,
        n_rows=n,
    )


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
