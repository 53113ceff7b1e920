"""Atomic writes: whole files or nothing, NaN refused, exclusive writes never replace a file."""

from __future__ import annotations

import json
import os
import stat

import numpy as np
import pytest

from comp_daemon.common.atomic import SECRET_MODE, current_umask, write_json_atomic, write_text_atomic


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


def test_a_fifo_is_written_into_not_replaced(tmp_path) -> None:
    # as /dev/null or /dev/stdout: a rename over it would leave a regular file in its place
    dest = tmp_path / "out.fifo"
    os.mkfifo(dest)
    reader = os.open(dest, os.O_RDONLY | os.O_NONBLOCK)
    try:
        write_json_atomic(dest, {"a": 1})
        assert stat.S_ISFIFO(os.stat(dest).st_mode)
        assert json.loads(os.read(reader, 1 << 16)) == {"a": 1}
    finally:
        os.close(reader)
    assert [p.name for p in tmp_path.iterdir()] == ["out.fifo"]


@pytest.fixture()
def umask_022():
    old = os.umask(0o022)
    try:
        yield
    finally:
        os.umask(old)


def test_written_files_follow_the_umask(tmp_path, umask_022) -> None:
    """Under umask 022 a written file is 0644, like one from ``open(path, "w")``, not mkstemp's 0600."""
    assert current_umask() == 0o022
    text_file = write_text_atomic(tmp_path / "report.html", "<p>ok</p>")
    json_file = write_json_atomic(tmp_path / "model.json", {"a": 1})
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    for path in (text_file, json_file):
        assert stat.S_IMODE(path.stat().st_mode) == stat.S_IMODE(plain.stat().st_mode) == 0o644
    os.umask(0o027)
    assert stat.S_IMODE(write_text_atomic(tmp_path / "group.txt", "x").stat().st_mode) == 0o640


def test_secrets_stay_owner_only_whatever_the_umask(tmp_path, umask_022) -> None:
    os.umask(0)
    token = write_text_atomic(tmp_path / "token", "s3cret", mode=SECRET_MODE)
    key = write_json_atomic(tmp_path / "key.json", {"key": "k"}, mode=SECRET_MODE)
    assert stat.S_IMODE(token.stat().st_mode) == 0o600
    assert stat.S_IMODE(key.stat().st_mode) == 0o600


def test_a_data_set_written_by_the_cli_is_readable_by_the_group(tmp_path, umask_022) -> None:
    """``sim sample`` / ``data`` write data sets through :func:`write_dataset`: 0644 under umask 022."""
    from comp_daemon.data.dataset import Dataset, write_dataset

    path = tmp_path / "campaign.csv"
    write_dataset(Dataset(a_deg=np.zeros((3, 6)), xyz_mm=np.ones((3, 3))), path)
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
