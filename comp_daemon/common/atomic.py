"""Atomic file writes: a reader sees the old file or the new one, never half of either.

The text goes to a temporary file in the destination's folder, is flushed and fsynced, then
``os.replace`` puts it in place (atomic on POSIX within one file system).
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["write_json_atomic", "write_text_atomic"]


def write_text_atomic(
    path: str | os.PathLike[str], text: str, *, mode: int | None = None, exclusive: bool = False
) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; the folder must exist. Returns the path.

    ``exclusive``: never replace an existing file — :class:`FileExistsError` if ``path`` exists,
    also when another writer creates it meanwhile (the finished file is hard-linked into place).
    """
    dest = Path(path)
    folder = dest.parent if str(dest.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{dest.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        if mode is not None:
            os.chmod(tmp, mode)
        if exclusive:
            os.link(tmp, dest)
            os.unlink(tmp)
        else:
            os.replace(tmp, dest)
    except BaseException:
        with _suppress_oserror():
            os.unlink(tmp)
        raise
    return dest


def write_json_atomic(
    path: str | os.PathLike[str],
    doc: Mapping[str, Any] | list[Any],
    *,
    indent: int | None = 2,
    sort_keys: bool = False,
    default: Any = None,
    allow_nan: bool = False,
) -> Path:
    """Write ``doc`` as JSON (UTF-8, trailing newline) to ``path`` atomically; NaN refused unless allowed."""
    text = json.dumps(doc, indent=indent, sort_keys=sort_keys, default=default, allow_nan=allow_nan)
    return write_text_atomic(path, text + "\n")


class _suppress_oserror:
    def __enter__(self) -> None:
        return None

    def __exit__(self, exc_type: object, exc: object, tb: object) -> bool:
        return isinstance(exc, OSError)
