"""Dataset: writer round trip (bit-exact), content hash, JSON records, subsets and the held-out draw."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from comp_daemon.data.dataset import (
    Dataset,
    DatasetError,
    dataset_from_records,
    dataset_to_csv,
    read_dataset,
    read_dataset_json,
    write_dataset,
)

EXTREME_FLOATS = [
    0.1,
    -0.0,
    5e-324,
    1.7976931348623157e308,
    -2.2250738585072014e-308,
    1 / 3,
    123456789.98765433,
]


def full_dataset(n: int, seed: int) -> Dataset:
    """A data set with every column the format knows, values with awkward bits, awkward text."""
    rng = np.random.default_rng(seed)

    def awkward(shape: tuple[int, ...]) -> np.ndarray:
        values = rng.standard_normal(shape) * 10.0 ** rng.integers(-12, 12, size=shape)
        flat = values.reshape(-1)
        flat[: len(EXTREME_FLOATS)] = EXTREME_FLOATS[: flat.size]
        return values

    g_deg = awkward((n, 6))
    g_deg[:, [1, 4]] = np.nan
    return Dataset(
        a_deg=rng.uniform(-100, 100, (n, 6)) + 1e-13,
        xyz_mm=awkward((n, 3)),
        dir=rng.choice(np.array([-1, 1], dtype=np.int8), (n, 6)),
        g_deg=g_deg,
        payload_kg=rng.choice([0.0, 50.0, 120.5], n),
        temp_c=rng.uniform(15, 30, n),
        t_s=np.cumsum(rng.uniform(0, 10, n)),
        split=rng.choice(["fit", "check"], n),
        repeat=rng.integers(0, 3, n),
        pose_id=tuple(f"P{k},{k % 3}" for k in range(n)),
        target_xyz_mm=awkward((n, 3)),
        target_abc_deg=rng.uniform(-180, 180, (n, 3)),
        extra={
            "operator": tuple(
                ['Zoë "quoted"', " spaced ", "", "multi\nline", "x,y"][k % 5] for k in range(n)
            ),
            "tracker_id": tuple(str(k) for k in range(n)),
        },
        source="memory",
    )


def assert_bits_equal(a: np.ndarray | None, b: np.ndarray | None) -> None:
    assert (a is None) == (b is None)
    if a is not None and b is not None:
        assert a.dtype == b.dtype and a.shape == b.shape
        if a.dtype.kind == "f":
            np.testing.assert_array_equal(a.view(np.int64), b.view(np.int64))
        else:
            np.testing.assert_array_equal(a, b)


def assert_same_content(a: Dataset, b: Dataset) -> None:
    for name in (
        "a_deg",
        "xyz_mm",
        "dir",
        "g_deg",
        "g_present",
        "payload_kg",
        "temp_c",
        "t_s",
        "split",
        "repeat",
        "target_xyz_mm",
        "target_abc_deg",
    ):
        assert_bits_equal(getattr(a, name), getattr(b, name))
    assert a.pose_id == b.pose_id
    assert dict(a.extra) == dict(b.extra) and list(a.extra) == list(b.extra)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_round_trip_is_bit_exact(seed: int, tmp_path) -> None:
    original = full_dataset(40, seed)
    path = tmp_path / "out.csv"
    write_dataset(original, path)
    again = read_dataset(path, kind="any")
    assert_same_content(original, again)
    assert again == original
    assert again.content_sha256 == original.content_sha256
    assert path.read_text("utf-8") == dataset_to_csv(original)
    assert [p.name for p in tmp_path.iterdir()] == ["out.csv"]  # no temporary file left behind


def test_round_trip_through_text_file_and_minimal_columns() -> None:
    minimal = Dataset(
        a_deg=np.array([[0.0, -90.0, 90.0, 0.0, 30.0, 0.0]]), xyz_mm=np.array([[1.5, 2.5, 3.5]])
    )
    buffer = io.StringIO()
    write_dataset(minimal, buffer)
    assert buffer.getvalue() == "a1,a2,a3,a4,a5,a6,x,y,z\n0.0,-90.0,90.0,0.0,30.0,0.0,1.5,2.5,3.5\n"
    assert read_dataset(buffer.getvalue()) == minimal
    assert minimal.columns == ("a1", "a2", "a3", "a4", "a5", "a6", "x", "y", "z")


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.lists(st.floats(allow_nan=False, allow_infinity=False), min_size=3, max_size=3),
            # text a reader accepts: no lone surrogate (Cs), no NUL
            st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"), max_size=8),
        ),
        min_size=1,
        max_size=8,
    )
)
def test_round_trip_property(rows: list[tuple[list[float], str]]) -> None:
    original = Dataset(
        a_deg=np.zeros((len(rows), 6)),
        xyz_mm=np.array([xyz for xyz, _ in rows]),
        extra={"note": tuple(text for _, text in rows)},
    )
    again = read_dataset(dataset_to_csv(original).encode("utf-8"))
    assert_same_content(original, again)


def test_content_hash_follows_content_not_provenance() -> None:
    original = full_dataset(10, 3)
    moved = read_dataset(dataset_to_csv(original), kind="any", source="elsewhere.csv")
    assert moved.content_sha256 == original.content_sha256
    changed_a = np.array(original.a_deg)
    changed_a[4, 2] = np.nextafter(changed_a[4, 2], np.inf)
    changed = Dataset(**{**_fields(original), "a_deg": changed_a})
    assert changed.content_sha256 != original.content_sha256
    assert changed != original
    assert hash(moved) == hash(original)


def _fields(dataset: Dataset) -> dict:
    return {name: getattr(dataset, name) for name in dataset.__dataclass_fields__}


def test_dataset_is_read_only_and_validated() -> None:
    dataset = full_dataset(5, 4)
    assert dataset.a_deg is not None
    with pytest.raises(ValueError, match="read-only"):
        dataset.a_deg[0, 0] = 1.0
    with pytest.raises(AttributeError):
        dataset.source = "x"  # type: ignore[misc]
    base = _fields(dataset)
    for change, words in [
        ({"a_deg": np.zeros((5, 5))}, "shape"),
        ({"xyz_mm": np.full((5, 3), np.nan)}, "non-finite"),
        ({"dir": np.zeros((5, 6))}, "-1 or \\+1"),
        ({"split": ["fit"] * 4 + ["test"]}, "'fit' or 'check'"),
        ({"payload_kg": -np.ones(5)}, ">= 0"),
        ({"extra": {"A1": ("",) * 5}}, "extra column"),
        ({"pose_id": ("p",) * 4}, "expected 5"),
        ({"a_deg": None, "target_xyz_mm": None, "target_abc_deg": None}, "needs axis values"),
    ]:
        with pytest.raises(ValueError, match=words):
            Dataset(**{**base, **change})


def test_subset_keeps_rows_and_file_row_numbers() -> None:
    dataset = read_dataset(dataset_to_csv(full_dataset(12, 5)), kind="any")
    part = dataset.subset([7, 2])
    # record 3 holds a two-line text cell, so record 7 starts on line 10 of the file
    assert part.row_numbers.tolist() == [10, 4]
    assert part.a_deg is not None and dataset.a_deg is not None
    np.testing.assert_array_equal(part.a_deg, dataset.a_deg[[7, 2]])
    assert part.pose_id == (dataset.pose_id[7], dataset.pose_id[2])  # type: ignore[index]
    assert part.extra["tracker_id"] == ("7", "2")
    mask = np.zeros(12, bool)
    mask[[2, 7]] = True
    assert dataset.subset(mask) == dataset.subset([2, 7])
    fit, check = dataset.subset(dataset.fit_rows()), dataset.subset(dataset.check_rows())
    assert len(fit) + len(check) == 12
    assert set(fit.split.tolist()) <= {"fit"} and set(check.split.tolist()) <= {"check"}  # type: ignore[union-attr]


# ---- the held-out draw ------------------------------------------------------------------------------
def campaign_without_split(n: int, repeats: int = 1, pose_ids: bool = False) -> Dataset:
    rng = np.random.default_rng(11)
    a_deg = np.repeat(rng.uniform(-30, 30, (n, 6)), repeats, axis=0)
    return Dataset(
        a_deg=a_deg,
        xyz_mm=rng.uniform(-1000, 1000, (n * repeats, 3)),
        pose_id=tuple(f"pose{k // repeats}" for k in range(n * repeats)) if pose_ids else None,
        source="campaign.csv",
    )


def test_draw_is_reproducible_and_says_which_rows() -> None:
    dataset = campaign_without_split(100)
    first = dataset.split_or_draw(seed=7, check_fraction=0.2)
    again = dataset.split_or_draw(seed=7, check_fraction=0.2)
    other = dataset.split_or_draw(seed=8, check_fraction=0.2)
    assert first.drawn and first.seed == 7
    assert len(first.check_rows) == 20 and len(first.fit_rows) == 80
    np.testing.assert_array_equal(first.check_rows, again.check_rows)
    assert not np.array_equal(first.check_rows, other.check_rows)
    assert sorted(np.concatenate([first.fit_rows, first.check_rows]).tolist()) == list(range(100))
    rows_in_message = first.message.split("rows ")[-1]
    named = set()
    for part in rows_in_message.split(", "):
        low, _, high = part.partition("-")
        named.update(range(int(low), int(high or low) + 1))
    assert named == set((first.check_rows + 2).tolist())
    assert "seed 7" in first.message and "held out 20 of 100" in first.message
    # reading the same file again gives the same draw; the labels make a split column
    reread = read_dataset(dataset_to_csv(dataset))
    np.testing.assert_array_equal(reread.split_or_draw(seed=7).check_rows, first.check_rows)
    labelled = dataset.with_split(first.labels(len(dataset)))
    np.testing.assert_array_equal(labelled.check_rows(), first.check_rows)
    kept = labelled.split_or_draw(seed=99)
    assert not kept.drawn and "split column" in kept.message
    np.testing.assert_array_equal(kept.check_rows, first.check_rows)


@pytest.mark.parametrize("pose_ids", [False, True])
def test_draw_keeps_repeats_of_a_pose_together(pose_ids: bool) -> None:
    dataset = campaign_without_split(30, repeats=3, pose_ids=pose_ids)
    choice = dataset.split_or_draw(seed=1, check_fraction=0.25)
    assert len(choice.check_rows) == 3 * round(0.25 * 30)
    group = np.arange(90) // 3
    assert not set(group[choice.check_rows]) & set(group[choice.fit_rows])


def test_draw_edge_cases() -> None:
    assert len(campaign_without_split(2).split_or_draw(check_fraction=0.01).check_rows) == 1
    assert len(campaign_without_split(2).split_or_draw(check_fraction=0.99).fit_rows) == 1
    single = campaign_without_split(1).split_or_draw()
    assert single.fit_rows.tolist() == [0] and single.check_rows.tolist() == []
    with pytest.raises(ValueError, match="check_fraction"):
        campaign_without_split(5).split_or_draw(check_fraction=1.0)


# ---- JSON records ---------------------------------------------------------------------------------------
def as_records(dataset: Dataset) -> list[dict]:
    text = dataset_to_csv(dataset)
    import csv

    rows = list(csv.reader(io.StringIO(text, newline="")))
    header = rows[0]
    numeric = {"split", "pose_id", *dataset.extra}
    out = []
    for row in rows[1:]:
        record: dict = {}
        for name, cell in zip(header, row, strict=True):
            if name in numeric:
                record[name] = cell
            elif name in ("repeat",) or name.startswith("dir"):
                record[name] = int(cell)
            else:
                record[name] = float(cell)
        out.append(record)
    return out


def test_json_records_give_the_same_dataset() -> None:
    original = full_dataset(15, 6)
    records = as_records(original)
    from_records = dataset_from_records(records, kind="any")
    assert from_records == original
    assert_same_content(original, from_records)
    assert from_records.row_label == "record" and from_records.row_numbers.tolist() == list(range(1, 16))
    text = json.dumps(records)
    assert read_dataset_json(text.encode("utf-8"), kind="any") == original
    assert read_dataset_json(text, kind="any") == original


JSON_GOOD = {"a1": 0, "a2": -90, "a3": 90, "a4": 0, "a5": 30, "a6": 0, "x": 1.5, "y": 2, "z": 3}


@pytest.mark.parametrize(
    ("records", "record", "column", "words"),
    [
        ([JSON_GOOD, {**JSON_GOOD, "y": "2.0"}], 2, "y", "expected a JSON number"),
        ([JSON_GOOD, {**JSON_GOOD, "y": True}], 2, "y", "expected a JSON number"),
        ([JSON_GOOD, JSON_GOOD, {**JSON_GOOD, "z": None}], 3, "z", "empty"),
        ([JSON_GOOD, {**JSON_GOOD, "z": float("nan")}], 2, "z", "non-finite"),
        ([JSON_GOOD, {**JSON_GOOD, "a2": 10}], 2, "a2", "outside the axis limits"),
        ([JSON_GOOD, {k: v for k, v in JSON_GOOD.items() if k != "x"}], 2, "x", "missing key"),
        ([JSON_GOOD, {**JSON_GOOD, "extra": 1}], 2, "extra", "not in record 1"),
        ([{**JSON_GOOD, "split": "fit"}, {**JSON_GOOD, "split": 1}], 2, "split", "'fit' or 'check'"),
        ([{**JSON_GOOD, "split": "fit"}, {**JSON_GOOD, "split": "both"}], 2, "split", "'fit' or 'check'"),
        ([{**JSON_GOOD, "dir1": 1}], 1, "dir2", "column missing"),
        ([{**JSON_GOOD, "note": [1, 2]}], 1, "note", "single value"),
        ([{**JSON_GOOD, "X": 1}], 1, "X", "did you mean 'x'"),
        ([JSON_GOOD, 5], 2, None, "expected a JSON object"),
    ],
)
def test_json_records_refused_by_record_and_column(
    records: list, record: int, column: str | None, words: str
) -> None:
    from comp_daemon.robot.description import load_robot

    with pytest.raises(DatasetError) as caught:
        dataset_from_records(records, source="upload", limits_deg=load_robot("kr210").axis_limits_deg)
    error = caught.value
    assert (error.row, error.column, error.row_label) == (record, column, "record")
    assert f"record {record}" in str(error)
    assert words in str(error)


def test_json_text_refusals() -> None:
    duplicate = '[{"a1": 0, "a2": -90, "a3": 90, "a4": 0, "a5": 30, "a6": 0, "x": 1, "y": 2, "z": 3, "x": 4}]'
    with pytest.raises(DatasetError, match="record 1, column 'x': duplicate"):
        read_dataset_json(duplicate)
    with pytest.raises(DatasetError, match="not valid JSON"):
        read_dataset_json(b'[{"a1": 0,')
    with pytest.raises(DatasetError, match="not UTF-8"):
        read_dataset_json(b'[{"a1": "\xff"}]')
    with pytest.raises(DatasetError, match="list of records"):
        read_dataset_json(b'{"a1": 0}')
    with pytest.raises(DatasetError, match="no records"):
        read_dataset_json(b"[]")
    with pytest.raises(DatasetError, match="fewer rows than the chosen model has parameters \\(3\\)"):
        dataset_from_records([JSON_GOOD, JSON_GOOD], min_rows=3)


def test_pickles_for_worker_processes() -> None:
    import pickle

    original = full_dataset(8, 9)
    copy = pickle.loads(pickle.dumps(original))
    assert copy == original
    assert_same_content(original, copy)
    assert copy.source == original.source and copy.row_numbers.tolist() == original.row_numbers.tolist()
    assert copy.a_deg is not None and not copy.a_deg.flags.writeable
