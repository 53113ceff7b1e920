"""The header of a data set's table: the rules on its column names, checked before any cell is read.

A header is refused (as a :class:`~comp_daemon.data.columns.DatasetError` naming row 1 and the column)
when it is one column holding another separator, a name is empty, given twice or a case variant of
a known name, a column group (a1..a6, x/y/z, dir1..dir6, tx/ty/tz, ta/tb/tc, qw..qz, each further
target's xk/yk/zk) is given in part, a dependent group comes without the one it needs, or the
columns the kind of data set needs are missing.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from typing import Literal

from comp_daemon.data.columns import (
    AXIS_COLUMNS,
    DIR_COLUMNS,
    KNOWN_COLUMNS,
    QUATERNION_COLUMNS,
    TARGET_ABC_COLUMNS,
    TARGET_XYZ_COLUMNS,
    XYZ_COLUMNS,
    DatasetError,
    reflector_columns,
    reflector_index,
)

__all__ = ["DatasetKind", "check_header", "reflector_count", "separator_fault"]

#: What a table must hold: tracker measurements (a1..a6 and x, y, z), targets, or either.
DatasetKind = Literal["measurement", "targets", "any"]


def separator_fault(header: Sequence[str]) -> str | None:
    """Why a header that is one column holding ``;`` or tabs is refused (naming the option that
    reads it), ``None`` for any other header."""
    if len(header) == 1:
        for sep, what, option in ((";", "semicolons", "';'"), ("\t", "tabs", "tab")):
            if sep in header[0]:
                return (
                    f"the header is one column holding {what}; this format separates columns with commas "
                    f"(and writes decimals with '.'): read the file with --delimiter {option} (and "
                    "--decimal-comma when its numbers have decimal commas)"
                )
    return None


def check_header(header: Sequence[str], kind: DatasetKind, *, source: str, row_label: str = "row") -> None:
    """Refuse ``header`` on its first fault (module docstring) for a data set of ``kind``."""

    def refuse(problem: str, column: str | None) -> DatasetError:
        return DatasetError(problem, source=source, row=1, column=column, row_label=row_label)

    problem = separator_fault(header)
    if problem is not None:
        raise refuse(problem, None)
    seen: dict[str, int] = {}
    known = set(KNOWN_COLUMNS)
    for k, name in enumerate(header, start=1):
        if not name:
            raise refuse(f"column {k} of the header has no name", None)
        if name in seen:
            raise refuse(f"duplicate column name (columns {seen[name]} and {k})", name)
        seen[name] = k
        lower = name.lower()
        if name not in known and name != lower and (lower in known or reflector_index(lower) is not None):
            raise refuse(f"column names are lower case: did you mean '{lower}'?", name)

    present = set(header)

    def hint(column: str) -> str:
        near = [h for h in header if re.sub(r"_(mm|deg)$", "", h.lower()) == column and h != column]
        return f" (found {near[0]!r}; this format names it '{column}')" if near else ""

    def group(names: Sequence[str], what: str) -> bool:
        found = [c for c in names if c in present]
        if found and len(found) != len(names):
            missing = next(c for c in names if c not in present)
            raise refuse(
                f"column missing ({', '.join(found)} given without it; {what} come together)" + hint(missing),
                missing,
            )
        return bool(found)

    has_axes = group(AXIS_COLUMNS, "a1..a6")
    has_xyz = group(XYZ_COLUMNS, "x, y, z")
    _check_reflectors(header, has_xyz, group, refuse)
    group(DIR_COLUMNS, "dir1..dir6")
    has_targets = group(TARGET_XYZ_COLUMNS, "tx, ty, tz")
    has_abc = group(TARGET_ABC_COLUMNS, "ta, tb, tc")
    if has_abc and not has_targets:
        raise refuse("column missing (ta, tb, tc need the target position tx, ty, tz)", "tx")
    if group(QUATERNION_COLUMNS, "qw, qx, qy, qz") and not has_xyz:
        raise refuse("column missing (a probe's orientation qw, qx, qy, qz needs its position x, y, z)", "x")

    if kind == "measurement":
        for needed, names in ((has_axes, AXIS_COLUMNS), (has_xyz, XYZ_COLUMNS)):
            if not needed:
                raise refuse(
                    "required column missing (measurement data needs a1..a6 and x, y, z)" + hint(names[0]),
                    names[0],
                )
    elif not (has_axes or has_targets):
        raise refuse(
            "required column missing (axis values a1..a6, or a target pose tx, ty, tz, are needed)"
            + hint("a1"),
            "a1",
        )


def reflector_count(header: Sequence[str]) -> int:
    """K, the number of targets per row that ``header`` names (1 + the highest ``xk``; 1 without any)."""
    return max((k for k in map(reflector_index, header) if k is not None), default=1)


def _check_reflectors(
    header: Sequence[str],
    has_xyz: bool,
    group: Callable[[Sequence[str], str], bool],
    refuse: Callable[[str, str | None], DatasetError],
) -> None:
    """Further targets come as whole triplets ``xk, yk, zk``, numbered 2..K without a gap, after x, y, z."""
    count = reflector_count(header)
    if count == 1:
        return
    for k in range(2, count + 1):
        names = reflector_columns(k)
        if not any(c in header for c in names):
            raise refuse(
                f"column missing (targets are numbered without gaps: target {count} is given, "
                f"target {k} is not)",
                names[0],
            )
        group(names, f"the columns of target {k}")
    if not has_xyz:
        raise refuse("column missing (further targets x2, y2, z2 … need the first target's x, y, z)", "x")
