"""Files a user names: the refusals of an unreadable file and of a name that is neither a preset nor
a file, in the caller's error type."""

from __future__ import annotations

from pathlib import Path

import pytest

from comp_daemon.common.files import named_file, read_text


class _Refused(ValueError):
    pass


def test_read_text_gives_the_text_or_names_the_file_and_the_fault(tmp_path: Path) -> None:
    good = tmp_path / "good.toml"
    good.write_text("x = 'é'\n", encoding="utf-8")
    assert read_text(good, _Refused) == "x = 'é'\n"
    latin = tmp_path / "latin.toml"
    latin.write_bytes("x = 'é'\n".encode("latin-1"))
    with pytest.raises(_Refused, match=f"^{latin}: cannot read: 'utf-8' codec can't decode"):
        read_text(latin, _Refused)
    with pytest.raises(_Refused, match=f"^{tmp_path / 'gone.toml'}: cannot read: .*No such file"):
        read_text(tmp_path / "gone.toml", _Refused)


def test_named_file_is_a_path_or_the_refusal_lists_the_presets(tmp_path: Path) -> None:
    here = tmp_path / "cell.toml"
    here.write_text("")
    assert named_file(str(here), ("a", "b"), "scenario", _Refused) == here
    with pytest.raises(
        _Refused, match=r"^scenario 'nowhere': neither a preset \(a, b\) nor a readable file$"
    ):
        named_file("nowhere", ("a", "b"), "scenario", _Refused)
    with pytest.raises(_Refused, match="neither a preset"):
        named_file(str(tmp_path), ("a", "b"), "scenario", _Refused)  # a folder is not a file
