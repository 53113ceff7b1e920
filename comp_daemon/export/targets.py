"""Compensated target lists for cells that compensate offline: the values, point names and the CSV.

:class:`TargetList` holds, per target, a point name, the compensated axis values (deg, what the
robot is to be moved to) and the nominal Cartesian target (the TCP position in the robot base
frame, mm, and the flange's orientation there — the one asked for, or where none was, that of the
nominal solution). The KRL and RAPID lists are in :mod:`~comp_daemon.export.krl` and
:mod:`~comp_daemon.export.rapid`; the CSV one is here (:func:`format_csv_targets` /
:func:`parse_csv_targets`): the columns of a target file (``docs/data-format.md``), ``pose_id, a1..a6,
tx, ty, tz, ta, tb, tc`` (``ta, tb, tc``: KUKA A, B, C of the tool frame, deg), so that comp-daemon
reads it back as a target file too. Numbers are the shortest decimal that reads back to the same
double.
"""

from __future__ import annotations

import csv
import io
import re
from collections.abc import Collection, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from comp_daemon.export.frames import num
from comp_daemon.kinematics.kuka_abc import flange_rotation_of_tool_abc, tool_abc_of_flange_rotation

__all__ = [
    "CSV_TARGET_COLUMNS",
    "TargetList",
    "format_csv_targets",
    "module_name",
    "paired_names",
    "parse_csv_targets",
    "point_names",
]

CSV_TARGET_COLUMNS = ("pose_id", "a1", "a2", "a3", "a4", "a5", "a6", "tx", "ty", "tz", "ta", "tb", "tc")
MAX_NAME = 20  # KRL names are at most 24 characters, RAPID's 32; the prefixes take the rest
_NAME_CHARS = re.compile(r"[^A-Za-z0-9_]")


@dataclass(frozen=True, slots=True)
class TargetList:
    """n named targets: compensated axis values and the nominal Cartesian target (module docstring)."""

    names: tuple[str, ...]
    a_deg: NDArray[np.float64]  # (n, 6) compensated axis values
    xyz_mm: NDArray[np.float64]  # (n, 3) nominal TCP position, robot base frame
    flange_R: NDArray[np.float64]  # (n, 3, 3) nominal flange orientation, robot base frame

    @property
    def tool_abc_deg(self) -> NDArray[np.float64]:
        """(n, 3) KUKA A, B, C (deg) of the tool frame (x out of the flange) of the nominal target."""
        return tool_abc_of_flange_rotation(self.flange_R)


def point_names(pose_ids: Sequence[str] | None, n: int) -> tuple[str, ...]:
    """Names for KRL and RAPID: the pose ids with every character but letters, digits and ``_``
    replaced by ``_`` and a leading ``P`` where they do not start with a letter; ``P1..Pn`` when
    there are none, or two would be the same or longer than :data:`MAX_NAME`."""
    if pose_ids is not None:
        names = [_NAME_CHARS.sub("_", str(p)) for p in pose_ids]
        names = [s if s[:1].isalpha() else f"P{s}" for s in names]
        if len({s.upper() for s in names}) == n and all(len(s) <= MAX_NAME for s in names):
            return tuple(names)
    return tuple(f"P{i + 1}" for i in range(n))


def module_name(stem: str, default: str) -> str:
    """A KRL / RAPID module name from a file name's stem (letters, digits, ``_``; ≤ 24 characters)."""
    name = _NAME_CHARS.sub("_", stem)[:24]
    return name if name[:1].isalpha() else default


def paired_names(
    axes: Sequence[str], poses: Collection[str], where: str, axis_decl: str, pose_prefix: str
) -> tuple[str, ...]:
    """The target names of a controller's list, which declares each target twice (its axis values
    ``axes`` and its pose ``poses``, by name): in the order of the axis declarations; ValueError when
    there is none (``axis_decl``: how one reads) or one has no pose (``pose_prefix`` + its name)."""
    if not axes:
        raise ValueError(f"{where}: no {axis_decl} declarations")
    missing = [n for n in axes if n not in poses]
    if missing:
        raise ValueError(f"{where}: no {pose_prefix}{missing[0]}")
    return tuple(axes)


def format_csv_targets(targets: TargetList) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_TARGET_COLUMNS)
    abc = targets.tool_abc_deg
    for i, name in enumerate(targets.names):
        values = [*targets.a_deg[i], *targets.xyz_mm[i], *abc[i]]
        writer.writerow([name, *(num(v) for v in values)])
    return out.getvalue()


def parse_csv_targets(text: str, where: str = "<csv>") -> TargetList:
    reader = csv.DictReader(io.StringIO(text))
    if tuple(reader.fieldnames or ()) != CSV_TARGET_COLUMNS:
        raise ValueError(f"{where}: expected the columns {', '.join(CSV_TARGET_COLUMNS)}")
    rows = list(reader)
    if not rows:
        raise ValueError(f"{where}: no targets")
    values = np.array([[float(r[c]) for c in CSV_TARGET_COLUMNS[1:]] for r in rows])
    return TargetList(
        names=tuple(r["pose_id"] for r in rows),
        a_deg=values[:, :6],
        xyz_mm=values[:, 6:9],
        flange_R=flange_rotation_of_tool_abc(values[:, 9:12]),
    )
