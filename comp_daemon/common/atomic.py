"""Atomic file writes: a reader sees the old file or the new one, never half of either.

The text goes to a temporary file in the destination's folder, is flushed and fsynced, then
``os.replace`` puts it in place (atomic on POSIX within one file system).

A destination that is not a regular file or a folder — a device such as ``/dev/null`` or a
terminal, a FIFO, a socket, or a link to one (``/dev/stdout``) — is written into instead: a rename
would put a regular file in its place (``--json /dev/null`` run as root replaced the machine's
``/dev/null``), and such a destination has no half-written state a reader could see.

The finished file gets the mode an ordinary ``open(path, "w")`` would give it: ``0666`` less the
process's umask (``0644`` under the usual ``022``), not the ``0600`` of the temporary file. Secrets
(tokens, keys) pass ``mode=SECRET_MODE``, which no umask widens.
"""

from __future__ import annotations

import json
import os
import stat
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["SECRET_MODE", "current_umask", "write_json_atomic", "write_text_atomic"]

#: The mode of a file only its owner may read: tokens, keys.
SECRET_MODE = 0o600


def current_umask() -> int:
    """The process's umask, read without changing it where the system allows.

    Linux reports it in ``/proc/self/status``; elsewhere it is read by setting it and putting it
    back at once (``os.umask`` has no read-only form).
    """
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_text_atomic(
    path: str | os.PathLike[str], text: str, *, mode: int | None = None, exclusive: bool = False
) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; the folder must exist. Returns the path.

    ``mode``: the file's permission bits; by default ``0666`` less the umask (see the module's note),
    :data:`SECRET_MODE` for secrets.
    ``exclusive``: never replace an existing file — :class:`FileExistsError` if ``path`` exists,
    also when another writer creates it meanwhile (the finished file is hard-linked into place).
    """
    dest = Path(path)
    if not exclusive and _special(dest):
        with open(dest, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)
        return dest
    folder = dest.parent if str(dest.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{dest.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, mode if mode is not None else 0o666 & ~current_umask())
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


def _special(dest: Path) -> bool:
    """Whether ``dest`` exists and is (or links to) neither a regular file nor a folder."""
    try:
        mode = os.stat(dest).st_mode
    except OSError:
        return False
    return not (stat.S_ISREG(mode) or stat.S_ISDIR(mode))


def write_json_atomic(
    path: str | os.PathLike[str],
    doc: Mapping[str, Any] | list[Any],
    *,
    indent: int | None = 2,
    sort_keys: bool = False,
    default: Any = None,
    allow_nan: bool = False,
    mode: int | None = None,
) -> Path:
    """Write ``doc`` as JSON (UTF-8, trailing newline) to ``path`` atomically; NaN refused unless allowed."""
    text = json.dumps(doc, indent=indent, sort_keys=sort_keys, default=default, allow_nan=allow_nan)
    return write_text_atomic(path, text + "\n", mode=mode)


class _suppress_oserror:
    def __enter__(self) -> None:
        return None

    def __exit__(self, exc_type: object, exc: object, tb: object) -> bool:
        return isinstance(exc, OSError)
