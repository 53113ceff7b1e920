"""Observations beyond one tracker frame: tracker stations and a 6-DOF probe's orientation.

Both enter the kinematic calibration (:func:`comp_daemon.models.kinematic.calibrate_kinematic`)
as further parameters and residuals around its :class:`~comp_daemon.models.kinematic.KinematicProblem`
(:class:`ObservedProblem`), estimated jointly with the robot's parameters.

**Stations.** Rows of one ``station`` share a measurement frame; a tracker moved between sessions is
another station. The rows come in one frame (the preparation maps every station into its reference
station's frame by a first registration, :mod:`comp_daemon.preparation.campaign`); here each station
other than the one with the most rows gets a rigid correction of its measured points, six parameters
``station_<name>_x, _y, _z`` (mm) and ``_rx, _ry, _rz`` (rad, a rotation vector about the centroid
``c`` of the station's rows, which keeps the rotation and the translation apart)::

    q = exp(ω)·(p − c) + c + δt

The residual is ``predicted − q``; the measured orientations of the station turn with ``exp(ω)``.

**Probe orientation.** A 6-DOF probe reports the rotation ``R_meas`` of its frame (columns ``qw…qz``)
besides its origin ``x, y, z``. Its pose on the flange is unknown: the prediction is
``R_flange(x) · R_mount`` with ``R_mount = exp(φ)·R_mount0`` (``probe_rx, probe_ry, probe_rz``, rad,
started from the mean of ``R_flange⁻¹·R_meas`` over the rows). The orientation residual of a row is
the difference of the three axes of the predicted and the measured frame, ``R_pred·e_k − R_meas·e_k``
(k = x, y, z): for a small rotation error ``δθ`` its squared norm is ``2|δθ|²``. It is weighted against
the positions by the declared uncertainties: with ``σ_p`` the row's position σ per axis (``sigma_mm``,
else :data:`DEFAULT_PROBE_SIGMA_MM`) and ``σ_θ`` the probe's orientation σ per axis (option, default
:data:`~comp_daemon.models.rows.DEFAULT_PROBE_SIGMA_DEG`), the orientation residual is multiplied
by ``σ_p/(σ_θ·√2)`` mm/rad, so that each row's cost is ``σ_p²·(|Δp|²/σ_p² + |δθ|²/σ_θ²)``:
weighted least squares in mm.

The Jacobian is exact: the flange axis ``R_flange·m`` is the TCP of the twin with the tool at ``m``
minus the one with the tool at the flange origin, whose Jacobians the twin gives.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.kinematics.params import N_PARAMS
from comp_daemon.kinematics.so3 import left_jacobian, quat_to_matrix, rotvec_to_matrix, skew
from comp_daemon.models.effects import twin_state

__all__ = [
    "DEFAULT_PROBE_SIGMA_MM",
    "MIN_STATION_ROWS",
    "MOUNT_NAMES",
    "FrameObservations",
    "ObservedProblem",
    "angle_deg",
    "mean_rotation",
    "orientation_weight",
    "probe_axis_points_mm",
    "station_param_names",
]

FloatArray = NDArray[np.float64]

#: the position σ per axis (mm) the orientation is weighted against when the rows declare none
DEFAULT_PROBE_SIGMA_MM = 0.025
#: a station gets its own correction in a fit only with at least this many rows in it
MIN_STATION_ROWS = 6
STATION_SUFFIXES = ("x", "y", "z", "rx", "ry", "rz")
MOUNT_NAMES = ("probe_rx", "probe_ry", "probe_rz")


def station_param_names(labels: Sequence[str]) -> list[str]:
    """The six correction parameters of each station: ``station_<name>_x`` … ``_rz``."""
    return [f"station_{s}_{c}" for s in labels for c in STATION_SUFFIXES]


def mean_rotation(rot: FloatArray) -> FloatArray:
    """(3, 3) the rotation nearest (Frobenius) to the mean of rotations (n, 3, 3)."""
    u, _, vt = np.linalg.svd(np.asarray(rot, dtype=float).mean(axis=0))
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return np.asarray(u @ np.diag([1.0, 1.0, d]) @ vt)


def angle_deg(r_a: FloatArray, r_b: FloatArray) -> FloatArray:
    """(n,) the angle (deg) of the rotation between each pair of rotations (n, 3, 3)."""
    cos = (np.einsum("nij,nij->n", r_a, r_b) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def orientation_weight(sigma_mm: FloatArray | float | None, probe_sigma_deg: float) -> float:
    """``σ_p/(σ_θ·√2)`` (mm/rad): the weight of the probe's axis differences against positions
    (module docstring); ``σ_p`` the median of ``sigma_mm``, else :data:`DEFAULT_PROBE_SIGMA_MM`."""
    if not (probe_sigma_deg > 0 and np.isfinite(probe_sigma_deg)):
        raise ValueError(f"the probe's orientation sigma must be > 0 deg, got {probe_sigma_deg!r}")
    sigma_p = DEFAULT_PROBE_SIGMA_MM if sigma_mm is None else float(np.median(sigma_mm))
    return float(sigma_p / (np.radians(probe_sigma_deg) * np.sqrt(2.0)))


def probe_axis_points_mm(xyz_mm: FloatArray, q_wxyz: FloatArray, lever_mm: float) -> FloatArray:
    """(n, 3, 3) points ``lever_mm`` along the probe frame's x, y and z axes from its origin: the
    orientation as three further targets on the flange. With the lever :func:`orientation_weight`,
    a rotation error ``δθ`` moves them by ``2·lever²·|δθ|²`` in all, the weight of the module
    docstring (their positions carry the origin's noise too)."""
    rot = quat_to_matrix(q_wxyz)
    return np.asarray(xyz_mm, dtype=float)[:, None, :] + lever_mm * np.swapaxes(rot, 1, 2)


@dataclass(frozen=True)
class FrameObservations:
    """What a fit observes beyond positions in one frame (module docstring).

    ``station`` (n,) each row's station index (None: one frame); ``free`` the stations that get a
    correction, ``labels`` their names; ``probe_r`` (n, 3, 3) the probe's measured rotations (None:
    no probe); ``orientation_weight`` (mm/rad) ``σ_p/(σ_θ·√2)``; ``mount0`` (3, 3) the start of the
    probe's rotation on the flange.
    """

    station: NDArray[np.intp] | None = None
    free: tuple[int, ...] = ()
    labels: tuple[str, ...] = ()
    probe_r: FloatArray | None = None
    orientation_weight: float = 0.0
    mount0: FloatArray | None = None

    @property
    def active(self) -> bool:
        return bool(self.free) or self.probe_r is not None

    @property
    def names(self) -> list[str]:
        return station_param_names(self.labels) + (list(MOUNT_NAMES) if self.probe_r is not None else [])

    @classmethod
    def of(
        cls,
        n: int,
        station: NDArray[np.intp] | None,
        station_names: Sequence[str] | None,
        probe_r: FloatArray | None,
        sigma_mm: FloatArray | None,
        probe_sigma_deg: float,
    ) -> FrameObservations:
        """The observations of ``n`` rows: stations with at least :data:`MIN_STATION_ROWS` rows,
        all but the one with the most rows corrected; the probe weighted by the declared σ."""
        free: tuple[int, ...] = ()
        labels: tuple[str, ...] = ()
        st = None
        if station is not None:
            st = np.asarray(station, dtype=np.intp)
            if st.shape != (n,):
                raise ValueError(f"station indices must have shape ({n},), got {st.shape}")
            counts = np.bincount(st)
            present = [int(s) for s in np.flatnonzero(counts >= MIN_STATION_ROWS)]
            if len(present) > 1:
                ref = max(present, key=lambda s: (counts[s], -s))
                free = tuple(s for s in present if s != ref)
                names = station_names or [str(s) for s in range(int(st.max()) + 1)]
                labels = tuple(names[s] for s in free)
        weight = 0.0 if probe_r is None else orientation_weight(sigma_mm, probe_sigma_deg)
        return cls(st if free else None, free, labels, probe_r, weight)


class ObservedProblem:
    """A :class:`~comp_daemon.models.kinematic.KinematicProblem` with station corrections and probe
    orientations (module docstring).

    ``x`` is the inner problem's, then the selected ``extra_idx`` of the extra parameters (every
    free station's six, then the probe's three). The residual is the inner one (positions, every
    target, weighted) with the stations' corrections, then the orientation residual (n, 3 axes, 3).
    """

    def __init__(
        self,
        inner: Any,  # a comp_daemon.models.kinematic.KinematicProblem (which imports this module)
        obs: FrameObservations,
        extra_idx: NDArray[np.intp] | None = None,
        mount0: FloatArray | None = None,
    ) -> None:
        self.inner, self.obs = inner, obs
        self.n = inner.a.shape[0]
        self.n_in = inner._cols.size + inner.more_idx.size
        self.n_extra = len(obs.names)
        self.extra_idx = np.arange(self.n_extra) if extra_idx is None else np.asarray(extra_idx, np.intp)
        w = np.ones(self.n) if inner.weights is None else inner.weights[: 3 * self.n : 3]
        self.row_w = np.asarray(w, dtype=float)
        meas = [inner.p_meas[None]] + (
            [] if inner.more_meas is None else [inner.more_meas.transpose(1, 0, 2)]
        )
        self.meas = np.concatenate(meas, axis=0)  # (K, n, 3)
        self.members = [np.flatnonzero(obs.station == s) for s in obs.free] if obs.free else []
        self.centroids = [inner.p_meas[rows].mean(axis=0) for rows in self.members]
        self.mount0 = np.eye(3) if mount0 is None else np.asarray(mount0, dtype=float)

    @property
    def size(self) -> int:
        return self.n_in + self.extra_idx.size

    def extras(self, x: FloatArray) -> FloatArray:
        full = np.zeros(self.n_extra)
        full[self.extra_idx] = x[self.n_in :]
        return full

    def station_motion(self, x: FloatArray) -> list[tuple[FloatArray, FloatArray]]:
        """Each free station's ``(R, t)``: its rows' points ``p`` move to ``R·p + t``."""
        e = self.extras(x)
        out = []
        for j, c in enumerate(self.centroids):
            rot = rotvec_to_matrix(e[6 * j + 3 : 6 * j + 6])
            out.append((rot, c + e[6 * j : 6 * j + 3] - rot @ c))
        return out

    def mount(self, x: FloatArray) -> FloatArray:
        """(3, 3) the probe's rotation on the flange at ``x``."""
        phi = self.extras(x)[6 * len(self.centroids) :]
        return np.asarray(rotvec_to_matrix(phi) @ self.mount0)

    def _station_rotations(self, x: FloatArray) -> FloatArray:
        """(n, 3, 3) the rotation each row's measured frame turns by."""
        rots = np.tile(np.eye(3), (self.n, 1, 1))
        for rows, (rot, _) in zip(self.members, self.station_motion(x), strict=True):
            rots[rows] = rot
        return rots

    def measured_rotations(self, x: FloatArray) -> FloatArray:
        assert self.obs.probe_r is not None
        return np.asarray(self._station_rotations(x) @ self.obs.probe_r)

    def predicted_rotations(self, x: FloatArray) -> FloatArray:
        params, eff, _ = self.inner.unpack(x[: self.inner._cols.size])
        inner = self.inner
        st = twin_state(inner.robot, params, eff, inner.a, inner.dir, inner.payload, inner.temp)
        return np.asarray(st.chain.world_T_frame[:, 6, :3, :3] @ self.mount(x))

    def position_residual(self, x: FloatArray) -> FloatArray:
        """The weighted position residual (every target), mm."""
        r = self.inner.residual(x[: self.n_in])
        if not self.members:
            return r
        shift = np.zeros_like(self.meas)
        for rows, (rot, t) in zip(self.members, self.station_motion(x), strict=True):
            p = self.meas[:, rows]
            shift[:, rows] = p @ rot.T + t - p
        return np.asarray(r - (shift * self.row_w[None, :, None]).reshape(-1))

    def orientation_residual(self, x: FloatArray) -> FloatArray:
        """(n, 3, 3) the weighted axis differences ``λ·w·(R_pred − R_meas)ᵀ`` (row, axis, component)."""
        diff = self.predicted_rotations(x) - self.measured_rotations(x)
        lam = self.obs.orientation_weight * self.row_w
        return np.asarray(lam[:, None, None] * diff.transpose(0, 2, 1))

    def residual(self, x: FloatArray) -> FloatArray:
        r = self.position_residual(x)
        if self.obs.probe_r is None:
            return r
        return np.concatenate([r, self.orientation_residual(x).reshape(-1)])

    def jacobian(self, x: FloatArray) -> FloatArray:
        inner = self.inner
        n, n_st = self.n, len(self.centroids)
        j_pos_in = inner.jacobian(x[: self.n_in])
        k = self.meas.shape[0]
        j_pos_ex = np.zeros((k, n, 3, self.n_extra))
        e = self.extras(x)
        for j, (rows, (rot, _)) in enumerate(zip(self.members, self.station_motion(x), strict=True)):
            w = self.row_w[rows][None, :, None, None]
            j_pos_ex[:, rows, :, 6 * j : 6 * j + 3] = -np.eye(3) * w
            moved = (self.meas[:, rows] - self.centroids[j]) @ rot.T  # exp(ω)(p − c)
            jl = left_jacobian(e[6 * j + 3 : 6 * j + 6])
            j_pos_ex[:, rows, :, 6 * j + 3 : 6 * j + 6] = (skew(moved) @ jl) * w
        j_pos = np.concatenate([j_pos_in, j_pos_ex.reshape(k * n * 3, -1)[:, self.extra_idx]], axis=1)
        if self.obs.probe_r is None:
            return j_pos
        lam = (self.obs.orientation_weight * self.row_w)[:, None, None, None]
        params, eff, dx = inner.unpack(x[: inner._cols.size])
        mount = self.mount(x)
        base = inner._target_jacobian(replace(params, tool_xyz_mm=np.zeros(3)), eff, dx)
        n_cols = inner._cols.size
        j_in = np.zeros((n, 3, 3, self.n_in))  # row, axis, component, parameter
        for axis in range(3):
            jk = inner._target_jacobian(replace(params, tool_xyz_mm=mount[:, axis]), eff, dx) - base
            jk[:, :, N_PARAMS - 3 : N_PARAMS] = 0.0  # the tool's position does not turn the flange
            j_in[:, axis, :, :n_cols] = jk[:, :, inner._cols]
        j_ex = np.zeros((n, 3, 3, self.n_extra))
        flange = self.predicted_rotations(x) @ mount.T  # R_flange
        phi = e[6 * n_st :]
        jl_phi = left_jacobian(phi)
        meas = self.measured_rotations(x)
        for axis in range(3):
            # ∂(R_flange·exp(φ)·m0_k)/∂φ = −R_flange·skew(m_k)·J_l(φ)
            j_ex[:, axis, :, 6 * n_st :] = -flange @ (skew(mount[:, axis]) @ jl_phi)
        for j, rows in enumerate(self.members):
            jl = left_jacobian(e[6 * j + 3 : 6 * j + 6])
            for axis in range(3):
                # ∂(−exp(ω)·R_meas·e_k)/∂ω = skew(v_k)·J_l(ω)
                j_ex[rows, axis, :, 6 * j + 3 : 6 * j + 6] = skew(meas[rows, :, axis]) @ jl
        j_ori = np.concatenate([j_in, j_ex[..., self.extra_idx]], axis=3) * lam
        return np.concatenate([j_pos, j_ori.reshape(9 * n, -1)], axis=0)
