"""Several targets on one flange: the tracker's noise from their mutual distances, and the flange's
position and orientation errors.

Noise. Targets i and j are fixed to the same rigid flange, so their true distance ``D_ij`` is the
same at every pose; what the tracker reports varies. With measured positions ``p_i = P_i + e_i``
and independent, isotropic tracker noise ``e ~ N(0, σ² I)`` per target and pose,

    d_ij = |p_i − p_j| = |P_i − P_j + e_i − e_j| = D_ij + u_ijᵀ (e_i − e_j) + O(σ²/D_ij),

with ``u_ij`` the unit vector from j to i. ``e_i − e_j`` has covariance ``2σ² I``, so its projection
on any unit vector has variance ``2σ²``: ``var(d_ij) = 2σ²`` to first order (the second-order
terms are ``σ²/D`` ≈ 1e-7 mm for σ = 5 µm and D = 150 mm; they shift the mean of ``d``, not its
spread). Each pair's sample variance over the campaign (n − 1 degrees of freedom) estimates 2σ²
without any model of the robot; the K(K − 1)/2 pairs are pooled by their mean:
``σ̂² = mean_pairs s²(d_ij) / 2``. The noise floor of the diagnosis is the expected 3-D distance
of one measurement from the truth, ``√3·σ̂`` (as for repeats). What this sees is the tracker's
noise only: the robot's own repeatability moves every target alike and leaves the distances
unchanged. An anisotropic tracker (radial and angular noise differ) gives the noise along the
pairs' directions, averaged over the poses.

Flange. With three or more targets the flange's pose is measured, not only a point. Given a twin
(the geometric step's), the further targets' positions in the flange frame are fitted on the fit
rows (each the mean of its measured points seen from the twin's flange; the first target is the
twin's tool), and on each check row the rigid motion that best maps the twin's targets onto the
measured ones (Kabsch) is the flange's pose error: its rotation angle is the orientation error,
and the displacement of the flange origin the position error.

The diagnosis's geometric step fits the TCP alone, so a wrist error that turns the flange about the
TCP stays in its orientation error. ``six_dof`` therefore gives the same errors after a geometric
calibration on every target's position (:func:`~comp_daemon.models.kinematic.calibrate_kinematic`
with the further targets, fit rows only): what is left there is not geometry.
"""

from __future__ import annotations

from itertools import combinations
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.diagnosis.fitting import FitResult, flange_mm, seen_from_flange
from comp_daemon.models.effects import EffectParams, MassModel, twin_state
from comp_daemon.models.kinematic import calibrate_kinematic
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.robot.description import RobotDescription

__all__ = ["flange_errors", "flange_pose_errors", "flange_words", "noise_from_targets", "target_offsets_mm"]

FloatArray = NDArray[np.float64]


def noise_from_targets(reflectors_mm: FloatArray | None) -> tuple[float, float] | None:
    """``(σ̂, √3·σ̂)`` in mm from the spread of the targets' mutual distances (module docstring);
    None with fewer than two targets or two rows."""
    if reflectors_mm is None:
        return None
    pts = np.asarray(reflectors_mm, dtype=float)
    if pts.ndim != 3 or pts.shape[1] < 2 or pts.shape[0] < 2:
        return None
    variances = [
        float(np.var(np.linalg.norm(pts[:, i] - pts[:, j], axis=1), ddof=1))
        for i, j in combinations(range(pts.shape[1]), 2)
    ]
    sigma = float(np.sqrt(np.mean(variances) / 2.0))
    return sigma, float(np.sqrt(3.0) * sigma)


def _kabsch(src: FloatArray, dst: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Per row, the rotation (n, 3, 3) and translation (n, 3) that best map ``src`` (n, K, 3) onto ``dst``."""
    c_src, c_dst = src.mean(axis=1), dst.mean(axis=1)
    cov = np.einsum("nki,nkj->nij", dst - c_dst[:, None], src - c_src[:, None])
    u, _, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(u @ vt))
    d = np.where(d == 0, 1.0, d)
    fix = np.ones((len(src), 3))
    fix[:, 2] = d
    rot = (u * fix[:, None, :]) @ vt
    return rot, c_dst - np.einsum("nij,nj->ni", rot, c_src)


def _r(value: float) -> float:
    return float(f"{value:.4g}") if np.isfinite(value) and value != 0.0 else float(value)


def flange_pose_errors(
    origin: FloatArray, twin: FloatArray, meas: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Per row, the flange's position error (mm) and orientation error (deg): the rigid motion that
    best maps the twin's targets ``twin`` (n, K, 3) onto the measured ``meas``, at the twin's
    flange origin ``origin`` (n, 3)."""
    r_err, t_err = _kabsch(twin, meas)
    moved = np.einsum("nij,nj->ni", r_err, origin) + t_err
    cos = np.clip((np.trace(r_err, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return np.linalg.norm(moved - origin, axis=1), np.rad2deg(np.arccos(cos))


def _summary(position: FloatArray, angle: FloatArray) -> dict[str, float]:
    return {
        "position_rms_mm": _r(float(np.sqrt(np.mean(position**2)))),
        "position_max_mm": _r(float(position.max())),
        "orientation_rms_deg": _r(float(np.sqrt(np.mean(angle**2)))),
        "orientation_max_deg": _r(float(angle.max())),
    }


def _six_dof(
    robot: RobotDescription,
    obs: MeasuredRows,
    meas: FloatArray,
    frame: str,
    fit_rows: NDArray[np.int64],
    check_rows: NDArray[np.int64],
) -> dict[str, float]:
    """The flange's errors on the check rows after a geometric calibration on every target."""
    kf = calibrate_kinematic(
        robot,
        obs.a_deg[fit_rows],
        meas[fit_rows, 0],
        payload_kg=obs.payload_kg[fit_rows],
        frame="tracker" if frame == "tracker" else "base",
        more_targets_mm=meas[fit_rows, 1:],
    )
    a, payload = obs.a_deg[check_rows], obs.payload_kg[check_rows]
    twin = kf.model.predict_targets_mm(a, payload_kg=payload)
    st = twin_state(robot, kf.model.params, EffectParams.zeros(), a, None, payload)
    origin = st.chain.world_T_frame[:, 6, :3, 3]
    return _summary(*flange_pose_errors(origin, twin, meas[check_rows]))


def target_offsets_mm(mass: MassModel, fit: FitResult, obs: MeasuredRows, more_mm: FloatArray) -> FloatArray:
    """(K − 1, 3) the further targets' positions in the flange frame (mm): each the mean of its
    measured points ``more_mm`` (n, K − 1, 3) seen from the flange of the twin ``fit`` at ``obs``."""
    rot, origin = flange_mm(mass, fit.params, fit.effects, obs)
    more = np.asarray(more_mm, dtype=float)
    return np.array([seen_from_flange(rot, origin, more[:, k]) for k in range(more.shape[1])])


def flange_errors(
    mass: MassModel,
    fit: FitResult,
    obs: MeasuredRows,
    reflectors_mm: FloatArray | None,
    fit_rows: NDArray[np.int64],
    check_rows: NDArray[np.int64],
    robot: RobotDescription | None = None,
    frame: str = "base",
) -> dict[str, Any] | None:
    """The flange's position and orientation errors on the check rows left by the twin ``fit``
    and, given the ``robot``, by a 6-DOF geometric calibration (module docstring); None with fewer
    than three targets."""
    if reflectors_mm is None or np.asarray(reflectors_mm).shape[1] < 3 or len(check_rows) == 0:
        return None
    meas = np.asarray(reflectors_mm, dtype=float)
    rot, origin = flange_mm(mass, fit.params, fit.effects, obs)
    seen = target_offsets_mm(mass, fit, obs.take(fit_rows), meas[fit_rows, 1:])
    offsets = np.concatenate([fit.params.tool_xyz_mm[None, :], seen], axis=0)  # (K, 3)
    twin = np.einsum("nij,kj->nki", rot, offsets) + origin[:, None]
    radius = float(np.mean(np.linalg.norm(offsets - offsets.mean(axis=0), axis=1)))
    # target_radius_mm: the targets' mean distance from their centroid, the lever arm of the orientation
    out: dict[str, Any] = {
        "rows": "check",
        "after": "geometric",
        "targets": int(meas.shape[1]),
        **_summary(*flange_pose_errors(origin[check_rows], twin[check_rows], meas[check_rows])),
        "target_radius_mm": _r(radius),
    }
    if robot is not None:
        out["six_dof"] = {
            "after": "geometric calibration on every target",
            **_six_dof(robot, obs, meas, frame, fit_rows, check_rows),
        }
    return out


def flange_words(flange: dict[str, Any]) -> str:
    """One or two sentences on the flange's position and orientation errors."""
    words = (
        f"With {flange['targets']} targets on the flange, the error left after the geometric step is "
        f"{flange['position_rms_mm']:.3f} mm RMS in the flange's position and "
        f"{1000.0 * flange['orientation_rms_deg']:.1f} mdeg RMS in its orientation (check rows)"
    )
    six = flange.get("six_dof")
    if six is None:
        return words + "."
    return words + (
        f"; a geometric calibration on every target's position leaves {six['position_rms_mm']:.3f} mm "
        f"and {1000.0 * six['orientation_rms_deg']:.1f} mdeg."
    )
