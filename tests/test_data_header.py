"""The header rules (data/header.py) on their own, and the column-group parsers of data/cells.py."""

from __future__ import annotations

import numpy as np
import pytest

from comp_daemon.data.cells import CellFaults, CellTable, _parse_block, _parse_bounded
from comp_daemon.data.columns import AXIS_COLUMNS, DatasetError
from comp_daemon.data.header import check_header, reflector_count, separator_fault

AXES = list(AXIS_COLUMNS)
XYZ = ["x", "y", "z"]


def _refusal(header: list[str], kind: str = "measurement") -> DatasetError:
    with pytest.raises(DatasetError) as info:
        check_header(header, kind, source="h.csv")  # type: ignore[arg-type]
    assert info.value.row == 1
    return info.value


@pytest.mark.parametrize(
    ("header", "column", "words"),
    [
        ([*AXES, "x", "y"], "z", "x, y, z come together"),
        ([*AXES, *XYZ, "ta", "tb", "tc"], "tx", "need the target position"),
        ([*AXES, *XYZ, "x", "q"], "x", "duplicate column name"),
        ([*AXES, *XYZ, "X2", "y2", "z2"], "X2", "did you mean 'x2'"),
        ([*AXES, *XYZ, "x3", "y3", "z3"], "x2", "target 3 is given, target 2 is not"),
        ([*AXES, "qw", "qx", "qy", "qz"], "x", "needs its position"),
        (AXES, "x", "measurement data needs a1..a6 and x, y, z"),
        ([*AXES, "x_mm", "y", "z"], "x", "found 'x_mm'"),
    ],
)
def test_header_refusals_name_the_column(header: list[str], column: str, words: str) -> None:
    error = _refusal(header)
    assert error.column == column
    assert words in str(error)


def test_header_kinds_need_their_columns() -> None:
    check_header([*AXES, *XYZ], "measurement", source="h")
    check_header(["tx", "ty", "tz"], "targets", source="h")
    check_header(AXES, "any", source="h")
    assert "a1..a6, or a target pose" in str(_refusal(["pose_id"], "targets"))


def test_separator_fault_names_the_option_and_reflectors_count() -> None:
    assert "--delimiter ';'" in (separator_fault(["a1;a2;a3"]) or "")
    assert "--delimiter tab" in (separator_fault(["a1\ta2"]) or "")
    assert separator_fault(["a1", "a2"]) is None
    assert reflector_count([*XYZ]) == 1
    assert reflector_count([*XYZ, "x2", "y2", "z2", "x3", "y3", "z3"]) == 3


def _table(columns: dict[str, list[str]]) -> CellTable:
    n = len(next(iter(columns.values())))
    return CellTable(source="t", header=list(columns), columns=columns, row_numbers=list(range(2, n + 2)))


def test_block_checks_each_column_against_its_axis_limits() -> None:
    limits = np.array([[-10.0, 10.0]] * 6)
    ok = _table({name: ["1", "-2"] for name in AXES})
    np.testing.assert_array_equal(
        _parse_block(ok, CellFaults(ok), AXIS_COLUMNS, limits), [[1.0] * 6, [-2.0] * 6]
    )
    cells = {name: ["1", "-2"] for name in AXES} | {"a4": ["1", "10.5"]}
    bad = _table(cells)
    faults = CellFaults(bad)
    assert _parse_block(bad, faults, AXIS_COLUMNS, limits) is None
    with pytest.raises(DatasetError, match=r"10\.5 deg is outside the axis limits \[-10, 10\]") as info:
        faults.raise_first()
    assert (info.value.row, info.value.column) == (3, "a4")
    assert _parse_block(ok, CellFaults(ok), ("x", "y", "z")) is None  # an absent group


def test_bounded_column_refuses_the_first_marked_value_with_its_text() -> None:
    table = _table({"sigma_mm": ["0.1", "0", "-1"]})
    faults = CellFaults(table)
    _parse_bounded(table, faults, "sigma_mm", lambda v: v <= 0, "sigma must be > 0")
    with pytest.raises(DatasetError, match="sigma must be > 0, got '0'") as info:
        faults.raise_first()
    assert info.value.row == 3
    assert _parse_bounded(table, CellFaults(table), "payload_kg", lambda v: v < 0, "never") is None
