"""The sim-to-real gap diagnosis of ``shared/spec/diagnose.md``: the ladder from the nominal twin.

Units: mm for positions and errors, deg for axis values, the effect parameters in the units of
:mod:`comp_daemon.models.effects`. Joints are numbered 1..6 in every output. Errors are
``measured − twin``; ``check_rms_mm`` is the RMS of the 3-D distance over check rows.

Method (all choices on fit rows; check rows only report):

1. Frame. Data in the robot base frame is compared with the nominal twin as it is. Data in the
   tracker's own frame (``frame="tracker"``, or ``"auto"`` when the nominal twin misses the fit rows
   by more than :data:`~comp_daemon.models.registration.BASE_FRAME_MAX_RMS_MM` RMS) is first
   registered: the rigid transform that best maps the nominal TCP onto the measurements (Kabsch on
   the fit rows) becomes the twin's ``world_T_base``; the baseline is that registered nominal twin.
2. Geometric step. Every DH parameter (θ offset, d, a, α, β), the base frame (6) and the tool (3);
   zero and dependent columns of the identification Jacobian removed in MDH priority order
   (:func:`~comp_daemon.models.identifiability.analyze_identifiability`, seed 003);
   Gauss–Newton to convergence.
3. Effects. Candidates are (effect, joint) pairs of backlash, ratio, cyclic (K harmonics, 2K
   parameters per joint) and compliance, plus thermal (one κ). A candidate whose data is absent
   (no ``dir``, no ``temp_c`` or no spread in it, a joint that does not move or carries no gravity
   torque, a joint that does not move the TCP) or whose TCP signature is a combination of the
   parameters already in the model is skipped with the reason. Greedy forward selection: in each
   round the candidate with the lowest k-fold cross-validated error (folds of pose groups inside
   the fit rows) is tested with a cluster-robust Wald test (:mod:`comp_daemon.diagnosis.stats`); it
   is *significant* when its p-value is below ``alpha / m`` (Bonferroni over the m candidates of the
   round, so that the chance of a false alarm in a campaign without effects stays below ``alpha``)
   and it lowers the CV error. Parsimony: when a runner-up among the best five has fewer
   parameters and the best does not add to it significantly (same threshold), the runner-up is
   taken (a few harmonics mimic a ratio error over a limited joint range). A significant
   candidate joins the model (Gauss–Newton refit of everything); then each accepted candidate is
   offered for replacement by a rejected one that lowers the CV error further and passes the same
   test (forward selection alone can keep a candidate that stood in for two true effects); then
   the next round starts. Selection stops at the first round without a significant candidate.
4. Ladder. The significant effects in the order they were first selected, each step adding one
   effect (on all its selected joints) to everything before it, refitted on the fit rows; each step
   reports its check error. The best rejected candidate is appended as a step with
   ``significant: false``, so the report shows what the next effect would have bought.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from comp_daemon.data.dataset import DEFAULT_SPLIT_SEED, Dataset
from comp_daemon.diagnosis.fitting import FitResult, Observations, fit_twin, linearize, predict_mm
from comp_daemon.diagnosis.stats import LinearProblem, make_folds
from comp_daemon.diagnosis.where import locate
from comp_daemon.kinematics.forward import gravity_torques_nm
from comp_daemon.kinematics.params import N_PARAMS, PARAM_NAMES, KinematicParams, axes_deg_to_q_rad
from comp_daemon.models.effects import EFFECTS, EffectParams, MassModel, effect_param_names
from comp_daemon.models.identifiability import analyze_identifiability, mdh_priority
from comp_daemon.models.registration import detect_frame, rigid_registration
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "Candidate",
    "DiagnoseOptions",
    "Diagnosis",
    "Step",
    "diagnose",
    "observations_from_dataset",
]

FloatArray = NDArray[np.float64]
Frame = Literal["auto", "base", "tracker"]

#: a candidate is unidentifiable when less than this fraction of its (unit) columns is left after
#: projecting out the model's columns
CANDIDATE_RTOL = 1e-4
#: thermal needs at least this spread of ``temp_c`` on the fit rows (K)
MIN_TEMP_SPREAD_K = 0.5
JOINTS = (1, 2, 3, 4, 5, 6)


@dataclass(frozen=True)
class DiagnoseOptions:
    """Settings of a diagnosis; the defaults are the documented method."""

    frame: Frame = "auto"
    harmonics: int = 2  # K of the cyclic effect
    folds: int = 5  # k of the cross-validation inside the fit rows
    alpha: float = 0.002  # family-wise false-alarm level per selection round (calibrated, see docs)
    seed: int = DEFAULT_SPLIT_SEED  # folds, and the check rows when the data has no split column
    check_fraction: float = 0.3  # held out when the data has no split column
    t_ref_c: float = 20.0  # reference temperature of the thermal effect
    max_effects: int = 12  # at most this many (effect, joint) candidates are accepted

    def __post_init__(self) -> None:
        if self.frame not in ("auto", "base", "tracker"):
            raise ValueError(f"frame must be auto, base or tracker, got {self.frame!r}")
        if not 1 <= self.harmonics <= 8:
            raise ValueError(f"harmonics must be 1..8, got {self.harmonics}")
        if not 2 <= self.folds <= 20:
            raise ValueError(f"folds must be 2..20, got {self.folds}")
        if not 0.0 < self.alpha < 0.5:
            raise ValueError(f"alpha must be in (0, 0.5), got {self.alpha}")
        if not 0.0 < self.check_fraction < 1.0:
            raise ValueError(f"check_fraction must be in (0, 1), got {self.check_fraction}")


@dataclass(frozen=True)
class Candidate:
    """One effect on one joint (``joint`` None for thermal) and its parameter names."""

    effect: str
    joint: int | None
    names: tuple[str, ...]

    @property
    def label(self) -> str:
        return self.effect if self.joint is None else f"{self.effect} J{self.joint}"


@dataclass(frozen=True)
class Step:
    """One rung of the ladder, as in the JSON output (plus what the report draws)."""

    effect: str
    joints: list[int]
    significant: bool
    check_rms_mm: float
    check_max_mm: float
    shrink_pct: float
    params: dict[str, Any]
    fit_rms_mm: float
    cv_rms_mm: float | None
    p_value: float | None
    n_params: int
    fit: FitResult = field(repr=False)
    names: tuple[str, ...] = ()

    def to_json(self) -> dict[str, Any]:
        return {
            "effect": self.effect,
            "joints": self.joints,
            "significant": self.significant,
            "check_rms_mm": _r(self.check_rms_mm),
            "check_max_mm": _r(self.check_max_mm),
            "shrink_pct": round(self.shrink_pct, 2),
            "params": self.params,
            "fit_rms_mm": _r(self.fit_rms_mm),
            "cv_rms_mm": None if self.cv_rms_mm is None else _r(self.cv_rms_mm),
            "p_value": None if self.p_value is None else float(f"{self.p_value:.3g}"),
            "n_params": self.n_params,
        }


@dataclass(frozen=True)
class Diagnosis:
    """The result: ``to_json()`` is the document of diagnose.md; the arrays feed the report."""

    robot: RobotDescription
    dataset: Dataset
    obs: Observations
    fit_rows: NDArray[np.int64]
    check_rows: NDArray[np.int64]
    split_message: str
    split_drawn: bool
    frame: str
    world_T_base: FloatArray
    options: DiagnoseOptions
    baseline_fit: FitResult
    baseline_check_rms_mm: float
    baseline_check_max_mm: float
    steps: list[Step]
    skipped: list[dict[str, Any]]
    selection: list[dict[str, Any]]
    unidentifiable: list[str]
    noise_floor_mm: float
    noise_floor_source: str
    where: dict[str, Any]

    @property
    def significant_steps(self) -> list[Step]:
        return [s for s in self.steps if s.significant]

    @property
    def unmodelled(self) -> list[str]:
        return [s.effect for s in self.significant_steps if s.effect != "geometric"]

    @property
    def implicated_joints(self) -> list[int]:
        out: set[int] = set()
        for s in self.significant_steps:
            if s.effect != "geometric":
                out.update(s.joints)
        return sorted(out)

    @property
    def final_step(self) -> Step:
        return self.significant_steps[-1] if self.significant_steps else self.steps[0]

    @property
    def unexplained_rms_mm(self) -> float:
        return self.final_step.check_rms_mm

    def to_json(self) -> dict[str, Any]:
        return {
            "robot": self.robot.name,
            "robot_sha256": self.robot.sha256,
            "data": {"source": self.dataset.source, "content_sha256": self.dataset.content_sha256},
            "rows": {"fit": len(self.fit_rows), "check": len(self.check_rows)},
            "split": {"drawn": self.split_drawn, "message": self.split_message},
            "frame": {
                "measured_in": self.frame,
                "world_T_base": [[_r(v, 9) for v in row] for row in self.world_T_base],
            },
            "baseline": {
                "effect": "nominal",
                "check_rms_mm": _r(self.baseline_check_rms_mm),
                "check_max_mm": _r(self.baseline_check_max_mm),
            },
            "steps": [s.to_json() for s in self.steps],
            "unmodelled": self.unmodelled,
            "joints": self.implicated_joints,
            "where": self.where,
            "unexplained_rms_mm": _r(self.unexplained_rms_mm),
            "noise_floor_mm": _r(self.noise_floor_mm),
            "noise_floor_source": self.noise_floor_source,
            "unidentifiable": self.unidentifiable,
            "skipped": self.skipped,
            "selection": self.selection,
            "method": {
                "selection": "greedy forward selection by k-fold CV on fit rows (folds of pose groups)",
                "significance": "cluster-robust (CR3) Wald test, p < alpha / candidates, and lower CV error",
                "parsimony": "a runner-up with fewer parameters wins unless the best adds significantly",
                "alpha": self.options.alpha,
                "folds": self.options.folds,
                "cyclic_harmonics": self.options.harmonics,
                "t_ref_c": self.options.t_ref_c,
            },
        }


def _r(value: float, digits: int = 6) -> float:
    """A float rounded to ``digits`` significant digits, for JSON."""
    if not math.isfinite(value) or value == 0.0:
        return float(value)
    return float(f"{value:.{digits}g}")


# ------------------------------------------------------------------------------------------------
# Inputs
# ------------------------------------------------------------------------------------------------
def observations_from_dataset(dataset: Dataset) -> Observations:
    """The arrays of a measurement data set; pose groups by ``pose_id``, else by identical axes."""
    if dataset.a_deg is None or dataset.xyz_mm is None:
        raise ValueError(f"{dataset.source}: diagnosis needs axis values a1..a6 and measured x, y, z")
    if dataset.pose_id is not None:
        _, group = np.unique(np.asarray(dataset.pose_id, dtype=str), return_inverse=True)
    else:
        _, group = np.unique(dataset.a_deg, axis=0, return_inverse=True)
    return Observations(
        a_deg=np.array(dataset.a_deg, dtype=float),
        xyz_mm=np.array(dataset.xyz_mm, dtype=float),
        dir=None if dataset.dir is None else np.array(dataset.dir, dtype=float),
        payload_kg=np.array(dataset.payload_kg, dtype=float),
        temp_c=None if dataset.temp_c is None else np.array(dataset.temp_c, dtype=float),
        pose_group=np.asarray(group, dtype=np.int64).reshape(-1),
    )


def _distance_stats(resid: FloatArray) -> tuple[float, float]:
    dist = np.linalg.norm(resid, axis=1)
    if not len(dist):
        return float("nan"), float("nan")
    return float(np.sqrt(np.mean(dist**2))), float(dist.max())


def _shrink(before: float, after: float) -> float:
    return 100.0 * (1.0 - after / before) if before > 0 else 0.0


# ------------------------------------------------------------------------------------------------
# Candidates
# ------------------------------------------------------------------------------------------------
def _all_candidates(harmonics: int) -> list[Candidate]:
    out: list[Candidate] = []
    for effect in ("backlash", "ratio", "cyclic", "compliance"):
        for j in JOINTS:
            out.append(Candidate(effect, j, tuple(effect_param_names(effect, (j,), harmonics))))
    out.append(Candidate("thermal", None, ("kappa",)))
    return out


def _data_reasons(
    cands: Sequence[Candidate],
    obs_fit: Observations,
    mass: MassModel,
    params: KinematicParams,
    jac_theta_norm: FloatArray,
) -> dict[Candidate, str]:
    """Why candidates cannot be fitted from these data (absent columns, no variation)."""
    reasons: dict[Candidate, str] = {}
    q = axes_deg_to_q_rad(obs_fit.a_deg, params.sign)
    tau = gravity_torques_nm(params, q, mass.link_mass_kg, mass.link_com_mm, obs_fit.payload_kg)
    tau_scale = max(float(np.abs(tau).max(initial=0.0)), 1e-300)
    moves_tcp = jac_theta_norm > 1e-6 * max(float(jac_theta_norm.max(initial=0.0)), 1e-300)
    spread = np.ptp(obs_fit.a_deg, axis=0)
    payloads = np.unique(obs_fit.payload_kg)
    for c in cands:
        if c.effect == "thermal":
            if obs_fit.temp_c is None:
                reasons[c] = "no temp_c column: the temperature is unknown"
            elif np.ptp(obs_fit.temp_c) < MIN_TEMP_SPREAD_K:
                reasons[c] = (
                    f"temp_c spans only {np.ptp(obs_fit.temp_c):.2f} K on the fit rows "
                    f"(needs at least {MIN_TEMP_SPREAD_K} K to separate growth from constant lengths)"
                )
            continue
        j = int(c.joint or 0)
        if not moves_tcp[j - 1]:
            reasons[c] = f"joint {j} does not move the TCP in these poses (the TCP lies on its axis)"
        elif c.effect == "backlash":
            if obs_fit.dir is None:
                reasons[c] = "no dir1..dir6 columns: the approach direction is unknown"
            elif np.ptp(obs_fit.dir[:, j - 1]) == 0:
                reasons[c] = (
                    f"dir{j} is {int(obs_fit.dir[0, j - 1]):+d} on every fit row (play looks like an offset)"
                )
        elif c.effect in ("ratio", "cyclic"):
            if spread[j - 1] < 1e-6:
                reasons[c] = f"A{j} does not move on the fit rows"
        elif c.effect == "compliance":
            tau_j = tau[:, j - 1]
            if np.abs(tau_j).max() < 1e-9 * tau_scale:
                reasons[c] = f"no gravity torque on joint {j} in these poses (its axis is vertical)"
            elif np.ptp(tau_j) < 1e-6 * tau_scale:
                load = "payload" if len(payloads) == 1 else "payloads"
                reasons[c] = f"the gravity torque on joint {j} does not vary over these poses and {load}"
    return reasons


def _unidentifiable_candidates(
    cands: Sequence[Candidate], jac_base: FloatArray, jac_cand: dict[Candidate, FloatArray]
) -> set[Candidate]:
    """Candidates whose unit columns are (nearly) in the span of the base model's columns."""
    norms = np.linalg.norm(jac_base, axis=0)
    base = jac_base[:, norms > 0] / norms[norms > 0]
    qmat, _ = np.linalg.qr(base)
    out: set[Candidate] = set()
    for c in cands:
        cols = jac_cand[c]
        cn = np.linalg.norm(cols, axis=0)
        if np.any(cn == 0):
            out.add(c)
            continue
        cols = cols / cn
        rest = cols - qmat @ (qmat.T @ cols)
        sv = np.linalg.svd(rest, compute_uv=False)
        if sv.min() < CANDIDATE_RTOL:
            out.add(c)
    return out


def _group_skips(reasons: dict[Candidate, str]) -> list[dict[str, Any]]:
    grouped: dict[tuple[str, str], list[int]] = {}
    for c, why in reasons.items():
        grouped.setdefault((c.effect, why), [])
        if c.joint is not None:
            grouped[(c.effect, why)].append(c.joint)
    order = {e: i for i, e in enumerate(EFFECTS)}
    items = sorted(grouped.items(), key=lambda kv: (order[kv[0][0]], kv[1][:1]))
    return [{"effect": e, "joints": sorted(js), "reason": why} for (e, why), js in items]


# ------------------------------------------------------------------------------------------------
# Parameters as JSON
# ------------------------------------------------------------------------------------------------
def _geometric_params(
    fitted: KinematicParams, start: KinematicParams, free: NDArray[np.bool_]
) -> dict[str, Any]:
    dx = fitted.difference(start)
    out: dict[str, Any] = {}
    units = {
        "theta": ("theta_deg", True),
        "d": ("d_mm", False),
        "a": ("a_mm", False),
        "alpha": ("alpha_deg", True),
        "beta": ("beta_deg", True),
    }
    for k, name in enumerate(PARAM_NAMES):
        if not free[k]:
            continue
        value = float(dx[k])
        if k < 30:
            kind, joint = name[:-1], name[-1]
            key, is_angle = units[kind]
            out.setdefault(key, {})[joint] = _r(math.degrees(value) if is_angle else value)
        elif k < 33:
            out.setdefault("base_mm", {})[name[-1]] = _r(value)
        elif k < 36:
            out.setdefault("base_deg", {})[name[-2:]] = _r(math.degrees(value))
        else:
            out.setdefault("tool_mm", {})[name[-1]] = _r(value)
    return out


def _effect_params(effect: str, joints: Sequence[int], eff: EffectParams) -> dict[str, Any]:
    if effect == "backlash":
        return {"h_deg": {str(j): _r(float(eff.backlash_deg[j - 1])) for j in joints}}
    if effect == "ratio":
        return {"eps": {str(j): _r(float(eff.ratio[j - 1])) for j in joints}}
    if effect == "cyclic":
        return {
            "harmonics": eff.n_harmonics,
            "c_deg": {str(j): [_r(float(v)) for v in eff.cyclic_sin_deg[j - 1]] for j in joints},
            "s_deg": {str(j): [_r(float(v)) for v in eff.cyclic_cos_deg[j - 1]] for j in joints},
        }
    if effect == "compliance":
        return {"C_rad_per_nm": {str(j): _r(float(eff.compliance_rad_per_nm[j - 1])) for j in joints}}
    return {"kappa_per_k": _r(eff.thermal_per_k), "t_ref_c": eff.t_ref_c}


# ------------------------------------------------------------------------------------------------
# Noise floor
# ------------------------------------------------------------------------------------------------
def _noise_floor_from_repeats(obs: Observations) -> float | None:
    """3-D RMS scatter of repeated measurements of one pose (same axes, direction, load)."""
    keys = [obs.a_deg, obs.payload_kg[:, None]]
    if obs.dir is not None:
        keys.append(obs.dir)
    _, group = np.unique(np.concatenate(keys, axis=1), axis=0, return_inverse=True)
    group = np.asarray(group).reshape(-1)
    counts = np.bincount(group)
    repeated = counts[group] > 1
    n_groups = int(np.sum(counts > 1))
    if n_groups == 0:
        return None
    g = group[repeated]
    xyz = obs.xyz_mm[repeated]
    sums = np.zeros((int(group.max()) + 1, 3))
    np.add.at(sums, g, xyz)
    means = sums / np.maximum(counts, 1)[:, None]
    dev = xyz - means[g]
    dof = int(repeated.sum()) - n_groups
    return float(np.sqrt(np.sum(dev**2) / dof))


# ------------------------------------------------------------------------------------------------
# The diagnosis
# ------------------------------------------------------------------------------------------------
class _Context:
    """What every step of one diagnosis shares."""

    def __init__(
        self,
        mass: MassModel,
        obs: Observations,
        fit_rows: NDArray[np.int64],
        check_rows: NDArray[np.int64],
        geo_free: NDArray[np.bool_],
        options: DiagnoseOptions,
    ) -> None:
        self.mass = mass
        self.obs = obs
        self.obs_fit = obs.take(fit_rows)
        self.obs_check = obs.take(check_rows)
        self.geo_free = geo_free
        self.geo_idx = np.flatnonzero(geo_free)
        self.options = options
        self.fold = make_folds(self.obs_fit.pose_group, options.folds, options.seed)

    def fit(self, start: FitResult, names: Sequence[str]) -> FitResult:
        return fit_twin(self.mass, self.obs_fit, start.params, start.effects, self.geo_free, names)

    def problem(self, fit: FitResult, names: Sequence[str]) -> LinearProblem:
        """Linear problem with columns [free geometric | names] at ``fit``."""
        resid, jac = linearize(self.mass, fit.params, fit.effects, names, self.obs_fit)
        cols = np.concatenate([self.geo_idx, N_PARAMS + np.arange(len(names))])
        return LinearProblem(resid, jac[:, :, cols], self.obs_fit.pose_group, self.fold)

    def values(self, fit: FitResult, start: KinematicParams, names: Sequence[str]) -> FloatArray:
        """Values of the columns [free geometric | names] at ``fit``, measured from ``start``."""
        geo = fit.params.difference(start)[self.geo_idx]
        return np.concatenate([geo, fit.effects.get(list(names)) if names else np.zeros(0)])

    def check_stats(self, fit: FitResult) -> tuple[float, float]:
        resid = self.obs_check.xyz_mm - predict_mm(self.mass, fit.params, fit.effects, self.obs_check)
        return _distance_stats(resid)


def diagnose(dataset: Dataset, robot: RobotDescription, options: DiagnoseOptions | None = None) -> Diagnosis:
    """Diagnose the gap between ``robot``'s nominal twin and the measurements in ``dataset``."""
    options = options or DiagnoseOptions()
    obs = observations_from_dataset(dataset)
    split = dataset.split_or_draw(seed=options.seed, check_fraction=options.check_fraction)
    fit_rows, check_rows = np.asarray(split.fit_rows), np.asarray(split.check_rows)
    if len(check_rows) == 0:
        raise ValueError(
            f"{dataset.source}: the split column marks no row 'check'; the diagnosis needs check rows"
        )
    if len(fit_rows) < N_PARAMS:
        raise ValueError(
            f"{dataset.source}: {len(fit_rows)} fit rows, fewer than the {N_PARAMS} parameters "
            "of the geometric step"
        )
    mass = MassModel.from_robot(robot)
    nominal = KinematicParams.from_robot(robot)
    effects0 = EffectParams.zeros(options.harmonics, t_ref_c=options.t_ref_c)

    # 1. frame
    obs_fit = obs.take(fit_rows)
    p_nom = predict_mm(mass, nominal, effects0, obs_fit)
    rms_nominal = float(np.sqrt(np.mean(np.sum((obs_fit.xyz_mm - p_nom) ** 2, axis=1))))
    frame: str = options.frame
    if frame == "auto":
        frame = detect_frame(p_nom, obs_fit.xyz_mm)
    world_T_base = rigid_registration(p_nom, obs_fit.xyz_mm) if frame == "tracker" else np.eye(4)
    start_params = nominal.with_base(world_T_base)

    # 2. geometric step: identifiability, then Gauss–Newton
    _, jac0 = linearize(mass, start_params, effects0, [], obs_fit)
    ident = analyze_identifiability(jac0, PARAM_NAMES, priority=mdh_priority(start_params))
    geo_free = np.zeros(N_PARAMS, dtype=bool)
    geo_free[ident.identifiable_index] = True
    unidentifiable = [r.describe() for r in ident.removed]
    ctx = _Context(mass, obs, fit_rows, check_rows, geo_free, options)
    start = FitResult(start_params, effects0, rms_nominal, 0, True)
    base_rms, base_max = ctx.check_stats(start)
    geo_fit = ctx.fit(start, [])

    # 3. candidates and selection
    cands = _all_candidates(options.harmonics)
    theta_norm = np.linalg.norm(jac0[:, :, 0:30:5], axis=(0, 1))
    reasons = _data_reasons(cands, ctx.obs_fit, mass, start_params, theta_norm)
    avail = [c for c in cands if c not in reasons]
    all_names = [n for c in avail for n in c.names]
    _, jac_geo = linearize(mass, geo_fit.params, geo_fit.effects, all_names, ctx.obs_fit)
    jac_flat = jac_geo.reshape(-1, jac_geo.shape[2])
    offsets: dict[Candidate, NDArray[np.int64]] = {}
    pos = N_PARAMS
    for c in avail:
        offsets[c] = np.arange(pos, pos + len(c.names))
        pos += len(c.names)
    collinear = _unidentifiable_candidates(
        avail, jac_flat[:, ctx.geo_idx], {c: jac_flat[:, offsets[c]] for c in avail}
    )
    for c in collinear:
        reasons[c] = "with these poses its effect on the TCP is a combination of geometric parameters"
    avail = [c for c in avail if c not in collinear]

    accepted, rejected, selection, _ = _select(ctx, geo_fit, avail, options)

    # 4. the ladder
    steps: list[Step] = []
    geo_rms, geo_max = ctx.check_stats(geo_fit)
    lp_geo = ctx.problem(geo_fit, [])
    geo_cols = list(range(len(ctx.geo_idx)))
    wald_geo_p = _geo_pvalue(start, ctx, geo_cols)
    steps.append(
        Step(
            effect="geometric",
            joints=_geometric_joints(
                lp_geo, ctx.geo_idx, options.alpha, ctx.values(geo_fit, start_params, [])
            ),
            significant=bool(wald_geo_p < options.alpha),
            check_rms_mm=geo_rms,
            check_max_mm=geo_max,
            shrink_pct=_shrink(base_rms, geo_rms),
            params=_geometric_params(geo_fit.params, start_params, geo_free),
            fit_rms_mm=geo_fit.rms_mm,
            cv_rms_mm=lp_geo.cv_rms_mm(geo_cols),
            p_value=wald_geo_p,
            n_params=len(ctx.geo_idx),
            fit=geo_fit,
        )
    )
    order: list[str] = []
    for c in accepted:
        if c.effect not in order:
            order.append(c.effect)
    prev = geo_fit
    names_so_far: list[str] = []
    for effect in order:
        joints = sorted(int(c.joint) for c in accepted if c.effect == effect and c.joint is not None)
        new = [n for c in accepted if c.effect == effect for n in c.names]
        steps.append(
            _effect_step(
                ctx,
                start_params,
                prev,
                names_so_far,
                new,
                effect,
                joints,
                significant=True,
                before=steps[-1].check_rms_mm,
            )
        )
        names_so_far += new
        prev = steps[-1].fit
    if rejected is not None:
        joints = [] if rejected.joint is None else [rejected.joint]
        steps.append(
            _effect_step(
                ctx,
                start_params,
                prev,
                names_so_far,
                list(rejected.names),
                rejected.effect,
                joints,
                significant=False,
                before=steps[-1].check_rms_mm,
            )
        )

    # 5. noise floor
    floor = _noise_floor_from_repeats(obs)
    if floor is not None:
        floor_source = "repeats"
    else:
        final = next(s for s in reversed(steps) if s.significant or s.effect == "geometric")
        n_params = final.n_params
        dof = max(3 * len(fit_rows) - n_params, 1)
        floor = final.fit_rms_mm * math.sqrt(3 * len(fit_rows) / dof)
        floor_source = "fit_residual"

    diag = Diagnosis(
        robot=robot,
        dataset=dataset,
        obs=obs,
        fit_rows=fit_rows,
        check_rows=check_rows,
        split_message=split.message,
        split_drawn=split.drawn,
        frame=frame,
        world_T_base=world_T_base,
        options=options,
        baseline_fit=start,
        baseline_check_rms_mm=base_rms,
        baseline_check_max_mm=base_max,
        steps=steps,
        skipped=_group_skips(reasons),
        selection=selection,
        unidentifiable=unidentifiable,
        noise_floor_mm=floor,
        noise_floor_source=floor_source,
        where={},
    )
    by_joint = {j: [n for c in cands if c.joint == j and c not in reasons for n in c.names] for j in JOINTS}
    where = locate(diag, ctx.problem, by_joint)
    object.__setattr__(diag, "where", where)
    return diag


def _cols_of(cands: Sequence[Candidate], first: int) -> dict[Candidate, list[int]]:
    out: dict[Candidate, list[int]] = {}
    for c in cands:
        out[c] = list(range(first, first + len(c.names)))
        first += len(c.names)
    return out


def _names(cands: Sequence[Candidate]) -> list[str]:
    return [n for c in cands for n in c.names]


def _select(
    ctx: _Context, geo_fit: FitResult, candidates: Sequence[Candidate], options: DiagnoseOptions
) -> tuple[list[Candidate], Candidate | None, list[dict[str, Any]], FitResult]:
    """Greedy forward selection with a replacement pass (see the module docstring).

    Returns the accepted candidates in order, the best rejected one (None if none was left), the
    record of every round, and the fit of the final model.
    """
    avail = list(candidates)
    accepted: list[Candidate] = []
    selection: list[dict[str, Any]] = []
    current = geo_fit
    rejected: Candidate | None = None
    while avail and len(accepted) < options.max_effects:
        lp = ctx.problem(current, _names(accepted) + _names(avail))
        base_cols = list(range(len(ctx.geo_idx) + len(_names(accepted))))
        col_of = _cols_of(avail, len(base_cols))
        cv_base = lp.cv_rms_mm(base_cols)
        scored = sorted((lp.cv_rms_mm(base_cols + col_of[c]), i) for i, c in enumerate(avail))
        threshold = options.alpha / len(avail)
        ranked: list[dict[str, Any]] = []
        for cv, i in scored[:5]:
            c = avail[i]
            wald = lp.wald(base_cols + col_of[c], col_of[c])
            ranked.append({"candidate": c.label, "cv_rms_mm": _r(cv), "p_value": wald.p_value})
        best_cv, best_i = scored[0]
        best = avail[best_i]
        best_p = float(ranked[0]["p_value"])
        simpler = _simpler_alternative(
            lp, base_cols, col_of, best, [avail[i] for _, i in scored[1:5]], threshold
        )
        if simpler is not None:
            k = next(k for k, (_, i) in enumerate(scored) if avail[i] is simpler)
            best, best_cv, best_p = simpler, scored[k][0], float(ranked[k]["p_value"])
        significant = best_p < threshold and best_cv < cv_base
        for entry in ranked:
            entry["p_value"] = float(f"{entry['p_value']:.3g}")
        selection.append(
            {
                "round": len(selection) + 1,
                "cv_rms_mm_before": _r(cv_base),
                "candidates": len(avail),
                "p_threshold": float(f"{threshold:.3g}"),
                "best": ranked,
                "preferred_simpler": None if simpler is None else simpler.label,
                "accepted": best.label if significant else None,
            }
        )
        if not significant:
            rejected = best
            break
        accepted.append(best)
        avail.remove(best)
        current = ctx.fit(current, _names(accepted))
        current = _replace_pass(ctx, current, accepted, avail, options, selection)
    return accepted, rejected, selection, current


def _simpler_alternative(
    lp: LinearProblem,
    base_cols: list[int],
    col_of: dict[Candidate, list[int]],
    best: Candidate,
    runners_up: Sequence[Candidate],
    threshold: float,
) -> Candidate | None:
    """A runner-up with fewer parameters that ``best`` does not significantly improve on, if any.

    Over a limited range of a joint, a few harmonics reproduce a linear ratio error almost exactly,
    and cross-validation cannot tell the two apart; parsimony can: the larger candidate must add
    to the smaller one at the selection's own significance threshold, or the smaller one is taken.
    """
    for c in runners_up:  # in order of CV error
        if len(c.names) >= len(best.names):
            continue
        if lp.wald(base_cols + col_of[c] + col_of[best], col_of[best]).p_value >= threshold:
            return c
    return None


def _replace_pass(
    ctx: _Context,
    current: FitResult,
    accepted: list[Candidate],
    avail: list[Candidate],
    options: DiagnoseOptions,
    selection: list[dict[str, Any]],
) -> FitResult:
    """Replace an accepted candidate by a rejected one while that lowers the CV error.

    Forward selection can take a candidate that stood in for two true effects at once (a cyclic
    term absorbing a ratio error and part of a thermal drift); once the second one is in, the
    first may be better explained by another candidate. Each accepted candidate is taken out (its
    parameters set to zero, the problem linearised there), and the best replacement by CV must beat
    it and pass the same significance test. Changes are recorded in ``selection``.
    """
    for _ in range(3 * max(len(accepted), 1)):
        swapped = False
        for k, old in enumerate(accepted):
            others = [c for c in accepted if c is not old]
            point = FitResult(
                current.params,
                current.effects.with_values(list(old.names), np.zeros(len(old.names))),
                current.rms_mm,
                0,
                True,
            )
            pool = [old, *avail]
            lp = ctx.problem(point, _names(others) + _names(pool))
            base_cols = list(range(len(ctx.geo_idx) + len(_names(others))))
            col_of = _cols_of(pool, len(base_cols))
            cv_old = lp.cv_rms_mm(base_cols + col_of[old])
            cv_new, i = min((lp.cv_rms_mm(base_cols + col_of[c]), i) for i, c in enumerate(avail))
            new = avail[i]
            if cv_new >= cv_old:
                continue
            p_value = lp.wald(base_cols + col_of[new], col_of[new]).p_value
            if p_value >= options.alpha / len(pool):
                continue
            if len(new.names) > len(old.names):
                both = base_cols + col_of[old] + col_of[new]
                if lp.wald(both, col_of[new]).p_value >= options.alpha / len(pool):
                    continue  # the larger candidate does not add to the smaller one: keep the smaller
            selection.append(
                {
                    "round": len(selection) + 1,
                    "replaced": old.label,
                    "by": new.label,
                    "cv_rms_mm_before": _r(cv_old),
                    "cv_rms_mm_after": _r(cv_new),
                    "p_value": float(f"{p_value:.3g}"),
                }
            )
            accepted[k] = new
            avail[i] = old
            current = ctx.fit(point, _names(accepted))
            swapped = True
            break
        if not swapped:
            break
    return current


def _geo_pvalue(start: FitResult, ctx: _Context, geo_cols: list[int]) -> float:
    """Wald test of the whole geometric step against the (registered) nominal twin."""
    lp = ctx.problem(start, [])
    return lp.wald(geo_cols, geo_cols).p_value


def _geometric_joints(
    lp: LinearProblem, geo_idx: NDArray[np.int64], alpha: float, at: FloatArray
) -> list[int]:
    """Joints with at least one significant geometric parameter (Wald test per joint, Bonferroni)."""
    cols = list(range(len(geo_idx)))
    out = []
    for j in JOINTS:
        tested = [i for i, k in enumerate(geo_idx) if 5 * (j - 1) <= k < 5 * j]
        if tested and lp.wald(cols, tested, at).p_value < alpha / 6:
            out.append(j)
    return out


def _effect_step(
    ctx: _Context,
    start: KinematicParams,
    prev: FitResult,
    names_before: list[str],
    new: list[str],
    effect: str,
    joints: list[int],
    *,
    significant: bool,
    before: float,
) -> Step:
    names = names_before + new
    fit = ctx.fit(prev, names)
    rms, mx = ctx.check_stats(fit)
    lp = ctx.problem(fit, names)
    cols = list(range(len(ctx.geo_idx) + len(names)))
    tested = cols[len(ctx.geo_idx) + len(names_before) :]
    return Step(
        effect=effect,
        joints=joints,
        significant=significant,
        check_rms_mm=rms,
        check_max_mm=mx,
        shrink_pct=_shrink(before, rms),
        params=_effect_params(effect, joints, fit.effects),
        fit_rms_mm=fit.rms_mm,
        cv_rms_mm=lp.cv_rms_mm(cols),
        p_value=lp.wald(cols, tested, ctx.values(fit, start, names)).p_value,
        n_params=len(cols),
        fit=fit,
        names=tuple(new),
    )
