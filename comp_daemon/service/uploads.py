"""Checking a data-set upload without holding up the event loop.

- :class:`Spool` keeps the body as it arrives: in memory up to :data:`SPOOL_MEMORY_BYTES`, then in a
  temporary file (written a megabyte at a time from a worker thread).
- :func:`check_upload` parses, validates, renders (canonical CSV) and summarises it: seconds of CPU
  and a few hundred MB at the 20 MB limit. :class:`UploadChecker` runs it in a worker thread for a
  body held in memory and, for a spooled one, in a process of its own (spawned per upload, so its
  memory goes back to the system and its CPU time never competes with the loop for the GIL); at
  most ``concurrency`` at once.
- JSON follows the file reader's rules (:func:`comp_daemon.data.dataset.read_dataset_json`: a key
  given twice is refused) and adds what the reader lets through: a lone surrogate or a NUL in a
  string, an integer beyond any double. A CSV field with a NUL is refused with its row and column.

Every refusal is an :class:`UploadRefused` (a :class:`~comp_daemon.data.dataset.DatasetError`
becomes one with the same message, row and column); JSON faults carry the value's ``path``
(``$[3].a1``, ``$.records[0].note``).
"""

from __future__ import annotations

import asyncio
import contextlib
import csv
import io
import json
import multiprocessing
import os
import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import IO, Any, Literal

from comp_daemon.data.dataset import DatasetError, dataset_from_records, dataset_to_csv, parse_dataset
from comp_daemon.service.orphans import exit_with_parent

__all__ = ["SPOOL_MEMORY_BYTES", "CheckedUpload", "Spool", "UploadChecker", "UploadRefused", "check_upload"]

SPOOL_MEMORY_BYTES = 1 << 20  # a body beyond this goes to a temporary file (and its check to a process)
UploadFormat = Literal["csv", "json"]
UploadKind = Literal["measurement", "any"]


class UploadRefused(ValueError):
    """An upload that is not stored: ``message`` says why; ``path`` (JSON), ``row``, ``column`` where."""

    def __init__(
        self,
        message: str,
        *,
        path: str | None = None,
        row: int | None = None,
        column: str | None = None,
        row_label: str | None = None,
    ) -> None:
        super().__init__(message)
        self.message = message
        self.where = {"path": path, "row": row, "column": column, "row_label": row_label}

    def __reduce__(self) -> tuple[Any, ...]:  # crosses the process boundary with its fields
        return (_refused, (self.message, self.where))

    @classmethod
    def of(cls, exc: DatasetError) -> UploadRefused:
        label = exc.row_label if exc.row is not None else None
        return cls(str(exc), row=exc.row, column=exc.column, row_label=label)


def _refused(message: str, where: dict[str, Any]) -> UploadRefused:
    return UploadRefused(message, **where)


_MAX_INT_DIGITS = 309  # a longer JSON integer is beyond every double (1.8e308)


class _LongInteger(str):
    """A JSON integer too long to be a number of a data set (kept as its text, refused by path)."""


class _Object(dict[str, Any]):
    """A JSON object that remembers keys given more than once."""

    duplicate_keys: tuple[str, ...] = ()


def _object_pairs(pairs: list[tuple[str, Any]]) -> _Object:
    obj = _Object(pairs)
    if len(obj) != len(pairs):
        seen: set[str] = set()
        duplicates = []
        for key, _ in pairs:
            if key in seen:
                duplicates.append(key)
            seen.add(key)
        obj.duplicate_keys = tuple(duplicates)
    return obj


def _parse_int(text: str) -> int | _LongInteger:
    return _LongInteger(text) if len(text.lstrip("-")) > _MAX_INT_DIGITS else int(text)


def _text_fault(text: str) -> str | None:
    if "\x00" in text:
        return "a NUL character (U+0000) in text"
    try:
        text.encode("utf-8")
    except UnicodeEncodeError as exc:
        return f"a lone surrogate (U+{ord(text[exc.start]):04X}) in text: not Unicode"
    return None


def _json_fault(doc: Any) -> tuple[str, list[str | int]] | None:
    """The first value the file reader's rules refuse: (problem, path from the document's root)."""
    stack: list[tuple[Any, list[str | int]]] = [(doc, [])]
    while stack:
        value, path = stack.pop()
        if isinstance(value, _LongInteger):
            return f"an integer of {len(value.lstrip('-'))} digits (beyond any number)", path
        if isinstance(value, str):
            problem = _text_fault(value)
            if problem is not None:
                return problem, path
        elif isinstance(value, dict):
            duplicates = getattr(value, "duplicate_keys", ())
            if duplicates:
                return f"key {duplicates[0]!r} given twice", [*path, duplicates[0]]
            for key in value:
                problem = _text_fault(key)
                if problem is not None:
                    return f"{problem} (in a key)", [*path, key]
            stack.extend((v, [*path, k]) for k, v in reversed(value.items()))
        elif isinstance(value, list):
            stack.extend((v, [*path, i]) for i, v in reversed(list(enumerate(value))))
    return None


def _path_text(path: list[str | int]) -> str:
    out = "$"
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else f".{part}" if part.isidentifier() else f"[{part!r}]"
    return out


def _json_records(data: bytes, source: str) -> tuple[list[Any], str | None]:
    """The records of a JSON upload, by the file reader's rules and stricter: duplicate keys, lone
    surrogates, NUL characters and integers beyond any double are refused with the value's path."""
    try:
        text = data.decode("utf-8").removeprefix("\ufeff")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise DatasetError("not UTF-8 text", source=source, row=line) from None
    try:
        doc = json.loads(text, object_pairs_hook=_object_pairs, parse_int=_parse_int)
    except json.JSONDecodeError as exc:
        raise DatasetError(
            f"invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}", source=source, row=exc.lineno
        ) from None
    except RecursionError:
        raise DatasetError("JSON nested too deeply", source=source) from None
    fault = _json_fault(doc)
    if fault is not None:
        problem, path = fault
        records_at = 1 if isinstance(doc, dict) else 0  # {"records": [...]} or [...]
        row: int | None = None
        column: str | None = None
        index = path[records_at] if len(path) > records_at + 1 else None
        if isinstance(index, int):
            key = str(path[records_at + 1])
            row, column = index + 1, key.encode("utf-8", "backslashreplace").decode("utf-8")
        where = _path_text(path)
        raise UploadRefused(
            f"{source}: {where}: {problem}",
            path=where,
            row=row,
            column=column,
            row_label="record" if row is not None else None,
        )
    if isinstance(doc, list):
        return doc, None
    if isinstance(doc, dict) and isinstance(doc.get("records"), list):
        name = doc.get("name")
        return doc["records"], name if isinstance(name, str) and name.strip() else None
    raise DatasetError("expected a list of records or an object with 'records' (a list)", source=source)


def _refuse_nul(text: str, source: str) -> None:
    """Refuse a NUL character in CSV text, naming its row and column (the reader would keep it)."""
    if "\x00" not in text:
        return
    reader = csv.reader(io.StringIO(text, newline=""))
    header: list[str] = []
    line = 1
    with contextlib.suppress(csv.Error):
        for k, record in enumerate(reader):
            if k == 0:
                header = [h.strip() for h in record]
            for j, cell in enumerate(record):
                if "\x00" in cell:
                    column = header[j] if k > 0 and j < len(header) and header[j] else None
                    raise DatasetError(
                        f"a NUL character (U+0000) in field {j + 1}", source=source, row=line, column=column
                    )
            line = reader.line_num + 1
    raise DatasetError(
        "a NUL character (U+0000)", source=source, row=text.count("\n", 0, text.index("\x00")) + 1
    )


@dataclass(frozen=True, slots=True)
class CheckedUpload:
    """What is stored of an accepted upload."""

    name: str
    content: str  # canonical CSV
    sha256: str
    rows: int
    summary: dict[str, Any]


def check_upload(data: bytes, fmt: UploadFormat, name: str, limits: Any, kind: UploadKind) -> CheckedUpload:
    """Parse and validate an upload against the robot's axis ``limits``; render and summarise it.

    ``name`` is the data set's name (a JSON ``{"name": …, "records": …}`` may give another).
    Raises :class:`UploadRefused`.
    """
    try:
        if fmt == "csv":
            with contextlib.suppress(UnicodeDecodeError):  # the reader names undecodable bytes itself
                _refuse_nul(data.decode("utf-8"), name)
            ds = parse_dataset(data, source=name, limits_deg=limits, min_rows=1, kind=kind)
        else:
            records, inner = _json_records(data, name)
            name = (inner or name)[:200]
            ds = dataset_from_records(records, source=name, limits_deg=limits, min_rows=1, kind=kind)
    except DatasetError as exc:
        raise UploadRefused.of(exc) from None
    del data
    return CheckedUpload(name, dataset_to_csv(ds), ds.content_sha256, len(ds), ds.summary())


def _check_file(path: str, fmt: UploadFormat, name: str, limits: Any, kind: UploadKind) -> CheckedUpload:
    """:func:`check_upload` of a spooled body (in the checking process)."""
    with open(path, "rb") as f:
        data = f.read()
    return check_upload(data, fmt, name, limits, kind)


class Spool:
    """An upload body: in memory up to ``memory_bytes``, then in a temporary file."""

    def __init__(self, memory_bytes: int = SPOOL_MEMORY_BYTES) -> None:
        self.memory_bytes = memory_bytes
        self.size = 0
        self._buf = bytearray()
        self._file: IO[bytes] | None = None

    async def write(self, chunk: bytes) -> None:
        """Add a chunk; a megabyte gathered goes to the file from a worker thread."""
        self.size += len(chunk)
        self._buf += chunk
        if len(self._buf) > self.memory_bytes:
            await asyncio.to_thread(self._flush)

    def write_from(self, source: IO[bytes]) -> None:
        """Copy a whole file object (blocking: call it in a worker thread)."""
        while block := source.read(self.memory_bytes):
            self.size += len(block)
            self._buf += block
            if len(self._buf) > self.memory_bytes:
                self._flush()

    def _flush(self) -> None:
        if self._file is None:
            self._file = tempfile.NamedTemporaryFile(prefix="comp-daemon-upload-", delete=False)
        self._file.write(self._buf)
        self._buf = bytearray()

    @property
    def in_memory(self) -> bool:
        return self._file is None

    def data(self) -> bytes:
        """The body, when it is in memory."""
        assert self._file is None, "the body is in a file"
        return bytes(self._buf)

    def path(self) -> str:
        """The file holding the whole body (blocking: the last bytes are written now)."""
        if self._buf or self._file is None:
            self._flush()
        assert self._file is not None
        self._file.flush()
        return self._file.name

    def close(self) -> None:
        """Forget the body; remove the file."""
        self._buf = bytearray()
        if self._file is not None:
            self._file.close()
            with contextlib.suppress(OSError):
                os.unlink(self._file.name)
            self._file = None


class UploadChecker:
    """Runs :func:`check_upload`: small bodies in a worker thread, spooled ones in a fresh process
    each. An upload holds one of the ``concurrency`` :attr:`slots` from before its body is read
    until it is checked; :meth:`busy` says whether one more would have to wait."""

    def __init__(self, concurrency: int) -> None:
        self.concurrency = concurrency
        self.slots = asyncio.Semaphore(concurrency)
        self._pool: ProcessPoolExecutor | None = None

    def busy(self) -> bool:
        return self.slots.locked()

    async def check(
        self, spool: Spool, fmt: UploadFormat, name: str, limits: Any, kind: UploadKind
    ) -> CheckedUpload:
        if spool.in_memory:
            return await asyncio.to_thread(check_upload, spool.data(), fmt, name, limits, kind)
        path = await asyncio.to_thread(spool.path)
        if self._pool is None:
            self._pool = ProcessPoolExecutor(
                max_workers=self.concurrency,
                mp_context=multiprocessing.get_context("spawn"),
                max_tasks_per_child=1,
                initializer=exit_with_parent,
                initargs=(os.getpid(),),
            )
        future = self._pool.submit(_check_file, path, fmt, name, limits, kind)
        return await asyncio.wrap_future(future)

    def shutdown(self) -> None:
        """End the checking processes (an upload still being checked fails)."""
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)
