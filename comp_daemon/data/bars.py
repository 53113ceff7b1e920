"""Common ground of the ballbar and cross-bar campaign readers (``docs/data-format.md``, "Ballbar
and cross-bar campaigns"): the table is read by the data set reader (:mod:`comp_daemon.data.readers`, with
``kind="any"``: its header, cell, axis-limit, ``split``, ``repeat`` and ``pose_id`` rules), and the
campaign's own columns, which that reader keeps as unknown text columns, are parsed here with the
same cell rules (:mod:`comp_daemon.data.cells`) and the same errors naming row and column.
"""

from __future__ import annotations

import csv
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from comp_daemon.data.cells import CellFaults, CellTable, parse_numbers
from comp_daemon.data.columns import DatasetError
from comp_daemon.data.jsontext import load_json_records
from comp_daemon.data.options import ReadOptions
from comp_daemon.data.readers import dataset_from_json, parse_dataset
from comp_daemon.data.table import Dataset

__all__ = [
    "BALLBAR_MARKERS",
    "CROSSBAR_MARKERS",
    "CampaignKind",
    "campaign_kind",
    "header_kind",
    "read_table",
    "sniff_campaign",
    "sniff_campaign_file",
]

CampaignKind = Literal["ballbar", "crossbar"]
BALLBAR_MARKERS: tuple[str, ...] = ("bar_mm", "bar_nominal_mm", "dr_um")
CROSSBAR_MARKERS: tuple[str, ...] = ("placement", "socket", "bar_l_mm")


def header_kind(names: Iterable[str]) -> CampaignKind | None:
    """``ballbar`` or ``crossbar`` when the column names hold that form's markers
    (:data:`BALLBAR_MARKERS`, :data:`CROSSBAR_MARKERS`), else ``None``: the one test of a campaign's
    form, on a file's header (:func:`sniff_campaign`) or a table's columns (:func:`campaign_kind`)."""
    present = {name.strip() for name in names}
    if present.intersection(BALLBAR_MARKERS):
        return "ballbar"
    if present.intersection(CROSSBAR_MARKERS):
        return "crossbar"
    return None


def campaign_kind(dataset: Dataset) -> CampaignKind | None:
    """``ballbar`` or ``crossbar`` when the table carries that form's columns, else ``None``."""
    return header_kind(dataset.extra)


SNIFF_BYTES = 65536  # a header longer than this is not a campaign's


def sniff_campaign(data: bytes | bytearray | str, delimiter: str = ",") -> CampaignKind | None:
    """The form a CSV body's first line (fields separated by ``delimiter``) names
    (:func:`header_kind`), the rest unread."""
    head = data[:SNIFF_BYTES]
    text = head.decode("utf-8", "replace") if isinstance(head, bytes | bytearray) else head
    first = text.splitlines()[0] if text else ""
    return header_kind(next(csv.reader([first.removeprefix("\ufeff")], delimiter=delimiter), []))


def sniff_campaign_file(
    path: str | os.PathLike[str], options: ReadOptions | None = None
) -> CampaignKind | None:
    """The form of a campaign file: a CSV file's first line (:func:`sniff_campaign`, fields
    separated as ``options`` say); a ``.json`` file is read whole. ``None`` for a file that cannot
    be read (its reader will say why)."""
    try:
        if Path(path).suffix.lower() == ".json":
            return campaign_kind(read_table(path, options=options))
        with open(path, "rb") as f:
            return sniff_campaign(f.read(SNIFF_BYTES), (options or ReadOptions()).delimiter)
    except (OSError, DatasetError):
        return None


def read_table(
    path_or_data: str | os.PathLike[str] | bytes | bytearray,
    *,
    fmt: Literal["csv", "json"] | None = None,
    source: str | None = None,
    limits_deg: ArrayLike | None = None,
    options: ReadOptions | None = None,
) -> Dataset:
    """The campaign's table: CSV (or JSON records, ``fmt="json"`` or a ``.json`` path) read by the
    data set reader with every column kept; the axis columns a1..a6 are required. ``options``: how
    the file is written (:class:`~comp_daemon.data.options.ReadOptions`; ``--units`` scales the bar
    lengths and the pivot too)."""
    if isinstance(path_or_data, bytes | bytearray):
        raw, name = bytes(path_or_data), "<bytes>"
    elif isinstance(path_or_data, str) and ("\n" in path_or_data or "\r" in path_or_data):
        raw, name = path_or_data.encode("utf-8", "surrogatepass"), "<text>"
    else:
        path = Path(path_or_data)
        raw, name = path.read_bytes(), str(path)
        if fmt is None and path.suffix.lower() == ".json":
            fmt = "json"
    name = source or name
    try:
        if fmt == "json":
            doc = load_json_records(raw, name)
            ds = dataset_from_json(doc, source=name, limits_deg=limits_deg, kind="any", options=options)
        else:
            ds = parse_dataset(raw, source=name, limits_deg=limits_deg, kind="any", options=options)
    except DatasetError as exc:
        if exc.column == "a1" and exc.problem.startswith("required column missing"):
            raise DatasetError(
                "required column missing (a campaign needs the axis values a1..a6)",
                source=exc.source,
                row=exc.row,
                column="a1",
                row_label=exc.row_label,
            ) from None
        raise
    if ds.a_deg is None:
        raise DatasetError(
            "required column missing (a campaign needs the axis values a1..a6)",
            source=ds.source,
            row=1,
            column="a1",
            row_label=ds.row_label,
        )
    return ds


class Columns:
    """The campaign columns of ``dataset`` parsed with the cell rules; faults gathered, the first in
    reading order (row, then column) raised by :meth:`done`."""

    def __init__(self, dataset: Dataset) -> None:
        self.dataset = dataset
        names = list(dataset.extra)
        self.table = CellTable(
            source=dataset.source,
            header=names,
            columns={k: list(v) for k, v in dataset.extra.items()},
            row_numbers=[int(r) for r in dataset.row_numbers],
            row_label=dataset.row_label,
        )
        self.faults = CellFaults(self.table)

    def has(self, name: str) -> bool:
        return name in self.dataset.extra

    def require(self, names: Sequence[str], what: str) -> None:
        """Refuse (header row) a missing column of ``names``."""
        for name in names:
            if not self.has(name):
                raise self.error(f"required column missing ({what})", None, name)

    def error(self, problem: str, i: int | None, column: str | None) -> DatasetError:
        ds = self.dataset
        row = 1 if i is None else int(ds.row_numbers[i])
        return DatasetError(problem, source=ds.source, row=row, column=column, row_label=ds.row_label)

    def numbers(self, name: str) -> NDArray[np.float64] | None:
        return parse_numbers(self.table, self.faults, name)

    def positive(self, name: str) -> NDArray[np.float64] | None:
        values = self.numbers(name)
        if values is None:
            return None
        bad = np.flatnonzero(values <= 0)
        if bad.size:
            i = int(bad[0])
            self.faults.add(name, i, f"must be > 0, got {self.table.columns[name][i]!r}")
            return None
        return values

    def counter(self, name: str) -> NDArray[np.int64] | None:
        """An integer >= 1 per row (``arc``, ``placement``)."""
        values = self.numbers(name)
        if values is None:
            return None
        bad = np.flatnonzero((values != np.round(values)) | (values < 1))
        if bad.size:
            i = int(bad[0])
            self.faults.add(name, i, f"{name} must be an integer >= 1, got {self.table.columns[name][i]!r}")
            return None
        return values.astype(np.int64)

    def choice(self, name: str, allowed: Sequence[str]) -> tuple[str, ...] | None:
        cells = tuple(c.strip() for c in self.table.columns[name])
        for i, cell in enumerate(cells):
            if cell not in allowed:
                hint = f"; did you mean '{cell.upper()}'?" if cell.upper() in allowed else ""
                self.faults.add(
                    name,
                    i,
                    f"{name} must be one of {', '.join(allowed)}, got {self.table.columns[name][i]!r}{hint}",
                )
                return None
        return cells

    def done(self) -> None:
        self.faults.raise_first()


def constant(
    cols: Columns, name: str, values: NDArray[np.float64], groups: NDArray[np.int64] | None = None
) -> None:
    """Refuse ``values`` that vary (within each group when ``groups`` is given), at the first row
    that differs from its group's first."""
    keys = np.zeros(len(values), dtype=np.int64) if groups is None else groups
    first: dict[int, float] = {}
    for i, (k, v) in enumerate(zip(keys.tolist(), values.tolist(), strict=True)):
        if k not in first:
            first[k] = v
        elif v != first[k]:
            where = "the file" if groups is None else "its group"
            raise cols.error(
                f"{name} must be the same in {where} ({first[k]!r} earlier, {v!r} here)", i, name
            )


def whole_groups_split(cols: Columns, groups: NDArray[np.int64], what: str) -> None:
    """Refuse a ``split`` that cuts a group (an arc, a placement) in two."""
    split = cols.dataset.split
    if split is None:
        return
    first: dict[int, str] = {}
    for i, (k, s) in enumerate(zip(groups.tolist(), split.tolist(), strict=True)):
        if k not in first:
            first[k] = s
        elif s != first[k]:
            raise cols.error(f"split applies to whole {what}s: {what} {k} has fit and check rows", i, "split")


def group_split(
    dataset: Dataset, groups: NDArray[np.int64], *, seed: int, check_fraction: float
) -> tuple[NDArray[np.intp], NDArray[np.intp], bool]:
    """(fit rows, check rows, drawn): the file's split, or whole groups drawn reproducibly; with
    one group only, every row is a fit row."""
    if dataset.split is not None:
        return dataset.fit_rows(), dataset.check_rows(), False
    ids = np.unique(groups)
    if ids.size < 2 or check_fraction <= 0.0:
        return np.arange(len(dataset)), np.zeros(0, dtype=np.intp), False
    rng = np.random.default_rng(seed)
    n_check = min(max(1, round(check_fraction * ids.size)), ids.size - 1)
    check_ids = rng.permutation(ids)[:n_check]
    is_check = np.isin(groups, check_ids)
    return np.flatnonzero(~is_check), np.flatnonzero(is_check), True
