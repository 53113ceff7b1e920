"""The CSV reader: every refusal rule of shared/spec/dataset.md, each with a malformed file."""

from __future__ import annotations

import numpy as np
import pytest

from comp_daemon.data.dataset import DatasetError, read_dataset
from comp_daemon.robot.description import load_robot

LIMITS_DEG = load_robot("kr210").axis_limits_deg

HEADER = "a1,a2,a3,a4,a5,a6,x,y,z"
GOOD_ROW = "0,-90,90,0,30,0,1500.5,-20.25,1700"


def table(*rows: str, header: str = HEADER) -> str:
    return "\n".join((header, *rows)) + "\n"


def row_with(**cells: str) -> str:
    """GOOD_ROW with some cells replaced, by column name of HEADER."""
    names = HEADER.split(",")
    values = GOOD_ROW.split(",")
    for name, value in cells.items():
        values[names.index(name)] = value
    return ",".join(values)


# (id, file content, reader keyword arguments, row, column, words the message must contain)
REFUSALS = [
    ("missing a6", table("0,-90,90,0,30,1,2,3", header="a1,a2,a3,a4,a5,x,y,z"), {}, 1, "a6", "missing"),
    ("missing x,y,z", table("0,-90,90,0,30,0", header="a1,a2,a3,a4,a5,a6"), {}, 1, "x", "missing"),
    (
        "targets need axes or tx,ty,tz",
        table("1,2", header="pose_id,note"),
        {"kind": "targets"},
        1,
        "a1",
        "missing",
    ),
    ("partial x,y,z", table("0,-90,90,0,30,0,1,2", header="a1,a2,a3,a4,a5,a6,x,y"), {}, 1, "z", "missing"),
    (
        "partial dir set",
        table(GOOD_ROW + ",1,1", header=HEADER + ",dir1,dir2"),
        {},
        1,
        "dir3",
        "come together",
    ),
    (
        "ta without tx",
        table("0,-90,90,0,30,0,0,0,0", header="a1,a2,a3,a4,a5,a6,ta,tb,tc"),
        {"kind": "targets"},
        1,
        "tx",
        "tx, ty, tz",
    ),
    ("non-numeric", table(GOOD_ROW, row_with(y="abc")), {}, 3, "y", "not a number"),
    ("decimal comma", table(GOOD_ROW, row_with(x='"1500,5"')), {}, 3, "x", "not a number"),
    ("empty cell", table(row_with(a4="")), {}, 2, "a4", "empty cell"),
    ("blank-space cell", table(row_with(a4="  ")), {}, 2, "a4", "empty cell"),
    ("NaN", table(GOOD_ROW, GOOD_ROW, row_with(z="NaN")), {}, 4, "z", "non-finite"),
    ("inf", table(row_with(x="-inf")), {}, 2, "x", "non-finite"),
    ("overflow", table(row_with(x="1e999")), {}, 2, "x", "non-finite"),
    ("hex float", table(row_with(x="0x1p3")), {}, 2, "x", "not a number"),
    ("underscore digits", table(row_with(x="1_500")), {}, 2, "x", "not a plain decimal"),
    (
        "axis outside limits",
        table(GOOD_ROW, row_with(a2="0")),
        {"limits_deg": LIMITS_DEG},
        3,
        "a2",
        "outside the axis limits [-140, -5]",
    ),
    (
        "axis just outside the upper limit",
        table(row_with(a1="185.000001")),
        {"limits_deg": LIMITS_DEG},
        2,
        "a1",
        "outside",
    ),
    (
        "dir 0",
        table(GOOD_ROW + ",1,1,0,1,1,1", header=HEADER + ",dir1,dir2,dir3,dir4,dir5,dir6"),
        {},
        2,
        "dir3",
        "-1 or +1",
    ),
    (
        "dir 2",
        table(GOOD_ROW + ",1,1,1,1,1,2", header=HEADER + ",dir1,dir2,dir3,dir4,dir5,dir6"),
        {},
        2,
        "dir6",
        "-1 or +1",
    ),
    (
        "dir text",
        table(GOOD_ROW + ",+,1,1,1,1,1", header=HEADER + ",dir1,dir2,dir3,dir4,dir5,dir6"),
        {},
        2,
        "dir1",
        "not a number",
    ),
    (
        "split value",
        table(GOOD_ROW + ",fit", GOOD_ROW + ",train", header=HEADER + ",split"),
        {},
        3,
        "split",
        "'fit' or 'check'",
    ),
    (
        "split case",
        table(GOOD_ROW + ",Check", header=HEADER + ",split"),
        {},
        2,
        "split",
        "did you mean 'check'",
    ),
    ("split empty", table(GOOD_ROW + ",", header=HEADER + ",split"), {}, 2, "split", "'fit' or 'check'"),
    ("duplicate column", table(GOOD_ROW + ",1", header=HEADER + ",x"), {}, 1, "x", "duplicate"),
    ("duplicate after spaces", table(GOOD_ROW + ",1", header=HEADER + ", a3 "), {}, 1, "a3", "duplicate"),
    (
        "duplicate unknown column",
        table(GOOD_ROW + ",1,2", header=HEADER + ",note,note"),
        {},
        1,
        "note",
        "duplicate",
    ),
    ("upper-case name", table(GOOD_ROW, header="A1,a2,a3,a4,a5,a6,x,y,z"), {}, 1, "A1", "did you mean 'a1'"),
    ("unnamed column", table(GOOD_ROW + ",", header=HEADER + ","), {}, 1, None, "no name"),
    ("empty file", "", {}, 1, None, "empty file"),
    ("only spaces and newlines", "  \n\n", {}, 1, None, "empty file"),
    ("blank first line", "\n" + table(GOOD_ROW), {}, 1, None, "header"),
    ("header only", HEADER + "\n", {}, 2, None, "no data rows"),
    ("short row", table(GOOD_ROW, "0,-90,90,0,30,0,1500,1"), {}, 3, "z", "8 fields"),
    ("long row", table(GOOD_ROW + ",7"), {}, 2, None, "10 fields"),
    ("blank line inside", table(GOOD_ROW, "", GOOD_ROW), {}, 3, None, "empty row"),
    ("bad quoting", table(GOOD_ROW, row_with(x='"15"00')), {}, 3, None, "malformed CSV"),
    ("repeat negative", table(GOOD_ROW + ",-1", header=HEADER + ",repeat"), {}, 2, "repeat", "integer >= 0"),
    ("repeat fraction", table(GOOD_ROW + ",1.5", header=HEADER + ",repeat"), {}, 2, "repeat", "integer"),
    ("payload negative", table(GOOD_ROW + ",-5", header=HEADER + ",payload_kg"), {}, 2, "payload_kg", ">= 0"),
    ("grating NaN", table(GOOD_ROW + ",nan", header=HEADER + ",g2"), {}, 2, "g2", "non-finite"),
    (
        "temperature text",
        table(GOOD_ROW + ",warm", header=HEADER + ",temp_c"),
        {},
        2,
        "temp_c",
        "not a number",
    ),
    ("target tz empty", table("1,2,", header="tx,ty,tz"), {"kind": "targets"}, 2, "tz", "empty cell"),
]


@pytest.mark.parametrize(
    ("content", "kwargs", "row", "column", "words"),
    [pytest.param(*case[1:], id=case[0]) for case in REFUSALS],
)
def test_refused_with_row_and_column(
    content: str, kwargs: dict, row: int | None, column: str | None, words: str
) -> None:
    with pytest.raises(DatasetError) as caught:
        read_dataset(content.encode("utf-8"), source="campaign.csv", **kwargs)
    error = caught.value
    message = str(error)
    assert (error.row, error.column) == (row, column), message
    assert message.startswith("campaign.csv, ")
    assert f"row {row}" in message
    if column is not None:
        assert f"column '{column}'" in message
    assert words in message


def test_not_utf8_names_row_and_column() -> None:
    content = (table(GOOD_ROW + ",p1", GOOD_ROW + ",p2", header=HEADER + ",pose_id")).encode("utf-8")
    content = content.replace(b"p2", "pé".encode("latin-1"))
    with pytest.raises(DatasetError) as caught:
        read_dataset(content)
    assert (caught.value.row, caught.value.column) == (3, "pose_id")
    assert "not UTF-8" in str(caught.value)
    assert "0xe9" in str(caught.value)


def test_not_utf8_utf16_file() -> None:
    content = table(GOOD_ROW).encode("utf-16")
    with pytest.raises(DatasetError, match=r"row 1.*not UTF-8"):
        read_dataset(content)


def test_fewer_rows_than_model_parameters_names_both_numbers() -> None:
    content = table(*[GOOD_ROW] * 12)
    with pytest.raises(DatasetError) as caught:
        read_dataset(content, min_rows=39)
    message = str(caught.value)
    assert "12 data rows" in message
    assert "fewer rows than the chosen model has parameters (39)" in message
    assert read_dataset(content, min_rows=12).n == 12


def test_first_fault_in_reading_order_is_reported() -> None:
    content = table(GOOD_ROW, row_with(z="?"), row_with(a1="?"), row_with(a2="-1"))
    with pytest.raises(DatasetError) as caught:
        read_dataset(content, limits_deg=LIMITS_DEG)
    assert (caught.value.row, caught.value.column) == (3, "z")
    content = table(GOOD_ROW, row_with(a2="-1", z="?"))
    with pytest.raises(DatasetError) as caught:
        read_dataset(content, limits_deg=LIMITS_DEG)
    assert (caught.value.row, caught.value.column) == (3, "a2")
    content = table(GOOD_ROW, row_with(a5="999"), row_with(a3="?"))
    with pytest.raises(DatasetError) as caught:
        read_dataset(content, limits_deg=LIMITS_DEG)
    assert (caught.value.row, caught.value.column) == (3, "a5")


def test_fault_in_last_of_many_rows_refuses_the_whole_file() -> None:
    rows = [GOOD_ROW] * 2000 + [row_with(y="")]
    with pytest.raises(DatasetError) as caught:
        read_dataset(table(*rows))
    assert caught.value.row == 2002


def test_row_numbers_follow_lines_of_the_file() -> None:
    content = table(GOOD_ROW, row_with(x='"1500"'), header=HEADER + "") + "\n\n"
    dataset = read_dataset("\ufeff" + content)
    assert dataset.row_numbers.tolist() == [2, 3]
    quoted = HEADER + ",note\n" + GOOD_ROW + ',"two\nlines"\n' + GOOD_ROW + ",x\n"
    with_newline = read_dataset(quoted)
    assert with_newline.row_numbers.tolist() == [2, 4]
    assert with_newline.extra["note"] == ("two\nlines", "x")


def test_accepts_what_the_spec_allows() -> None:
    header = (
        "pose_id, z ,y,x,a6,a5,a4,a3,a2,a1,g3,g1,payload_kg,temp_c,t_s,split,repeat,note,"
        "dir1,dir2,dir3,dir4,dir5,dir6"
    )
    content = (
        header
        + "\r\n"
        + "P1,1700,-20.25,1500.5,0,30,0,90,-90,0,90.001,0.002,120,21.5,0,fit,0,first,1,-1,+1,1.0,-1.0,1\r\n"
        + "P2, 1e3 ,.5,-0.0,0,30,0,90,-90,0,89.999,-0.002,0,21.75,12.5,check,1,,-1,1,1,1,1,1\r\n"
    )
    dataset = read_dataset(content, limits_deg=LIMITS_DEG)
    assert dataset.a_deg is not None and dataset.xyz_mm is not None and dataset.dir is not None
    np.testing.assert_array_equal(dataset.a_deg[0], [0, -90, 90, 0, 30, 0])
    np.testing.assert_array_equal(dataset.xyz_mm, [[1500.5, -20.25, 1700], [-0.0, 0.5, 1000]])
    assert np.signbit(dataset.xyz_mm[1, 0])
    assert dataset.dir.dtype == np.int8
    np.testing.assert_array_equal(dataset.dir[0], [1, -1, 1, 1, -1, 1])
    assert dataset.g_present.tolist() == [True, False, True, False, False, False]
    assert dataset.g_deg is not None
    np.testing.assert_array_equal(dataset.g_deg[:, [0, 2]], [[0.002, 90.001], [-0.002, 89.999]])
    assert np.isnan(dataset.g_deg[:, [1, 3, 4, 5]]).all()
    np.testing.assert_array_equal(dataset.payload_kg, [120, 0])
    assert dataset.split is not None and dataset.split.tolist() == ["fit", "check"]
    assert dataset.fit_rows().tolist() == [0] and dataset.check_rows().tolist() == [1]
    assert dataset.repeat is not None and dataset.repeat.tolist() == [0, 1]
    assert dataset.pose_id == ("P1", "P2")
    assert dict(dataset.extra) == {"note": ("first", "")}
    assert dataset.temp_c is not None and dataset.t_s is not None
    assert dataset.target_xyz_mm is None


def test_payload_defaults_to_zero_and_limits_are_inclusive() -> None:
    edge = row_with(a1="185", a2="-5", a3="-120")
    dataset = read_dataset(table(edge), limits_deg=LIMITS_DEG)
    np.testing.assert_array_equal(dataset.payload_kg, [0.0])
    assert dataset.dir is None and dataset.g_deg is None and dataset.split is None


def test_target_files() -> None:
    poses = read_dataset(
        table("1500,0,1700,180,0,180", "1400,10,1650,170,5,-175", header="tx,ty,tz,ta,tb,tc"), kind="targets"
    )
    assert poses.a_deg is None
    assert poses.target_xyz_mm is not None and poses.target_abc_deg is not None
    np.testing.assert_array_equal(poses.target_abc_deg[1], [170, 5, -175])
    axes = read_dataset(
        table("0,-90,90,0,30,0", header="a1,a2,a3,a4,a5,a6"), kind="targets", limits_deg=LIMITS_DEG
    )
    assert axes.a_deg is not None and axes.xyz_mm is None
    with pytest.raises(DatasetError, match="column 'a1'"):
        read_dataset(table("1500,0,1700", header="tx,ty,tz"), kind="measurement")
    with pytest.raises(DatasetError, match=r"row 2, column 'a2'.*outside"):
        read_dataset(
            table("0,0,90,0,30,0", header="a1,a2,a3,a4,a5,a6"), kind="targets", limits_deg=LIMITS_DEG
        )


def test_reads_path_and_binary_file(tmp_path) -> None:
    path = tmp_path / "campaign.csv"
    path.write_text(table(GOOD_ROW), encoding="utf-8")
    from_path = read_dataset(path)
    assert from_path.source == str(path)
    with path.open("rb") as handle:
        assert read_dataset(handle) == from_path
    assert read_dataset(str(path)) == from_path
    bad = tmp_path / "bad.csv"
    bad.write_text(table(row_with(z="")), encoding="utf-8")
    with pytest.raises(DatasetError, match=r"bad\.csv, row 2, column 'z'"):
        read_dataset(bad)


def test_bad_arguments_are_programming_errors() -> None:
    with pytest.raises(ValueError, match="kind"):
        read_dataset(table(GOOD_ROW), kind="poses")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"shape \(6, 2\)"):
        read_dataset(table(GOOD_ROW), limits_deg=np.zeros((6, 3)))
