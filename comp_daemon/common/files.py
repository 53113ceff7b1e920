"""Files a user names: a packaged preset by its name, or a file by its path, read as UTF-8 text.

The refusals are the same wherever a file is named (a robot description, a scenario, a model): the
error type is the caller's, the words are these.
"""

from __future__ import annotations

import os
from collections.abc import Collection
from pathlib import Path

__all__ = ["named_file", "read_text"]


def read_text(path: str | os.PathLike[str], error: type[Exception]) -> str:
    """The UTF-8 text of the file at ``path``; ``error("<path>: cannot read: <why>")`` when the file
    cannot be opened or is not UTF-8."""
    try:
        return Path(path).read_text("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{path}: cannot read: {exc}") from None


def named_file(key: str, presets: Collection[str], what: str, error: type[Exception]) -> Path:
    """The path of the file ``key`` names where it is not one of ``presets``;
    ``error("<what> '<key>': neither a preset (<presets>) nor a readable file")`` where no such file is."""
    path = Path(key)
    if not path.is_file():
        raise error(f"{what} '{key}': neither a preset ({', '.join(presets)}) nor a readable file")
    return path
