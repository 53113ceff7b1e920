"""``comp-daemon fit | evaluate``: fit error models and compare them (``compensate``:
:mod:`comp_daemon.commands.compensate`).

- ``fit DATA --robot R --model NAME [--order m|cv] --out MODEL.json`` fits one model on the data
  set's fit rows (every row when there is no ``split`` column) and writes the artifact.
- ``evaluate DATA --robot R --models nominal,kinematic,chebyshev|all [--json OUT.json]`` fits each
  model on the fit rows and prints seed 000's Table 2 on the check rows (drawn reproducibly when
  the file has no ``split`` column), sorted by the check rows' 3-D RMS, with each model's fit and
  predict time; ``all`` is every kind and the seeds' stacks
  (:data:`comp_daemon.models.registry.ALL_MODELS`). On a terminal, stderr shows the progress
  (:mod:`comp_daemon.commands.progress`) and a line per model fitted.

On a data set without ``dir1..dir6`` columns, ``fit`` and ``evaluate`` of a model that needs the
approach directions (backlash) derive them from the pose order
(:func:`comp_daemon.preparation.prepare_campaign`, the preparation every door shares) and say so;
``--no-infer-dir`` turns that off.

Model names and kinds are those of :mod:`comp_daemon.models.registry`: ``kind[:order][+effect…]``,
e.g. ``kinematic+ratio+backlash`` (the MDH calibration with seed 001's per-joint reduction-ratio
error and backlash), ``chebyshev:cv``, ``kriging-backlash``, ``compliance``. Files ending in
``.json`` are read as JSON records, anything else as CSV.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import sys
import time
from collections.abc import Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from comp_daemon.commands.campaigns import (
    evaluate_calibrated,
    evaluate_solvers,
    fit_campaign_file,
    is_campaign_file,
)
from comp_daemon.commands.data import read_options_of, reader_options
from comp_daemon.commands.errors import UserError
from comp_daemon.commands.progress import progress
from comp_daemon.common.atomic import write_json_atomic
from comp_daemon.data.dataset import Dataset, DatasetError, read_dataset_file
from comp_daemon.data.options import ReadOptions
from comp_daemon.estimation.selection import selection_line
from comp_daemon.models.artifact import save_model
from comp_daemon.models.chebyshev import ChebyshevModel
from comp_daemon.models.covariance import near_dependent_note
from comp_daemon.models.evaluation import (
    REGISTERED_NOMINAL,
    SEED000_TABLE2_MM,
    error_statistics,
    format_table2,
    outside_fit_ranges,
    registered_nominal,
)
from comp_daemon.models.fitting import FitOptions, FittedModel
from comp_daemon.models.registry import (
    ALL_MODELS,
    KINDS,
    MAX_ORDER,
    ModelSpec,
    UnknownModelError,
    get_kind,
    parse_model_name,
    undetermined_reason,
    uses_directions,
    with_order,
)
from comp_daemon.models.rows import DEFAULT_PROBE_SIGMA_DEG
from comp_daemon.preparation.campaign import CampaignError, PreparedCampaign
from comp_daemon.preparation.pipeline import (
    FitRequest,
    fit_prepared,
    fit_rows_checked,
    prepare_fit,
    prepare_for_models,
)
from comp_daemon.preparation.stations import judge_stations
from comp_daemon.robot.description import PRESETS, RobotDescription, load_robot

__all__ = ["read_data", "register"]

ROBOT_HELP = f"preset ({', '.join(PRESETS)}) or path to a robot TOML file"
MODEL_HELP = (
    f"model kind ({' | '.join(KINDS)}), kind:order for Chebyshev (chebyshev:3, chebyshev:cv), "
    "kinematic+ratio+backlash for seed 001's joint effects"
)
ORDER_HELP = f"Chebyshev order 0..{MAX_ORDER}, or cv (cross-validation); default 3 (seed 000)"
Order = int | Literal["cv"]


def _order_arg(text: str) -> Order:
    if text == "cv":
        return "cv"
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an order 0..{MAX_ORDER} or 'cv', got {text!r}") from None


def _jobs_arg(text: str) -> int:
    if not text.strip().isdigit():
        raise argparse.ArgumentTypeError(f"expected a number of processes (0: one per core), got {text!r}")
    if int(text) > 0:
        return int(text)
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _folds_arg(text: str) -> int:
    if not (text.strip().isdigit() and 2 <= int(text) <= 20):
        raise argparse.ArgumentTypeError(f"expected 2..20 folds, got {text!r}")
    return int(text)


def register(subparsers: argparse._SubParsersAction) -> None:
    fit = subparsers.add_parser("fit", help="fit an error model on a measurement data set, write MODEL.json")
    fit.add_argument(
        "data",
        metavar="DATA",
        help="measurement data set, or a ballbar / cross-bar campaign (CSV, or .json records)",
    )
    fit.add_argument("--robot", required=True, help=ROBOT_HELP)
    fit.add_argument("--model", required=True, help=MODEL_HELP)
    fit.add_argument("--order", type=_order_arg, default=None, help=ORDER_HELP)
    _common(fit)
    fit.add_argument("--out", required=True, help="model artifact to write (JSON)")
    fit.add_argument(
        "--fix-near-dependent",
        action="store_true",
        help="ballbar campaigns: hold the weaker parameter of each near-dependent pair (|correlation| > 0.9) "
        "at zero and fit again (never a pivot offset); the pairs are named either way",
    )
    fit.add_argument(
        "--ridge",
        action="store_true",
        help="ballbar campaigns: pull every POE error toward zero (5 mm of dl or 2 deg of dtheta cost as "
        "much as 1 mm of length residual on one reading); docs/seeds-002-003.md measures it",
    )
    fit.set_defaults(func=_fit)

    ev = subparsers.add_parser(
        "evaluate", help="fit models on fit rows, print seed 000's Table 2 on check rows"
    )
    ev.add_argument("data", metavar="DATA", help="measurement data set (CSV, or .json records)")
    ev.add_argument("--robot", required=True, help=ROBOT_HELP)
    ev.add_argument(
        "--models",
        default="nominal,kinematic,chebyshev",
        help="comma-separated models (default nominal,kinematic,chebyshev; e.g. kinematic+ratio+backlash), "
        f"or all ({', '.join(ALL_MODELS)})",
    )
    ev.add_argument("--order", type=_order_arg, default=None, help=ORDER_HELP)
    ev.add_argument(
        "--jobs",
        type=_jobs_arg,
        default=1,
        metavar="N",
        help="fit the models in N processes side by side (default 1; 0: one per core the process may "
        "use); each uses the numeric threads of --threads",
    )
    _common(ev)
    ev.add_argument("--json", default=None, metavar="OUT.json", help="write the statistics and fits as JSON")
    ev.add_argument(
        "--calibrated",
        default=None,
        metavar="MODEL.json,...",
        help="also judge these artifacts (e.g. fitted from a ballbar or cross-bar campaign) on the check "
        "rows; only their base frame is fitted, on the fit rows",
    )
    ev.add_argument(
        "--solvers",
        default=None,
        metavar="lm,mfo,imfo,woa",
        help="instead of models: compare these solvers on a ballbar campaign's identification, one row "
        "per run (LM once; each metaheuristic per --solver-seeds)",
    )
    ev.add_argument("--agents", type=int, default=100, help="with --solvers: population N (default 100)")
    ev.add_argument("--iterations", type=int, default=300, help="with --solvers: K_max (default 300)")
    ev.add_argument(
        "--solver-seeds", default="0,1", help="with --solvers: comma-separated seeds (default 0,1)"
    )
    ev.set_defaults(func=_evaluate)


def _common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--frame",
        choices=("auto", "base", "tracker"),
        default="auto",
        help="frame of x, y, z: robot base, tracker (registered first), or auto (default)",
    )
    parser.add_argument(
        "--folds", type=_folds_arg, default=5, help="cross-validation folds, 2..20 (default 5)"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the cross-validation folds (default 0)")
    parser.add_argument(
        "--no-infer-dir",
        dest="infer_dir",
        action="store_false",
        help="without dir1..dir6 columns, do not derive the approach directions from the pose order "
        "(models with backlash then refuse the data)",
    )
    parser.add_argument(
        "--probe-sigma-deg",
        type=_probe_sigma_arg,
        default=DEFAULT_PROBE_SIGMA_DEG,
        metavar="DEG",
        help="a 6-DOF probe's orientation uncertainty (σ per axis, deg): weighs its qw..qz against the "
        "positions in the kinematic calibration (default %(default)s)",
    )
    reader_options(parser)


def _probe_sigma_arg(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (np.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected an angle in degrees > 0, got {text!r}")
    return value


def _prepare(
    dataset: Dataset, specs: list[ModelSpec], args: argparse.Namespace, *, hold_out: bool
) -> PreparedCampaign:
    """The campaign prepared for these models (:func:`comp_daemon.preparation.pipeline.prepare_for_models`),
    the refusals as :class:`UserError`."""
    try:
        return prepare_for_models(
            dataset,
            load_robot_cached(args),
            specs,
            frame=args.frame,
            infer_directions=args.infer_dir,
            hold_out=hold_out,
            probe_sigma_deg=args.probe_sigma_deg,
        )
    except CampaignError as exc:
        raise UserError(str(exc)) from None


def _parse_model(token: str, order: Order | None) -> ModelSpec:
    try:
        return with_order(parse_model_name(token), order)
    except UnknownModelError as exc:
        raise UserError(str(exc)) from None


def read_data(
    path: str, robot: RobotDescription, min_rows: int, kind: Any, options: ReadOptions | None = None
) -> Dataset:
    """A data set or target file (``.json`` records, else CSV) checked against the robot's axis limits,
    read with ``options`` (separator, decimal comma, units); the reader's refusals as :class:`UserError`."""
    try:
        return read_dataset_file(
            path, limits_deg=robot.axis_limits_deg, min_rows=min_rows, kind=kind, options=options
        )
    except DatasetError as exc:
        raise UserError(str(exc)) from None


def _fit_checked(
    prepared: PreparedCampaign,
    spec: ModelSpec,
    robot: RobotDescription,
    options: FitOptions,
    rows: np.ndarray,
) -> FittedModel:
    """The pipeline's fit of ``spec`` on ``rows`` (:func:`comp_daemon.preparation.pipeline.fit_rows_checked`),
    its refusals as :class:`UserError` naming the data set."""
    try:
        return fit_rows_checked(prepared, spec, robot, options, rows)
    except CampaignError as exc:
        raise UserError(str(exc)) from None


Judged = tuple[FittedModel, np.ndarray, float, float, int | None]  # fit, check predictions, times


def _fit_and_predict(token: str, spec: ModelSpec, work: tuple[Any, ...]) -> Judged:
    """One model of ``evaluate``: fitted on the fit rows, its predictions of the check rows, the fit's
    and the prediction's time (s), and for a Chebyshev model the check rows outside its range.
    Module level: ``--jobs`` runs it in worker processes."""
    prepared, robot, options, fit_rows, check = work
    t0 = time.perf_counter()
    fitted = _fit_checked(prepared, spec, robot, options, fit_rows)
    t1 = time.perf_counter()
    rows = prepared.rows(check)
    pred = fitted.model.predict_tcp_mm(rows.a_deg, rows.dir, rows.payload_kg, rows.temp_c)
    t2 = time.perf_counter()
    outside = None
    if isinstance(fitted.model, ChebyshevModel):
        outside = int(fitted.model.outside_range(rows.a_deg).sum())
    return fitted, pred, t1 - t0, t2 - t1, outside


def _fit_each(
    models: list[tuple[str, ModelSpec]], work: tuple[Any, ...], jobs: int
) -> Iterator[tuple[str, Judged]]:
    """:func:`_fit_and_predict` of each model, in the given order, on ``jobs`` processes (each with
    the command line's numeric threads, from the environment it inherits); the progress says which
    model is fitted and how many remain."""
    total = len(models)
    rows = len(work[3])
    with progress(f"evaluate: {total} models", total=total) as steps:

        def done(token: str, outcome: Judged, left: int) -> None:
            steps.advance()
            err = work[0].dataset.xyz_mm[work[4]] - outcome[1]
            rms = float(np.sqrt(np.mean(np.sum(err**2, axis=1))))
            steps.log(
                f"{token}: check RMS {rms:.4f} mm, fit {outcome[2]:.2f} s, "
                f"predict {1e3 * outcome[3]:.1f} ms ({left} models left)"
            )

        if jobs <= 1 or total <= 1:
            for i, (token, spec) in enumerate(models):
                steps.note(f"fitting {token} on {rows} rows ({i + 1} of {total}, {total - i - 1} after it)")
                outcome = _fit_and_predict(token, spec, work)
                done(token, outcome, total - i - 1)
                yield token, outcome
            return
        ctx = multiprocessing.get_context("spawn")  # the progress display runs a thread: no fork
        with ProcessPoolExecutor(max_workers=min(jobs, total), mp_context=ctx) as pool:
            futures = {token: pool.submit(_fit_and_predict, token, spec, work) for token, spec in models}
            pending = dict(futures)
            steps.note(f"fitting {', '.join(list(pending)[:jobs])} ({total} models on {jobs} processes)")
            results: dict[str, Judged] = {}
            while pending:
                finished, _ = wait(pending.values(), return_when=FIRST_COMPLETED)
                for token in [t for t, f in pending.items() if f in finished]:
                    results[token] = pending.pop(token).result()
                    done(token, results[token], len(pending))
                if pending:
                    steps.note(f"fitting {', '.join(list(pending)[:jobs])} ({len(pending)} models left)")
            for token, _ in models:
                yield token, results[token]


def load_robot_cached(args: argparse.Namespace) -> RobotDescription:
    robot = getattr(args, "_robot", None)
    if robot is None:
        robot = load_robot(args.robot)
        args._robot = robot
    return robot


def _fit(args: argparse.Namespace) -> int:
    if is_campaign_file(args.data, read_options_of(args)):  # a ballbar or cross-bar campaign
        return fit_campaign_file(args, load_robot_cached(args))
    spec = _parse_model(args.model, args.order)
    robot = load_robot_cached(args)
    dataset = read_data(args.data, robot, 0, "measurement", read_options_of(args))
    request = FitRequest(
        spec,
        frame=args.frame,
        infer_directions=args.infer_dir,
        hold_out=False,
        cv_folds=args.folds,
        seed=args.seed,
        probe_sigma_deg=args.probe_sigma_deg,
    )
    try:
        prepared = prepare_fit(dataset, robot, request)
        for sentence in prepared.describe():
            print(f"{dataset.source}: {sentence}")
        rows = prepared.fit_rows
        with progress(f"fitting {spec.name} on {len(rows)} rows"):
            outcome = fit_prepared(prepared, robot, request)
    except CampaignError as exc:
        raise UserError(str(exc)) from None
    fitted, fit_info = outcome.fitted, outcome.info
    save_model(fitted.model, args.out, data_sha256=prepared.data_sha256, frame=fitted.frame, fit=fit_info)
    order = f", order {fitted.model.order}" if fitted.model.order is not None else ""
    extra = ""
    if "identifiability" in fitted.info:
        ident = fitted.info["identifiability"]
        extra = f", {ident['identifiable']} of {ident['candidates']} parameters identifiable"
    if "targets" in fitted.info:
        extra += f", {fitted.info['targets']} targets per pose ({fitted.info['identification']})"
    print(
        f"{args.model}{order}: {len(rows)} rows ({fitted.frame} frame), "
        f"fit RMS {fitted.info['rms_mm']:.4f} mm{extra} -> {args.out}"
    )
    line = selection_line(fitted.info)
    if line:
        print(f"{args.model}: {line} (out of fold on the fit rows)")
    note = near_dependent_note(fitted.info)
    if note:
        print(f"{args.model}: {note}")
    for warning in ("frame_warning", "mass_warning"):
        if warning in fitted.info:
            print(f"{args.model}: {fitted.info[warning]}")
    return 0


def _evaluate_specs(args: argparse.Namespace) -> list[tuple[str, ModelSpec]]:
    """The models ``--models`` names, parsed (``all``: :data:`ALL_MODELS`, ``--order`` for the plain
    ``chebyshev``)."""
    tokens = [t.strip() for t in args.models.split(",") if t.strip()]
    if not tokens:
        raise UserError("--models: name at least one model")
    if tokens == ["all"]:
        return [(t, _parse_model(t, args.order if t == "chebyshev" else None)) for t in ALL_MODELS]
    if len(set(tokens)) != len(tokens):
        raise UserError("--models: a model is named twice")
    return [(t, _parse_model(t, args.order if get_kind(_head(t)).takes_order else None)) for t in tokens]


@dataclass
class _Evaluation:
    """What ``evaluate`` gathers per model: Table 2 on the check rows, the fit's information, the
    times, and the models left out with the reason."""

    table: dict[str, dict[str, Any]] = field(default_factory=dict)
    fits: dict[str, dict[str, Any]] = field(default_factory=dict)
    timing: dict[str, dict[str, float]] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    predictions: dict[str, np.ndarray] = field(default_factory=dict)  # on the check rows
    station_lines: list[str] = field(default_factory=list)  # a station whose check rows jump
    station_doc: dict[str, Any] = field(default_factory=dict)  # the check rows' error per station


def _evaluate(args: argparse.Namespace) -> int:
    if args.solvers is not None:
        return evaluate_solvers(args, load_robot_cached(args))
    robot = load_robot_cached(args)
    dataset = read_data(args.data, robot, 0, "measurement", read_options_of(args))
    ev = _Evaluation()
    parsed = _determinable(_evaluate_specs(args), robot, dataset, ev)
    prepared = _prepare(dataset, [spec for _, spec in parsed], args, hold_out=True)
    dataset, split = prepared.dataset, prepared.split
    if prepared.directions.note:
        print(f"{dataset.source}: {prepared.directions.note}")
    if args.models.strip() == "all" and dataset.dir is None:
        no_dir = {t: "no dir1..dir6 columns (--no-infer-dir)" for t, spec in parsed if uses_directions(spec)}
        parsed = [(t, spec) for t, spec in parsed if t not in no_dir]
        if no_dir:
            print(f"{dataset.source}: left out (no dir columns): {', '.join(no_dir)}", file=sys.stderr)
        ev.skipped.update(no_dir)
    if split.drawn:
        print(split.message, file=sys.stderr)
    if prepared.still_axes:
        print(f"{dataset.source}: {prepared.still_axes}")
    if prepared.stations is not None:
        print(f"{dataset.source}: {prepared.stations.note}")
    assert dataset.a_deg is not None and dataset.xyz_mm is not None
    extrapolated = outside_fit_ranges(dataset.a_deg[split.fit_rows], dataset.a_deg[split.check_rows])
    _judge(parsed, prepared, robot, args, extrapolated["rows"], ev)
    if "nominal" in ev.table:  # beside the raw nominal row, the one that does not count unknown targets
        _judge_registered_nominal(prepared, robot, extrapolated["rows"], ev)
    if args.calibrated:
        t0 = time.perf_counter()
        check = split.check_rows
        calibrated, calibrated_fits = evaluate_calibrated(
            args.calibrated, robot, dataset, split.fit_rows, check
        )
        for name in calibrated:
            ev.table[name] = calibrated[name]
            ev.fits[name] = calibrated_fits[name]
            ev.timing[name] = {
                "fit_s": 0.0,
                "predict_s": time.perf_counter() - t0,
                "predict_rows": len(check),
            }
    ranking = sorted(ev.table, key=lambda name: ev.table[name]["3d"]["rms"])
    ev.table = {name: ev.table[name] for name in ranking}
    best = next((name for name in ranking if name in ev.predictions), None)
    if best is not None:  # each station's check rows judged by the best model
        check_rows = np.asarray(prepared.split.check_rows, dtype=np.int64)
        ev.station_lines, ev.station_doc = judge_stations(
            prepared.dataset, check_rows, ev.predictions[best], best
        )
    _print_evaluation(prepared, ev, ranking, extrapolated)
    if args.json:
        _write_json(args.json, _evaluation_document(prepared, robot, ev, ranking))
    return 0


def _determinable(
    parsed: list[tuple[str, ModelSpec]], robot: RobotDescription, dataset: Dataset, ev: _Evaluation
) -> list[tuple[str, ModelSpec]]:
    """The models the rows can determine; the others are left out by name (``ev.skipped``) and the
    evaluation goes on with the rest, refused when none is left."""
    for t, spec in parsed:
        reason = undetermined_reason(spec, robot, len(dataset), dataset.payload_kg)
        if reason is not None:
            ev.skipped[t] = reason
    if len(ev.skipped) == len(parsed):
        reasons = "; ".join(f"{t}: {r}" for t, r in ev.skipped.items())
        raise UserError(f"{dataset.source}: {len(dataset)} data rows; no model can be evaluated ({reasons})")
    for token, reason in ev.skipped.items():
        print(f"{dataset.source}: left out {token}: {reason}")
    return [(t, spec) for t, spec in parsed if t not in ev.skipped]


def _judge(
    parsed: list[tuple[str, ModelSpec]],
    prepared: PreparedCampaign,
    robot: RobotDescription,
    args: argparse.Namespace,
    extrapolated_rows: int,
    ev: _Evaluation,
) -> None:
    """Each model fitted on the fit rows (``--jobs`` processes) and judged on the check rows; one
    with fewer fit rows than identifiable parameters is left out."""
    dataset, split = prepared.dataset, prepared.split
    assert dataset.xyz_mm is not None
    check = split.check_rows
    frame_warned = False
    options = FitOptions(frame=prepared.frame, cv_folds=args.folds, seed=args.seed)
    for token, outcome in _fit_each(parsed, (prepared, robot, options, split.fit_rows, check), args.jobs):
        fitted, pred, t_fit, t_pred, outside = outcome
        ev.predictions[token] = pred
        identifiable = fitted.info.get("identifiability", {}).get("identifiable", 0)
        if len(split.fit_rows) < identifiable:
            ev.skipped[token] = (
                f"{len(split.fit_rows)} fit rows for {identifiable} identifiable parameters: not determined"
            )
            print(f"{dataset.source}: left out {token}: {ev.skipped[token]}")
            continue
        ev.table[token] = error_statistics(dataset.xyz_mm[check], pred)
        ev.timing[token] = {"fit_s": t_fit, "predict_s": t_pred, "predict_rows": len(check)}
        ev.fits[token] = {"frame": fitted.frame, **fitted.info}
        if "frame_warning" in fitted.info and not frame_warned:  # the same for every model: once
            print(f"{dataset.source}: {fitted.info['frame_warning']}")
            frame_warned = True
        if "mass_warning" in fitted.info:
            print(f"{dataset.source}: {token}: {fitted.info['mass_warning']}")
        if outside is not None:
            ev.fits[token]["check_rows_outside_range"] = outside
        elif token != "nominal":
            ev.fits[token]["check_rows_outside_range"] = extrapolated_rows


def _judge_registered_nominal(
    prepared: PreparedCampaign, robot: RobotDescription, extrapolated_rows: int, ev: _Evaluation
) -> None:
    """The nominal twin registered to the measurements on the fit rows, judged on the check rows."""
    dataset, fit_rows, check = prepared.dataset, prepared.split.fit_rows, prepared.split.check_rows
    assert dataset.a_deg is not None and dataset.xyz_mm is not None
    t0 = time.perf_counter()
    more = None if dataset.more_xyz_mm is None else dataset.more_xyz_mm[fit_rows]
    reg_model, reg_info = registered_nominal(robot, dataset.a_deg[fit_rows], dataset.xyz_mm[fit_rows], more)
    t1 = time.perf_counter()
    ev.table[REGISTERED_NOMINAL] = error_statistics(
        dataset.xyz_mm[check], reg_model.predict_tcp_mm(dataset.a_deg[check])
    )
    ev.fits[REGISTERED_NOMINAL] = {
        "frame": "registered",
        **reg_info,
        "check_rows_outside_range": extrapolated_rows,
    }
    ev.timing[REGISTERED_NOMINAL] = {
        "fit_s": t1 - t0,
        "predict_s": time.perf_counter() - t1,
        "predict_rows": len(check),
    }


def _print_evaluation(
    prepared: PreparedCampaign, ev: _Evaluation, ranking: list[str], extrapolated: dict[str, Any]
) -> None:
    """Table 2 in ``ranking`` order, the extrapolation, what each selection kept, seed 000's figures."""
    source, split = prepared.source, prepared.split
    check = split.check_rows
    print(
        f"{source}: {len(split.fit_rows)} fit rows, {len(check)} check rows; "
        "error = measured - model (mm); sorted by the check rows' 3-D RMS"
    )
    outside_by_model = {
        name: ev.fits[name]["check_rows_outside_range"]
        for name in ranking
        if "check_rows_outside_range" in ev.fits[name]
    }
    print(format_table2(ev.table, ev.timing, outside_by_model))
    for sentence in ev.station_lines:
        print(f"{source}: {sentence}")
    if extrapolated["rows"]:
        axes = ", ".join(f"{axis} {count}" for axis, count in extrapolated["per_axis"].items())
        print(
            f"extrapolation: {extrapolated['rows']} of {len(check)} check rows lie outside the fit rows' "
            "axis "
            f"ranges ({axes}); 'outside' counts them per model (a fitted polynomial or kriging model "
            "is not to be trusted there)"
        )
    chosen = {name: selection_line(ev.fits[name]) for name in ranking}
    if any(chosen.values()):
        print("kept and dropped out of fold on the fit rows (the check rows unseen):")
        for name, line in chosen.items():
            if line:
                print(f"  {name}: {line}")
    ref = "; ".join(
        f"{k} " + "/".join(f"{s} {v:.2f}" for s, v in row.items()) for k, row in SEED000_TABLE2_MM.items()
    )
    print(f"for reference, seed 000's published Table 2 (its own KR210 campaign of 104 points, 3-D): {ref}")


def _evaluation_document(
    prepared: PreparedCampaign, robot: RobotDescription, ev: _Evaluation, ranking: list[str]
) -> dict[str, Any]:
    """``evaluate --json``'s document."""
    split = prepared.split
    return {
        "data": prepared.source,
        "data_sha256": prepared.data_sha256,
        "robot": {"name": robot.name, "sha256": robot.sha256},
        "split": {
            "drawn": split.drawn,
            "seed": split.seed,
            "fit_rows": len(split.fit_rows),
            "check_rows": len(split.check_rows),
            "message": split.message,
        },
        "directions": prepared.directions.note,
        "stations": None if prepared.stations is None else prepared.stations.to_json(),
        "check_by_station": ev.station_doc or None,
        "error_definition": "measured - predicted, mm; per axis signed mean/std and max |component|; "
        "3-D |error| mean/std/max/rms (seed 000 eq. 27)",
        "ranking": ranking,
        "table2": ev.table,
        "timing": {name: ev.timing[name] for name in ranking},
        "skipped": ev.skipped,
        "fits": ev.fits,
        "seed000_table2_mm": SEED000_TABLE2_MM,
    }


def _head(token: str) -> str:
    """The kind named by a model token (``kinematic+ratio`` -> ``kinematic``), as a user error if unknown."""
    name = token.split("+")[0].partition(":")[0].strip()
    if name not in KINDS:
        raise UserError(f"unknown model '{name}' (known: {', '.join(KINDS)})")
    return name


def _write_json(path: str, doc: dict[str, Any]) -> None:
    write_json_atomic(path, doc, indent=1, default=_json_default)


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
