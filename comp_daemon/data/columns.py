"""Column names of the measurement data set (``docs/data-format.md``) and the error a reader raises.

Column names are case-sensitive and lower case, exactly as the spec writes them; surrounding
whitespace in a header cell is ignored. Further targets (reflectors) on the flange have the
numbered columns ``x2, y2, z2`` … ``xK, yK, zK`` (:func:`reflector_columns`). A header cell
that differs from a known column only in case (``A1``, ``X``) is refused with a hint rather than
kept as an unknown column, so that a file written for another tool cannot silently lose its axis values.
"""

from __future__ import annotations

import re
from typing import Any

__all__ = [
    "ANGLE_COLUMNS",
    "AXIS_COLUMNS",
    "DIR_COLUMNS",
    "GRATING_COLUMNS",
    "KNOWN_COLUMNS",
    "LENGTH_COLUMNS",
    "NUMERIC_COLUMNS",
    "QUATERNION_COLUMNS",
    "QUATERNION_NORM_TOL",
    "SCALAR_NUMBER_COLUMNS",
    "TARGET_ABC_COLUMNS",
    "TARGET_XYZ_COLUMNS",
    "XYZ_COLUMNS",
    "DatasetError",
    "is_numeric_column",
    "is_reflector_column",
    "reflector_columns",
    "reflector_index",
]

AXIS_COLUMNS: tuple[str, ...] = ("a1", "a2", "a3", "a4", "a5", "a6")
XYZ_COLUMNS: tuple[str, ...] = ("x", "y", "z")
DIR_COLUMNS: tuple[str, ...] = ("dir1", "dir2", "dir3", "dir4", "dir5", "dir6")
GRATING_COLUMNS: tuple[str, ...] = ("g1", "g2", "g3", "g4", "g5", "g6")
TARGET_XYZ_COLUMNS: tuple[str, ...] = ("tx", "ty", "tz")
TARGET_ABC_COLUMNS: tuple[str, ...] = ("ta", "tb", "tc")
SCALAR_NUMBER_COLUMNS: tuple[str, ...] = ("payload_kg", "temp_c", "t_s")
#: a 6-DOF probe's orientation (unit quaternion, w first) in the frame of x, y, z
QUATERNION_COLUMNS: tuple[str, ...] = ("qw", "qx", "qy", "qz")
#: |q| may differ from 1 by this much (exporters round to 6 or 7 digits)
QUATERNION_NORM_TOL = 1e-3

KNOWN_COLUMNS: tuple[str, ...] = (
    *AXIS_COLUMNS,
    *XYZ_COLUMNS,
    *DIR_COLUMNS,
    *GRATING_COLUMNS,
    *SCALAR_NUMBER_COLUMNS,
    "split",
    "repeat",
    "pose_id",
    "station",
    *QUATERNION_COLUMNS,
    "sigma_mm",
    *TARGET_XYZ_COLUMNS,
    *TARGET_ABC_COLUMNS,
)


#: the columns whose cells are numbers (besides the further targets' ``xK, yK, zK``)
NUMERIC_COLUMNS: frozenset[str] = frozenset(
    (
        *AXIS_COLUMNS,
        *XYZ_COLUMNS,
        *DIR_COLUMNS,
        *GRATING_COLUMNS,
        *SCALAR_NUMBER_COLUMNS,
        *TARGET_XYZ_COLUMNS,
        *TARGET_ABC_COLUMNS,
        *QUATERNION_COLUMNS,
        "sigma_mm",
        "repeat",
    )
)
#: lengths (mm) and angles (deg) among them, the columns a reader's unit option scales
LENGTH_COLUMNS: tuple[str, ...] = (*XYZ_COLUMNS, *TARGET_XYZ_COLUMNS, "sigma_mm")
ANGLE_COLUMNS: tuple[str, ...] = (*AXIS_COLUMNS, *GRATING_COLUMNS, *TARGET_ABC_COLUMNS)

_REFLECTOR = re.compile(r"([xyz])([1-9][0-9]*)")


def reflector_columns(k: int) -> tuple[str, ...]:
    """The columns of target (reflector) ``k`` >= 1: ``x, y, z`` for the first, ``xk, yk, zk`` after."""
    if k < 1:
        raise ValueError(f"targets are numbered from 1, got {k}")
    return XYZ_COLUMNS if k == 1 else (f"x{k}", f"y{k}", f"z{k}")


def reflector_index(name: str) -> int | None:
    """``k`` of a further target's column ``xk``/``yk``/``zk`` (k >= 2), else None."""
    found = _REFLECTOR.fullmatch(name)
    if found is None:
        return None
    k = int(found.group(2))
    return k if k >= 2 else None


def is_reflector_column(name: str) -> bool:
    """Whether ``name`` is a further target's column (``x2`` … ``zK``)."""
    return reflector_index(name) is not None


def is_numeric_column(name: str) -> bool:
    """Whether the cells of column ``name`` are numbers."""
    return name in NUMERIC_COLUMNS or is_reflector_column(name)


class DatasetError(ValueError):
    """A data set that is refused as a whole.

    ``row`` is the 1-based row of the file (header = row 1), or the 1-based record number for
    JSON records (then ``row_label`` is ``"record"``; ``"line"`` for a fault in the JSON text
    itself); ``column`` is the column's name. Either is ``None`` when the fault is not in one
    place (an empty file, too few rows). ``path`` names the value at fault in a JSON document
    (``$[3].a1``, ``$.records[0].note``), ``None`` for CSV.
    """

    def __init__(
        self,
        problem: str,
        *,
        source: str = "<data>",
        row: int | None = None,
        column: str | None = None,
        row_label: str = "row",
        path: str | None = None,
    ) -> None:
        self.problem = problem
        self.source = source
        self.row = row
        self.column = column
        self.row_label = row_label
        self.path = path
        where = [source]
        if path is not None:
            where.append(path)
        if row is not None:
            where.append(f"{row_label} {row}")
        if column is not None:
            where.append(f"column '{column}'")
        super().__init__(f"{', '.join(where)}: {problem}")

    def __reduce__(self) -> tuple[Any, ...]:  # crosses a process boundary with its fields
        where = {
            "source": self.source,
            "row": self.row,
            "column": self.column,
            "row_label": self.row_label,
            "path": self.path,
        }
        return (_dataset_error, (self.problem, where))


def _dataset_error(problem: str, where: dict[str, Any]) -> DatasetError:
    return DatasetError(problem, **where)
