"""A table of text cells → a validated :class:`~comp_daemon.data.table.Dataset`: the common ground of
the CSV and JSON readers (:mod:`comp_daemon.data.readers`, whose docstring states the rules).

:class:`CellTable` holds the cells by column with the row (or record) number each came from;
:func:`build_dataset` checks the header (:mod:`comp_daemon.data.header`), parses every column by
its cell rules (one parser a column or column group) and raises the first fault in reading order
(row, then column in header order) as a :class:`~comp_daemon.data.columns.DatasetError`.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from comp_daemon.data.columns import (
    AXIS_COLUMNS,
    DIR_COLUMNS,
    GRATING_COLUMNS,
    KNOWN_COLUMNS,
    QUATERNION_COLUMNS,
    QUATERNION_NORM_TOL,
    TARGET_ABC_COLUMNS,
    TARGET_XYZ_COLUMNS,
    XYZ_COLUMNS,
    DatasetError,
    reflector_columns,
    reflector_index,
)
from comp_daemon.data.header import DatasetKind, check_header, reflector_count
from comp_daemon.data.table import SPLIT_VALUES, Dataset, FloatArray, IntArray

__all__ = [
    "CellFaults",
    "CellTable",
    "DatasetKind",
    "build_dataset",
    "parse_numbers",
    "printable",
    "text_fault",
]

_NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?", re.ASCII)
_INTEGER = re.compile(r"[+-]?\d+", re.ASCII)
_TEXT_FAULT = re.compile("[\x00\ud800-\udfff]")
_DECIMAL_COMMA = re.compile(r"[+-]?\d*,\d+(?:[eE][+-]?\d+)?", re.ASCII)


def text_fault(text: str) -> str | None:
    """Why ``text`` cannot be a cell or a key: a NUL character or a lone surrogate (not Unicode,
    cannot be written as UTF-8); ``None`` if it can."""
    found = _TEXT_FAULT.search(text)
    if found is None:
        return None
    if found.group() == "\x00":
        return "a NUL character (U+0000) in text"
    return f"a lone surrogate (U+{ord(found.group()):04X}) in text: not Unicode"


def printable(text: str) -> str:
    """``text`` with lone surrogates written as escapes (``\\udc80``), so that a message naming it
    can be written as UTF-8."""
    return text.encode("utf-8", "backslashreplace").decode("utf-8")


@dataclass
class CellTable:
    """Text cells by column, with where each row came from; the common ground of CSV and JSON."""

    source: str
    header: list[str]
    columns: dict[str, list[str]]
    row_numbers: list[int]
    row_label: str = "row"
    # column -> (row index, problem): faults found while building the table (JSON types)
    pre_errors: dict[str, tuple[int, str]] = field(default_factory=dict)


class CellFaults:
    """Collects the first fault of each column; the one reported is the first in reading order."""

    def __init__(self, table: CellTable) -> None:
        self.table = table
        self.position = {name: k for k, name in enumerate(table.header)}
        self.best: tuple[int, int, str, str] | None = None
        for name, (i, problem) in table.pre_errors.items():
            self.add(name, i, problem)

    def add(self, column: str, i: int, problem: str) -> None:
        key = (i, self.position.get(column, len(self.position)), column, problem)
        if self.best is None or key[:2] < self.best[:2]:
            self.best = key

    def raise_first(self) -> None:
        if self.best is None:
            return
        i, _, column, problem = self.best
        t = self.table
        raise DatasetError(
            problem, source=t.source, row=t.row_numbers[i], column=column, row_label=t.row_label
        )


def _number_fault(cell: str) -> str:
    text = cell.strip()
    if not text:
        return "empty cell; a number is required"
    try:
        value = float(text)
    except ValueError:
        if _DECIMAL_COMMA.fullmatch(text):
            return f"not a number: {cell!r} has a decimal comma; read the file with --decimal-comma"
        return f"not a number: {cell!r}"
    if not math.isfinite(value):
        return f"non-finite number {cell!r}"
    return f"not a plain decimal number: {cell!r} (use digits, '.', and an optional exponent)"


_FURTHER_TARGET = re.compile(r"[xyz]([2-9]|[1-9][0-9]+)")
_UNSEEN_TARGET = (
    "; a target the tracker did not see at a pose has no number: leave out that pose's row, "
    "or that target's columns"
)


def parse_numbers(table: CellTable, faults: CellFaults, name: str) -> FloatArray | None:
    """The column as floats, or None after recording its first fault (for a further target's
    column, a missing or non-finite value says how to leave out an unseen target)."""
    cells = table.columns[name]
    if not all(map(_NUMBER.fullmatch, map(str.strip, cells))):
        for i, cell in enumerate(cells):
            if not _NUMBER.fullmatch(cell.strip()):
                problem = _number_fault(cell)
                if _FURTHER_TARGET.fullmatch(name) and (not cell.strip() or "non-finite" in problem):
                    problem += _UNSEEN_TARGET
                faults.add(name, i, problem)
                break
        return None
    values = np.fromiter(map(float, cells), dtype=np.float64, count=len(cells))
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        faults.add(name, int(bad[0]), f"non-finite number {cells[bad[0]]!r} (out of the float range)")
        return None
    return values


def _parse_dir(table: CellTable, faults: CellFaults, name: str) -> NDArray[np.int8] | None:
    values = parse_numbers(table, faults, name)
    if values is None:
        return None
    bad = np.flatnonzero((values != 1.0) & (values != -1.0))
    if bad.size:
        cell = table.columns[name][bad[0]]
        faults.add(name, int(bad[0]), f"direction must be -1 or +1, got {cell!r}")
        return None
    return values.astype(np.int8)


# what other tools call the two sides of a split
_SPLIT_SYNONYMS = {
    "train": "fit",
    "training": "fit",
    "calibration": "fit",
    "test": "check",
    "testing": "check",
    "validation": "check",
    "verification": "check",
}


def _parse_split(table: CellTable, faults: CellFaults) -> NDArray[np.str_] | None:
    cells = [c.strip() for c in table.columns["split"]]
    for i, cell in enumerate(cells):
        if cell not in SPLIT_VALUES:
            meant = _SPLIT_SYNONYMS.get(cell.lower(), cell.lower())
            hint = f"; did you mean '{meant}'?" if meant in SPLIT_VALUES else ""
            faults.add("split", i, f"split must be 'fit' or 'check', got {table.columns['split'][i]!r}{hint}")
            return None
    return np.array(cells, dtype="<U5")


def _parse_repeat(table: CellTable, faults: CellFaults) -> IntArray | None:
    cells = table.columns["repeat"]
    for i, cell in enumerate(cells):
        text = cell.strip()
        if not _INTEGER.fullmatch(text) or int(text) < 0:
            faults.add("repeat", i, f"repeat must be an integer >= 0, got {cell!r}")
            return None
    return np.array([int(c) for c in cells], dtype=np.int64)


def _parse_quaternions(table: CellTable, faults: CellFaults, q: FloatArray | None) -> FloatArray | None:
    """The (n, 4) probe orientations, each a unit quaternion within :data:`QUATERNION_NORM_TOL`."""
    if q is None:
        return None
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > QUATERNION_NORM_TOL)
    if bad.size:
        i = int(bad[0])
        cells = [table.columns[c][i].strip() for c in QUATERNION_COLUMNS]
        faults.add(
            "qw",
            i,
            f"the probe orientation (qw, qx, qy, qz) = ({', '.join(cells)}) has norm {norm[i]:.6g}; "
            f"a unit quaternion is required (|q| = 1 within {QUATERNION_NORM_TOL:g})",
        )
        return None
    return q


def _parse_station(table: CellTable, faults: CellFaults) -> tuple[str, ...] | None:
    cells = tuple(c.strip() for c in table.columns["station"])
    empty = [i for i, c in enumerate(cells) if not c]
    if empty:
        faults.add(
            "station", empty[0], "empty station; every row names the tracker set-up it was measured from"
        )
        return None
    return cells


def _parse_block(
    table: CellTable, faults: CellFaults, names: Sequence[str], limits: FloatArray | None = None
) -> FloatArray | None:
    """A group of number columns as an (n, len(names)) array, each column within its ``limits`` row
    ([min, max] deg) when given; None if the group is absent or a cell of it is faulty."""
    if names[0] not in table.header:
        return None
    columns = []
    for j, name in enumerate(names):
        values = parse_numbers(table, faults, name)
        if values is None:
            continue
        if limits is not None:
            outside = np.flatnonzero((values < limits[j, 0]) | (values > limits[j, 1]))
            if outside.size:
                i = int(outside[0])
                faults.add(
                    name,
                    i,
                    f"{float(values[i])!r} deg is outside the axis limits "
                    f"[{limits[j, 0]:g}, {limits[j, 1]:g}] deg",
                )
                continue
        columns.append(values)
    return np.stack(columns, axis=1) if len(columns) == len(names) else None


def _parse_dirs(table: CellTable, faults: CellFaults) -> NDArray[np.int8] | None:
    """dir1..dir6 as an (n, 6) array of -1 / +1; None if absent or faulty."""
    if "dir1" not in table.header:
        return None
    dirs = [d for d in (_parse_dir(table, faults, name) for name in DIR_COLUMNS) if d is not None]
    return np.stack(dirs, axis=1) if len(dirs) == len(DIR_COLUMNS) else None


def _parse_gratings(table: CellTable, faults: CellFaults) -> tuple[FloatArray | None, NDArray[np.bool_]]:
    """The grating readings (n, 6), NaN in the columns not given (None if none is), and which are given."""
    g_present = np.array([name in table.header for name in GRATING_COLUMNS])
    if not g_present.any():
        return None, g_present
    g_deg = np.full((len(table.row_numbers), 6), np.nan)
    for j in np.flatnonzero(g_present):
        values = parse_numbers(table, faults, GRATING_COLUMNS[j])
        if values is not None:
            g_deg[:, j] = values
    return g_deg, g_present


def _parse_bounded(
    table: CellTable, faults: CellFaults, name: str, bad: Callable[[FloatArray], NDArray[np.bool_]], rule: str
) -> FloatArray | None:
    """A number column whose values ``bad`` marks are refused by ``rule`` (with the cell's text)."""
    values = parse_numbers(table, faults, name) if name in table.header else None
    if values is not None and bad(values).any():
        i = int(np.flatnonzero(bad(values))[0])
        faults.add(name, i, f"{rule}, got {table.columns[name][i]!r}")
    return values


def _axis_limits(limits_deg: ArrayLike | None) -> FloatArray | None:
    if limits_deg is None:
        return None
    limits = np.asarray(limits_deg, dtype=float)
    if limits.shape != (6, 2):
        raise ValueError(f"limits_deg must have shape (6, 2), got {limits.shape}")
    return limits


def build_dataset(
    table: CellTable,
    *,
    limits_deg: ArrayLike | None,
    min_rows: int,
    kind: DatasetKind,
) -> Dataset:
    """The data set of ``table``, refused whole on its first fault (module docstring)."""
    if kind not in ("measurement", "targets", "any"):
        raise ValueError(f"kind must be 'measurement', 'targets' or 'any', got {kind!r}")
    check_header(table.header, kind, source=table.source, row_label=table.row_label)
    n = len(table.row_numbers)
    if n == 0:
        raise DatasetError("no data rows after the header", source=table.source, row=2)
    present = set(table.header)
    faults = CellFaults(table)
    a_deg = _parse_block(table, faults, AXIS_COLUMNS, _axis_limits(limits_deg))
    xyz_mm = _parse_block(table, faults, XYZ_COLUMNS)
    further = range(2, reflector_count(table.header) + 1)
    more = [_parse_block(table, faults, reflector_columns(k)) for k in further]
    target_xyz_mm = _parse_block(table, faults, TARGET_XYZ_COLUMNS)
    target_abc_deg = _parse_block(table, faults, TARGET_ABC_COLUMNS)
    dir_sign = _parse_dirs(table, faults)
    g_deg, g_present = _parse_gratings(table, faults)
    payload = _parse_bounded(table, faults, "payload_kg", lambda v: v < 0, "payload must be >= 0 kg")
    temp_c = parse_numbers(table, faults, "temp_c") if "temp_c" in present else None
    t_s = parse_numbers(table, faults, "t_s") if "t_s" in present else None
    split = _parse_split(table, faults) if "split" in present else None
    repeat = _parse_repeat(table, faults) if "repeat" in present else None
    probe_q = _parse_quaternions(table, faults, _parse_block(table, faults, QUATERNION_COLUMNS))
    sigma = _parse_bounded(
        table, faults, "sigma_mm", lambda v: v <= 0, "sigma_mm must be > 0 mm (a standard deviation)"
    )
    station = _parse_station(table, faults) if "station" in present else None
    faults.raise_first()

    if n < min_rows:
        raise DatasetError(
            f"{n} data {table.row_label}s; fewer rows than the chosen model has parameters ({min_rows})",
            source=table.source,
        )
    return Dataset(
        a_deg=a_deg,
        xyz_mm=xyz_mm,
        dir=dir_sign,
        g_deg=g_deg,
        g_present=g_present,
        payload_kg=np.zeros(n) if payload is None else payload,
        temp_c=temp_c,
        t_s=t_s,
        split=split,
        repeat=repeat,
        pose_id=tuple(table.columns["pose_id"]) if "pose_id" in present else None,
        station=station,
        probe_q_wxyz=probe_q,
        sigma_mm=sigma,
        target_xyz_mm=target_xyz_mm,
        target_abc_deg=target_abc_deg,
        more_xyz_mm=np.stack([m for m in more if m is not None], axis=1) if more else None,
        extra={
            name: tuple(table.columns[name])
            for name in table.header
            if name not in KNOWN_COLUMNS and reflector_index(name) is None
        },
        source=table.source,
        row_numbers=np.asarray(table.row_numbers, dtype=np.int64),
        row_label=table.row_label,
    )
