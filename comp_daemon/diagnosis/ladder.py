"""The sim-to-real gap diagnosis of ``docs/diagnosis-output.md``: the ladder from the nominal twin.

Units: mm for positions and errors, deg for axis values, the effect parameters in the units of
:mod:`comp_daemon.models.effects`. Joints are numbered 1..6 in every output. Errors are
``measured − twin``; ``check_rms_mm`` is the RMS of the 3-D distance over check rows.

Method (all choices on fit rows; check rows only report):

1. Frame. Data in the robot base frame is compared with the nominal twin as it is. Data in the
   tracker's own frame (``frame="tracker"``, or ``"auto"`` when the nominal twin misses the fit rows
   by more than :data:`~comp_daemon.estimation.registration.BASE_FRAME_MAX_RMS_MM` RMS) is first
   registered: the rigid transform that best maps the nominal TCP onto the measurements (Kabsch on
   the fit rows) becomes the twin's ``world_T_base``; the baseline is that registered nominal twin.
2. Geometric step. Every DH parameter (θ offset, d, a, α, β), the base frame (6) and the tool (3);
   zero and dependent columns of the identification Jacobian removed in MDH priority order
   (:func:`~comp_daemon.estimation.identifiability.analyze_identifiability`, seed 003);
   Gauss–Newton to convergence.
3. Effects. Candidates are the entries of the effect catalogue
   (:data:`~comp_daemon.models.effects.EFFECT_CATALOGUE`): (effect, joint) pairs of the per-joint
   effects (backlash, ratio, cyclic with K harmonics, 2K parameters per joint, compliance, and
   step), plus the whole-robot ones (thermal, one κ; drift, six rates)
   (:mod:`comp_daemon.diagnosis.candidates`), or those of ``options.effects``. The step's moment
   is searched first (:func:`_search_step`) and its candidates' p-values carry the number of
   moments tried. When no time effect is tried and the geometric remainder follows the campaign
   clock, every candidate is tested against a time nuisance
   (:func:`~comp_daemon.diagnosis.selection.time_nuisance`). A
   candidate whose data is absent (no ``dir``, no ``temp_c`` or no spread in it, a joint that does
   not move or carries no gravity torque, a joint that does not move the TCP: each entry's
   ``unfit_reason``) or whose TCP signature is a combination of the parameters already in the model
   is skipped with the reason. Greedy forward selection (:mod:`comp_daemon.diagnosis.selection`):
   in each round the candidate with the lowest k-fold cross-validated error (folds of pose groups
   inside the fit rows) is tested with a cluster-robust Wald test
   (:mod:`comp_daemon.diagnosis.stats`); it is *significant* when its p-value is below
   ``alpha/m`` (Bonferroni over the m candidates of the round, so that the chance of a false alarm in a
   campaign without effects stays below ``alpha``) and it lowers the CV error. Parsimony: when a
   runner-up among the best five has fewer parameters and the best does not add to it significantly
   (same threshold), the runner-up is taken (a few harmonics mimic a ratio error over a limited
   joint range). A significant candidate joins the model (Gauss–Newton refit of everything); then
   each accepted candidate is offered for replacement by a rejected one that lowers the CV error
   further and passes the same test (forward selection alone can keep a candidate that stood in for
   two true effects); then the next round starts. Selection stops at the first round without a
   significant candidate.
4. Ladder. The significant effects in the order they were first selected, each step adding one
   effect (on all its selected joints) to everything before it, refitted on the fit rows; each step
   reports its check error. The best rejected candidate is appended as a step with
   ``significant: false``, so the report shows what the next effect would have bought.
5. Noise floor. From independent evidence only (:func:`_noise_floor`): repeated poses, else a
   declared tracker uncertainty (``--tracker-sigma-mm``, else the ``sigma_mm`` column), else the
   spread of the mutual distances of several targets on the flange, else none (``None``). Never
   the fit residual. With three or more targets, ``where`` also gives the flange's position and
   orientation errors apart (:mod:`comp_daemon.diagnosis.targets`).
6. Remainder structure. The final model's remainder (check rows; fit rows out of fold) against
   time or row order, axis values, payload, temperature and directions
   (:mod:`comp_daemon.diagnosis.structure`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comp_daemon.data.dataset import Dataset
from comp_daemon.diagnosis.agreement import Agreement, fit_check_agreement
from comp_daemon.diagnosis.attribution import flexible_attribution
from comp_daemon.diagnosis.candidates import (
    JOINTS,
    Candidate,
    all_candidates,
    data_reasons,
    effect_params_json,
    geometric_params_json,
    group_skips,
    unidentifiable_candidates,
)
from comp_daemon.diagnosis.comparison import compare_models
from comp_daemon.diagnosis.fitting import (
    FitResult,
    at_fit,
    linearize_targets,
    predict_mm,
    project_out,
)
from comp_daemon.diagnosis.remainder import RemainderModel, judge_remainder
from comp_daemon.diagnosis.result import DiagnoseOptions, Diagnosis, Step, final_step, rounded
from comp_daemon.diagnosis.selection import Context, select, time_nuisance
from comp_daemon.diagnosis.stats import LinearProblem
from comp_daemon.diagnosis.structure import StructureResult, describe_structure, residual_structure
from comp_daemon.diagnosis.targets import flange_errors, flange_words, noise_from_targets, target_offsets_mm
from comp_daemon.diagnosis.where import Baseline, locate
from comp_daemon.estimation.identifiability import analyze_identifiability, mdh_priority
from comp_daemon.kinematics.params import N_PARAMS, PARAM_NAMES, KinematicParams
from comp_daemon.models.effects import TIME_EFFECTS, EffectParams, MassModel
from comp_daemon.models.observations import orientation_weight, probe_axis_points_mm
from comp_daemon.models.rows import MeasuredRows
from comp_daemon.preparation.campaign import PreparedCampaign, PrepareOptions, prepare_campaign
from comp_daemon.robot.description import RobotDescription

__all__ = [
    "Candidate",
    "DiagnoseOptions",
    "Diagnosis",
    "Step",
    "diagnose",
]

FloatArray = NDArray[np.float64]


def _shrink(before: float, after: float) -> float:
    return 100.0 * (1.0 - after / before) if before > 0 else 0.0


def _noise_floor_from_repeats(obs: MeasuredRows) -> float | None:
    """3-D RMS scatter of repeated measurements of one pose (same pose, axes, direction, load).

    Per axis, the within-pose variance pooled over every repeated pose (``Σ (x − x̄_pose)²`` over
    ``rows − poses`` degrees of freedom); the three summed: the expected squared 3-D distance of a
    measurement from the truth, ``√3·σ`` for a tracker with σ per axis. None without repeats.
    """
    keys = [obs.pose_group[:, None].astype(float), obs.a_deg, obs.payload_kg[:, None]]
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


def diagnose(dataset: Dataset, robot: RobotDescription, options: DiagnoseOptions | None = None) -> Diagnosis:
    """Diagnose the gap between ``robot``'s nominal twin and the measurements in ``dataset``."""
    options = options or DiagnoseOptions()
    prepared = prepare_campaign(dataset, robot, _preparation(options))
    obs = prepared.measured
    split = prepared.split
    fit_rows, check_rows = prepared.fit_rows, prepared.check_rows
    mass = MassModel.from_robot(robot)
    nominal = KinematicParams.from_robot(robot)
    effects0 = EffectParams.zeros(options.harmonics, t_ref_c=options.t_ref_c)

    # 1. frame (prepared: registered on the fit rows when the data are in a tracker's frame)
    frame, world_T_base = prepared.frame, prepared.world_T_base
    rms_nominal = prepared.nominal_fit_rms_mm
    start_params = nominal.with_base(world_T_base)
    start = FitResult(start_params, effects0, rms_nominal, 0, True)
    # every target: the further ones as rows of their own, at their place on the flange
    obs_all, fit_all, check_all, probe = _every_target(prepared, mass, start, options.tracker_sigma_mm)

    # 2. geometric step: identifiability, then Gauss–Newton
    geo_free, unidentifiable, jac0 = _free_geometry(mass, start, obs_all.take(fit_all))
    ctx = Context(mass, obs_all, fit_all, check_all, geo_free, options)
    base_rms, base_max = ctx.check_stats(start)
    geo_fit = ctx.fit(start, [])
    step_at, searched = _search_step(ctx, geo_fit)
    start = _with_step_at(start, step_at)
    geo_fit = _with_step_at(geo_fit, step_at)

    # 3. candidates and selection
    cands = _candidates(options, searched)
    theta_norm = np.linalg.norm(jac0[:, :, 0:30:5], axis=(0, 1))
    reasons = data_reasons(cands, ctx.obs_fit, mass, start_params, theta_norm)
    avail = _identifiable(ctx, geo_fit, [c for c in cands if c not in reasons], reasons)
    if not any(c.effect in TIME_EFFECTS for c in avail) and _follows_time(ctx, geo_fit):
        ctx.nuisance = time_nuisance(np.asarray(ctx.obs_fit.clock))
    accepted, rejected, selection, final_fit = select(ctx, geo_fit, avail, options)
    accepted = _physical_over_clock(ctx, final_fit, accepted, selection)
    accepted, unnamed = flexible_attribution(ctx, final_fit, accepted)

    # 4. the ladder, 5. the noise floor, 6. the remainder's structure, 7. where the gap lies
    steps = _ladder(ctx, start, geo_fit, accepted, rejected, base_rms)
    floor, floor_source = _noise_floor(obs, options.tracker_sigma_mm, dataset.reflectors_mm, dataset.sigma_mm)
    structure = _structure(ctx, dataset, steps)
    skipped = group_skips(reasons)
    by_joint = {j: [n for c in cands if c.joint == j and c not in reasons for n in c.names] for j in JOINTS}
    agreement = _agreement(ctx, obs, fit_rows, check_rows, prepared.dataset, steps)
    baseline = Baseline(
        check_rms_mm=base_rms,
        check_max_mm=base_max,
        noise_floor_mm=floor,
        skipped=skipped,
        noise_floor_source=floor_source,
        structure=describe_structure(structure),
        disagreement=agreement.describe(),
    )
    where = locate(obs, mass, steps, baseline, ctx.problem, by_joint)
    flange = flange_errors(mass, steps[0].fit, obs, dataset.reflectors_mm, fit_rows, check_rows, robot, frame)
    if flange is not None:
        where["flange"] = flange
        where["summary"] += " " + flange_words(flange)
    remainder = _remainder(ctx, steps)
    where["summary"] = " ".join([where["summary"], *(u.describe() for u in unnamed), remainder.describe()])
    comparison = None
    if options.compare_models:  # 8. the compensation models on the same rows
        comparison = compare_models(
            prepared,
            robot,
            options.compare_models,
            final_step(steps).check_rms_mm,
            remainder,
            [u.to_json() for u in unnamed],
            folds=options.folds,
            seed=options.seed,
        )
    return Diagnosis(
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
        skipped=skipped,
        selection=selection,
        unidentifiable=unidentifiable,
        noise_floor_mm=floor,
        noise_floor_source=floor_source,
        where=where,
        directions=prepared.directions,
        stations=None if prepared.stations is None else prepared.stations.to_json(),
        orientation=_orientation_words(prepared.probe_sigma_deg) if probe else None,
        agreement=agreement,
        unnamed=[u.to_json() for u in unnamed],
        residual_structure=structure,
        remainder_rows="check rows, and fit rows out of fold",
        time_nuisance=ctx.nuisance is not None,
        remainder_model=remainder,
        model_comparison=comparison,
    )


def _identifiable(
    ctx: Context, geo_fit: FitResult, avail: list[Candidate], reasons: dict[Candidate, str]
) -> list[Candidate]:
    """The candidates whose TCP signature is not a combination of the geometric columns.

    The others are added to ``reasons``.
    """
    all_names = [n for c in avail for n in c.names]
    obs = at_fit(ctx.obs_fit, geo_fit)
    _, jac_geo, tcols = linearize_targets(ctx.mass, geo_fit.params, geo_fit.effects, all_names, obs)
    (jac_geo,) = project_out(tcols, jac_geo)  # what the targets' places absorb is not identifiable
    jac_flat = jac_geo.reshape(-1, jac_geo.shape[2])
    offsets: dict[Candidate, NDArray[np.int64]] = {}
    pos = N_PARAMS
    for c in avail:
        offsets[c] = np.arange(pos, pos + len(c.names))
        pos += len(c.names)
    collinear = unidentifiable_candidates(
        avail, jac_flat[:, ctx.geo_idx], {c: jac_flat[:, offsets[c]] for c in avail}
    )
    for c in collinear:
        reasons[c] = "with these poses its effect on the TCP is a combination of geometric parameters"
    return [c for c in avail if c not in collinear]


def _ladder(
    ctx: Context,
    start: FitResult,
    geo_fit: FitResult,
    accepted: list[Candidate],
    rejected: Candidate | None,
    base_rms: float,
) -> list[Step]:
    """The geometric step, one step per accepted effect, and the best rejected candidate."""
    start_params = start.params
    alpha = ctx.options.alpha
    geo_rms, geo_max = ctx.check_stats(geo_fit)
    lp_geo = ctx.problem(geo_fit, [])
    geo_cols = list(range(len(ctx.geo_idx)))
    wald_geo_p = _geo_pvalue(start, ctx, geo_cols)
    steps = [
        Step(
            effect="geometric",
            joints=_geometric_joints(lp_geo, ctx.geo_idx, alpha, ctx.values(geo_fit, start_params, [])),
            significant=bool(wald_geo_p < alpha),
            check_rms_mm=geo_rms,
            check_max_mm=geo_max,
            shrink_pct=_shrink(base_rms, geo_rms),
            params=geometric_params_json(geo_fit.params, start_params, ctx.geo_free),
            fit_rms_mm=geo_fit.rms_mm,
            cv_rms_mm=lp_geo.cv_rms_mm(geo_cols),
            p_value=wald_geo_p,
            n_params=len(ctx.geo_idx),
            fit=geo_fit,
        )
    ]
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
    return steps


def _noise_floor(
    obs: MeasuredRows,
    tracker_sigma_mm: float | None,
    reflectors_mm: FloatArray | None = None,
    sigma_mm: FloatArray | None = None,
) -> tuple[float | None, str | None]:
    """The noise floor (mm, 3-D RMS) and its source, from independent evidence only.

    Repeated poses first (they measure the tracker and the robot's repeatability together), else
    the uncertainty the user declares: ``--tracker-sigma-mm`` (σ per axis: ``√3·σ``), else the
    rows' ``sigma_mm`` column (``√3·`` their RMS); a declared σ overrides the floor inferred from
    targets, since the targets may be a 6-DOF probe's virtual reflectors, whose exact mutual
    distances say nothing of the noise. Else the spread of the mutual distances of several targets
    on the flange (the tracker alone, :func:`~comp_daemon.diagnosis.targets.noise_from_targets`:
    ``√3·σ̂``), else ``(None, None)``. The fit residual is never a noise floor: it is the quantity
    the diagnosis explains.
    """
    floor = _noise_floor_from_repeats(obs)
    if floor is not None:
        return floor, "repeats"
    if tracker_sigma_mm is not None:
        return math.sqrt(3.0) * tracker_sigma_mm, "declared"
    if sigma_mm is not None:
        return math.sqrt(3.0 * float(np.mean(np.square(sigma_mm)))), "declared"
    from_targets = noise_from_targets(reflectors_mm)
    if from_targets is not None:
        return from_targets[1], "targets"
    return None, None


#: the step's moment is searched at this many quantiles of the clock on the fit rows
STEP_POSITIONS = 19


def _search_step(ctx: Context, geo_fit: FitResult) -> tuple[float, int]:
    """The moment of a joint's step that best explains the geometric fit's residual, and the positions tried.

    Positions are the clock values at :data:`STEP_POSITIONS` quantiles (5 % … 95 %) of the fit
    rows; at each, the six joints' step columns are projected off the geometric columns and the
    largest single-joint drop of the residual's sum of squares scores the position. The step
    candidates' p-values are multiplied by the number of positions tried (Bonferroni).
    """
    clock = ctx.obs_fit.clock
    if clock is None or len(np.unique(clock)) < 2:
        return math.inf, 1
    obs = at_fit(ctx.obs_fit, geo_fit)
    resid, jac, tcols = linearize_targets(ctx.mass, geo_fit.params, geo_fit.effects, [], obs)
    resid, jac = project_out(tcols, resid, jac)
    geo = jac[:, :, ctx.geo_idx].reshape(-1, len(ctx.geo_idx))
    norms = np.linalg.norm(geo, axis=0)
    qmat, _ = np.linalg.qr(geo / np.where(norms > 0, norms, 1.0))
    r = resid.reshape(-1)
    r = r - qmat @ (qmat.T @ r)
    j_theta = jac[:, :, 0:30:5]  # (n, 3, 6)
    positions = np.unique(np.quantile(clock, np.linspace(0.05, 0.95, STEP_POSITIONS), method="higher"))
    positions = positions[positions > clock.min()]
    if len(positions) == 0:
        return math.inf, 1
    best, best_at = -1.0, math.inf
    for t0 in positions:
        cols = (j_theta * (clock >= t0)[:, None, None]).reshape(-1, 6)
        cols = cols - qmat @ (qmat.T @ cols)
        power = np.sum(cols * cols, axis=0)
        drop = np.where(
            power > 1e-12 * max(float(power.max()), 1e-300),
            (cols.T @ r) ** 2 / np.maximum(power, 1e-300),
            0.0,
        )
        if float(drop.max()) > best:
            best, best_at = float(drop.max()), float(t0)
    return best_at, len(positions)


#: temperature and clock this correlated on the fit rows are collinear drivers
COLLINEAR_DRIVERS = 0.9
#: a time effect beside thermal growth must lower the CV error by this share to be needed as well
NEEDED_GAIN = 0.02


def _physical_over_clock(
    ctx: Context, fit: FitResult, accepted: list[Candidate], selection: list[dict[str, Any]]
) -> list[Candidate]:
    """``accepted`` without its time effects when thermal growth is accepted, the temperature follows
    the clock (|r| > :data:`COLLINEAR_DRIVERS` on the fit rows) and the time effects do not lower
    the cross-validated error by :data:`NEEDED_GAIN` beside it: collinear drivers, the physical one
    is named unless both are needed out of fold. The decision is recorded in ``selection``."""
    timed = [c for c in accepted if c.effect in TIME_EFFECTS]
    temp, clock = ctx.obs_fit.temp_c, ctx.obs_fit.clock
    if not timed or not any(c.effect == "thermal" for c in accepted) or temp is None or clock is None:
        return accepted
    if np.std(temp) == 0 or np.std(clock) == 0:
        return accepted
    r = float(np.corrcoef(temp, clock)[0, 1])
    if abs(r) <= COLLINEAR_DRIVERS:
        return accepted
    names = [n for c in accepted for n in c.names]
    lp = ctx.problem(fit, names)
    cols = ctx.own_cols(len(names))
    n_base = len(ctx.geo_idx)
    drop: list[int] = []
    pos = 0
    for c in accepted:
        if c in timed:
            drop += cols[n_base + pos : n_base + pos + len(c.names)]
        pos += len(c.names)
    cv_both = lp.cv_rms_mm(cols)
    cv_thermal = lp.cv_rms_mm([k for k in cols if k not in drop])
    needed = cv_thermal > (1.0 + NEEDED_GAIN) * cv_both
    selection.append(
        {
            "round": len(selection) + 1,
            "collinear_drivers": {"temp_c": ctx.obs.clock_name, "r": rounded(r)},
            "cv_rms_mm_thermal_and_time": rounded(cv_both),
            "cv_rms_mm_thermal_only": rounded(cv_thermal),
            "kept_time_effects": needed,
            "time_effects": [c.label for c in timed],
        }
    )
    return accepted if needed else [c for c in accepted if c not in timed]


def _follows_time(ctx: Context, geo_fit: FitResult) -> bool:
    """Whether the geometric step's remainder on the fit rows (out of fold) follows the clock."""
    if ctx.obs_fit.clock is None:
        return False
    resid = ctx.problem(geo_fit, []).oof_residuals(list(range(len(ctx.geo_idx))))
    found = residual_structure(
        resid,
        {ctx.obs.clock_name: ctx.obs_fit.clock},
        ctx.obs_fit.pose_group,
        folds=ctx.options.folds,
        seed=ctx.options.seed,
    )
    return any(r.significant for r in found)


def _with_step_at(fit: FitResult, step_at: float) -> FitResult:
    effects = dataclasses.replace(fit.effects, step_at=step_at)
    return dataclasses.replace(fit, effects=effects)


def _structure(ctx: Context, dataset: Dataset, steps: list[Step]) -> list[StructureResult]:
    """The remainder of the final model (check rows; fit rows out of fold) against each variable."""
    final = final_step(steps)
    names = [n for s in steps if s.significant and s.effect != "geometric" for n in s.names]
    lp = ctx.problem(final.fit, names)
    resid = np.empty_like(ctx.obs.xyz_mm)
    fit_rows, check_rows = ctx.fit_rows, ctx.check_rows
    resid[fit_rows] = lp.oof_residuals(ctx.own_cols(len(names)))
    obs_check = at_fit(ctx.obs_check, final.fit)
    resid[check_rows] = obs_check.xyz_mm - predict_mm(
        ctx.mass, final.fit.params, final.fit.effects, obs_check
    )
    obs = ctx.obs
    copies = len(obs) // len(dataset)  # the targets per pose: their rows follow one another
    columns: dict[str, FloatArray | None] = {}
    if obs.clock_name == "t_s":
        columns["t_s"] = np.tile(np.asarray(dataset.t_s, dtype=float), copies)
    else:
        columns["pose_order"] = np.tile(np.arange(len(dataset), dtype=float), copies)
    for j in JOINTS:
        columns[f"a{j}"] = obs.a_deg[:, j - 1]
    columns["payload_kg"] = obs.payload_kg
    columns["temp_c"] = obs.temp_c
    for j in JOINTS:
        columns[f"dir{j}"] = None if obs.dir is None else obs.dir[:, j - 1]
    return residual_structure(resid, columns, obs.pose_group, folds=ctx.options.folds, seed=ctx.options.seed)


def _agreement(
    ctx: Context,
    obs: MeasuredRows,
    fit_rows: NDArray[np.int64],
    check_rows: NDArray[np.int64],
    dataset: Dataset,
    steps: list[Step],
) -> Agreement:
    """Whether the fit and check rows agree along the ladder (:mod:`comp_daemon.diagnosis.agreement`),
    on the TCP's rows ``obs``."""
    ladder = [steps[0], *(s for s in steps[1:] if s.significant)]
    final = final_step(steps)
    predicted = predict_mm(ctx.mass, final.fit.params, final.fit.effects, obs.take(check_rows))
    return fit_check_agreement(
        [s.check_rms_mm for s in ladder],
        [s.cv_rms_mm for s in ladder],
        obs,
        fit_rows,
        check_rows,
        predicted,
        dataset,
    )


def _probe_targets(
    dataset: Dataset, tracker_sigma_mm: float | None, probe_sigma_deg: float
) -> FloatArray | None:
    """(n, 3, 3) a 6-DOF probe's orientation as points along its axes
    (:func:`~comp_daemon.models.observations.probe_axis_points_mm`), at the lever that weighs it
    against the positions by the declared σ (``--tracker-sigma-mm``, else the ``sigma_mm``
    column, else the default); None without ``qw…qz``."""
    if dataset.probe_q_wxyz is None or dataset.xyz_mm is None:
        return None
    sigma = tracker_sigma_mm if tracker_sigma_mm is not None else dataset.sigma_mm
    lever = orientation_weight(sigma, probe_sigma_deg)
    return probe_axis_points_mm(dataset.xyz_mm, dataset.probe_q_wxyz, lever)


def _orientation_words(probe_sigma_deg: float) -> str:
    return (
        "a 6-DOF probe's orientation (qw..qz) enters the geometric step as three further targets "
        f"along its axes, weighted against the positions by the declared sigmas (orientation "
        f"{probe_sigma_deg:g} deg per axis)"
    )


def _every_target(
    prepared: PreparedCampaign, mass: MassModel, start: FitResult, tracker_sigma_mm: float | None
) -> tuple[MeasuredRows, NDArray[np.int64], NDArray[np.int64], bool]:
    """The rows of every target (:meth:`MeasuredRows.stack_targets`: the data set's further
    reflectors, then a 6-DOF probe's orientation as three further targets along its axes, each at
    its place on the flange of the twin ``start``), their fit and check rows, and whether the
    probe's orientation is among them. The rows as they are with one target and no probe."""
    obs, fit_rows, check_rows = prepared.measured, prepared.fit_rows, prepared.check_rows
    more = prepared.dataset.more_xyz_mm
    probe = _probe_targets(prepared.dataset, tracker_sigma_mm, prepared.probe_sigma_deg)
    if probe is not None:
        more = probe if more is None else np.concatenate([more, probe], axis=1)
    if more is None:
        return obs, fit_rows, check_rows, False
    offsets = target_offsets_mm(mass, start, obs.take(fit_rows), more[fit_rows])
    k, n = 1 + more.shape[1], len(obs)
    return (
        obs.stack_targets(np.asarray(more, dtype=float), offsets),
        np.concatenate([fit_rows + i * n for i in range(k)]),
        np.concatenate([check_rows + i * n for i in range(k)]),
        probe is not None,
    )


def _preparation(options: DiagnoseOptions) -> PrepareOptions:
    """How the diagnosis prepares a campaign: directions inferred when the file has none, and at
    least as many fit rows as the geometric step has parameters."""
    return PrepareOptions(
        frame=options.frame,
        need_directions=True,
        infer_directions=options.infer_directions,
        min_fit_rows=N_PARAMS,
        min_fit_rows_for="parameters of the geometric step",
        seed=options.seed,
        check_fraction=options.check_fraction,
        probe_sigma_deg=options.probe_sigma_deg,
    )


def _free_geometry(
    mass: MassModel, start: FitResult, obs_fit: MeasuredRows
) -> tuple[NDArray[np.bool_], list[str], FloatArray]:
    """The geometric step's free entries (mask of 39: the identifiable ones at the fit rows, in MDH
    priority, with the targets' places profiled out), the others in words, and the identification
    Jacobian (n, 3, 39) of ``start`` there."""
    _, jac0, tcols0 = linearize_targets(mass, start.params, start.effects, [], obs_fit)
    (jac0_free,) = project_out(tcols0, jac0)
    ident = analyze_identifiability(jac0_free, PARAM_NAMES, priority=mdh_priority(start.params))
    geo_free = np.zeros(N_PARAMS, dtype=bool)
    geo_free[ident.identifiable_index] = True
    return geo_free, [r.describe() for r in ident.removed], jac0


def _candidates(options: DiagnoseOptions, searched: int) -> list[Candidate]:
    """The candidates tried (``options.effects``, else every one); the step's carry the number of
    moments searched."""
    return [
        dataclasses.replace(c, searched=searched) if c.effect == "step" else c
        for c in all_candidates(options.harmonics)
        if options.effects is None or c.effect in options.effects
    ]


def _remainder(ctx: Context, steps: list[Step]) -> RemainderModel:
    """The joint-space remainder model on top of the final step, kept only if it wins out of fold."""
    if not ctx.options.remainder_model:
        return RemainderModel(False, False, "not asked for (DiagnoseOptions.remainder_model)")
    final = final_step(steps)
    names = [n for s in steps if s.significant and s.effect != "geometric" for n in s.names]
    lp = ctx.problem(final.fit, names, tcp_only=True)  # a function of the axes: the TCP's rows
    obs_check = ctx.obs_check_tcp
    resid_check = obs_check.xyz_mm - predict_mm(ctx.mass, final.fit.params, final.fit.effects, obs_check)
    return judge_remainder(
        lp,
        ctx.own_cols(len(names)),
        ctx.obs_fit.a_deg[ctx.tcp_fit],
        lp.r,
        obs_check.a_deg,
        resid_check,
        seed=ctx.options.seed,
    )


def _geo_pvalue(start: FitResult, ctx: Context, geo_cols: list[int]) -> float:
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
    ctx: Context,
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
    cols = list(range(ctx.n_base + len(names)))
    tested = cols[ctx.n_base + len(names_before) :]
    return Step(
        effect=effect,
        joints=joints,
        significant=significant,
        check_rms_mm=rms,
        check_max_mm=mx,
        shrink_pct=_shrink(before, rms),
        params=effect_params_json(effect, joints, fit.effects),
        fit_rms_mm=fit.rms_mm,
        cv_rms_mm=lp.cv_rms_mm(ctx.own_cols(len(names))),
        p_value=lp.wald(cols, tested, ctx.values(fit, start, names)).p_value,
        n_params=len(ctx.geo_idx) + len(names),
        fit=fit,
        names=tuple(new),
    )
