"""Error-similarity model of seed 001: ordinary kriging of the positioning error in joint space.

Seed 001 (§2) observes that robot positioning errors are similar at similar joint states (the
semivariogram of the error vs the joint-space distance rises from near zero, eq. 12 and
:mod:`comp_daemon.models.variogram`), but that errors caused by joint backlash are not: two poses at
the same axis values reached from opposite directions differ by the backlash. The similarity must
therefore be stated over joint angles *and* motion direction, and the backlash identified by the
kinematic model (seed 001 §1, eqs 7–11: MDH + base + TCP + reduction ratio + backlash) is a
prerequisite of the similarity model. This module is that model, used as the paper uses it: on top
of a calibrated kinematic model, it predicts the model's residual at new joint states.

Joint state and distance. A pose is its axis values ``A`` (deg, controller convention) and approach
directions ``dir`` (−1/+1, 0 unknown). Its coordinates are the 12-vector::

    s(A, dir) = (w_1·A_1, …, w_6·A_6,  ρ_1·dir_1/2, …, ρ_6·dir_6/2)

so that the distance between two states is::

    d² = Σ_i w_i²·(A_i − A'_i)²  +  Σ_i ρ_i²·[dir_i ≠ dir'_i]

(``w_i`` joint weights, 1 by default: the plain Euclidean joint-space distance of seed 001 Figs 3–4;
``ρ_i`` the *direction separation* of joint i in deg: reversing joint i's approach direction counts
as ρ_i degrees of joint motion; an unknown direction sits half way). ``ρ = 0`` is the
direction-blind distance of the ordinary-kriging methods the paper compares against ("method one",
Cai et al.); :func:`fit_kriging` chooses ρ by leave-one-out cross-validation on the sampling points.
The seed's text lost its equations 14–17 (the similarity model with backlash); the embedding above
is the form we reconstruct from what the text states, and it is a Euclidean distance, so every
variogram model valid in 12 dimensions stays valid.

Ordinary kriging (seed 001 eqs 18–28). For each error component (x, y, z, mm) separately, the
prediction at a state ``s0`` is a weighted sum of the n sample residuals ``z``: ``ẑ0 = λᵀz``.
Unbiasedness requires ``1ᵀλ = 1`` (eq. 23); the mean squared error is ``σ²(1 + λᵀRλ − 2λᵀr)``
(eq. 24; ``R`` the correlation matrix of the samples, ``r`` their correlation with ``s0``, both from
the fitted variogram, ``ρ(h) = 1 − (γ(h) − c0)/c``). The Lagrangian
``L = σ²(1 + λᵀRλ − 2λᵀr) − μ(1ᵀλ − 1)`` (eq. 25) is stationary (eq. 26) where::

    [R  1] [λ    ]   [r]
    [1ᵀ 0] [−μ/2σ²] = [1]

whose solution is ``λ = R⁻¹r + R⁻¹1·(1 − 1ᵀR⁻¹r)/(1ᵀR⁻¹1)`` and ``ẑ0 = β + rᵀR⁻¹(z − 1β)`` with
``β = 1ᵀR⁻¹z / 1ᵀR⁻¹1`` (eqs 27–28). The minimum MSE is
``σ²·(1 − rᵀR⁻¹r + (1 − 1ᵀR⁻¹r)²/1ᵀR⁻¹1)``. A nugget ``c0`` (measurement noise and other
unstructured error) adds ``c0/c`` to the diagonal of ``R`` and is filtered from the prediction; with
no nugget the predictor interpolates the samples exactly. The system is factorised once
(Cholesky of ``R``); a batch of m queries costs one (m, n) distance matrix and a product.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from comp_daemon.kinematics.params import KinematicParams
from comp_daemon.models.base import ErrorModel, as_axes
from comp_daemon.models.variogram import (
    EmpiricalVariogram,
    VariogramModel,
    empirical_semivariogram,
    fit_variogram,
    pairwise_distances,
    valid_models,
)
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "DEFAULT_DIR_GRID_DEG",
    "JointStateMetric",
    "KrigingFit",
    "KrigingModel",
    "OrdinaryKriging",
    "fit_kriging",
    "joint_space_semivariogram",
]

N_JOINTS = 6
BaseLoader = Callable[[str, RobotDescription, dict[str, Any], "int | None", NDArray[np.float64]], ErrorModel]
AXES = ("x", "y", "z")
DEFAULT_DIR_GRID_DEG: tuple[float, ...] = (0.0, 2.0, 5.0, 10.0, 20.0, 40.0, 80.0)
DirectionChoice = Literal["aware", "blind"]


def _dir_array(dir: NDArray[np.float64] | None, n: int) -> NDArray[np.float64]:
    if dir is None:
        return np.zeros((n, N_JOINTS))
    d = np.asarray(dir, dtype=float)
    if d.ndim == 1:
        d = d[None, :]
    if d.shape != (n, N_JOINTS):
        raise ValueError(f"dir: expected shape ({n}, 6) like the axis values, got {d.shape}")
    if not np.all(np.isin(d, (-1.0, 0.0, 1.0))):
        raise ValueError("dir: values must be -1, +1 (or 0 for unknown)")
    return d


@dataclass(frozen=True, slots=True)
class JointStateMetric:
    """The (direction-aware) joint-space distance; see the module docstring."""

    joint_weights: NDArray[np.float64] = field(default_factory=lambda: np.ones(N_JOINTS))
    dir_separation_deg: NDArray[np.float64] = field(default_factory=lambda: np.zeros(N_JOINTS))

    def __post_init__(self) -> None:
        for name in ("joint_weights", "dir_separation_deg"):
            v = np.array(getattr(self, name), dtype=float)
            if v.shape == ():
                v = np.full(N_JOINTS, float(v))
            if v.shape != (N_JOINTS,) or not np.all(np.isfinite(v)) or np.any(v < 0.0):
                raise ValueError(f"JointStateMetric.{name}: expected 6 finite values >= 0, got {v}")
            object.__setattr__(self, name, v)

    @classmethod
    def blind(cls) -> JointStateMetric:
        """The plain Euclidean distance of axis values (deg), directions ignored."""
        return cls()

    @property
    def direction_aware(self) -> bool:
        return bool(np.any(self.dir_separation_deg > 0.0))

    def embed(
        self, a_deg: NDArray[np.float64], dir: NDArray[np.float64] | None = None
    ) -> NDArray[np.float64]:
        """(n, 12) coordinates of the joint states; Euclidean distances between them are the metric."""
        a = as_axes(a_deg)
        d = _dir_array(dir, a.shape[0])
        return np.concatenate([a * self.joint_weights, 0.5 * d * self.dir_separation_deg], axis=1)

    def distances(
        self,
        a_deg: NDArray[np.float64],
        dir: NDArray[np.float64] | None,
        b_deg: NDArray[np.float64] | None = None,
        b_dir: NDArray[np.float64] | None = None,
    ) -> NDArray[np.float64]:
        """(n, m) distances between the states (a, dir) and (b, b_dir) (or among the a's)."""
        x = self.embed(a_deg, dir)
        return pairwise_distances(x, None if b_deg is None else self.embed(b_deg, b_dir))

    def to_dict(self) -> dict[str, Any]:
        return {
            "joint_weights": self.joint_weights.tolist(),
            "dir_separation_deg": self.dir_separation_deg.tolist(),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> JointStateMetric:
        return cls(
            np.array(data["joint_weights"], dtype=float), np.array(data["dir_separation_deg"], dtype=float)
        )


def joint_space_semivariogram(
    a_deg: NDArray[np.float64],
    error_mm: NDArray[np.float64],
    dir: NDArray[np.float64] | None = None,
    metric: JointStateMetric | None = None,
    *,
    n_bins: int = 12,
    max_lag: float | None = None,
) -> EmpiricalVariogram:
    """Seed 001 eq. 12: semivariogram of the error components (n, k) vs joint-space distance."""
    metric = metric if metric is not None else JointStateMetric.blind()
    x = metric.embed(a_deg, dir)
    return empirical_semivariogram(x, error_mm, n_bins=n_bins, max_lag=max_lag)


class OrdinaryKriging:
    """Ordinary kriging of k components on shared coordinates, one fitted variogram per component.

    ``coords`` (n, d), ``values`` (n, k), ``variograms`` k models. Solved as in the module docstring;
    ``alpha``/``beta`` may be given (a stored model) to skip the solve for prediction; ``distances``
    (n, n) among the samples, if already computed.
    """

    def __init__(
        self,
        coords: NDArray[np.float64],
        values: NDArray[np.float64],
        variograms: Sequence[VariogramModel],
        *,
        alpha: NDArray[np.float64] | None = None,
        beta: NDArray[np.float64] | None = None,
        distances: NDArray[np.float64] | None = None,
    ) -> None:
        x = np.asarray(coords, dtype=float)
        z = np.asarray(values, dtype=float)
        if z.ndim == 1:
            z = z[:, None]
        if x.ndim != 2 or z.ndim != 2 or x.shape[0] != z.shape[0]:
            raise ValueError(
                f"coords (n, d) and values (n, k) must have the same n, got {x.shape}, {z.shape}"
            )
        if x.shape[0] < 2:
            raise ValueError(f"kriging needs at least 2 samples, got {x.shape[0]}")
        if len(variograms) != z.shape[1]:
            raise ValueError(f"{z.shape[1]} components but {len(variograms)} variograms")
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(z))):
            raise ValueError("kriging samples must be finite")
        self.coords = x
        self.values = z
        self.variograms = tuple(variograms)
        self._dist: NDArray[np.float64] | None = None if distances is None else np.asarray(distances)
        self._factors: list[tuple[NDArray[np.float64], bool]] | None = None
        self._ones: list[NDArray[np.float64]] | None = None  # R⁻¹1 per component
        if alpha is not None and beta is not None:
            self.alpha = np.asarray(alpha, dtype=float)
            self.beta = np.asarray(beta, dtype=float)
            if self.alpha.shape != z.shape or self.beta.shape != (z.shape[1],):
                raise ValueError(f"alpha must be {z.shape} and beta ({z.shape[1]},)")
        else:
            self._solve()

    @property
    def n_samples(self) -> int:
        return int(self.coords.shape[0])

    def _sample_distances(self) -> NDArray[np.float64]:
        if self._dist is None:
            self._dist = pairwise_distances(self.coords)
        return self._dist

    def _factorise(self) -> None:
        if self._factors is not None:
            return
        dist = self._sample_distances()
        n = dist.shape[0]
        factors: list[tuple[NDArray[np.float64], bool]] = []
        ones: list[NDArray[np.float64]] = []
        iu, ju = np.triu_indices(n, k=1)
        has_duplicates = bool(np.any(dist[iu, ju] <= 1e-9 * max(float(dist.max()), 1e-300)))
        for c, vg in enumerate(self.variograms):
            if has_duplicates and vg.nugget == 0.0:
                raise ValueError(
                    _singular_message(dist, vg, AXES[c] if len(self.variograms) == 3 else str(c))
                )
            r = vg.correlation(dist)
            r[np.diag_indices(n)] = 1.0 + vg.nugget / vg.psill
            factor = None
            for jitter in (0.0, 1e-10, 1e-8):
                try:
                    factor = scipy.linalg.cho_factor(
                        r + jitter * np.eye(n) if jitter else r, lower=True, check_finite=False
                    )
                    break
                except np.linalg.LinAlgError:
                    continue
            if factor is None:
                raise ValueError(
                    _singular_message(dist, vg, AXES[c] if len(self.variograms) == 3 else str(c))
                )
            factors.append(factor)
            ones.append(scipy.linalg.cho_solve(factor, np.ones(n), check_finite=False))
        self._factors = factors
        self._ones = ones

    def _solve(self) -> None:
        self._factorise()
        assert self._factors is not None and self._ones is not None
        k = self.values.shape[1]
        alpha = np.empty_like(self.values)
        beta = np.empty(k)
        for c in range(k):
            z = self.values[:, c]
            v = self._ones[c]
            rz = scipy.linalg.cho_solve(self._factors[c], z, check_finite=False)
            beta[c] = float(v @ z) / float(v.sum())
            alpha[:, c] = rz - beta[c] * v  # R⁻¹(z − 1β)
        self.alpha = alpha
        self.beta = beta

    def predict(
        self, coords: NDArray[np.float64], *, return_std: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(m, k) predictions at ``coords`` (m, d); with ``return_std`` also the kriging std (m, k)."""
        q = np.asarray(coords, dtype=float)
        if q.ndim != 2 or q.shape[1] != self.coords.shape[1]:
            raise ValueError(f"query coordinates must be (m, {self.coords.shape[1]}), got {q.shape}")
        dist = pairwise_distances(q, self.coords)
        k = self.values.shape[1]
        out = np.empty((q.shape[0], k))
        std = np.empty((q.shape[0], k)) if return_std else None
        for c, vg in enumerate(self.variograms):
            r = vg.correlation(dist)  # (m, n)
            out[:, c] = self.beta[c] + r @ self.alpha[:, c]
            if std is not None:
                self._factorise()
                assert self._factors is not None and self._ones is not None
                rr = scipy.linalg.cho_solve(self._factors[c], r.T, check_finite=False)  # (n, m)
                v = self._ones[c]
                lag_term = 1.0 - v @ r.T  # 1 − 1ᵀR⁻¹r
                mse = 1.0 - np.einsum("mn,nm->m", r, rr) + lag_term**2 / float(v.sum())
                std[:, c] = np.sqrt(np.maximum(vg.psill * mse, 0.0))
        if std is not None:
            return out, std
        return out

    def weights(self, coords: NDArray[np.float64], component: int = 0) -> NDArray[np.float64]:
        """(m, n) kriging weights λ of the samples for each query (each row sums to 1)."""
        self._factorise()
        assert self._factors is not None and self._ones is not None
        q = np.asarray(coords, dtype=float)
        r = self.variograms[component].correlation(pairwise_distances(q, self.coords))
        rr = scipy.linalg.cho_solve(self._factors[component], r.T, check_finite=False)  # (n, m)
        v = self._ones[component]
        return (rr + np.outer(v, 1.0 - v @ r.T) / float(v.sum())).T

    def loo_residuals(self) -> NDArray[np.float64]:
        """(n, k) leave-one-out residuals ``z_i − ẑ_{−i}`` in closed form (Dubrule's formula).

        With ``Q`` the sample block of the inverse of the bordered kriging matrix,
        ``Q = R⁻¹ − R⁻¹11ᵀR⁻¹/1ᵀR⁻¹1``, the residual is ``α_i / Q_ii``.
        """
        self._factorise()
        assert self._factors is not None and self._ones is not None
        n = self.n_samples
        out = np.empty_like(self.values)
        eye = np.eye(n)
        for c in range(self.values.shape[1]):
            rinv_diag = np.diag(scipy.linalg.cho_solve(self._factors[c], eye, check_finite=False))
            v = self._ones[c]
            q_diag = rinv_diag - v * v / float(v.sum())
            out[:, c] = self.alpha[:, c] / q_diag
        return out


def _singular_message(dist: NDArray[np.float64], vg: VariogramModel, comp: str) -> str:
    n = dist.shape[0]
    iu, ju = np.triu_indices(n, k=1)
    dup = np.flatnonzero(dist[iu, ju] <= 1e-9 * max(float(dist.max()), 1e-300))
    if dup.size and vg.nugget == 0.0:
        i, j = int(iu[dup[0]]), int(ju[dup[0]])
        return (
            f"kriging system of component {comp} is singular: samples {i + 1} and {j + 1} are the same "
            f"joint state ({dup.size} such pair(s)); fit a variogram with a nugget or drop repeats"
        )
    return f"kriging system of component {comp} is not positive definite ({vg.kind} model)"


class KrigingModel(ErrorModel):
    """A base model plus the ordinary-kriging prediction of its residual (seed 001)."""

    kind: ClassVar[str] = "kriging"

    def __init__(
        self,
        base: ErrorModel,
        metric: JointStateMetric,
        sample_a_deg: NDArray[np.float64],
        sample_dir: NDArray[np.float64] | None,
        residual_mm: NDArray[np.float64],
        variograms: Sequence[VariogramModel],
        *,
        alpha: NDArray[np.float64] | None = None,
        beta: NDArray[np.float64] | None = None,
        distances: NDArray[np.float64] | None = None,
    ) -> None:
        a = as_axes(sample_a_deg)
        res = np.asarray(residual_mm, dtype=float)
        if res.shape != (a.shape[0], 3):
            raise ValueError(f"residual_mm must be ({a.shape[0]}, 3), got {res.shape}")
        if len(variograms) != 3:
            raise ValueError(f"one variogram per axis (3) expected, got {len(variograms)}")
        self.base = base
        self.robot: RobotDescription = base.robot
        self.world_T_base = base.world_T_base
        self.registration = base.registration
        self.metric = metric
        self.sample_a_deg = a
        self.sample_dir = None if sample_dir is None else _dir_array(sample_dir, a.shape[0])
        self.residual_mm = res
        self.variograms = tuple(variograms)
        self.kriging = OrdinaryKriging(
            metric.embed(a, self.sample_dir),
            res,
            self.variograms,
            alpha=alpha,
            beta=beta,
            distances=distances,
        )

    def predict_residual_mm(
        self, a_deg: NDArray[np.float64], dir: NDArray[np.float64] | None = None, *, return_std: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(m, 3) kriged residual of the base model (mm); with ``return_std`` also its kriging std."""
        a = as_axes(a_deg)
        return self.kriging.predict(self.metric.embed(a, _dir_array(dir, a.shape[0])), return_std=return_std)

    def predict_tcp_mm(
        self,
        a_deg: NDArray[np.float64],
        dir: NDArray[np.float64] | None = None,
        payload_kg: NDArray[np.float64] | float | None = None,
        temp_c: NDArray[np.float64] | None = None,
    ) -> NDArray[np.float64]:
        a = as_axes(a_deg)
        base = self.base.predict_tcp_mm(a, dir, payload_kg, temp_c)
        res = self.predict_residual_mm(a, dir)
        assert isinstance(res, np.ndarray)
        return base + res

    def weights(
        self, a_deg: NDArray[np.float64], dir: NDArray[np.float64] | None = None, axis: int = 0
    ) -> NDArray[np.float64]:
        """(m, n) kriging weights of the sampling points for the queries, for error axis 0/1/2."""
        a = as_axes(a_deg)
        return self.kriging.weights(self.metric.embed(a, _dir_array(dir, a.shape[0])), axis)

    def ik_params(self) -> KinematicParams:
        return self.base.ik_params()

    def to_payload(self) -> dict[str, Any]:
        return {
            "base": {
                "kind": self.base.kind,
                "order": self.base.order,
                "registration": self.base.registration.tolist(),
                "model": self.base.to_payload(),
            },
            "metric": self.metric.to_dict(),
            "variograms": {ax: vg.to_dict() for ax, vg in zip(AXES, self.variograms, strict=True)},
            "samples": {
                "a_deg": self.sample_a_deg.tolist(),
                "dir": None if self.sample_dir is None else self.sample_dir.astype(int).tolist(),
                "residual_mm": self.residual_mm.tolist(),
            },
            "alpha": self.kriging.alpha.tolist(),
            "beta": self.kriging.beta.tolist(),
        }

    @classmethod
    def from_payload(
        cls,
        robot: RobotDescription,
        payload: dict[str, Any],
        order: int | None,
        registration: NDArray[np.float64],
        *,
        base_loader: BaseLoader | None = None,
    ) -> KrigingModel:
        """Rebuild a stored model; its base model, stored inside it by kind, is rebuilt by
        ``base_loader(kind, robot, payload, order, registration)`` (the model registry's
        :func:`comp_daemon.models.registry.model_from_payload`, which passes itself)."""
        if base_loader is None:
            raise ValueError("kriging model: its base model is rebuilt by a base_loader (the model registry)")
        try:
            entry = payload["base"]
            kind = str(entry["kind"])
            if kind == cls.kind:
                raise ValueError(f"kriging model: cannot stand on a base model of kind '{kind}'")
            base_order = entry["order"]
            base = base_loader(
                kind,
                robot,
                entry["model"],
                None if base_order is None else int(base_order),
                np.array(entry["registration"], dtype=float),
            )
            samples = payload["samples"]
            variograms = [VariogramModel.from_dict(payload["variograms"][ax]) for ax in AXES]
            return cls(
                base,
                JointStateMetric.from_dict(payload["metric"]),
                np.array(samples["a_deg"], dtype=float),
                None if samples["dir"] is None else np.array(samples["dir"], dtype=float),
                np.array(samples["residual_mm"], dtype=float),
                variograms,
                alpha=np.array(payload["alpha"], dtype=float),
                beta=np.array(payload["beta"], dtype=float),
            )
        except KeyError as exc:
            raise ValueError(f"kriging model: missing field {exc.args[0]!r}") from None


@dataclass(frozen=True, slots=True)
class KrigingFit:
    """The result of :func:`fit_kriging`: the model and how it was chosen."""

    model: KrigingModel
    empirical: EmpiricalVariogram  # of the base model's residual under the chosen metric
    loo_rms_mm: float  # leave-one-out 3-D RMS of the chosen model on the sampling points
    candidates: tuple[tuple[tuple[float, ...], float], ...]  # (dir separation per joint, LOO RMS)
    base_rms_mm: float  # 3-D RMS of the base model's residual on the sampling points


def _fit_for_metric(
    base: ErrorModel,
    metric: JointStateMetric,
    a: NDArray[np.float64],
    d: NDArray[np.float64] | None,
    residual: NDArray[np.float64],
    kind: str,
    n_bins: int,
    max_lag: float | None,
    nugget: bool,
) -> tuple[KrigingModel, EmpiricalVariogram, float]:
    x = metric.embed(a, d)
    dist = pairwise_distances(x)
    emp = empirical_semivariogram(None, residual, n_bins=n_bins, max_lag=max_lag, distances=dist)
    dim = 12 if metric.direction_aware else N_JOINTS
    variograms = [fit_variogram(emp, c, kind=kind, dim=dim, nugget=nugget) for c in range(3)]
    model = KrigingModel(base, metric, a, d, residual, variograms, distances=dist)
    loo = model.kriging.loo_residuals()
    return model, emp, float(np.sqrt(np.mean(np.sum(loo**2, axis=1))))


def fit_kriging(
    base: ErrorModel,
    a_deg: NDArray[np.float64],
    p_measured_mm: NDArray[np.float64],
    *,
    dir: NDArray[np.float64] | None = None,
    payload_kg: NDArray[np.float64] | float | None = None,
    temp_c: NDArray[np.float64] | None = None,
    direction: DirectionChoice | Sequence[float] = "aware",
    variogram: str = "auto",
    n_bins: int = 12,
    max_lag: float | None = None,
    nugget: bool = True,
    joint_weights: Sequence[float] | None = None,
    dir_grid_deg: Sequence[float] = DEFAULT_DIR_GRID_DEG,
) -> KrigingFit:
    """Fit the error-similarity model of seed 001 on sampling points, on top of ``base``.

    The residual ``p_measured − base.predict`` (n, 3) is kriged per axis with a variogram fitted to
    its empirical semivariogram (``variogram``: a model name or ``"auto"``, the best valid one).
    ``direction``: ``"blind"`` (ρ = 0), ``"aware"`` (one ρ for every joint, chosen by the
    leave-one-out 3-D RMS over ``dir_grid_deg``), or six explicit direction separations (deg).
    Without ``dir`` data the metric is blind.
    """
    a = as_axes(a_deg)
    n = a.shape[0]
    p = np.asarray(p_measured_mm, dtype=float)
    if p.shape != (n, 3):
        raise ValueError(f"measured positions must have shape ({n}, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("measured positions must be finite")
    if n < 4:
        raise ValueError(f"kriging needs at least 4 sampling points, got {n}")
    d = None if dir is None else _dir_array(dir, n)
    if variogram != "auto" and variogram not in valid_models(12 if direction != "blind" else N_JOINTS):
        raise ValueError(f"variogram '{variogram}' is not valid in joint space (use exponential or gaussian)")
    residual = p - base.predict_tcp_mm(a, d, payload_kg, temp_c)
    base_rms = float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))
    weights = np.ones(N_JOINTS) if joint_weights is None else np.asarray(joint_weights, dtype=float)

    def evaluate(sep: NDArray[np.float64]) -> tuple[KrigingModel, EmpiricalVariogram, float]:
        metric = JointStateMetric(weights, sep if d is not None else np.zeros(N_JOINTS))
        return _fit_for_metric(base, metric, a, d, residual, variogram, n_bins, max_lag, nugget)

    candidates: list[tuple[tuple[float, ...], float]] = []
    if isinstance(direction, str):
        if direction not in ("aware", "blind"):
            raise ValueError(f"direction must be 'aware', 'blind' or 6 separations (deg), got {direction!r}")
        grid = [0.0] if direction == "blind" or d is None else [float(g) for g in dir_grid_deg]
        best: tuple[KrigingModel, EmpiricalVariogram, float] | None = None
        for g in grid:
            sep = np.full(N_JOINTS, g)
            result = evaluate(sep)
            candidates.append((tuple(sep.tolist()), result[2]))
            if best is None or result[2] < best[2]:
                best = result
        assert best is not None
    else:
        sep = np.asarray(direction, dtype=float)
        if sep.shape != (N_JOINTS,):
            raise ValueError(f"direction separations: expected 6 values (deg), got shape {sep.shape}")
        best = evaluate(sep)
        candidates.append((tuple(sep.tolist()), best[2]))
    model, emp, loo = best
    return KrigingFit(
        model=model, empirical=emp, loo_rms_mm=loo, candidates=tuple(candidates), base_rms_mm=base_rms
    )
