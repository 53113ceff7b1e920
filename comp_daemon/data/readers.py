"""Readers of the data set format (``shared/spec/dataset.md``): CSV files and JSON records.

Every reader refuses its input as a whole with a :class:`~comp_daemon.data.columns.DatasetError`
naming the row (1-based, header = row 1; ``record k`` for JSON), the column and the fault, and
never returns a partial data set. Of several faults, the first in reading order (row, then
column in header order) is reported.

Conventions of this implementation, where the spec leaves room:

- Column names are lower case and case-sensitive; spaces around a header cell are ignored. A
  case variant of a known name (``A1``, ``X``) is refused with a hint ("did you mean 'a1'?")
  instead of being kept as an unknown column.
- Numbers are plain decimals (``-12``, ``0.5``, ``.5``, ``1e-3``; spaces around them ignored);
  ``nan``, ``inf``, empty cells, decimal commas, hex and ``1_000`` are refused.
- ``dir`` cells are numbers equal to -1 or +1 (``1``, ``+1``, ``-1.0``); ``split`` is exactly
  ``fit`` or ``check``; ``repeat`` an integer >= 0; ``payload_kg`` >= 0.
- Column groups come whole or not at all: a1..a6, x/y/z, dir1..dir6, tx/ty/tz, ta/tb/tc
  (ta/tb/tc need tx/ty/tz). Any subset of g1..g6 is allowed.
- Measurement data (``kind="measurement"``) needs a1..a6 and x, y, z. Target files
  (``kind="targets"``, or ``"any"``) need a1..a6 or tx, ty, tz.
- A UTF-8 byte order mark is accepted. Blank lines are accepted only at the end of the file.
  Quoting follows RFC 4180 (``csv`` module, strict); a malformed quote is refused.
- Unknown columns are kept verbatim as text (no stripping).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from comp_daemon.data.columns import (
    AXIS_COLUMNS,
    DIR_COLUMNS,
    GRATING_COLUMNS,
    KNOWN_COLUMNS,
    SCALAR_NUMBER_COLUMNS,
    TARGET_ABC_COLUMNS,
    TARGET_XYZ_COLUMNS,
    XYZ_COLUMNS,
    DatasetError,
)
from comp_daemon.data.table import SPLIT_VALUES, Dataset, FloatArray, IntArray

__all__ = [
    "DatasetKind",
    "dataset_from_records",
    "parse_dataset",
    "read_dataset",
    "read_dataset_json",
]

DatasetKind = Literal["measurement", "targets", "any"]

_NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?", re.ASCII)
_INTEGER = re.compile(r"[+-]?\d+", re.ASCII)
_UNDECODABLE = re.compile("[\udc80-\udcff]")


# ---------------------------------------------------------------------------------------------
# Reading: a table of text cells -> validated Dataset
# ---------------------------------------------------------------------------------------------
@dataclass
class _Table:
    """Text cells by column, with where each row came from; the common ground of CSV and JSON."""

    source: str
    header: list[str]
    columns: dict[str, list[str]]
    row_numbers: list[int]
    row_label: str = "row"
    # column -> (row index, problem): faults found while building the table (JSON types)
    pre_errors: dict[str, tuple[int, str]] = field(default_factory=dict)


class _Faults:
    """Collects the first fault of each column; the one reported is the first in reading order."""

    def __init__(self, table: _Table) -> None:
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
        return f"not a number: {cell!r}"
    if not math.isfinite(value):
        return f"non-finite number {cell!r}"
    return f"not a plain decimal number: {cell!r} (use digits, '.', and an optional exponent)"


def _parse_numbers(table: _Table, faults: _Faults, name: str) -> FloatArray | None:
    """The column as floats, or None after recording its first fault."""
    cells = table.columns[name]
    if not all(map(_NUMBER.fullmatch, map(str.strip, cells))):
        for i, cell in enumerate(cells):
            if not _NUMBER.fullmatch(cell.strip()):
                faults.add(name, i, _number_fault(cell))
                break
        return None
    values = np.fromiter(map(float, cells), dtype=np.float64, count=len(cells))
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        faults.add(name, int(bad[0]), f"non-finite number {cells[bad[0]]!r} (out of the float range)")
        return None
    return values


def _parse_dir(table: _Table, faults: _Faults, name: str) -> NDArray[np.int8] | None:
    values = _parse_numbers(table, faults, name)
    if values is None:
        return None
    bad = np.flatnonzero((values != 1.0) & (values != -1.0))
    if bad.size:
        cell = table.columns[name][bad[0]]
        faults.add(name, int(bad[0]), f"direction must be -1 or +1, got {cell!r}")
        return None
    return values.astype(np.int8)


def _parse_split(table: _Table, faults: _Faults) -> NDArray[np.str_] | None:
    cells = [c.strip() for c in table.columns["split"]]
    for i, cell in enumerate(cells):
        if cell not in SPLIT_VALUES:
            hint = f"; did you mean '{cell.lower()}'?" if cell.lower() in SPLIT_VALUES else ""
            faults.add("split", i, f"split must be 'fit' or 'check', got {table.columns['split'][i]!r}{hint}")
            return None
    return np.array(cells, dtype="<U5")


def _parse_repeat(table: _Table, faults: _Faults) -> IntArray | None:
    cells = table.columns["repeat"]
    for i, cell in enumerate(cells):
        text = cell.strip()
        if not _INTEGER.fullmatch(text) or int(text) < 0:
            faults.add("repeat", i, f"repeat must be an integer >= 0, got {cell!r}")
            return None
    return np.array([int(c) for c in cells], dtype=np.int64)


def _check_header(table: _Table, kind: DatasetKind) -> None:
    header = table.header

    def refuse(problem: str, column: str | None) -> DatasetError:
        return DatasetError(problem, source=table.source, row=1, column=column, row_label=table.row_label)

    seen: dict[str, int] = {}
    known = set(KNOWN_COLUMNS)
    for k, name in enumerate(header, start=1):
        if not name:
            raise refuse(f"column {k} of the header has no name", None)
        if name in seen:
            raise refuse(f"duplicate column name (columns {seen[name]} and {k})", name)
        seen[name] = k
        if name not in known and name.lower() in known:
            raise refuse(f"column names are lower case: did you mean '{name.lower()}'?", name)

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
    group(DIR_COLUMNS, "dir1..dir6")
    has_targets = group(TARGET_XYZ_COLUMNS, "tx, ty, tz")
    has_abc = group(TARGET_ABC_COLUMNS, "ta, tb, tc")
    if has_abc and not has_targets:
        raise refuse("column missing (ta, tb, tc need the target position tx, ty, tz)", "tx")

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


def _build(
    table: _Table,
    *,
    limits_deg: ArrayLike | None,
    min_rows: int,
    kind: DatasetKind,
) -> Dataset:
    if kind not in ("measurement", "targets", "any"):
        raise ValueError(f"kind must be 'measurement', 'targets' or 'any', got {kind!r}")
    _check_header(table, kind)
    n = len(table.row_numbers)
    if n == 0:
        raise DatasetError("no data rows after the header", source=table.source, row=2)
    present = set(table.header)
    faults = _Faults(table)

    def block(names: Sequence[str], limits: FloatArray | None = None) -> FloatArray | None:
        """The group of columns as an (n, len(names)) array; None if absent or faulty."""
        if names[0] not in present:
            return None
        columns = []
        for j, name in enumerate(names):
            values = _parse_numbers(table, faults, name)
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

    limits = None
    if limits_deg is not None:
        limits = np.asarray(limits_deg, dtype=float)
        if limits.shape != (6, 2):
            raise ValueError(f"limits_deg must have shape (6, 2), got {limits.shape}")
    a_deg = block(AXIS_COLUMNS, limits)
    xyz_mm = block(XYZ_COLUMNS)
    target_xyz_mm = block(TARGET_XYZ_COLUMNS)
    target_abc_deg = block(TARGET_ABC_COLUMNS)

    dir_sign = None
    if "dir1" in present:
        dirs = [d for d in (_parse_dir(table, faults, name) for name in DIR_COLUMNS) if d is not None]
        if len(dirs) == len(DIR_COLUMNS):
            dir_sign = np.stack(dirs, axis=1)

    g_present = np.array([name in present for name in GRATING_COLUMNS])
    g_deg = None
    if g_present.any():
        g_deg = np.full((n, 6), np.nan)
        for j in np.flatnonzero(g_present):
            values = _parse_numbers(table, faults, GRATING_COLUMNS[j])
            if values is not None:
                g_deg[:, j] = values

    scalars: dict[str, FloatArray | None] = {}
    for name in SCALAR_NUMBER_COLUMNS:
        scalars[name] = _parse_numbers(table, faults, name) if name in present else None
    payload = scalars["payload_kg"]
    if payload is not None and (payload < 0).any():
        i = int(np.flatnonzero(payload < 0)[0])
        faults.add("payload_kg", i, f"payload must be >= 0 kg, got {table.columns['payload_kg'][i]!r}")

    split = _parse_split(table, faults) if "split" in present else None
    repeat = _parse_repeat(table, faults) if "repeat" in present else None
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
        temp_c=scalars["temp_c"],
        t_s=scalars["t_s"],
        split=split,
        repeat=repeat,
        pose_id=tuple(table.columns["pose_id"]) if "pose_id" in present else None,
        target_xyz_mm=target_xyz_mm,
        target_abc_deg=target_abc_deg,
        extra={name: tuple(table.columns[name]) for name in table.header if name not in KNOWN_COLUMNS},
        source=table.source,
        row_numbers=np.asarray(table.row_numbers, dtype=np.int64),
        row_label=table.row_label,
    )


# ---------------------------------------------------------------------------------------------
# CSV
# ---------------------------------------------------------------------------------------------
class _CsvRecords:
    """CSV records with the file line each starts on; ``line`` is where reading stopped."""

    def __init__(self, text: str) -> None:
        self._reader = csv.reader(io.StringIO(text, newline=""), strict=True)
        self.line = 1

    def __iter__(self) -> Iterator[tuple[int, list[str]]]:
        for record in self._reader:
            yield self.line, record
            self.line = self._reader.line_num + 1


def _refuse_undecodable(data: bytes, source: str, exc: UnicodeDecodeError) -> DatasetError:
    """The error for bytes that are not UTF-8, naming the row and, if it can, the column."""
    byte = f"0x{data[exc.start]:02x}"
    text = data.decode("utf-8", "surrogateescape").removeprefix("\ufeff")
    header: list[str] = []
    try:
        for k, (line, record) in enumerate(_CsvRecords(text)):
            if k == 0:
                header = [h.strip() for h in record]
            for j, cell in enumerate(record):
                if _UNDECODABLE.search(cell):
                    column = header[j] if 0 < k and j < len(header) and header[j] else None
                    return DatasetError(
                        f"not UTF-8 text (byte {byte} in field {j + 1})",
                        source=source,
                        row=line,
                        column=column,
                    )
    except csv.Error:
        pass
    line = data.count(b"\n", 0, exc.start) + 1
    return DatasetError(f"not UTF-8 text (byte {byte})", source=source, row=line)


def parse_dataset(
    data: str | bytes | bytearray | memoryview,
    *,
    source: str = "<data>",
    limits_deg: ArrayLike | None = None,
    min_rows: int = 0,
    kind: DatasetKind = "measurement",
) -> Dataset:
    """Parse CSV text or bytes (UTF-8) into a :class:`Dataset`, refusing it whole on any fault.

    ``limits_deg`` is the robot's (6, 2) [min, max] axis limits (``RobotDescription.axis_limits_deg``);
    ``min_rows`` the number of parameters of the model the data is for. ``kind``:
    ``"measurement"`` needs a1..a6 and x, y, z; ``"targets"`` and ``"any"`` need a1..a6 or tx, ty, tz.
    """
    if isinstance(data, bytes | bytearray | memoryview):
        raw = bytes(data)
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise _refuse_undecodable(raw, source, exc) from None
    else:
        text = data
    text = text.removeprefix("\ufeff")

    if not text.strip():
        raise DatasetError("empty file (no header row)", source=source, row=1)

    header: list[str] | None = None
    rows: list[list[str]] = []
    row_numbers: list[int] = []
    blank_at: int | None = None
    records = _CsvRecords(text)
    try:
        for line, record in records:
            if header is None:
                if not record:
                    raise DatasetError("empty line where the header row should be", source=source, row=1)
                header = [h.strip() for h in record]
                continue
            if not record:
                blank_at = line if blank_at is None else blank_at
                continue
            if blank_at is not None:
                raise DatasetError(
                    "empty row (blank lines are allowed only at the end)", source=source, row=blank_at
                )
            if len(record) != len(header):
                column = header[len(record)] if len(record) < len(header) else None
                what = f"no value for '{column}' and after" if column else "more fields than columns"
                raise DatasetError(
                    f"{len(record)} fields, but the header has {len(header)} columns ({what})",
                    source=source,
                    row=line,
                    column=column,
                )
            rows.append(record)
            row_numbers.append(line)
    except csv.Error as exc:
        raise DatasetError(f"malformed CSV: {exc}", source=source, row=records.line) from None
    if header is None:
        raise DatasetError("empty file (no header row)", source=source, row=1)

    columns = {name: [r[k] for r in rows] for k, name in enumerate(header)}
    table = _Table(source=source, header=header, columns=columns, row_numbers=row_numbers)
    return _build(table, limits_deg=limits_deg, min_rows=min_rows, kind=kind)


def read_dataset(
    path_or_data: str | os.PathLike[str] | bytes | bytearray | BinaryIO,
    *,
    limits_deg: ArrayLike | None = None,
    min_rows: int = 0,
    kind: DatasetKind = "measurement",
    source: str | None = None,
) -> Dataset:
    """Read a CSV data set from a path, bytes, a binary file, or CSV text.

    A ``str`` is taken as CSV text when it contains a newline, else as a path. See
    :func:`parse_dataset` for ``limits_deg``, ``min_rows`` and ``kind``.
    """
    data: str | bytes
    if isinstance(path_or_data, bytes | bytearray):
        data, name = bytes(path_or_data), "<bytes>"
    elif isinstance(path_or_data, str) and ("\n" in path_or_data or "\r" in path_or_data):
        data, name = path_or_data, "<text>"
    elif isinstance(path_or_data, str | os.PathLike):
        data, name = Path(path_or_data).read_bytes(), str(path_or_data)
    else:
        data, name = path_or_data.read(), getattr(path_or_data, "name", "<stream>")
    return parse_dataset(
        data, source=source or str(name), limits_deg=limits_deg, min_rows=min_rows, kind=kind
    )


# ---------------------------------------------------------------------------------------------
# JSON records
# ---------------------------------------------------------------------------------------------
class _Record(dict[str, Any]):
    """A JSON object that remembers keys it saw more than once."""

    duplicate_keys: tuple[str, ...] = ()


def _object_pairs(pairs: list[tuple[str, Any]]) -> _Record:
    record = _Record(pairs)
    if len(record) != len(pairs):
        seen: set[str] = set()
        duplicates: list[str] = []
        for key, _ in pairs:
            if key in seen:
                duplicates.append(key)
            seen.add(key)
        record.duplicate_keys = tuple(duplicates)
    return record


_NUMERIC_COLUMNS = frozenset(
    (
        *AXIS_COLUMNS,
        *XYZ_COLUMNS,
        *DIR_COLUMNS,
        *GRATING_COLUMNS,
        *SCALAR_NUMBER_COLUMNS,
        *TARGET_XYZ_COLUMNS,
        *TARGET_ABC_COLUMNS,
        "repeat",
    )
)


def _json_number_text(value: Any) -> str | None:
    """The text of a JSON number (exact for floats and small ints), None if not a number."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    if isinstance(value, int):
        if abs(value) < 10**15:
            return str(value)
        try:
            return repr(float(value))
        except OverflowError:
            return "inf"
    return repr(value)


def _json_cell(column: str, value: Any) -> tuple[str, str | None]:
    """(cell text, type problem or None) for one JSON value."""
    if column in _NUMERIC_COLUMNS:
        if value is None:
            return "", None
        text = _json_number_text(value)
        if text is None:
            return "", f"expected a JSON number, got {json.dumps(value)[:40]}"
        return text, None
    if column == "split":
        if not isinstance(value, str):
            return "", f"split must be the string 'fit' or 'check', got {json.dumps(value)[:40]}"
        return value, None
    if column == "pose_id":
        if isinstance(value, str):
            return value, None
        if isinstance(value, int) and not isinstance(value, bool):
            return str(value), None
        return "", f"pose_id must be a string or an integer, got {json.dumps(value)[:40]}"
    if isinstance(value, str):
        return value, None
    if value is None:
        return "", None
    if isinstance(value, dict | list):
        return "", "expected a single value (text or number), got a JSON " + type(value).__name__
    return json.dumps(value), None


def dataset_from_records(
    records: Sequence[Mapping[str, Any]],
    *,
    source: str = "<records>",
    limits_deg: ArrayLike | None = None,
    min_rows: int = 0,
    kind: DatasetKind = "measurement",
) -> Dataset:
    """A :class:`Dataset` from JSON-style records (one object per row, same keys in each).

    The rules are those of the CSV reader; errors name ``record k`` (1-based) instead of a row.
    Numeric columns take JSON numbers (not strings), ``split`` a string, ``pose_id`` a string or
    an integer; unknown keys are kept as text. Records must all have the same keys.
    """

    def refuse(problem: str, record: int | None, column: str | None = None) -> DatasetError:
        return DatasetError(problem, source=source, row=record, column=column, row_label="record")

    if isinstance(records, str | bytes) or not isinstance(records, Sequence):
        raise refuse("expected a list of records (JSON objects)", None)
    if not records:
        raise refuse("no records", None)
    header: list[str] | None = None
    columns: dict[str, list[str]] = {}
    pre_errors: dict[str, tuple[int, str]] = {}
    for i, record in enumerate(records):
        if not isinstance(record, Mapping):
            raise refuse(f"expected a JSON object, got {type(record).__name__}", i + 1)
        if any(not isinstance(k, str) for k in record):
            raise refuse("keys must be strings", i + 1)
        duplicates = getattr(record, "duplicate_keys", ())
        if duplicates:
            raise refuse("duplicate column name (key given twice)", i + 1, duplicates[0].strip())
        stripped = {k.strip(): v for k, v in record.items()}
        if len(stripped) != len(record):
            name = next(k.strip() for k in record if list(map(str.strip, record)).count(k.strip()) > 1)
            raise refuse("duplicate column name (keys differing only in spaces)", i + 1, name)
        if header is None:
            header = list(stripped)
            columns = {name: [] for name in header}
        elif stripped.keys() != columns.keys():
            missing = [k for k in header if k not in stripped]
            if missing:
                raise refuse("missing key (every record needs the keys of record 1)", i + 1, missing[0])
            unexpected = next(k for k in stripped if k not in columns)
            raise refuse("key not in record 1 (every record needs the same keys)", i + 1, unexpected)
        for name in header:
            text, problem = _json_cell(name, stripped[name])
            if problem is not None and name not in pre_errors:
                pre_errors[name] = (i, problem)
            columns[name].append(text)
    assert header is not None
    table = _Table(
        source=source,
        header=header,
        columns=columns,
        row_numbers=list(range(1, len(records) + 1)),
        row_label="record",
        pre_errors=pre_errors,
    )
    return _build(table, limits_deg=limits_deg, min_rows=min_rows, kind=kind)


def read_dataset_json(
    path_or_data: str | os.PathLike[str] | bytes | bytearray,
    *,
    limits_deg: ArrayLike | None = None,
    min_rows: int = 0,
    kind: DatasetKind = "measurement",
    source: str | None = None,
) -> Dataset:
    """Read a JSON data set: a list of records (see :func:`dataset_from_records`), UTF-8.

    A ``str`` is taken as JSON text when it starts with ``[`` or ``{`` (after spaces), else as a path.
    """
    if isinstance(path_or_data, bytes | bytearray):
        raw, name = bytes(path_or_data), "<bytes>"
    elif isinstance(path_or_data, str) and path_or_data.lstrip()[:1] in ("[", "{"):
        raw, name = path_or_data.encode("utf-8", "surrogatepass"), "<text>"
    else:
        raw, name = Path(path_or_data).read_bytes(), str(path_or_data)
    name = source or name
    try:
        text = raw.decode("utf-8").removeprefix("\ufeff")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise DatasetError(f"not UTF-8 text (byte 0x{raw[exc.start]:02x})", source=name, row=line) from None
    try:
        records = json.loads(text, object_pairs_hook=_object_pairs)
    except json.JSONDecodeError as exc:
        raise DatasetError(
            f"not valid JSON: {exc.msg} (line {exc.lineno}, column {exc.colno})", source=name
        ) from None
    except RecursionError:
        raise DatasetError("not a list of records (nested too deeply)", source=name) from None
    return dataset_from_records(records, source=name, limits_deg=limits_deg, min_rows=min_rows, kind=kind)
