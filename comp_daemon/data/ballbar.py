"""Ballbar campaigns (``kind = ballbar``, ``docs/data-format.md``, "Ballbar and cross-bar campaigns").

Columns (free order, unknown columns kept, names lower case):

- ``a1`` … ``a6`` (deg, required): axis values at the sample, as commanded;
- ``bar_mm`` (mm): the measured centre-to-centre length L_a; or instead ``bar_nominal_mm`` (mm) and
  ``dr_um`` (µm), the calibrated nominal length and the reading, L_a = nominal + dr/1000;
- ``cx``, ``cy``, ``cz`` (mm, required, the same in every row): nominal pivot centre, robot base frame;
- ``arc`` (integer ≥ 1, required): trajectory index;
- optional ``pose_id``, ``repeat`` (rows sharing a pose_id are repeats of one sample, needed for the
  uncertainty mode), ``split`` (applies to whole arcs), ``t_s``, ``temp_c``, as the data set format.

Refused, besides the data set format's own rules (header, cells, axis limits): a missing required
column; ``bar_mm`` given together with ``bar_nominal_mm``/``dr_um``; L_a ≤ 0; a pivot column that
varies; an ``arc`` that is not an integer ≥ 1; a ``split`` that cuts an arc; fewer than 15 rows;
in the uncertainty mode a pose with fewer than 2 repeats (the mode is on when asked for, and by
default when some ``pose_id`` is repeated); and, when the caller gives the nominal
TCP (``tcp_mm``, the robot description's forward kinematics), a length more than 5 mm from the
nominal distance of the TCP to the pivot (a wrong pivot or a wrong bar). Each refusal is a
:class:`~comp_daemon.data.columns.DatasetError` naming the row and the column.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from comp_daemon.data.bars import Columns, constant, group_split, read_table, whole_groups_split
from comp_daemon.data.options import ReadOptions
from comp_daemon.data.table import Dataset

__all__ = [
    "BALLBAR_COLUMNS",
    "MIN_BALLBAR_ROWS",
    "PIVOT_TOLERANCE_MM",
    "BallbarCampaign",
    "ballbar_dataset",
    "ballbar_from_dataset",
    "read_ballbar",
]

BALLBAR_COLUMNS: tuple[str, ...] = ("bar_mm", "bar_nominal_mm", "dr_um", "cx", "cy", "cz", "arc")
MIN_BALLBAR_ROWS = 15
PIVOT_TOLERANCE_MM = 5.0

TcpFunction = Callable[[NDArray[np.float64]], NDArray[np.float64]]


@dataclass(frozen=True, slots=True)
class BallbarCampaign:
    """A checked ballbar campaign: the table (``rows``), the lengths L_a, the nominal pivot, the arcs."""

    rows: Dataset
    bar_mm: NDArray[np.float64]  # (n,) measured centre-to-centre length L_a
    pivot_mm: NDArray[np.float64]  # (3,) nominal pivot, robot base frame
    arc: NDArray[np.int64]  # (n,)

    @property
    def a_deg(self) -> NDArray[np.float64]:
        assert self.rows.a_deg is not None
        return self.rows.a_deg

    @property
    def source(self) -> str:
        return self.rows.source

    def __len__(self) -> int:
        return len(self.bar_mm)

    def split(
        self, *, seed: int = 0, check_fraction: float = 0.0
    ) -> tuple[NDArray[np.intp], NDArray[np.intp], bool]:
        """(fit rows, check rows, drawn): the file's ``split``; without one, every row is a fit row
        unless ``check_fraction`` > 0 asks for whole arcs drawn as check arcs."""
        return group_split(self.rows, self.arc, seed=seed, check_fraction=check_fraction)

    @property
    def repeated(self) -> bool:
        """Whether the campaign measures its poses repeatedly (some ``pose_id`` in several rows):
        the uncertainty mode, every pose then has at least 2 repeats."""
        return any(g.size > 1 for g in self.repeat_groups())

    def repeat_groups(self, rows: NDArray[np.intp] | None = None) -> list[NDArray[np.intp]]:
        """Row indices of each pose (rows sharing a ``pose_id``) among ``rows`` (default: all), in
        order of first appearance; within a pose ordered by ``repeat`` when the file has it, so the
        last index is the last repeat."""
        idx = np.arange(len(self)) if rows is None else np.asarray(rows, dtype=np.intp)
        ids = self.rows.pose_id
        if ids is None:
            return [np.array([i]) for i in idx]
        order: dict[str, list[int]] = {}
        for i in idx:
            order.setdefault(ids[int(i)], []).append(int(i))
        rep = self.rows.repeat
        if rep is None:
            return [np.array(v) for v in order.values()]
        return [np.array(sorted(v, key=lambda i: (int(rep[i]), i))) for v in order.values()]


def ballbar_from_dataset(
    dataset: Dataset,
    *,
    tcp_mm: TcpFunction | None = None,
    uncertainty: bool | None = None,
    min_rows: int = MIN_BALLBAR_ROWS,
) -> BallbarCampaign:
    """The ballbar campaign of a table read with every column kept (module docstring for the rules).

    ``uncertainty``: the uncertainty mode (every pose repeated at least twice); ``None`` turns it on
    when some ``pose_id`` is repeated."""
    cols = Columns(dataset)
    has_bar = cols.has("bar_mm")
    has_pair = cols.has("bar_nominal_mm") or cols.has("dr_um")
    if has_bar and has_pair:
        other = "bar_nominal_mm" if cols.has("bar_nominal_mm") else "dr_um"
        raise cols.error("give bar_mm, or bar_nominal_mm with dr_um, not both", None, other)
    if not has_bar:
        if not has_pair:
            raise cols.error(
                "required column missing (the length: bar_mm, or bar_nominal_mm and dr_um)", None, "bar_mm"
            )
        cols.require(("bar_nominal_mm", "dr_um"), "bar_nominal_mm and dr_um come together")
    cols.require(("cx", "cy", "cz"), "the nominal pivot cx, cy, cz")
    cols.require(("arc",), "the trajectory index arc")
    if has_bar:
        bar = cols.positive("bar_mm")
        bar_column = "bar_mm"
    else:
        nominal, dr = cols.positive("bar_nominal_mm"), cols.numbers("dr_um")
        bar = None if nominal is None or dr is None else nominal + dr / 1000.0
        bar_column = "dr_um"
    pivot = [cols.numbers(c) for c in ("cx", "cy", "cz")]
    arc = cols.counter("arc")
    cols.done()
    assert bar is not None and arc is not None and all(p is not None for p in pivot)
    bad = np.flatnonzero(bar <= 0)
    if bad.size:
        raise cols.error(f"the length L_a = {bar[bad[0]]:.6g} mm must be > 0", int(bad[0]), bar_column)
    for name, values in zip(("cx", "cy", "cz"), pivot, strict=True):
        assert values is not None
        constant(cols, name, values)
    whole_groups_split(cols, arc, "arc")
    if len(bar) < min_rows:
        raise cols.error(f"{len(bar)} rows; a ballbar campaign needs at least {min_rows}", None, None)
    pivot_mm = np.array([float(p[0]) for p in pivot if p is not None])
    if tcp_mm is not None:
        assert dataset.a_deg is not None
        nominal_length = np.linalg.norm(tcp_mm(np.asarray(dataset.a_deg)) - pivot_mm, axis=1)
        off = np.abs(bar - nominal_length)
        worst = np.flatnonzero(off > PIVOT_TOLERANCE_MM)
        if worst.size:
            i = int(worst[0])
            raise cols.error(
                f"length {bar[i]:.4f} mm, but the nominal TCP is {nominal_length[i]:.4f} mm from the pivot "
                f"(more than {PIVOT_TOLERANCE_MM:g} mm: a wrong pivot cx, cy, cz or a wrong bar)",
                i,
                bar_column,
            )
    campaign = BallbarCampaign(dataset, bar, pivot_mm, arc)
    if uncertainty is None:
        uncertainty = campaign.repeated
    if uncertainty:
        if dataset.pose_id is None:
            raise cols.error("required column missing (the uncertainty mode needs pose_id)", None, "pose_id")
        for group in campaign.repeat_groups():
            if group.size < 2:
                raise cols.error(
                    f"pose {dataset.pose_id[int(group[0])]!r} has {group.size} repeat; the uncertainty mode "
                    "needs at least 2",
                    int(group[0]),
                    "pose_id",
                )
    return campaign


def read_ballbar(
    path_or_data: str | os.PathLike[str] | bytes | bytearray,
    *,
    fmt: Literal["csv", "json"] | None = None,
    source: str | None = None,
    limits_deg: ArrayLike | None = None,
    options: ReadOptions | None = None,
    tcp_mm: TcpFunction | None = None,
    uncertainty: bool | None = None,
) -> BallbarCampaign:
    """Read a ballbar campaign (CSV, or JSON records) from a path, bytes or text, as ``options`` say
    it is written."""
    table = read_table(path_or_data, fmt=fmt, source=source, limits_deg=limits_deg, options=options)
    return ballbar_from_dataset(table, tcp_mm=tcp_mm, uncertainty=uncertainty)


def ballbar_dataset(
    a_deg: NDArray[np.float64],
    arc: NDArray[np.int64],
    pivot_mm: ArrayLike,
    *,
    bar_mm: NDArray[np.float64] | None = None,
    split: NDArray[np.str_] | None = None,
    pose_id: tuple[str, ...] | None = None,
    repeat: NDArray[np.int64] | None = None,
    extra: dict[str, tuple[str, ...]] | None = None,
    source: str = "<ballbar>",
) -> Dataset:
    """The table of a ballbar campaign (or, without ``bar_mm``, of a ballbar plan) for
    :func:`comp_daemon.data.dataset.write_dataset`."""
    n = len(a_deg)
    pivot = np.asarray(pivot_mm, dtype=float)
    columns: dict[str, tuple[str, ...]] = {}
    if bar_mm is not None:
        columns["bar_mm"] = tuple(repr(float(v)) for v in bar_mm)
    for name, value in zip(("cx", "cy", "cz"), pivot, strict=True):
        columns[name] = (repr(float(value)),) * n
    columns["arc"] = tuple(str(int(k)) for k in arc)
    columns.update(extra or {})
    return Dataset(a_deg=a_deg, split=split, pose_id=pose_id, repeat=repeat, extra=columns, source=source)
