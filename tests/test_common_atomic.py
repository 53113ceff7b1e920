"""Atomic writes: whole files or nothing, NaN refused, exclusive writes never replace a file."""

from __future__ import annotations

import json

import pytest

from comp_daemon.common.atomic import write_json_atomic, write_text_atomic


def test_atomic_json_write_replaces_whole_file_and_refuses_nan(tmp_path) -> None:
    dest = tmp_path / "doc.json"
    write_json_atomic(dest, {"a": 1})
    write_json_atomic(dest, {"b": [1.5, 2]})
    assert json.loads(dest.read_text()) == {"b": [1.5, 2]}
    try:
        write_json_atomic(dest, {"c": float("nan")})
    except ValueError:
        pass
    else:
        raise AssertionError("NaN was written")
    assert json.loads(dest.read_text()) == {"b": [1.5, 2]}
    assert [p.name for p in tmp_path.iterdir()] == ["doc.json"]


def test_exclusive_write_never_replaces_an_existing_file(tmp_path) -> None:
    dest = tmp_path / "v0001.json"
    write_text_atomic(dest, "first")
    with pytest.raises(FileExistsError):
        write_text_atomic(dest, "second", exclusive=True)
    assert dest.read_text() == "first"
    assert [p.name for p in tmp_path.iterdir()] == ["v0001.json"]
