"""``comp-daemon data check``: validate a data set file against a robot and summarise it as JSON.

Exit 0 with a JSON summary on stdout when the file is accepted; exit 2 when it is refused, with
the reason (row, column, fault) on stderr and as JSON (``"ok": false``) on stdout. Measured
positions that cannot be millimetres of the robot (metres, inches …) are refused by the same rule
as ``fit`` and ``diagnose`` (:func:`comp_daemon.models.units.millimetre_problem`). Files ending
in ``.json`` are read as JSON records, anything else as CSV.

:func:`reader_options` adds the options that say how a file from another tool is written
(``--delimiter``, ``--decimal-comma``, ``--units``, ``--euler``; :mod:`comp_daemon.data.options`) to every
command that reads a campaign or a target file; :func:`read_options_of` turns them into
:class:`~comp_daemon.data.options.ReadOptions`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from comp_daemon.data.dataset import DatasetError, read_dataset_file
from comp_daemon.data.options import DELIMITERS, ReadOptions
from comp_daemon.models.units import millimetre_problem
from comp_daemon.robot.description import PRESETS, load_robot


def register(subparsers: argparse._SubParsersAction) -> None:
    data = subparsers.add_parser("data", help="measurement data sets: check a file")
    sub = data.add_subparsers(dest="data_command", metavar="DATA_COMMAND", required=True)

    check = sub.add_parser(
        "check",
        help="validate a data set (CSV, or JSON records if FILE ends in .json) and print a JSON summary",
    )
    check.add_argument("file", metavar="FILE", help="data set file (CSV per docs/data-format.md, or .json)")
    check.add_argument(
        "--robot",
        required=True,
        help=f"preset ({', '.join(PRESETS)}) or path to a TOML or URDF file (axis limits)",
    )
    check.add_argument(
        "--kind",
        choices=("measurement", "targets", "any"),
        default="measurement",
        help="measurement data needs a1..a6 and x, y, z; targets need a1..a6 or tx, ty, tz "
        "(default: measurement)",
    )
    check.add_argument(
        "--min-rows", type=int, default=0, help="refuse fewer rows than this (a model's parameter count)"
    )
    reader_options(check)
    check.set_defaults(func=_check)


def reader_options(parser: argparse.ArgumentParser) -> None:
    """``--delimiter``, ``--decimal-comma``, ``--units`` and ``--euler``: how the data file is written."""
    group = parser.add_argument_group("how the data file is written (default: the data set format)")
    group.add_argument(
        "--delimiter",
        choices=tuple(DELIMITERS),
        default=None,
        help="field separator of a CSV file: ',' (default), ';' or tab",
    )
    group.add_argument(
        "--decimal-comma",
        action="store_true",
        help="numbers with ',' as the decimal mark (fields then separated by ';' unless --delimiter says "
        "tab)",
    )
    group.add_argument(
        "--units",
        default=None,
        metavar="LENGTH,ANGLE",
        help="units of the file's positions (mm or m) and angles (deg or rad), e.g. m,rad; default mm,deg. "
        "Stating it also turns off the refusal of files that look like metres or radians",
    )
    group.add_argument(
        "--euler",
        default=None,
        metavar="CONVENTION",
        help="a 6-DOF probe's orientation as Euler angles in columns e1, e2, e3 (the first, second, third "
        "rotation), e.g. intrinsic-zyx (R = Rz(e1) Ry(e2) Rx(e3), KUKA's A, B, C) or extrinsic-xyz; "
        "angles in --units' unit unless it ends in -deg or -rad. Read into qw, qx, qy, qz",
    )


def read_options_of(args: argparse.Namespace) -> ReadOptions:
    """The :class:`ReadOptions` of a command's ``--delimiter``, ``--decimal-comma``, ``--units``,
    ``--euler``."""
    return ReadOptions.of(args.delimiter, args.decimal_comma, args.units, args.euler)


def _check(args: argparse.Namespace) -> int:
    robot = load_robot(args.robot)
    path = Path(args.file)
    options = read_options_of(args)
    try:
        dataset = read_dataset_file(
            path, limits_deg=robot.axis_limits_deg, min_rows=args.min_rows, kind=args.kind, options=options
        )
    except DatasetError as exc:
        return _refuse(str(exc), exc.row, exc.column)
    if dataset.a_deg is not None and dataset.xyz_mm is not None:
        units = millimetre_problem(robot, dataset.a_deg, dataset.xyz_mm, dataset.station)
        if units is not None:  # the rule fit and diagnose refuse by
            return _refuse(f"{dataset.source}: {units}", None, "x, y, z")
    summary: dict[str, Any] = {"ok": True, "robot": robot.name, "kind": args.kind, **dataset.summary()}
    if not options.is_default:
        summary["read_as"] = options.describe()
    if dataset.split is None and len(dataset) >= 2:
        choice = dataset.split_or_draw()
        summary["split"]["drawn"] = {
            "fit": len(choice.fit_rows),
            "check": len(choice.check_rows),
            "seed": choice.seed,
            "check_rows": [int(r) for r in dataset.row_numbers[choice.check_rows]],
        }
    print(json.dumps(summary, indent=2))
    return 0


def _refuse(error: str, row: int | None, column: str | None) -> int:
    print(json.dumps({"ok": False, "error": error, "row": row, "column": column}, indent=2))
    print(f"comp-daemon data check: error: {error}", file=sys.stderr)
    return 2
