"""The readers' input rules: text no data set may hold is refused with a DatasetError that names
where it is (JSON: the value's path, record and column; CSV: row and column), never another error."""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from comp_daemon.data.dataset import (
    Dataset,
    DatasetError,
    dataset_from_records,
    dataset_to_csv,
    parse_dataset,
    read_dataset,
    read_dataset_json,
)
from comp_daemon.data.jsontext import JSON_MAX_INT_DIGITS, load_json_records

GOOD = {"a1": 0, "a2": -90, "a3": 90, "a4": 0, "a5": 30, "a6": 0, "x": 1.5, "y": 2, "z": 3}


def record(extra: str = "") -> str:
    """One record as JSON text with ``extra`` (``, "key": value`` text) written verbatim at its end."""
    return "{" + ", ".join(f'"{k}": {v}' for k, v in GOOD.items()) + extra + "}"


@pytest.mark.parametrize(
    ("text", "path", "row", "column", "words"),
    [
        ("[" + record(', "x": 4') + "]", "$[0].x", 1, "x", "given twice"),
        (
            '{"records": [' + record() + ", " + record(', "a2": -80') + "]}",
            "$.records[1].a2",
            2,
            "a2",
            "twice",
        ),
        ('{"records": [], "records": [' + record() + "]}", "$.records", None, None, "twice"),
        ("[" + record(', "note": "\\ud800"') + "]", "$[0].note", 1, "note", "lone surrogate (U+D800)"),
        ("[" + record(', "note": "ok\\udfffok"') + "]", "$[0].note", 1, "note", "lone surrogate (U+DFFF)"),
        ("[" + record(', "note": "a\\u0000b"') + "]", "$[0].note", 1, "note", "NUL"),
        ("[" + record(', "pose_id": "\\u0000"') + "]", "$[0].pose_id", 1, "pose_id", "NUL"),
        ("[" + record(', "n": ' + "1" * 5000) + "]", "$[0].n", 1, "n", "5000 digits"),
        ("[" + record(', "n": -' + "9" * 400) + "]", "$[0].n", 1, "n", "400 digits"),
        ("[" + record(', "q": [1, ' + "7" * 310 + "]") + "]", "$[0].q[1]", 1, "q", "310 digits"),
        ('[{"a1\\udc80": 1}]', "$[0]['a1\\udc80']", 1, "a1\\udc80", "in a key"),
        ('[{"a\\u0000": 1}]', "$[0]['a\\x00']", 1, "a\x00", "in a key"),
        ('{"name": "\\ud800", "records": [' + record() + "]}", "$.name", None, None, "lone surrogate"),
        ("[" + record() + ", " + record(', "a2": -80, "a2": -70') + "]", "$[1].a2", 2, "a2", "twice"),
    ],
)
def test_json_text_faults_name_the_path_record_and_column(
    tmp_path: Path, text: str, path: str, row: int | None, column: str | None, words: str
) -> None:
    file = tmp_path / "data.json"
    file.write_text(text, encoding="utf-8")
    with pytest.raises(DatasetError) as caught:
        read_dataset_json(file)
    error = caught.value
    assert (error.path, error.row, error.column) == (path, row, column)
    assert words in error.problem and path in str(error) and str(file) in str(error)
    if row is not None:
        assert error.row_label == "record" and f"record {row}, column '{column}'" in str(error)
    str(error).encode("utf-8")  # the message itself is Unicode that can be written


def test_escapes_that_are_unicode_are_kept() -> None:
    ds = read_dataset_json("[" + record(', "note": "\\u00e9\\ud83d\\ude00 \\\\u0000"') + "]")
    assert ds.extra["note"] == ("\u00e9\U0001f600 \\u0000",)


def test_a_faulty_value_is_found_in_document_order() -> None:
    text = "[" + record(', "n": ' + "1" * 400) + ", " + record(', "x": 9') + "]"
    with pytest.raises(DatasetError, match="400 digits") as caught:
        read_dataset_json(text)
    assert caught.value.path == "$[0].n"


def test_integers_up_to_any_double_are_numbers() -> None:
    big = "1" + "0" * (JSON_MAX_INT_DIGITS - 1)  # 1e308: a double
    doc = load_json_records(("[" + record(', "n": ' + big) + "]").encode(), "t")
    assert doc.records[0]["n"] == 10 ** (JSON_MAX_INT_DIGITS - 1)
    with pytest.raises(DatasetError, match="finite") as caught:
        read_dataset_json("[" + record().replace('"x": 1.5', '"x": ' + "9" * JSON_MAX_INT_DIGITS) + "]")
    assert (caught.value.row, caught.value.column, caught.value.path) == (1, "x", "$[0].x")


def test_record_faults_carry_the_path_of_the_value(tmp_path: Path) -> None:
    file = tmp_path / "targets.json"
    file.write_text(
        '{"name": "n", "records": [' + record() + ", " + record().replace('"z": 3', '"z": "3"') + "]}"
    )
    with pytest.raises(DatasetError, match="expected a JSON number") as caught:
        read_dataset_json(file)
    assert (caught.value.path, caught.value.row, caught.value.column) == ("$.records[1].z", 2, "z")
    missing = "[" + record() + ", " + record().replace(', "z": 3', "") + "]"
    with pytest.raises(DatasetError, match="missing key") as caught:
        read_dataset_json(missing)
    assert (caught.value.path, caught.value.row, caught.value.column) == ("$[1]", 2, "z")
    with pytest.raises(DatasetError, match="no records") as caught:
        read_dataset_json('{"records": []}')
    assert caught.value.path == "$.records"


def test_the_object_form_reads_as_the_list() -> None:
    listed = read_dataset_json("[" + record() + "]")
    assert read_dataset_json('{"name": "cell 3", "records": [' + record() + "]}") == listed
    doc = load_json_records(b'{"name": "cell 3", "records": []}', "t")
    assert (doc.name, doc.prefix) == ("cell 3", ("records",))


def test_json_syntax_and_encoding_faults_name_the_line() -> None:
    with pytest.raises(DatasetError, match="not valid JSON") as caught:
        read_dataset_json(b'[\n{"a1": 0,\n')
    assert (caught.value.row, caught.value.row_label, caught.value.path) == (3, "line", None)
    with pytest.raises(DatasetError, match="not UTF-8") as caught:
        read_dataset_json(b'[\n{"a1": "\xff"}]')
    assert (caught.value.row, caught.value.row_label) == (2, "line")
    with pytest.raises(DatasetError, match="nested too deeply"):
        read_dataset_json(b"[" * 100_000)


@pytest.mark.parametrize(
    ("value", "column", "words"),
    [
        ("a\x00b", "note", "NUL"),
        ("\ud800", "note", "lone surrogate"),
        ("fi\x00t", "split", "NUL"),
        ("p\udc00", "pose_id", "lone surrogate"),
        (10**5000, "pose_id", "beyond any number"),
        (-(10**400), "note", "beyond any number"),
        (10**5000, "a1", "finite"),
        ([10**5000], "split", "'fit' or 'check'"),
    ],
    ids=["nul", "surrogate", "split-nul", "pose-id-surrogate", "pose-id-int", "int-text", "int-axis", "list"],
)
def test_records_given_as_objects_follow_the_same_rules(value: Any, column: str, words: str) -> None:
    records = (
        [GOOD, {**GOOD, column: value}]
        if column in GOOD
        else [{**GOOD, column: "x"}, {**GOOD, column: value}]
    )
    if column == "split":
        records[0] = {**GOOD, "split": "fit"}
    with pytest.raises(DatasetError, match=words) as caught:
        dataset_from_records(records)
    assert (caught.value.row, caught.value.column) == (2, column)


def test_a_key_that_is_not_unicode_is_refused_in_records() -> None:
    with pytest.raises(DatasetError, match="lone surrogate") as caught:
        dataset_from_records([{**GOOD, "n\ud800": 1}])
    assert (caught.value.row, caught.value.column) == (1, "n\\ud800")


CSV_HEADER = ",".join([*GOOD, "note"])
CSV_LINE = ",".join(str(v) for v in GOOD.values())


@pytest.mark.parametrize(
    ("text", "row", "column", "words"),
    [
        (f"{CSV_HEADER}\n{CSV_LINE},fine\n{CSV_LINE},bad\x00value\n", 3, "note", "NUL"),
        (f'{CSV_HEADER}\n{CSV_LINE},"quoted\x00"\n', 2, "note", "NUL"),
        (CSV_HEADER + "\n" + CSV_LINE.replace("1.5", "1.5\x00") + ",x\n", 2, "x", "NUL"),
        (f"{CSV_HEADER},n\x00te\n{CSV_LINE},x,y\n", 1, None, "NUL"),
        (f"{CSV_HEADER}\n{CSV_LINE},x\n{CSV_LINE},x\x00\n{CSV_LINE},1\n", 3, "note", "field 10"),
    ],
)
def test_csv_nul_is_refused_with_row_and_column(
    tmp_path: Path, text: str, row: int, column: str | None, words: str
) -> None:
    file = tmp_path / "data.csv"
    file.write_bytes(text.encode("utf-8"))
    with pytest.raises(DatasetError, match=words) as caught:
        read_dataset(file)
    assert (caught.value.row, caught.value.column, caught.value.path) == (row, column, None)


def test_csv_text_with_a_lone_surrogate_is_refused() -> None:
    with pytest.raises(DatasetError, match="lone surrogate") as caught:
        parse_dataset(f"{CSV_HEADER}\n{CSV_LINE},\udc80\n")
    assert (caught.value.row, caught.value.column) == (2, "note")


def test_a_refusal_keeps_its_fields_across_processes() -> None:
    error = DatasetError("bad", source="s", row=2, column="a1", row_label="record", path="$[1].a1")
    copy = pickle.loads(pickle.dumps(error))
    fields = ("problem", "source", "row", "column", "row_label", "path")
    assert [getattr(copy, f) for f in fields] == [getattr(error, f) for f in fields]
    assert str(copy) == str(error)


# ------------------------------------------------------------------------- property: JSON-ish bytes
JSON_PIECES = st.sampled_from(
    [
        "[",
        "]",
        "{",
        "}",
        ",",
        ":",
        " ",
        "\n",
        '"a1"',
        '"x"',
        '"note"',
        '"records"',
        '"name"',
        '"\\ud800"',
        '"\\udc80x"',
        '"\\u0000"',
        '"\\ud83d\\ude00"',
        '"fit"',
        "0",
        "-90",
        "1.5",
        "1e999",
        "NaN",
        "-Infinity",
        "true",
        "null",
        "1" * 400,
        "-" + "9" * 5000,
        "\ufeff",
        "\xff",
        record(),
        record(', "x": 2'),
        record(', "note": "\\ud800"'),
        record(', "n": ' + "1" * 320),
    ]
)
JSON_ISH = st.one_of(
    st.lists(JSON_PIECES, max_size=24).map(lambda parts: "".join(parts).encode("utf-8", "surrogatepass")),
    st.binary(max_size=200),
)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(JSON_ISH)
def test_json_ish_bytes_give_a_dataset_or_a_dataset_error(data: bytes) -> None:
    try:
        dataset = read_dataset_json(data, kind="any")
    except DatasetError as exc:
        str(exc).encode("utf-8")
        assert exc.path is None or exc.path.startswith("$")
        return
    assert isinstance(dataset, Dataset)
    dataset_to_csv(dataset).encode("utf-8")  # what is accepted can be stored
    assert dataset.content_sha256
