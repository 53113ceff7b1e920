"""Seed 000's Table 2: statistics of the positioning error on check rows.

The positioning error of a row is ``e = measured − predicted`` (mm, measurement frame; seed 000:
ΔP = P_actual − P_theoretical, the theoretical position being the model's prediction). Per axis x,
y, z the table gives the *signed* components' mean and standard deviation and the largest absolute
component: seed 000 reports that after compensation "the error components in x, y and z are within
±0.2 mm" and "the mean value of error components in the three directions is close to zero", which
only makes sense for signed components. The 3-D (absolute positioning) error is ``|e|`` (seed 000
eq. 27) with its mean, standard deviation and maximum. Standard deviations are sample ones (n − 1).

Seed 000's own figures (KUKA KR210, 104 target points, absolute error): before compensation
max 0.76 / mean 0.42 mm; kinematic calibration max 0.42 / mean 0.24 mm; Chebyshev model with the
closed joint loop max 0.19 mm, every axis within ±0.2 mm.

Two honest companions of the table:

- :func:`registered_nominal`: the nominal robot after a rigid registration of its base (6
  parameters) and of every target's offset on the flange (3 per target), fitted on the fit rows
  with the joints' geometry left nominal. The raw ``nominal`` row measures, besides the robot,
  the user's unknown reflector offsets (tens of mm on a campaign with three reflectors); this row
  is the baseline a calibration must beat.
- :func:`outside_fit_ranges`: how many check rows lie outside the fitted rows' range of some
  axis (extrapolation; a polynomial or kriging model is not to be trusted there).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.estimation.lm import improved_lm
from comp_daemon.estimation.registration import rigid_registration
from comp_daemon.kinematics.forward import tcp_position_mm
from comp_daemon.kinematics.params import BASE_SLICE, N_PARAMS, TOOL_SLICE, KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.base import as_axes
from comp_daemon.models.effects import EffectParams
from comp_daemon.models.kinematic import KinematicModel, KinematicProblem
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "REGISTERED_NOMINAL",
    "SEED000_TABLE2_MM",
    "error_statistics",
    "format_table2",
    "outside_fit_ranges",
    "registered_nominal",
]

#: the table's name of the nominal robot with its base and targets registered
REGISTERED_NOMINAL = "nominal, base+tool registered"

SEED000_TABLE2_MM: dict[str, dict[str, float]] = {
    "before compensation": {"max": 0.76, "mean": 0.42},
    "kinematic calibration": {"max": 0.42, "mean": 0.24},
    "Chebyshev + closed loop": {"max": 0.19},
}


def error_statistics(measured_mm: NDArray[np.float64], predicted_mm: NDArray[np.float64]) -> dict[str, Any]:
    """Table 2 statistics of ``measured − predicted`` (both (n, 3), mm)."""
    e = np.asarray(measured_mm, dtype=float) - np.asarray(predicted_mm, dtype=float)
    if e.ndim != 2 or e.shape[1] != 3 or e.shape[0] == 0:
        raise ValueError(f"need (n, 3) positions with n >= 1, got {e.shape}")
    n = e.shape[0]
    ddof = 1 if n > 1 else 0
    d = np.linalg.norm(e, axis=1)
    out: dict[str, Any] = {"n": n}
    for k, axis in enumerate("xyz"):
        out[axis] = {
            "mean": float(e[:, k].mean()),
            "std": float(e[:, k].std(ddof=ddof)),
            "max_abs": float(np.abs(e[:, k]).max()),
        }
    out["3d"] = {
        "mean": float(d.mean()),
        "std": float(d.std(ddof=ddof)),
        "max": float(d.max()),
        "rms": float(np.sqrt(np.mean(d**2))),
    }
    return out


def registered_nominal(
    robot: RobotDescription,
    a_deg: NDArray[np.float64],
    p_measured_mm: NDArray[np.float64],
    more_measured_mm: NDArray[np.float64] | None = None,
    *,
    max_iter: int = 100,
) -> tuple[KinematicModel, dict[str, Any]]:
    """The nominal robot with its base frame (6 parameters) and every target's offset on the
    flange (3 per target) fitted by least squares on these rows, its joints' geometry nominal;
    and ``{"parameters", "rms_mm", "tool_mm", "targets_mm"}`` of the fit."""
    a = as_axes(a_deg)
    p = np.asarray(p_measured_mm, dtype=float)
    nominal = KinematicParams.from_robot(robot)
    registration = rigid_registration(tcp_position_mm(nominal, axes_deg_to_q_rad(a, nominal.sign)), p)
    start = nominal.with_base(registration)
    more = None if more_measured_mm is None or more_measured_mm.shape[1] == 0 else more_measured_mm
    m = 0 if more is None else more.shape[1]
    geo_idx = np.r_[np.arange(N_PARAMS)[BASE_SLICE], np.arange(N_PARAMS)[TOOL_SLICE]]
    problem = KinematicProblem(
        robot,
        start,
        EffectParams.zeros(),
        geo_idx,
        [],
        a,
        p,
        None,
        0.0,
        None,
        more_measured_mm=more,
        more_start_mm=np.tile(start.tool_xyz_mm, (m, 1)) if m else None,
    )
    result = improved_lm(
        problem.residual, problem.jacobian, np.zeros(geo_idx.size + 3 * m), x_scale="jac", max_iter=max_iter
    )
    params, _, _ = problem.unpack(result.x)
    more_fit = problem.more_targets(result.x) if m else None
    model = KinematicModel(robot, params, None, registration, more_fit)
    err = model.predict_tcp_mm(a) - p
    info = {
        "parameters": int(geo_idx.size + 3 * m),
        "rms_mm": float(np.sqrt(np.mean(np.sum(err**2, axis=1)))),
        "tool_mm": [float(v) for v in params.tool_xyz_mm],
        "targets_mm": [] if more_fit is None else more_fit.tolist(),
    }
    return model, info


def outside_fit_ranges(a_fit_deg: NDArray[np.float64], a_check_deg: NDArray[np.float64]) -> dict[str, Any]:
    """How many check rows lie outside the fit rows' range of at least one axis, and per axis."""
    a_fit, a_check = as_axes(a_fit_deg), as_axes(a_check_deg)
    low, high = a_fit.min(axis=0), a_fit.max(axis=0)
    out = (a_check < low) | (a_check > high)
    return {
        "rows": int(out.any(axis=1).sum()),
        "per_axis": {f"A{j + 1}": int(out[:, j].sum()) for j in range(6) if out[:, j].any()},
    }


def format_table2(
    rows: Mapping[str, Mapping[str, Any]],
    timing: Mapping[str, Mapping[str, float]] | None = None,
    outside: Mapping[str, int] | None = None,
) -> str:
    """A text table: one line per model, per-axis mean/std/max|·| and 3-D mean/std/max (mm); with
    ``timing`` (per model ``fit_s`` and ``predict_s``) also the 3-D RMS and the two times; with
    ``outside`` (per model) the number of check rows outside its fitted axis ranges."""
    w = max([12, *(len(name) for name in rows)])
    head = (
        f"{'model':<{w}} {'n':>4} | "
        + " | ".join(f"{ax + ' mean':>7} {'std':>6} {'max|.|':>6}" for ax in "xyz")
        + f" | {'3D mean':>7} {'std':>6} {'max':>6}"
        + (f" | {'3D rms':>6} {'fit s':>7} {'pred ms':>8}" if timing is not None else "")
        + (f" | {'outside':>7}" if outside is not None else "")
    )
    lines = [head, "-" * len(head)]
    for name, st in rows.items():
        cells = " | ".join(
            f"{st[ax]['mean']:>7.3f} {st[ax]['std']:>6.3f} {st[ax]['max_abs']:>6.3f}" for ax in "xyz"
        )
        d = st["3d"]
        line = f"{name:<{w}} {st['n']:>4} | {cells} | {d['mean']:>7.3f} {d['std']:>6.3f} {d['max']:>6.3f}"
        if timing is not None:
            t = timing[name]
            line += f" | {d['rms']:>6.3f} {t['fit_s']:>7.2f} {1e3 * t['predict_s']:>8.2f}"
        if outside is not None:
            count = outside.get(name)
            line += f" | {'-' if count is None else count:>7}"
        lines.append(line)
    return "\n".join(lines)
