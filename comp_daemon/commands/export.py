"""``comp-daemon export params | targets``: a model in the controller's own form.

- ``export params --model MODEL.json --format kuka|abb|csv|urdf -o FILE [--data DATA]`` lists a
  kinematic model's identified parameters (``kinematic``, ``kinematic+ratio+backlash`` …) for a
  KUKA or ABB engineer to review, or as CSV with the nominal value, the change and the 1-σ of each
  (:mod:`comp_daemon.export.params`), or writes its calibrated geometry as a URDF
  (:mod:`comp_daemon.export.urdf`); ``--data`` adds the RMS on the data set's check rows
  to the header.
- ``export targets --model MODEL.json --targets TARGETS.csv --format krl|rapid|csv -o FILE``
  compensates the targets as ``compensate`` does (the same refusals and options; any model kind)
  and writes the compensated axis values with the nominal Cartesian target, one named point a
  target (:mod:`comp_daemon.export.targets`).

Both read their output back before they finish and refuse to leave a file that does not give the
values it was written from (parameters: the same TCP to 1e-6 mm at the model's corner poses;
targets: the same axis values to 1e-9 deg). The formats, their fields and units are in
``docs/export.md``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from comp_daemon.commands.compensate import compensate_targets, compensation_options
from comp_daemon.commands.data import read_options_of, reader_options
from comp_daemon.commands.errors import UserError
from comp_daemon.common.atomic import write_text_atomic
from comp_daemon.data.dataset import DatasetError, read_dataset_file
from comp_daemon.export.formats import PARAM_FORMATS, TARGET_FORMATS, params_text, write_targets
from comp_daemon.export.params import listing_of
from comp_daemon.export.targets import TargetList, module_name, point_names
from comp_daemon.export.urdf import urdf_text
from comp_daemon.kinematics.kuka_abc import flange_rotation_of_tool_abc
from comp_daemon.models.artifact import LoadedModel, ModelArtifactError, load_model
from comp_daemon.models.compensation import nominal_targets
from comp_daemon.models.kinematic import KinematicModel
from comp_daemon.preparation.campaign import CampaignError, PrepareOptions, prepare_campaign
from comp_daemon.robot.description import PRESETS, load_robot

__all__ = ["register"]

#: the largest axis difference (deg) a target list read back may have
ROUND_TRIP_DEG = 1e-9


def register(subparsers: argparse._SubParsersAction) -> None:
    export = subparsers.add_parser(
        "export",
        help="a model in the controller's form: KUKA/ABB/CSV parameter listings, KRL/RAPID/CSV target lists",
    )
    sub = export.add_subparsers(dest="export_command", metavar="WHAT", required=True)
    robot_help = (
        f"refuse the model unless it belongs to this robot (preset: {', '.join(PRESETS)}, "
        "or a TOML or URDF file)"
    )

    params = sub.add_parser(
        "params", help="a kinematic model's identified parameters as a reviewable listing"
    )
    params.add_argument(
        "--model", required=True, metavar="MODEL.json", help="model artifact written by 'fit'"
    )
    params.add_argument(
        "--format",
        required=True,
        choices=(*PARAM_FORMATS, "urdf"),
        help="listing format; urdf: the calibrated geometry as a URDF (docs/urdf.md)",
    )
    params.add_argument("-o", "--out", required=True, metavar="FILE", help="listing to write")
    params.add_argument(
        "--data", default=None, metavar="DATA", help="measurement data set: report the RMS on its check rows"
    )
    params.add_argument("--robot", default=None, help=robot_help)
    reader_options(params)
    params.set_defaults(func=_params)

    targets = sub.add_parser("targets", help="compensated targets as a KRL, RAPID or CSV point list")
    targets.add_argument(
        "--model", required=True, metavar="MODEL.json", help="model artifact written by 'fit'"
    )
    targets.add_argument(
        "--targets",
        required=True,
        metavar="TARGETS.csv",
        help="targets: a1..a6 (nominal program) or tx,ty,tz[,ta,tb,tc] (robot base frame, mm / KUKA deg)",
    )
    targets.add_argument("--format", required=True, choices=tuple(TARGET_FORMATS), help="list format")
    targets.add_argument("-o", "--out", required=True, metavar="FILE", help="target list to write")
    targets.add_argument("--robot", default=None, help=robot_help)
    compensation_options(targets)
    reader_options(targets)
    targets.set_defaults(func=_targets)


def _load(args: argparse.Namespace) -> LoadedModel:
    robot = load_robot(args.robot) if args.robot else None
    try:
        return load_model(args.model, robot)
    except ModelArtifactError as exc:
        raise UserError(str(exc)) from None


def _check_rms_mm(loaded: LoadedModel, path: str, args: argparse.Namespace) -> float:
    model = loaded.model
    try:
        data = read_dataset_file(
            path, limits_deg=model.robot.axis_limits_deg, kind="measurement", options=read_options_of(args)
        )
    except DatasetError as exc:
        raise UserError(str(exc)) from None
    try:  # the preparation every door shares: the split, the directions, each station's frame
        prepared = prepare_campaign(data, model.robot, PrepareOptions(need_directions=True))
    except CampaignError as exc:
        raise UserError(str(exc)) from None
    err = prepared.rows(prepared.check_rows).errors(model)
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def _params(args: argparse.Namespace) -> int:
    loaded = _load(args)
    model = loaded.model
    check = _check_rms_mm(loaded, args.data, args) if args.data else None
    try:
        listing = listing_of(model, loaded.document, check)
    except ValueError as exc:
        raise UserError(f"{args.model}: {exc}") from None
    info = listing.info
    assert isinstance(model, KinematicModel)  # listing_of refused the others
    try:
        if args.format == "urdf":
            text, diff = urdf_text(model, listing.info.lines())
        else:
            text, diff = params_text(listing, model, args.format)
    except ValueError as exc:
        raise UserError(f"{args.out}: {exc}; not written") from None
    write_text_atomic(args.out, text)
    print(
        f"{info.model} ({model.robot.name}): {len(text.splitlines())} lines, {args.format} listing "
        f"(read back: TCP within {diff:.1e} mm) -> {args.out}"
    )
    return 0


def _targets(args: argparse.Namespace) -> int:
    loaded = _load(args)
    model = loaded.model
    try:
        targets = read_dataset_file(
            args.targets,
            limits_deg=model.robot.axis_limits_deg,
            kind="targets",
            options=read_options_of(args),
        )
    except DatasetError as exc:
        raise UserError(str(exc)) from None
    wanted, result, _ = compensate_targets(model, targets, args)
    n = len(targets)
    if targets.target_abc_deg is not None:
        flange_R = flange_rotation_of_tool_abc(targets.target_abc_deg)
    else:  # the nominal program's orientation, or where only a position was asked for, the nominal solution's
        _, flange_R = nominal_targets(model, result.a_uncompensated_deg)
    # KRL and RAPID take identifiers; the CSV keeps the pose ids as they were
    names = targets.pose_id if args.format == "csv" and targets.pose_id else point_names(targets.pose_id, n)
    points = TargetList(tuple(names), result.a_deg, np.asarray(wanted), flange_R)
    fit = loaded.document.get("fit", {})
    model_id = str(loaded.document["checksum_sha256"])[:16]
    header = [
        f"comp-daemon compensated targets: {n} points, robot {model.robot.name}",
        f"model: {fit.get('model', model.kind)} (id {model_id}), {args.mapping} mapping, "
        f"max predicted error {result.residual_mm.max():.2e} mm",
    ]
    text = write_targets(args.format, points, module_name(Path(args.out).stem, "CD_TARGETS"), header)
    back = TARGET_FORMATS[args.format](text, args.out)
    diff = float(np.max(np.abs(back.a_deg - points.a_deg)))
    if back.names != points.names or diff > ROUND_TRIP_DEG:
        raise UserError(f"{args.out}: the list read back differs by {diff:.3g} deg; not written")
    write_text_atomic(args.out, text)
    da = np.abs(result.da_deg).max()
    print(
        f"{n} targets compensated with the {model.kind} model ({args.mapping} mapping), "
        f"max axis change {da:.4f} deg, {args.format} list -> {args.out}"
    )
    return 0
