"""Reading a target file row by row: the good rows, and each refused row with its reason.

A measurement campaign is refused as a whole on any fault (:mod:`comp_daemon.data.readers`): a fit
on part of a campaign would be silently different. A target file is a program, one row per hole;
a bad row there must not stop the others. :func:`read_rows` applies the very same rules (the same
table builder, :func:`comp_daemon.data.cells.build_dataset`) and, when the reader refuses a data
row, sets that row aside with the reader's sentence and reads the rest again, until what is left
is accepted. A fault that is not one row's (the header, a missing column, text that is not UTF-8
or not CSV / JSON at all) still refuses the file: :class:`DatasetError`, as from the reader.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from comp_daemon.data.cells import CellTable, DatasetKind, build_dataset, text_fault
from comp_daemon.data.columns import DatasetError
from comp_daemon.data.jsontext import load_json_records
from comp_daemon.data.options import ReadOptions
from comp_daemon.data.readers import dataset_from_records, read_dataset, read_dataset_json
from comp_daemon.data.table import Dataset

__all__ = ["RowRefusal", "RowwiseRead", "read_rows"]


@dataclass(frozen=True, slots=True)
class RowRefusal:
    """One row set aside: ``row`` as the reader numbers it (CSV: file row, header = 1; JSON: the
    1-based record), the ``column`` at fault when there is one, and the reader's ``problem``."""

    row: int
    column: str | None
    problem: str
    row_label: str = "row"

    def __str__(self) -> str:
        where = f"{self.row_label} {self.row}" + (f", column '{self.column}'" if self.column else "")
        return f"{where}: {self.problem}"


@dataclass(frozen=True, slots=True)
class RowwiseRead:
    """The accepted rows (``dataset``, whose ``row_numbers`` are the file's) and the refused ones;
    ``dataset`` is None when no row was accepted. ``row_label`` is how the file numbers its rows:
    ``"row"`` (CSV, header = row 1) or ``"record"`` (JSON)."""

    dataset: Dataset | None
    refused: tuple[RowRefusal, ...]
    row_label: str = "row"


@dataclass(frozen=True, slots=True)
class _Rows:
    """A file's data rows: their numbers as the reader gives them, those refused before the table is
    built (a record of the wrong length), and a reader of a subset that keeps the file's numbers."""

    numbers: list[int]
    read: Callable[[list[int]], Dataset]
    refused: dict[int, RowRefusal]


def read_rows(
    path: str | os.PathLike[str],
    *,
    limits_deg: ArrayLike | None = None,
    kind: DatasetKind = "targets",
    options: ReadOptions | None = None,
) -> RowwiseRead:
    """Read ``path`` (``.json`` records, else CSV) by the reader's rules, setting refused rows aside.

    ``options`` say how the file is written (separator, decimal comma, units), as for the reader;
    a JSON file read with options other than the defaults is refused whole on a row's fault."""
    options = options or ReadOptions()
    is_json = Path(path).suffix.lower() == ".json"
    reader = read_dataset_json if is_json else read_dataset
    label = "record" if is_json else "row"
    try:
        return RowwiseRead(reader(path, limits_deg=limits_deg, kind=kind, options=options), (), label)
    except DatasetError as exc:
        if not _one_rows_fault(exc) or (is_json and not options.is_default):
            raise
    source = str(path)
    data = Path(path).read_bytes()
    rows = (
        _json_rows(data, source, limits_deg, kind)
        if is_json
        else _csv_rows(data, source, limits_deg, kind, options)
    )
    refused = dict(rows.refused)
    keep = [i for i in range(len(rows.numbers)) if i not in refused]
    while keep:
        try:
            return RowwiseRead(rows.read(keep), _sorted(refused), label)
        except DatasetError as exc:
            if not _one_rows_fault(exc):
                raise
            assert exc.row is not None
            # CSV faults name the file's row; JSON ones the record's place among those read
            index = rows.numbers.index(exc.row) if exc.row_label == "row" else keep[exc.row - 1]
            refused[index] = RowRefusal(rows.numbers[index], exc.column, exc.problem, exc.row_label)
            keep.remove(index)
    return RowwiseRead(None, _sorted(refused), label)


def _one_rows_fault(exc: DatasetError) -> bool:
    """A fault in one data row (not the header, a whole column's absence, or the text itself)."""
    if exc.row is None or exc.row_label == "line":
        return False
    return exc.row_label == "record" or exc.row > 1


def _sorted(refused: dict[int, RowRefusal]) -> tuple[RowRefusal, ...]:
    return tuple(refused[i] for i in sorted(refused))


def _csv_rows(
    data: bytes, source: str, limits_deg: ArrayLike | None, kind: DatasetKind, options: ReadOptions
) -> _Rows:
    """The CSV file's data records (the reader has accepted its text and header) and a reader of a
    subset of them that keeps the file's row numbers."""
    text = data.decode("utf-8").removeprefix("\ufeff")
    reader = csv.reader(io.StringIO(text, newline=""), strict=True, delimiter=options.delimiter)
    header = [h.strip() for h in next(reader)]
    records: list[list[str]] = []
    lines: list[int] = []
    refused: dict[int, RowRefusal] = {}
    line = reader.line_num + 1
    for record in reader:
        if record:  # blank lines: the reader allows them only at the end, and then ignores them
            problem = next(filter(None, map(text_fault, record)), None)
            if len(record) != len(header):
                problem = f"{len(record)} fields, but the header has {len(header)} columns"
            if problem is not None:
                refused[len(records)] = RowRefusal(line, None, problem)  # read() fills it in blank
            records.append(record)
            lines.append(line)
        line = reader.line_num + 1

    def subset(keep: list[int]) -> Dataset:
        columns = {
            name: [records[i][k] if len(records[i]) == len(header) else "" for i in keep]
            for k, name in enumerate(header)
        }
        table = CellTable(source=source, header=header, columns=columns, row_numbers=[lines[i] for i in keep])
        dataset = build_dataset(options.convert(table), limits_deg=limits_deg, min_rows=0, kind=kind)
        options.check_units(dataset)
        return dataset

    return _Rows(lines, subset, refused)


def _json_rows(data: bytes, source: str, limits_deg: ArrayLike | None, kind: DatasetKind) -> _Rows:
    """The JSON file's records and a reader of a subset of them numbered as in the file."""
    records = load_json_records(data, source).records

    def subset(keep: list[int]) -> Dataset:
        dataset = dataset_from_records(
            [records[i] for i in keep], source=source, limits_deg=limits_deg, kind=kind
        )
        return dataclasses.replace(dataset, row_numbers=np.asarray(keep, dtype=np.int64) + 1)

    return _Rows(list(range(1, len(records) + 1)), subset, {})
