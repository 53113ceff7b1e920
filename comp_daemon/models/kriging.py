"""Error-similarity model of seed 001: ordinary kriging of the positioning error in joint space.

Seed 001 (§2) observes that robot positioning errors are similar at similar joint states (the
semivariogram of the error vs the joint-space distance rises from near zero, eq. 12 and
:mod:`comp_daemon.estimation.variogram`), but that errors caused by joint backlash are not: two poses at
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
(Cholesky of ``R``, :mod:`comp_daemon.estimation.ordinary_kriging`); a batch of m queries costs one
(m, n) distance matrix and a product. Larger sampling sets (beyond :data:`DENSE_MAX_SAMPLES`, or
whenever ``neighbours`` is given) are kriged in local neighbourhoods: each query on its k nearest
samples in the same metric (:mod:`comp_daemon.estimation.local_kriging`), the dense solution when
k = n. ``anisotropic`` fits replace the isotropic joint weights by per-joint ones (per-joint
ranges), chosen on the leave-one-out error.

The kinds. ``kriging`` (``KIND``) krigs the residual of the kinematic calibration, with the spec's
effects if any, over the plain joint-space distance (seed 001 §2's "method one" after
calibration); ``kriging-backlash`` (``BACKLASH_KIND``) is seed 001 §2's model, the direction-aware
distance on the residual of kinematic + ratio + backlash (needs ``dir``). Both take joint effects
for their base (``kriging-backlash+compliance``), the options ``k=N`` (local neighbourhoods of N
samples; dense is the default up to :data:`DENSE_MAX_SAMPLES`), ``aniso`` (per-joint ranges) and
``all``; the kriging stage and per-joint ranges are kept only if they lower the leave-one-out
error against the base (:mod:`comp_daemon.models.fitting`), and a kind whose kriging is dropped is
its kinematic base.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray

from comp_daemon.estimation import steps
from comp_daemon.estimation.local_kriging import LocalKriging
from comp_daemon.estimation.ordinary_kriging import OrdinaryKriging
from comp_daemon.estimation.selection import Decision, Selection, judge
from comp_daemon.estimation.variogram import (
    EmpiricalVariogram,
    JointStatePairs,
    VariogramModel,
    binned_semivariogram,
    empirical_semivariogram,
    fit_variograms,
    pairwise_distances,
    valid_models,
)
from comp_daemon.kinematics.params import KinematicParams
from comp_daemon.models.base import (
    ErrorModel,
    Query,
    StoredModel,
    approach_directions,
    as_axes,
    measured_positions,
)
from comp_daemon.models.effects import TRANSMISSION_EFFECTS
from comp_daemon.models.fitting import (
    FitOptions,
    FittedModel,
    ModelSpec,
    attach_tcp_covariance,
    kinematic_info,
    rms_mm,
    selected_base,
)
from comp_daemon.models.kind import ModelKind
from comp_daemon.models.kinematic_kind import kinematic_parameters
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "BACKLASH_KIND",
    "DEFAULT_DIR_GRID_DEG",
    "KIND",
    "KRIGING_OPTIONS",
    "LOO_MAX_SAMPLES",
    "JointStateMetric",
    "KrigingFit",
    "KrigingModel",
    "OrdinaryKriging",
    "fit_kriging",
    "fit_kriging_backlash_kind",
    "fit_kriging_kind",
    "joint_space_semivariogram",
    "kriging_backlash_parameters",
    "kriging_parameters",
]

N_JOINTS = 6
AXES = ("x", "y", "z")
DEFAULT_DIR_GRID_DEG: tuple[float, ...] = (0.0, 2.0, 5.0, 10.0, 20.0, 40.0, 80.0)
DirectionChoice = Literal["aware", "blind"]
DENSE_MAX_SAMPLES = 2000  # above this many sampling points the default is a local neighbourhood
DEFAULT_NEIGHBOURS = 32  # samples per local neighbourhood (the default above DENSE_MAX_SAMPLES)
LOO_MAX_SAMPLES = 500  # the leave-one-out RMS of local models is taken on a random subset
ANISO_MAX_SAMPLES = 600  # the per-joint weights are searched on at most this many samples
ANISO_FACTORS = (0.25, 0.5, 2.0, 4.0)  # multipliers tried on each joint weight per sweep
KEPT_DISTANCES_MAX = 8_000_000  # distances (64 MB) kept between the variograms and the models of a fit


def _dir_array(dir: NDArray[np.float64] | None, n: int) -> NDArray[np.float64]:
    d = approach_directions(dir, n)
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
        neighbours: int | None = None,
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
        self.neighbours = None if neighbours is None else int(neighbours)
        coords = metric.embed(a, self.sample_dir)
        self.kriging: OrdinaryKriging | LocalKriging
        if self.neighbours is None:
            self.kriging = OrdinaryKriging(
                coords, res, self.variograms, alpha=alpha, beta=beta, distances=distances
            )
        else:
            self.kriging = LocalKriging(coords, res, self.variograms, self.neighbours)

    def predict_residual_mm(
        self, a_deg: NDArray[np.float64], dir: NDArray[np.float64] | None = None, *, return_std: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(m, 3) kriged residual of the base model (mm); with ``return_std`` also its kriging std."""
        a = as_axes(a_deg)
        return self.kriging.predict(self.metric.embed(a, _dir_array(dir, a.shape[0])), return_std=return_std)

    def tcp_mm(self, query: Query) -> NDArray[np.float64]:
        base = self.base.tcp_mm(query)
        res = self.predict_residual_mm(query.a, query.dir)
        assert isinstance(res, np.ndarray)
        return base + res

    def std_mm(self, query: Query) -> NDArray[np.float64]:
        """(m, 3) ordinary-kriging standard deviation of the kriged residual (mm, per axis), the
        nugget filtered: the uncertainty of the prediction, not of a new measurement."""
        out = self.predict_residual_mm(query.a, query.dir, return_std=True)
        assert isinstance(out, tuple)
        return out[1]

    def weights(
        self, a_deg: NDArray[np.float64], dir: NDArray[np.float64] | None = None, axis: int = 0
    ) -> NDArray[np.float64]:
        """(m, n) kriging weights of the sampling points for the queries, for error axis 0/1/2
        (dense models; a local model's weights differ per query neighbourhood)."""
        if not isinstance(self.kriging, OrdinaryKriging):
            raise ValueError("kriging weights over every sample exist for dense models only")
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
            "neighbours": self.neighbours,
            "alpha": self.kriging.alpha.tolist() if isinstance(self.kriging, OrdinaryKriging) else None,
            "beta": self.kriging.beta.tolist() if isinstance(self.kriging, OrdinaryKriging) else None,
        }

    @classmethod
    def from_stored(cls, stored: StoredModel) -> KrigingModel:
        """Rebuild a stored model; its base model, stored inside it by kind, is rebuilt by the
        stored record's ``base_loader`` (the model registry's
        :func:`comp_daemon.models.registry.model_from_payload`, which passes itself)."""
        robot, payload, base_loader = stored.robot, stored.payload, stored.base_loader
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
                alpha=None if payload["alpha"] is None else np.array(payload["alpha"], dtype=float),
                beta=None if payload["beta"] is None else np.array(payload["beta"], dtype=float),
                neighbours=None if payload.get("neighbours") is None else int(payload["neighbours"]),
            )
        except KeyError as exc:
            raise ValueError(f"kriging model: missing field {exc.args[0]!r}") from None


@dataclass(frozen=True, slots=True)
class KrigingFit:
    """The result of :func:`fit_kriging`: the model and how it was chosen."""

    model: KrigingModel
    empirical: EmpiricalVariogram  # of the base model's residual under the chosen metric
    loo_rms_mm: float  # leave-one-out 3-D RMS of the chosen model (on loo_samples sampling points)
    candidates: tuple[tuple[tuple[float, ...], float], ...]  # (dir separation per joint, LOO RMS)
    base_rms_mm: float  # 3-D RMS of the base model's residual on the sampling points
    loo_samples: int = 0  # sampling points the LOO RMS was taken on
    weight_candidates: tuple[tuple[tuple[float, ...], float], ...] = ()  # anisotropic search: (w, LOO)
    # the points the LOO RMS was taken on, and their leave-one-out residuals (len(loo_rows), 3)
    loo_rows: NDArray[np.intp] = field(default_factory=lambda: np.zeros(0, dtype=np.intp))
    loo_residual_mm: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    anisotropic_decision: Decision | None = None  # per-joint ranges against the isotropic distance
    unbiased_rows: NDArray[np.intp] | None = None  # the samples not used to choose the metric, if any


def _subset(n: int, most: int, seed: int) -> NDArray[np.intp]:
    """Every index below ``n``, or ``most`` of them drawn reproducibly."""
    if n <= most:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, most, replace=False))


@dataclass(frozen=True)
class _KrigingProblem:
    """What a kriging fit under any metric shares: the base model, the samples and their residual,
    and how the variograms are fitted (``kind``, bins, nugget) and the system solved (dense, or
    local ``neighbours``). :meth:`fits` gives the model under each of several metrics."""

    base: ErrorModel
    a: NDArray[np.float64]
    d: NDArray[np.float64] | None
    residual: NDArray[np.float64]
    kind: str
    n_bins: int
    max_lag: float | None
    nugget: bool
    neighbours: int | None

    def rows(self, rows: NDArray[np.intp]) -> _KrigingProblem:
        """The dense problem on some of the samples."""
        d = None if self.d is None else self.d[rows]
        return replace(self, a=self.a[rows], d=d, residual=self.residual[rows], neighbours=None)

    @cached_property
    def _pairs(self) -> JointStatePairs:
        """Local models: the sample pairs their empirical variograms are taken on."""
        return JointStatePairs(self.a, self.d, self.residual)

    @cached_property
    def _increments(self) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
        """Dense models: every pair (i < j) and its half squared residual increment, for any metric."""
        iu, ju = np.triu_indices(self.a.shape[0], k=1)
        return iu, ju, 0.5 * (self.residual[iu] - self.residual[ju]) ** 2

    def _distances(self, metric: JointStateMetric) -> NDArray[np.float64]:
        return pairwise_distances(metric.embed(self.a, self.d))

    def _empirical(
        self, metric: JointStateMetric, keep: bool
    ) -> tuple[EmpiricalVariogram, NDArray[np.float64] | None]:
        """The empirical variogram under ``metric``; with ``keep``, the dense model's distances too."""
        if self.neighbours is not None:
            w, sep = metric.joint_weights, metric.dir_separation_deg
            return self._pairs.semivariogram(w, sep, self.n_bins, self.max_lag), None
        iu, ju, half_sq = self._increments
        dist = self._distances(metric)
        emp = binned_semivariogram(dist[iu, ju], half_sq, n_bins=self.n_bins, max_lag=self.max_lag)
        return emp, dist if keep else None

    def fits(self, metrics: Sequence[JointStateMetric]) -> Iterator[_MetricFit]:
        """The model under each metric, its empirical variogram and its LOO 3-D RMS (and on how many
        points), one after the other; the variogram fits of all of them are solved together first.
        The distance matrices of the empirical variograms serve the models if they are small
        (:data:`KEPT_DISTANCES_MAX` entries together), else they are computed again."""
        n = self.a.shape[0]
        keep = len(metrics) * n * n <= KEPT_DISTANCES_MAX
        emps, dists = zip(*(self._empirical(m, keep) for m in metrics), strict=True)
        variograms: list[list[VariogramModel]] = [[] for _ in metrics]
        dims = [12 if m.direction_aware else N_JOINTS for m in metrics]
        for dim in sorted(set(dims)):
            at = [i for i, d in enumerate(dims) if d == dim]
            fitted = fit_variograms([emps[i] for i in at], kind=self.kind, dim=dim, nugget=self.nugget)
            for i, vgs in zip(at, fitted, strict=True):
                variograms[i] = vgs
        for metric, emp, vgs, kept in zip(metrics, emps, variograms, dists, strict=True):
            dist = kept if kept is not None or self.neighbours is not None else self._distances(metric)
            model = KrigingModel(
                self.base,
                metric,
                self.a,
                self.d,
                self.residual,
                vgs,
                distances=dist,
                neighbours=self.neighbours,
            )
            if isinstance(model.kriging, OrdinaryKriging):
                rows = np.arange(n)
                loo = model.kriging.loo_residuals()
            else:
                rows = _subset(n, LOO_MAX_SAMPLES, 2)
                loo = model.kriging.loo_residuals(rows)
            yield _MetricFit(model, emp, float(np.sqrt(np.mean(np.sum(loo**2, axis=1)))), rows, loo)


@dataclass(frozen=True, slots=True)
class _MetricFit:
    """The kriging model under one metric, its empirical variogram and its leave-one-out residuals."""

    model: KrigingModel
    empirical: EmpiricalVariogram
    loo_rms_mm: float
    loo_rows: NDArray[np.intp]
    loo_residual_mm: NDArray[np.float64]


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
    neighbours: int | Literal["auto"] | None = "auto",
    anisotropic: bool = False,
    select_anisotropic: bool = True,
) -> KrigingFit:
    """Fit the error-similarity model of seed 001 on sampling points, on top of ``base``.

    The residual ``p_measured − base.predict`` (n, 3) is kriged per axis with a variogram fitted to
    its empirical semivariogram (``variogram``: a model name or ``"auto"``, the best valid one).
    ``direction``: ``"blind"`` (ρ = 0), ``"aware"`` (one ρ for every joint, chosen by the
    leave-one-out 3-D RMS over ``dir_grid_deg``), or six explicit direction separations (deg).
    Without ``dir`` data the metric is blind.

    ``neighbours``: ``None`` one dense system over every sample; an int, local neighbourhoods of
    that many samples (:mod:`comp_daemon.estimation.local_kriging`); ``"auto"`` dense up to
    :data:`DENSE_MAX_SAMPLES` samples, :data:`DEFAULT_NEIGHBOURS` beyond. Local models take their
    empirical variogram on a random subset of the sample pairs
    (:data:`comp_daemon.estimation.variogram.VARIOGRAM_MAX_PAIRS`) and
    their LOO RMS on a random subset of the samples (:data:`LOO_MAX_SAMPLES`).

    ``anisotropic``: after the direction separation, the six joint weights (the inverse per-joint
    ranges) are chosen by a coordinate search on the LOO RMS (each weight times
    :data:`ANISO_FACTORS`, two sweeps, on at most :data:`ANISO_MAX_SAMPLES` samples) instead of the
    paper's isotropic distance (``joint_weights``, default 1, is the starting point). With
    ``select_anisotropic`` the weights are searched on one random half of the samples and kept only
    if, on the other half, their leave-one-out errors beat the isotropic distance's by the rule of
    :mod:`comp_daemon.estimation.selection`; the decision is in :attr:`KrigingFit.anisotropic_decision`
    and the half they were not chosen on in :attr:`KrigingFit.unbiased_rows`.
    """
    a = as_axes(a_deg)
    n = a.shape[0]
    p = measured_positions(p_measured_mm, n)
    if n < 4:
        raise ValueError(f"kriging needs at least 4 sampling points, got {n}")
    d = None if dir is None else _dir_array(dir, n)
    if variogram != "auto" and variogram not in valid_models(12 if direction != "blind" else N_JOINTS):
        raise ValueError(f"variogram '{variogram}' is not valid in joint space (use exponential or gaussian)")
    if neighbours == "auto":
        neighbours = None if n <= DENSE_MAX_SAMPLES else DEFAULT_NEIGHBOURS
    if neighbours is not None and int(neighbours) < 4:
        raise ValueError(f"a kriging neighbourhood needs at least 4 samples, got {neighbours}")
    residual = p - base.predict_tcp_mm(a, d, payload_kg, temp_c)
    base_rms = float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))
    weights = np.ones(N_JOINTS) if joint_weights is None else np.asarray(joint_weights, dtype=float)

    problem = _KrigingProblem(base, a, d, residual, variogram, n_bins, max_lag, nugget, neighbours)

    def metric(sep: NDArray[np.float64], w: NDArray[np.float64] = weights) -> JointStateMetric:
        return JointStateMetric(w, sep if d is not None else np.zeros(N_JOINTS))

    candidates: list[tuple[tuple[float, ...], float]] = []
    if isinstance(direction, str):
        if direction not in ("aware", "blind"):
            raise ValueError(f"direction must be 'aware', 'blind' or 6 separations (deg), got {direction!r}")
        grid = [0.0] if direction == "blind" or d is None else [float(g) for g in dir_grid_deg]
        seps = [np.full(N_JOINTS, g) for g in grid]
        best: _MetricFit | None = None
        for sep, result in zip(seps, problem.fits([metric(sep) for sep in seps]), strict=True):
            candidates.append((tuple(sep.tolist()), result.loo_rms_mm))
            if best is None or result.loo_rms_mm < best.loo_rms_mm:
                best = result
        assert best is not None
    else:
        sep = np.asarray(direction, dtype=float)
        if sep.shape != (N_JOINTS,):
            raise ValueError(f"direction separations: expected 6 values (deg), got shape {sep.shape}")
        best = next(problem.fits([metric(sep)]))
        candidates.append((tuple(sep.tolist()), best.loo_rms_mm))
    weight_candidates: tuple[tuple[tuple[float, ...], float], ...] = ()
    decision: Decision | None = None
    unbiased: NDArray[np.intp] | None = None
    if anisotropic:
        sep = best.model.metric.dir_separation_deg
        refit, weight_candidates, decision, unbiased = _choose_weights(
            problem, sep, weights, select_anisotropic
        )
        if refit is not None:
            best = next(problem.fits([JointStateMetric(refit, sep)]))
    return KrigingFit(
        model=best.model,
        empirical=best.empirical,
        loo_rms_mm=best.loo_rms_mm,
        candidates=tuple(candidates),
        base_rms_mm=base_rms,
        loo_samples=int(best.loo_rows.size),
        weight_candidates=weight_candidates,
        loo_rows=best.loo_rows,
        loo_residual_mm=best.loo_residual_mm,
        anisotropic_decision=decision,
        unbiased_rows=unbiased,
    )


def _choose_weights(
    problem: _KrigingProblem, sep: NDArray[np.float64], start: NDArray[np.float64], select: bool
) -> tuple[
    NDArray[np.float64] | None,
    tuple[tuple[tuple[float, ...], float], ...],
    Decision | None,
    NDArray[np.intp] | None,
]:
    """The per-joint weights of fit_kriging's ``anisotropic`` stage: the weights to refit with (None:
    the isotropic model stays), the candidates tried, the held-out decision and the rows it was
    taken on. With ``select`` the weights are searched on one half of the samples and judged on
    the other."""
    n = problem.a.shape[0]
    if select:
        half = np.random.default_rng(4).permutation(n)
        search, held = np.sort(half[: n // 2]), np.sort(half[n // 2 :])
    else:
        search, held = np.arange(n), np.zeros(0, dtype=np.intp)
    searched = problem.rows(search[_subset(search.size, ANISO_MAX_SAMPLES, 3)])
    w_best, candidates = _search_weights(searched, sep, start)
    if np.array_equal(w_best, start):
        return None, candidates, None, None
    if held.size < 4:
        return w_best, candidates, None, None
    judged = held[_subset(held.size, ANISO_MAX_SAMPLES, 5)]
    with_w, without = (
        np.sum(f.loo_residual_mm**2, axis=1)
        for f in problem.rows(judged).fits([JointStateMetric(w_best, sep), JointStateMetric(start, sep)])
    )
    decision = judge(
        "anisotropic ranges",
        with_w,
        without,
        f"leave-one-out on {judged.size} samples not used to choose the weights, "
        "against the isotropic distance",
    )
    if decision.kept:
        return w_best, candidates, decision, held
    return None, candidates, decision, None


def _search_weights(
    problem: _KrigingProblem, sep: NDArray[np.float64], start: NDArray[np.float64]
) -> tuple[NDArray[np.float64], tuple[tuple[tuple[float, ...], float], ...]]:
    """Per-joint weights by coordinate search on the dense LOO RMS of ``problem``'s samples (see
    fit_kriging). The factors tried on one joint start from the same weights: they are fitted
    together."""

    def loo(ws: list[NDArray[np.float64]]) -> list[float]:
        try:
            return [f.loo_rms_mm for f in problem.fits([JointStateMetric(w, sep) for w in ws])]
        except ValueError:  # a degenerate metric (e.g. a singular system): not a candidate
            if len(ws) == 1:
                return [float("inf")]
            return [loo([w])[0] for w in ws]

    w = np.array(start, dtype=float)
    best = loo([w])[0]
    tried: list[tuple[tuple[float, ...], float]] = [(tuple(w.tolist()), best)]
    sweeps = 2
    most = 1 + sweeps * N_JOINTS * len(ANISO_FACTORS)  # fewer if the second sweep is not needed
    for _sweep in range(sweeps):
        improved = False
        for j in range(N_JOINTS):
            trials = []
            for f in ANISO_FACTORS:
                trial = w.copy()
                trial[j] *= f
                trials.append(trial)
            for trial, value in zip(trials, loo(trials), strict=True):
                tried.append((tuple(trial.tolist()), value))
                steps.report("joint-weight candidates", len(tried), most)
                if value < best:
                    best, w, improved = value, trial, True
        if not improved:
            break
    return w, tuple(tried)


def _kriging_info(kg: KrigingFit, rows: MeasuredRows) -> dict[str, Any]:
    model = kg.model
    return {
        "rms_mm": rms_mm(model, rows),
        "base_rms_mm": kg.base_rms_mm,
        "loo_rms_mm": kg.loo_rms_mm,
        "samples": int(model.sample_a_deg.shape[0]),
        "solver": "dense" if model.neighbours is None else f"local, {model.neighbours} nearest samples",
        "loo_samples": kg.loo_samples,
        "joint_weights": model.metric.joint_weights.tolist(),
        "direction_separation_deg": model.metric.dir_separation_deg.tolist(),
        "direction_candidates": [
            {"separation_deg": list(sep), "loo_rms_mm": loo} for sep, loo in kg.candidates
        ],
        "joint_weight_candidates": len(kg.weight_candidates),
        "variograms": [v.to_dict() for v in model.variograms],
    }


def _fit_kriging(
    robot: RobotDescription,
    rows: MeasuredRows,
    spec: ModelSpec,
    options: FitOptions,
    effects: Sequence[str],
    direction: Literal["aware", "blind"],
) -> FittedModel:
    effects, selection, kf = selected_base(robot, rows, spec, options, effects)
    kg = fit_kriging(
        kf.model,
        rows.a_deg,
        rows.xyz_mm,
        dir=rows.dir if direction == "aware" else None,
        payload_kg=rows.payload_kg,
        temp_c=rows.temp_c,
        direction=direction,
        neighbours="auto" if spec.neighbours is None else spec.neighbours,
        anisotropic=spec.anisotropic,
        select_anisotropic=not spec.keep_all,
    )
    if kg.anisotropic_decision is not None:
        selection = selection + _decided(kg.anisotropic_decision)
    base_info = {"kind": "kinematic", **kinematic_info(kf, effects)}
    if not spec.keep_all:
        use = np.ones(kg.loo_rows.size, dtype=bool)
        if kg.unbiased_rows is not None:  # per-joint ranges: only the samples they were not chosen on
            use = np.isin(kg.loo_rows, kg.unbiased_rows)
        rows_loo = kg.loo_rows[use]
        decision = judge(
            "kriging",
            np.sum(kg.loo_residual_mm[use] ** 2, axis=1),
            np.sum(kg.model.residual_mm[rows_loo] ** 2, axis=1),
            f"leave-one-out on {rows_loo.size} of the {rows.n} fit rows against the base model's residual",
        )
        selection = selection + _decided(decision)
        if not decision.kept:
            attach_tcp_covariance(kf)
            info = {
                "kind": spec.kind,
                "rows": rows.n,
                "model_kind": "kinematic",
                **kinematic_info(kf, effects),
                "base": base_info,  # the model itself, under the key the kept case uses too
                "kriging": _kriging_info(kg, rows),
                "selection": selection.to_info(),
            }
            return FittedModel(kf.model, kf.frame, info)
    info = {
        "kind": spec.kind,
        "rows": rows.n,
        **_kriging_info(kg, rows),
        "base": base_info,
        "selection": selection.to_info(),
    }
    return FittedModel(kg.model, kf.frame, info)


def _decided(decision: Decision) -> Selection:
    kept = (decision.part,) if decision.kept else ()
    dropped = () if decision.kept else (decision.part,)
    return Selection(kept, dropped, (decision,))


def fit_kriging_kind(
    robot: RobotDescription, rows: MeasuredRows, spec: ModelSpec, options: FitOptions
) -> FittedModel:
    """Kriging of the residual of the kinematic calibration (with the spec's effects, if any) over
    the plain joint-space distance."""
    return _fit_kriging(robot, rows, spec, options, spec.effects, "blind")


def fit_kriging_backlash_kind(
    robot: RobotDescription, rows: MeasuredRows, spec: ModelSpec, options: FitOptions
) -> FittedModel:
    """Seed 001 §2: direction-aware kriging on the kinematic + ratio + backlash calibration (and
    the spec's further effects, e.g. ``kriging-backlash+compliance``)."""
    effects = tuple(dict.fromkeys((*TRANSMISSION_EFFECTS, *spec.effects)))
    return _fit_kriging(robot, rows, spec, options, effects, "aware")


KRIGING_OPTIONS = ("k=N", "aniso", "all")


def kriging_parameters(spec: ModelSpec) -> int:
    """The parameters of the kinematic base with the spec's effects."""
    return kinematic_parameters(ModelSpec("kinematic", spec.effects))


def kriging_backlash_parameters(spec: ModelSpec) -> int:
    """The parameters of the kinematic base with ratio, backlash and the spec's further effects."""
    effects = tuple(dict.fromkeys((*TRANSMISSION_EFFECTS, *spec.effects)))
    return kinematic_parameters(ModelSpec("kinematic", effects))


KIND = ModelKind(
    "kriging",
    "kriging of the kinematic calibration's residual over the joint-space distance (seed 001 §2);"
    " kriging:k=64 local neighbourhoods, kriging:aniso per-joint ranges, +effect on the base",
    KrigingModel,
    fit_kriging_kind,
    kriging_parameters,
    takes_effects=True,
    option_words=KRIGING_OPTIONS,
    uses=("payload_kg", "temp_c"),
)

BACKLASH_KIND = ModelKind(
    "kriging-backlash",
    "direction-aware kriging on kinematic+ratio+backlash (seed 001 §2)",
    KrigingModel,
    fit_kriging_backlash_kind,
    kriging_backlash_parameters,
    takes_effects=True,
    option_words=KRIGING_OPTIONS,
    needs=("dir",),
    uses=("payload_kg", "temp_c"),
)
