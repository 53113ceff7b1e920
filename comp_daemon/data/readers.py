"""Readers of the data set format (``docs/data-format.md``): CSV files and JSON records.

Both build a table of text cells and leave the checks to :func:`comp_daemon.data.cells.build_dataset`.
Every reader refuses its input as a whole with a :class:`~comp_daemon.data.columns.DatasetError`
naming the row (1-based, header = row 1; ``record k`` for JSON), the column and the fault, and
never returns a partial data set. Of several faults, the first in reading order (row, then
column in header order) is reported.

Conventions of this implementation, where the spec leaves room:

- Column names are lower case and case-sensitive; spaces around a header cell are ignored. A
  case variant of a known name (``A1``, ``X``) is refused with a hint ("did you mean 'a1'?")
  instead of being kept as an unknown column.
- Numbers are plain decimals (``-12``, ``0.5``, ``.5``, ``1e-3``; spaces around them ignored);
  ``nan``, ``inf``, empty cells, decimal commas, hex and ``1_000`` are refused. Files from other
  tools (``;``-separated, decimal commas, metres, radians) are read with stated
  :class:`~comp_daemon.data.options.ReadOptions` (``--delimiter``, ``--decimal-comma``,
  ``--units``), never by guess; one that looks as if it needed them is refused naming the option
  (:mod:`comp_daemon.data.options`).
- ``dir`` cells are numbers equal to -1 or +1 (``1``, ``+1``, ``-1.0``); ``split`` is exactly
  ``fit`` or ``check``; ``repeat`` an integer >= 0; ``payload_kg`` >= 0.
- Column groups come whole or not at all: a1..a6, x/y/z, dir1..dir6, tx/ty/tz, ta/tb/tc
  (ta/tb/tc need tx/ty/tz). Any subset of g1..g6 is allowed.
- Further targets on the flange: ``x2, y2, z2`` … ``xK, yK, zK``, each triplet whole, numbered
  without a gap, only beside ``x, y, z``; their cells follow the number rules of ``x, y, z``.
- Measurement data (``kind="measurement"``) needs a1..a6 and x, y, z. Target files
  (``kind="targets"``, or ``"any"``) need a1..a6 or tx, ty, tz.
- A UTF-8 byte order mark is accepted. Blank lines are accepted only at the end of the file.
  Quoting follows RFC 4180 (``csv`` module, strict); a malformed quote is refused.
- ``station`` names the tracker's set-up (any non-empty text, spaces around it ignored);
  ``qw, qx, qy, qz`` (whole, beside x, y, z) a 6-DOF probe's orientation, a unit quaternion
  (``|q|`` within 1e-3 of 1; refused naming the row and ``qw``); ``sigma_mm`` the row's declared
  position σ per axis, a number > 0.
- Unknown columns are kept verbatim as text (no stripping).
- No cell may hold a NUL character or a lone surrogate (text that cannot be written as UTF-8).
- JSON: a list of records or ``{"name": ..., "records": [...]}``; a key given twice, a NUL or a
  lone surrogate in a string or key, and an integer beyond any double are refused with the value's
  ``path`` (:mod:`comp_daemon.data.jsontext`); every refusal inside a record names its path too.
"""

from __future__ import annotations

import csv
import io
import json
import os
import re
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, BinaryIO

from numpy.typing import ArrayLike

from comp_daemon.data.cells import (
    CellTable,
    DatasetKind,
    build_dataset,
    printable,
    text_fault,
)
from comp_daemon.data.columns import DatasetError, is_numeric_column
from comp_daemon.data.header import separator_fault
from comp_daemon.data.jsontext import JsonRecords, load_json_records, record_path
from comp_daemon.data.options import ReadOptions
from comp_daemon.data.table import Dataset

__all__ = [
    "DatasetKind",
    "dataset_from_json",
    "dataset_from_records",
    "parse_dataset",
    "read_dataset",
    "read_dataset_file",
    "read_dataset_json",
]

_UNDECODABLE = re.compile("[\udc80-\udcff]")


# ---------------------------------------------------------------------------------------------
# CSV
# ---------------------------------------------------------------------------------------------
class _CsvRecords:
    """CSV records with the file line each starts on; ``line`` is where reading stopped."""

    def __init__(self, text: str, delimiter: str = ",") -> None:
        self._reader = csv.reader(io.StringIO(text, newline=""), strict=True, delimiter=delimiter)
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


def _refuse_text(record: list[str], line: int, header: list[str] | None, source: str) -> None:
    """Refuse a field holding a NUL character or a lone surrogate, naming its row and column."""
    for j, cell in enumerate(record):
        problem = text_fault(cell)
        if problem is not None:
            column = header[j] if header is not None and j < len(header) and header[j] else None
            raise DatasetError(
                f"{problem} (field {j + 1})", source=source, row=line, column=column and printable(column)
            )


def parse_dataset(
    data: str | bytes | bytearray | memoryview,
    *,
    source: str = "<data>",
    limits_deg: ArrayLike | None = None,
    min_rows: int = 0,
    kind: DatasetKind = "measurement",
    options: ReadOptions | None = None,
) -> Dataset:
    """Parse CSV text or bytes (UTF-8) into a :class:`Dataset`, refusing it whole on any fault.

    ``limits_deg`` is the robot's (6, 2) [min, max] axis limits (``RobotDescription.axis_limits_deg``);
    ``min_rows`` the number of parameters of the model the data is for. ``kind``:
    ``"measurement"`` needs a1..a6 and x, y, z; ``"targets"`` and ``"any"`` need a1..a6 or tx, ty, tz.
    ``options``: separator, decimal comma and units (:class:`~comp_daemon.data.options.ReadOptions`;
    default the format as specified).
    """
    options = options or ReadOptions()
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
    records = _CsvRecords(text, options.delimiter)
    check_text = text_fault(text) is not None  # then find the field
    try:
        for line, record in records:
            if check_text:
                _refuse_text(record, line, header, source)
            if header is None:
                if not record:
                    raise DatasetError("empty line where the header row should be", source=source, row=1)
                header = [h.strip() for h in record]
                problem = separator_fault(header)
                if problem is not None:  # before the rows, which split on the decimal commas
                    raise DatasetError(problem, source=source, row=1)
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
    table = CellTable(source=source, header=header, columns=columns, row_numbers=row_numbers)
    return _built(table, options, limits_deg=limits_deg, min_rows=min_rows, kind=kind)


def _built(
    table: CellTable, options: ReadOptions, *, limits_deg: ArrayLike | None, min_rows: int, kind: DatasetKind
) -> Dataset:
    """The data set of a cell table read with ``options`` (converted first, its units checked after)."""
    data = build_dataset(options.convert(table), limits_deg=limits_deg, min_rows=min_rows, kind=kind)
    options.check_units(data)
    return data


def read_dataset(
    path_or_data: str | os.PathLike[str] | bytes | bytearray | BinaryIO,
    *,
    limits_deg: ArrayLike | None = None,
    min_rows: int = 0,
    kind: DatasetKind = "measurement",
    source: str | None = None,
    options: ReadOptions | None = None,
) -> Dataset:
    """Read a CSV data set from a path, bytes, a binary file, or CSV text.

    A ``str`` is taken as CSV text when it contains a newline, else as a path. See
    :func:`parse_dataset` for ``limits_deg``, ``min_rows``, ``kind`` and ``options``.
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
        data, source=source or str(name), limits_deg=limits_deg, min_rows=min_rows, kind=kind, options=options
    )


# ---------------------------------------------------------------------------------------------
# JSON records
# ---------------------------------------------------------------------------------------------
_MAX_INT_BITS = 1024  # 2**1024 is beyond every double


def _long_integer(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > _MAX_INT_BITS


def _shown(value: Any) -> str:
    """A short JSON rendering of ``value`` for a message."""
    if _long_integer(value):
        return "an integer beyond any number"
    try:
        return json.dumps(value)[:40]
    except (ValueError, TypeError, RecursionError):
        return f"a {type(value).__name__}"


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
    if is_numeric_column(column):
        if value is None:
            return "", None
        text = _json_number_text(value)
        if text is None:
            return "", f"expected a JSON number, got {_shown(value)}"
        return text, None
    if isinstance(value, str):
        return value, text_fault(value)
    if column == "split":
        return "", f"split must be the string 'fit' or 'check', got {_shown(value)}"
    if column in ("pose_id", "station"):
        if isinstance(value, int) and not isinstance(value, bool) and not _long_integer(value):
            return str(value), None
        return "", f"{column} must be a string or an integer, got {_shown(value)}"
    if value is None:
        return "", None
    if isinstance(value, dict | list):
        return "", "expected a single value (text or number), got a JSON " + type(value).__name__
    if _long_integer(value):
        return "", _shown(value)
    return json.dumps(value), None


def dataset_from_records(
    records: Sequence[Mapping[str, Any]],
    *,
    source: str = "<records>",
    limits_deg: ArrayLike | None = None,
    min_rows: int = 0,
    kind: DatasetKind = "measurement",
    options: ReadOptions | None = None,
) -> Dataset:
    """A :class:`Dataset` from JSON-style records (one object per row, same keys in each).

    The rules are those of the CSV reader; errors name ``record k`` (1-based) instead of a row.
    Numeric columns take JSON numbers (not strings), ``split`` a string, ``pose_id`` a string or
    an integer (so does ``station``); unknown keys are kept as text. Records must all have the same keys.
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
        for key in record:
            problem = text_fault(key)
            if problem is not None:
                raise refuse(f"{problem} (in a key)", i + 1, printable(key))
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
    table = CellTable(
        source=source,
        header=header,
        columns=columns,
        row_numbers=list(range(1, len(records) + 1)),
        row_label="record",
        pre_errors=pre_errors,
    )
    return _built(table, _json_options(options, source), limits_deg=limits_deg, min_rows=min_rows, kind=kind)


def _json_options(options: ReadOptions | None, source: str) -> ReadOptions:
    """JSON numbers have no separator or decimal mark to choose: only the units apply."""
    options = options or ReadOptions()
    if options.decimal_comma or options.delimiter != ",":
        raise DatasetError(
            "--decimal-comma and --delimiter apply to CSV files; JSON numbers are JSON numbers", source=source
        )
    return options


def dataset_from_json(
    doc: JsonRecords,
    *,
    source: str,
    limits_deg: ArrayLike | None = None,
    min_rows: int = 0,
    kind: DatasetKind = "measurement",
    options: ReadOptions | None = None,
) -> Dataset:
    """:func:`dataset_from_records` of a parsed JSON data set; a refusal also names its ``path``."""
    try:
        return dataset_from_records(
            doc.records, source=source, limits_deg=limits_deg, min_rows=min_rows, kind=kind, options=options
        )
    except DatasetError as exc:
        row = exc.row if exc.row_label == "record" else None
        raise DatasetError(
            exc.problem,
            source=exc.source,
            row=exc.row,
            column=exc.column,
            row_label=exc.row_label,
            path=record_path(doc, row, exc.column),
        ) from None


def read_dataset_json(
    path_or_data: str | os.PathLike[str] | bytes | bytearray,
    *,
    limits_deg: ArrayLike | None = None,
    min_rows: int = 0,
    kind: DatasetKind = "measurement",
    source: str | None = None,
    options: ReadOptions | None = None,
) -> Dataset:
    """Read a JSON data set (UTF-8): a list of records or ``{"name": ..., "records": [...]}``.

    The text's rules are :func:`comp_daemon.data.jsontext.load_json_records`'s, the records' those
    of :func:`dataset_from_records`; every refusal is a :class:`DatasetError`. A ``str`` is taken as
    JSON text when it starts with ``[`` or ``{`` (after spaces), else as a path.
    """
    if isinstance(path_or_data, bytes | bytearray):
        raw, name = bytes(path_or_data), "<bytes>"
    elif isinstance(path_or_data, str) and path_or_data.lstrip()[:1] in ("[", "{"):
        raw, name = path_or_data.encode("utf-8", "surrogatepass"), "<text>"
    else:
        raw, name = Path(path_or_data).read_bytes(), str(path_or_data)
    name = source or name
    doc = load_json_records(raw, name)
    return dataset_from_json(
        doc, source=name, limits_deg=limits_deg, min_rows=min_rows, kind=kind, options=options
    )


def read_dataset_file(
    path: str | os.PathLike[str],
    *,
    limits_deg: ArrayLike | None = None,
    min_rows: int = 0,
    kind: DatasetKind = "measurement",
    options: ReadOptions | None = None,
) -> Dataset:
    """A data set file: JSON records when its name ends in ``.json``, else CSV; read with ``options``."""
    reader = read_dataset_json if Path(path).suffix.lower() == ".json" else read_dataset
    return reader(path, limits_deg=limits_deg, min_rows=min_rows, kind=kind, options=options)
