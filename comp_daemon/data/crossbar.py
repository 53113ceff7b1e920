"""Cross-bar campaigns (``kind = crossbar``, ``docs/data-format.md``, "Ballbar and cross-bar campaigns").

Columns (free order, unknown columns kept, names lower case):

- ``a1`` … ``a6`` (deg, required): axis readings with the probe ball seated;
- ``placement`` (integer ≥ 1, required): the cross-bar placement;
- ``socket`` (``A``/``B``/``C``/``D``, required): A–C and B–D are the two bars;
- ``bar_l_mm`` (mm, required): the known length |AC| = |BD| of this cross;
- optional ``x``, ``y``, ``z`` (the TCP the controller shows: kept, not fitted), ``repeat``,
  ``pose_id``, ``split`` (applies to whole placements), ``t_s``, ``temp_c``.

Refused, besides the data set format's own rules: a missing required column; a placement (within a
repeat) lacking a socket or holding one twice; ``bar_l_mm`` ≤ 0 or varying within a placement; a
``split`` that cuts a placement; fewer placements than the 21 identifiable parameters need (3 rows
per placement, twice the unknowns: 14). Errors name the row and the column.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from comp_daemon.data.bars import Columns, constant, group_split, read_table, whole_groups_split
from comp_daemon.data.options import ReadOptions
from comp_daemon.data.table import Dataset

__all__ = [
    "CROSSBAR_COLUMNS",
    "CROSSBAR_UNKNOWNS",
    "SOCKETS",
    "CrossbarCampaign",
    "crossbar_dataset",
    "crossbar_from_dataset",
    "read_crossbar",
]

SOCKETS: tuple[str, ...] = ("A", "B", "C", "D")
CROSSBAR_COLUMNS: tuple[str, ...] = ("placement", "socket", "bar_l_mm")
CROSSBAR_UNKNOWNS = 21  # identifiable MDH parameters with an off-axis probe (spec B.3)


@dataclass(frozen=True, slots=True)
class CrossbarCampaign:
    """A checked cross-bar campaign, grouped by (placement, repeat): one group is one seated cross."""

    rows: Dataset
    placement: NDArray[np.int64]  # (n,)
    socket: tuple[str, ...]  # (n,)
    bar_l_mm: NDArray[np.float64]  # (n,)
    group_rows: NDArray[np.intp]  # (g, 4) row of socket A, B, C, D of each group
    group_placement: NDArray[np.int64]  # (g,)

    @property
    def source(self) -> str:
        return self.rows.source

    def __len__(self) -> int:
        return len(self.placement)

    @property
    def n_placements(self) -> int:
        return int(np.unique(self.placement).size)

    def readings(
        self, groups: NDArray[np.intp] | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Axis readings (g, 4, 6), sockets in A, B, C, D order, and the bar lengths (g,)."""
        assert self.rows.a_deg is not None
        idx = self.group_rows if groups is None else self.group_rows[groups]
        return np.asarray(self.rows.a_deg)[idx], self.bar_l_mm[idx[:, 0]]

    def split(
        self, *, seed: int = 0, check_fraction: float = 0.0
    ) -> tuple[NDArray[np.intp], NDArray[np.intp], bool]:
        """(fit groups, check groups, drawn), indices into the groups: the file's ``split``, or
        whole placements drawn as check placements when ``check_fraction`` > 0."""
        _, check_rows, drawn = group_split(
            self.rows, self.placement, seed=seed, check_fraction=check_fraction
        )
        is_check = np.isin(self.group_rows[:, 0], check_rows)
        return np.flatnonzero(~is_check), np.flatnonzero(is_check), drawn


def crossbar_from_dataset(dataset: Dataset, *, min_placements: int | None = None) -> CrossbarCampaign:
    """The cross-bar campaign of a table read with every column kept (module docstring for the rules)."""
    cols = Columns(dataset)
    cols.require(CROSSBAR_COLUMNS, "a cross-bar campaign needs placement, socket and bar_l_mm")
    placement = cols.counter("placement")
    socket = cols.choice("socket", SOCKETS)
    bar_l = cols.positive("bar_l_mm")
    cols.done()
    assert placement is not None and socket is not None and bar_l is not None
    constant(cols, "bar_l_mm", bar_l, placement)
    whole_groups_split(cols, placement, "placement")
    repeat = np.zeros(len(placement), dtype=np.int64) if dataset.repeat is None else dataset.repeat
    groups: dict[tuple[int, int], dict[str, int]] = {}
    for i, key in enumerate(zip(placement.tolist(), repeat.tolist(), strict=True)):
        seen = groups.setdefault(key, {})
        if socket[i] in seen:
            raise cols.error(
                f"placement {key[0]} (repeat {key[1]}) holds socket {socket[i]} twice "
                f"(rows {int(dataset.row_numbers[seen[socket[i]]])} and {int(dataset.row_numbers[i])})",
                i,
                "socket",
            )
        seen[socket[i]] = i
    for (p, r), seen in groups.items():
        if len(seen) < len(SOCKETS):
            missing = ", ".join(s for s in SOCKETS if s not in seen)
            first = min(seen.values())
            raise cols.error(f"placement {p} (repeat {r}) lacks socket {missing}", first, "socket")
    needed = (2 * CROSSBAR_UNKNOWNS + 2) // 3 if min_placements is None else min_placements
    n_placements = int(np.unique(placement).size)
    if n_placements < needed:
        raise cols.error(
            f"{n_placements} placements give {3 * n_placements} rows; {CROSSBAR_UNKNOWNS} unknowns need "
            f"twice as many ({needed} placements)",
            None,
            None,
        )
    group_rows = np.array([[seen[s] for s in SOCKETS] for seen in groups.values()], dtype=np.intp)
    group_placement = np.array([k[0] for k in groups], dtype=np.int64)
    return CrossbarCampaign(dataset, placement, socket, bar_l, group_rows, group_placement)


def read_crossbar(
    path_or_data: str | os.PathLike[str] | bytes | bytearray,
    *,
    fmt: Literal["csv", "json"] | None = None,
    source: str | None = None,
    limits_deg: ArrayLike | None = None,
    options: ReadOptions | None = None,
) -> CrossbarCampaign:
    """Read a cross-bar campaign (CSV, or JSON records) from a path, bytes or text, as ``options`` say
    it is written."""
    table = read_table(path_or_data, fmt=fmt, source=source, limits_deg=limits_deg, options=options)
    return crossbar_from_dataset(table)


def crossbar_dataset(
    a_deg: NDArray[np.float64],
    bar_l_mm: NDArray[np.float64],
    *,
    xyz_mm: NDArray[np.float64] | None = None,
    split: NDArray[np.str_] | None = None,
    source: str = "<crossbar>",
) -> Dataset:
    """The table of a cross-bar campaign from readings ``a_deg`` (p, 4, 6) in A, B, C, D order and the
    bar length of each placement (p,), placements numbered from 1; ``split`` (p,) per placement."""
    a = np.asarray(a_deg, dtype=float)
    p = a.shape[0]
    placement = np.repeat(np.arange(1, p + 1), 4)
    lengths = np.repeat(np.asarray(bar_l_mm, dtype=float), 4)
    extra = {
        "placement": tuple(str(int(k)) for k in placement),
        "socket": SOCKETS * p,
        "bar_l_mm": tuple(repr(float(v)) for v in lengths),
    }
    return Dataset(
        a_deg=a.reshape(-1, 6),
        xyz_mm=None if xyz_mm is None else np.asarray(xyz_mm).reshape(-1, 3),
        split=None if split is None else np.repeat(np.asarray(split), 4),
        extra=extra,
        source=source,
    )
