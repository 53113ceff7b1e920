"""``comp-daemon compensate``: compensated axis values for targets, by a fitted model.

``compensate MODEL.json TARGETS.csv --out CORRECTED.csv`` writes, for every target, the axis values
whose predicted TCP (by the model) is the wanted one, and, where the model has one, the 3-D 1-σ
uncertainty of that prediction (``predicted_sigma_mm``, :meth:`ErrorModel.predict_std_mm`). Targets are
``a1..a6`` (the nominal program) or ``tx, ty, tz[, ta, tb, tc]`` (robot base frame). The options
(:func:`compensation_options`) and :func:`compensate_targets` are shared with ``export targets``.

A program of a thousand holes is not thrown away for one bad row: :func:`compensate_rows` compensates
every row it can and lists each refused one (its row in the file, the column when one is at fault,
what is wrong) on stderr and, with ``--refused``, in a CSV file. The output holds the compensated
rows, each with its ``target_row`` in the target file. Exit status: 0 when every row was compensated,
:data:`SOME_REFUSED` (3) when some were refused, 2 when none could be (or the file itself is refused:
its header, a missing column, not CSV).
"""

from __future__ import annotations

import argparse
import csv
import io
import sys
from dataclasses import dataclass

import numpy as np

from comp_daemon.commands.data import read_options_of, reader_options
from comp_daemon.commands.errors import UserError
from comp_daemon.common.atomic import write_text_atomic
from comp_daemon.data.dataset import Dataset, DatasetError, write_dataset
from comp_daemon.data.rowwise import RowRefusal, read_rows
from comp_daemon.kinematics.inverse import UnreachableTargetError
from comp_daemon.kinematics.kuka_abc import flange_rotation_of_tool_abc
from comp_daemon.models.artifact import ModelArtifactError, load_model
from comp_daemon.models.base import ErrorModel, uses_approach_directions
from comp_daemon.models.chebyshev import ChebyshevModel
from comp_daemon.models.compensation import (
    DEFAULT_LIMITS,
    MAPPINGS,
    RENAMED_MAPPINGS,
    CompensationLimits,
    CompensationRefused,
    CompensationResult,
    compensate,
    nominal_targets,
    renamed_mapping_note,
)
from comp_daemon.preparation.campaign import prepare_directions
from comp_daemon.robot.description import load_robot

__all__ = [
    "SOME_REFUSED",
    "CompensatedRows",
    "compensate_rows",
    "compensate_targets",
    "compensation_options",
    "register",
]

#: exit status when some rows were compensated and others refused (0: all; 2: none, or a bad file)
SOME_REFUSED = 3


def register(subparsers: argparse._SubParsersAction) -> None:
    comp = subparsers.add_parser("compensate", help="compensated axis values for targets, by a model")
    comp.add_argument("model", metavar="MODEL.json", help="model artifact written by 'fit'")
    comp.add_argument(
        "targets",
        metavar="TARGETS.csv",
        help="targets: a1..a6 (nominal program) or tx,ty,tz[,ta,tb,tc] (robot base frame, mm / KUKA deg)",
    )
    comp.add_argument("--out", required=True, metavar="CORRECTED.csv", help="data set of compensated targets")
    comp.add_argument("--robot", default=None, help="refuse the model unless it belongs to this robot")
    comp.add_argument(
        "--refused",
        default=None,
        metavar="REFUSED.csv",
        help="also write the refused rows here (row, column, reason); they are always listed on stderr",
    )
    compensation_options(comp)
    reader_options(comp)
    comp.set_defaults(func=_compensate)


def compensation_options(parser: argparse.ArgumentParser) -> None:
    """The options of ``compensate`` (tolerance, limits, joint mapping), also taken by ``export targets``."""
    parser.add_argument(
        "--tol-mm", type=float, default=1e-6, help="predicted-position tolerance (default 1e-6 mm)"
    )
    parser.add_argument(
        "--max-axis-change-deg",
        type=float,
        default=DEFAULT_LIMITS.max_axis_change_deg,
        help="refuse a target whose compensation changes an axis by more than this from the nominal "
        f"solution (default {DEFAULT_LIMITS.max_axis_change_deg:g})",
    )
    parser.add_argument(
        "--wrist-singularity-deg",
        type=float,
        default=DEFAULT_LIMITS.wrist_singularity_deg,
        help="refuse a target whose axes 4 and 6 are nearer than this to in line, |A5| on a KUKA wrist "
        f"(default {DEFAULT_LIMITS.wrist_singularity_deg:g})",
    )
    parser.add_argument(
        "--hull-margin-deg",
        type=float,
        default=DEFAULT_LIMITS.hull_margin_deg,
        help="refuse a target this far beyond the model's sampled axis ranges "
        f"(default {DEFAULT_LIMITS.hull_margin_deg:g})",
    )
    parser.add_argument(
        "--mapping",
        type=_mapping_arg,
        default="six-axis",
        metavar="{" + ",".join(MAPPINGS) + "}",
        help="six-axis: inverse kinematics of every axis (default); three-axis: seed 000's mapping of "
        "the predicted error onto joints 1-3, the wrist from the nominal solution (formerly seed000)",
    )


def _mapping_arg(text: str) -> str:
    """A joint mapping; a former name (:data:`RENAMED_MAPPINGS`) is read as its new one, with a note."""
    if text in RENAMED_MAPPINGS:
        print(f"--mapping: {renamed_mapping_note(text)}", file=sys.stderr)
        return RENAMED_MAPPINGS[text]
    if text not in MAPPINGS:
        raise argparse.ArgumentTypeError(f"expected one of {', '.join(MAPPINGS)}, got {text!r}")
    return text


def _compensate(args: argparse.Namespace) -> int:
    robot = load_robot(args.robot) if args.robot else None
    try:
        loaded = load_model(args.model, robot)
    except ModelArtifactError as exc:
        raise UserError(str(exc)) from None
    model = loaded.model
    done = compensate_rows(model, args.targets, args)
    if args.refused is not None:
        _write_refusals(args.refused, done.refused)
    for refusal in done.refused:
        print(f"{args.targets}: refused {refusal}", file=sys.stderr)
    if done.targets is None:
        raise UserError(f"{args.targets}: no target could be compensated ({len(done.refused)} refused)")
    if done.dir is None and uses_approach_directions(model):
        print(
            f"{done.targets.source}: no dir1..dir6 columns: the model's backlash is not applied (approach "
            "directions unknown); give the direction each axis will approach its target from"
        )
    write_dataset(_compensated_table(done, model, args.out), args.out)
    print(_summary(done, model, args.mapping, args.out))
    return SOME_REFUSED if done.refused else 0


def _compensated_table(done: CompensatedRows, model: ErrorModel, source: str) -> Dataset:
    """The compensated target file: each target with its compensated axes and, as further columns,
    its row in the target file, the axis changes ``da1..da6``, the predicted error, the predicted
    3-D 1-σ uncertainty (a model that has one) and the model's kind."""
    targets, result = done.targets, done.result
    assert targets is not None and result is not None
    extra = dict(targets.extra)
    extra["target_row"] = tuple(str(int(r)) for r in targets.row_numbers)
    for k in range(6):
        extra[f"da{k + 1}"] = tuple(repr(float(v)) for v in result.da_deg[:, k])
    extra["predicted_error_mm"] = tuple(repr(float(v)) for v in result.residual_mm)
    sigma = model.predict_std_mm(result.a_deg, done.dir, targets.payload_kg, targets.temp_c)
    if sigma is not None:  # 3-D 1-sigma uncertainty of the model's TCP at the compensated axes
        extra["predicted_sigma_mm"] = tuple(repr(float(v)) for v in np.sqrt(np.sum(sigma**2, axis=1)))
    extra["model_kind"] = (model.kind,) * len(targets)
    return Dataset(
        a_deg=result.a_deg,
        dir=targets.dir,
        payload_kg=targets.payload_kg,
        temp_c=targets.temp_c,
        pose_id=targets.pose_id,
        target_xyz_mm=done.wanted,
        target_abc_deg=targets.target_abc_deg,
        extra=extra,
        source=source,
    )


def _summary(done: CompensatedRows, model: ErrorModel, mapping: str, out: str) -> str:
    """The line ``compensate`` ends with: how many, how far the axes moved, the region kept to."""
    targets, result, limits = done.targets, done.result, done.limits
    assert targets is not None and result is not None and limits is not None
    outside = ""
    if isinstance(model, ChebyshevModel) and model.order > 0:
        n_out = int(model.outside_range(result.a_deg).sum())
        if n_out:
            outside = f"; {n_out} outside the fitted joint ranges (error held at the range edge)"
    da = np.abs(result.da_deg)
    worst_axis = int(np.argmax(da.max(axis=0)))
    region = (
        f"within {limits.hull_margin_deg:g} deg of the model's sampled axis ranges"
        if result.region_deg is not None
        else f"the {model.kind} model has no sampled region to keep to"
    )
    refused = f"; {len(done.refused)} refused (listed on stderr)" if done.refused else ""
    return (
        f"{len(targets)} targets compensated with the {model.kind} model ({mapping} mapping) "
        f"in {result.iterations} iterations "
        f"(max predicted error {result.residual_mm.max():.2e} mm, "
        f"max axis change {da.max():.4f} deg on A{worst_axis + 1} from the nominal solution; {region})"
        f"{outside}{refused} -> {out}"
    )


@dataclass(frozen=True)
class CompensatedRows:
    """A target file's compensated rows and its refused ones (reading and compensation), by row.

    ``targets`` holds the compensated rows only (``row_numbers`` those of the file), ``wanted`` their
    wanted TCPs (robot base frame) and ``result`` their compensation; all three are None when no row
    could be compensated.
    """

    targets: Dataset | None
    wanted: np.ndarray | None
    result: CompensationResult | None
    limits: CompensationLimits | None
    refused: tuple[RowRefusal, ...]
    dir: np.ndarray | None = None  # the compensated rows' approach directions (0 where unknown)


def compensate_rows(model: ErrorModel, path: str, args: argparse.Namespace) -> CompensatedRows:
    """Read the target file at ``path`` row by row (:func:`comp_daemon.data.rowwise.read_rows`) and
    compensate every row the reader accepts, with the options of :func:`compensation_options`.

    A row the reader refuses, an unreachable one, one the limits refuse and one whose compensation
    does not converge within ``--tol-mm`` are set aside with the reason; the others are compensated
    (each target's compensation is independent of the others'). A fault that is not one row's (the
    header, a missing column) refuses the file: :class:`UserError`.
    """
    try:
        read = read_rows(
            path, limits_deg=model.robot.axis_limits_deg, kind="targets", options=read_options_of(args)
        )
    except DatasetError as exc:
        raise UserError(str(exc)) from None
    limits = _limits(args)
    refused = {r.row: r for r in read.refused}
    if read.dataset is None:
        return CompensatedRows(None, None, None, None, read.refused)
    # a nominal program (a1..a6) is run in its row order (the refused rows left out): its directions
    # are that order's, as a fit's
    targets, directions = prepare_directions(read.dataset, need=uses_approach_directions(model))
    if directions.note:
        print(f"{targets.source}: {directions.note}")
    dir_ = _directions(targets, directions.unknown)  # unknown inferred ones 0: no backlash offset
    wanted, rot, seed = _wanted(model, targets)
    keep = np.arange(len(targets))
    while keep.size:
        try:
            result = compensate(
                model,
                wanted[keep],
                _take(rot, keep),
                a_seed_deg=_take(seed, keep),
                dir=_take(dir_, keep),
                payload_kg=_take(targets.payload_kg, keep),
                temp_c=_take(targets.temp_c, keep),
                tol_mm=args.tol_mm,
                limits=limits,
                mapping=args.mapping,
            )
        except UnreachableTargetError as exc:
            out = {
                int(i): f"unreachable within joint limits (left {e:.3f} mm)"
                for i, e in zip(exc.indices, exc.position_error_mm, strict=True)
            }
        except CompensationRefused as exc:
            out = {r.index: r.reason for r in exc.refusals}
        else:
            out = {}
            if not result.converged:
                out = {
                    int(i): f"compensation did not converge ({result.residual_mm[i]:.3g} mm left after "
                    f"{result.iterations} iterations; --tol-mm {args.tol_mm:g})"
                    for i in np.flatnonzero(result.residual_mm > args.tol_mm)
                }
            if not out:
                done = targets.subset(keep)
                dir_kept = _take(dir_, keep)
                return CompensatedRows(done, wanted[keep], result, limits, _by_row(refused), dir_kept)
        for i, reason in out.items():
            row = int(targets.row_numbers[keep[i]])
            refused[row] = RowRefusal(row, None, reason, read.row_label)
        keep = np.delete(keep, sorted(out))
    return CompensatedRows(None, None, None, None, _by_row(refused))


def _take(a: np.ndarray | None, keep: np.ndarray) -> np.ndarray | None:
    return None if a is None else np.asarray(a)[keep]


def _by_row(refused: dict[int, RowRefusal]) -> tuple[RowRefusal, ...]:
    return tuple(refused[row] for row in sorted(refused))


def _write_refusals(path: str, refused: tuple[RowRefusal, ...]) -> None:
    """The refused rows as CSV: ``row, column, reason`` (column empty when the row as a whole is)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(("row", "column", "reason"))
    writer.writerows((r.row, r.column or "", r.problem) for r in refused)
    write_text_atomic(path, buffer.getvalue())


def _limits(args: argparse.Namespace) -> CompensationLimits:
    try:
        return CompensationLimits(args.max_axis_change_deg, args.wrist_singularity_deg, args.hull_margin_deg)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def _wanted(model: ErrorModel, targets: Dataset) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """The wanted TCPs (n, 3), orientations (n, 3, 3) or None, and the inverse kinematics' seeds
    (n, 6) of a target file's rows: ``tx, ty, tz[, ta, tb, tc]``, or ``a1..a6`` (nominal program)."""
    n = len(targets)
    if targets.target_xyz_mm is not None:
        wanted = np.asarray(targets.target_xyz_mm)
        rot = None
        if targets.target_abc_deg is not None:
            rot = flange_rotation_of_tool_abc(targets.target_abc_deg)
        seed = targets.a_deg
        if seed is None:
            seed = np.broadcast_to(model.robot.axis_limits_deg.mean(axis=1), (n, 6))
        return wanted, rot, np.asarray(seed)
    assert targets.a_deg is not None
    wanted, rot = nominal_targets(model, targets.a_deg)
    return wanted, rot, targets.a_deg


def _directions(targets: Dataset, unknown_dir: np.ndarray | None) -> np.ndarray | None:
    """The targets' approach directions as floats, 0 where an inferred one is unknown."""
    if targets.dir is None:
        return None
    dir_ = targets.dir.astype(float)
    if unknown_dir is not None:
        dir_[unknown_dir] = 0.0
    return dir_


def compensate_targets(
    model: ErrorModel, targets: Dataset, args: argparse.Namespace, unknown_dir: np.ndarray | None = None
) -> tuple[np.ndarray, CompensationResult, CompensationLimits]:
    """The wanted TCPs (robot base frame), the compensation and its limits of a target file's rows
    (``a1..a6`` nominal program, or ``tx, ty, tz[, ta, tb, tc]``) by :func:`compensate`, with the
    options of :func:`compensation_options`; refusals, unreachable and unconverged targets as
    :class:`UserError` naming the rows. ``unknown_dir`` marks inferred approach directions that
    are unknown (no backlash offset there)."""
    if len(targets) == 0:
        raise UserError(f"{targets.source}: no targets")
    wanted, rot, seed = _wanted(model, targets)
    limits = _limits(args)
    dir_ = _directions(targets, unknown_dir)
    try:
        result = compensate(
            model,
            wanted,
            rot,
            a_seed_deg=seed,
            dir=dir_,
            payload_kg=targets.payload_kg,
            temp_c=targets.temp_c,
            tol_mm=args.tol_mm,
            limits=limits,
            mapping=args.mapping,
        )
    except UnreachableTargetError as exc:
        rows = ", ".join(
            f"row {int(targets.row_numbers[i])} (left {e:.3f} mm)"
            for i, e in zip(exc.indices[:5], exc.position_error_mm[:5], strict=False)
        )
        more = f" and {len(exc.indices) - 5} more" if len(exc.indices) > 5 else ""
        raise UserError(f"{targets.source}: unreachable within joint limits: {rows}{more}") from None
    except CompensationRefused as exc:
        rows = "; ".join(f"row {int(targets.row_numbers[r.index])}: {r.reason}" for r in exc.refusals[:5])
        more = f"; and {len(exc.refusals) - 5} more" if len(exc.refusals) > 5 else ""
        raise UserError(f"{targets.source}: compensation refused: {rows}{more}") from None
    if not result.converged:
        worst = int(np.argmax(result.residual_mm))
        raise UserError(
            f"{targets.source}: compensation did not converge (row {int(targets.row_numbers[worst])}: "
            f"{result.residual_mm[worst]:.3g} mm left after {result.iterations} iterations)"
        )
    return wanted, result, limits
