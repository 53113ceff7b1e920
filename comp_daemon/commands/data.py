"""``comp-daemon data check``: validate a data set file against a robot and summarise it as JSON.

Exit 0 with a JSON summary on stdout when the file is accepted; exit 2 when it is refused, with
the reason (row, column, fault) on stderr and as JSON (``"ok": false``) on stdout. Files ending
in ``.json`` are read as JSON records, anything else as CSV.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from comp_daemon.data.dataset import DatasetError, read_dataset, read_dataset_json
from comp_daemon.robot.description import PRESETS, load_robot


def register(subparsers: argparse._SubParsersAction) -> None:
    data = subparsers.add_parser("data", help="measurement data sets: check a file")
    sub = data.add_subparsers(dest="data_command", metavar="DATA_COMMAND", required=True)

    check = sub.add_parser(
        "check",
        help="validate a data set (CSV, or JSON records if FILE ends in .json) and print a JSON summary",
    )
    check.add_argument("file", metavar="FILE", help="data set file (CSV per the data set spec, or .json)")
    check.add_argument(
        "--robot", required=True, help=f"preset ({', '.join(PRESETS)}) or path to a TOML or URDF file (axis limits)"
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
    check.set_defaults(func=_check)


def _check(args: argparse.Namespace) -> int:
    robot = load_robot(args.robot)
    path = Path(args.file)
    reader = read_dataset_json if path.suffix.lower() == ".json" else read_dataset
    try:
        dataset = reader(path, limits_deg=robot.axis_limits_deg, min_rows=args.min_rows, kind=args.kind)
    except DatasetError as exc:
        refusal = {"ok": False, "error": str(exc), "row": exc.row, "column": exc.column}
        print(json.dumps(refusal, indent=2))
        print(f"comp-daemon data check: error: {exc}", file=sys.stderr)
        return 2
    summary: dict[str, Any] = {"ok": True, "robot": robot.name, "kind": args.kind, **dataset.summary()}
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
