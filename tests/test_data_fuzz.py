"""Fuzz: any bytes give a Dataset or a DatasetError, never another exception."""

from __future__ import annotations

import json

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from comp_daemon.data.dataset import Dataset, DatasetError, dataset_to_csv, read_dataset, read_dataset_json
from comp_daemon.robot.description import load_robot

LIMITS_DEG = load_robot("kr210").axis_limits_deg
FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def read_or_refuse(data: bytes, **kwargs) -> None:
    try:
        dataset = read_dataset(data, **kwargs)
    except DatasetError as exc:
        assert exc.row is None or exc.row >= 1
        assert str(exc)
        return
    assert isinstance(dataset, Dataset)
    # whatever was accepted writes back to a file that reads as the same data
    assert read_dataset(dataset_to_csv(dataset).encode("utf-8"), kind="any") == dataset


@FUZZ
@given(st.binary(max_size=400))
def test_random_bytes(data: bytes) -> None:
    for kind in ("measurement", "any"):
        read_or_refuse(data, kind=kind, limits_deg=LIMITS_DEG)


# near-valid text: whole column groups in any order; cells mostly valid, some hitting the parser's corners
CORNER_CELL = st.one_of(
    st.sampled_from(
        ["0", "nan", "inf", "", " ", "1,5", '"', '""', "1e999", "\r", "\n", "\ufeff", "\x00", "é"]
    ),
    st.text(alphabet='0123456789.,-+eE"\r\n aA', max_size=6),
)


def valid_cell(column: str) -> st.SearchStrategy[str]:
    if column.startswith("dir"):
        return st.sampled_from(["-1", "1", "+1", "1.0"])
    if column == "split":
        return st.sampled_from(["fit", "check"])
    if column == "repeat":
        return st.sampled_from(["0", "2"])
    if column in ("pose_id", "note"):
        return st.text(max_size=4)
    return st.sampled_from(["-90", "-9e1", " -90.0 ", "-100.25", "-5"])


GROUPS = [
    ("a1", "a2", "a3", "a4", "a5", "a6"),
    ("x", "y", "z"),
    ("dir1", "dir2", "dir3", "dir4", "dir5", "dir6"),
    ("g1",),
    ("g4",),
    ("payload_kg",),
    ("temp_c",),
    ("t_s",),
    ("split",),
    ("repeat",),
    ("pose_id",),
    ("tx", "ty", "tz"),
    ("ta", "tb", "tc"),
    ("note",),
]


@st.composite
def near_valid_csv(draw: st.DrawFn) -> str:
    groups = draw(st.sampled_from([[GROUPS[0]], [GROUPS[11]], GROUPS[:2], GROUPS[:2], []]))
    groups += draw(st.lists(st.sampled_from(GROUPS), unique=True, max_size=5))
    groups = list(dict.fromkeys(groups))
    header = draw(st.permutations([name for group in groups for name in group]))
    if draw(st.integers(0, 9)) == 0:  # now and then a broken header
        header = [*header, draw(st.sampled_from(["", "A1", "x", "dir1", " note "]))]
    rows = []
    for _ in range(draw(st.integers(0, 4))):
        width = len(header) if draw(st.integers(0, 9)) else draw(st.integers(0, len(header) + 1))
        names = [*header, *header][:width]
        rows.append([draw(CORNER_CELL if draw(st.integers(0, 19)) == 0 else valid_cell(c)) for c in names])
    newline = draw(st.sampled_from(["\n", "\r\n", "\r"]))
    return newline.join([",".join(header), *(",".join(r) for r in rows)]) + draw(
        st.sampled_from(["", newline])
    )


@FUZZ
@given(near_valid_csv())
def test_near_valid_csv(text: str) -> None:
    for kind in ("measurement", "targets", "any"):
        read_or_refuse(text.encode("utf-8"), kind=kind, limits_deg=LIMITS_DEG, min_rows=2)


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=3), inner, max_size=3),
    max_leaves=6,
)


@FUZZ
@given(
    st.one_of(
        st.binary(max_size=200),
        st.lists(
            st.dictionaries(
                st.sampled_from(
                    [
                        "a1",
                        "a2",
                        "a3",
                        "a4",
                        "a5",
                        "a6",
                        "x",
                        "y",
                        "z",
                        "split",
                        "pose_id",
                        "dir1",
                        "tx",
                        "ty",
                        "tz",
                        "n",
                    ]
                ),
                JSON_VALUES,
            ),
            max_size=4,
        ).map(lambda v: json.dumps(v).encode()),
    )
)
def test_json_garbage(data: bytes) -> None:
    try:
        dataset = read_dataset_json(data, kind="any")
    except DatasetError:
        return
    assert isinstance(dataset, Dataset)
