"""Checking a data-set upload without holding up the event loop.

- :class:`Spool` keeps the body as it arrives: in memory up to :data:`SPOOL_MEMORY_BYTES`, then in a
  temporary file (written a megabyte at a time from a worker thread).
- :func:`check_upload` parses, validates, renders (canonical CSV) and summarises it: seconds of CPU
  and a few hundred MB at the 20 MB limit. :class:`UploadChecker` runs it in a worker thread for a
  body held in memory and, for a spooled one, in a process of its own (spawned per upload, so its
  memory goes back to the system and its CPU time never competes with the loop for the GIL), at
  most ``processes`` such processes at once.
- :class:`UploadBudget` bounds the bytes of upload bodies being received or checked at once
  (``http.max_upload_bytes_in_flight``): the memory and CPU an upload takes grow with its size, so a
  burst of small uploads (80 KB each from 50 clients) all fit, while a third upload at the 20 MB
  limit beside two others is refused 503.
- The rules are the file readers' (:mod:`comp_daemon.data.readers`, :mod:`comp_daemon.data.jsontext`):
  CSV as :func:`~comp_daemon.data.dataset.parse_dataset` reads it, JSON as
  :func:`~comp_daemon.data.dataset.read_dataset_json` does (a key given twice, a NUL or a lone
  surrogate, an integer beyond any double are refused with the value's path). A ballbar or
  cross-bar campaign (told by its columns: ``bar_mm`` / ``dr_um``, ``placement`` / ``socket`` /
  ``bar_l_mm``) is checked by its own form's rules (:mod:`comp_daemon.data.ballbar`,
  :mod:`comp_daemon.data.crossbar`) and stored with every column; its summary names the campaign.

Every refusal is an :class:`UploadRefused`: a :class:`~comp_daemon.data.dataset.DatasetError`
with the same message, ``row``, ``column`` and, for JSON, the value's ``path`` (``$[3].a1``,
``$.records[0].note``), in a form that crosses the process boundary.
"""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing
import os
import tempfile
import threading
from collections import OrderedDict
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import IO, Any, Literal

from comp_daemon.data.bars import campaign_kind, header_kind, sniff_campaign
from comp_daemon.data.campaigns import campaign_of
from comp_daemon.data.dataset import DatasetError, dataset_from_json, dataset_to_csv, parse_dataset
from comp_daemon.data.jsontext import load_json_records
from comp_daemon.data.options import ReadOptions
from comp_daemon.data.table import Dataset
from comp_daemon.service.orphans import exit_with_parent

__all__ = [
    "SPOOL_MEMORY_BYTES",
    "CheckedUpload",
    "ParsedDatasets",
    "Spool",
    "UploadBudget",
    "UploadChecker",
    "UploadRefused",
    "check_upload",
]

SPOOL_MEMORY_BYTES = 1 << 20  # a body beyond this goes to a temporary file (and its check to a process)
PARSED_MAX_ROWS = 100_000  # rows of parsed uploads kept for the fits that follow (~650 B each: ~65 MB)
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
        return cls(str(exc), path=exc.path, row=exc.row, column=exc.column, row_label=label)


def _refused(message: str, where: dict[str, Any]) -> UploadRefused:
    return UploadRefused(message, **where)


@dataclass(frozen=True, slots=True)
class CheckedUpload:
    """What is stored of an accepted upload, and the data set as parsed when a fit can take it as
    it is (a measurement data set or a ballbar / cross-bar campaign; :class:`ParsedDatasets`)."""

    name: str
    content: str  # canonical CSV
    sha256: str
    rows: int
    summary: dict[str, Any]
    dataset: Dataset | None = None


class ParsedDatasets:
    """The data sets parsed at their upload, kept for the fit jobs that follow, so that a fit of a
    just-uploaded data set does not parse its stored CSV again.

    Keyed by data set id and content hash (a data set whose stored text differs is not the one
    kept); the newest are kept, at most ``max_rows`` rows in all. Thread-safe. The service starts
    empty: after a restart a fit parses the stored text, with the same result.
    """

    def __init__(self, max_rows: int = PARSED_MAX_ROWS) -> None:
        self.max_rows = max_rows
        self._kept: OrderedDict[int, tuple[str, Dataset]] = OrderedDict()
        self._lock = threading.Lock()

    def put(self, dataset_id: int, dataset: Dataset) -> None:
        """Keep ``dataset`` (as parsed at its upload) for the stored data set ``dataset_id``."""
        kept = dataset.renamed(f"dataset {dataset_id}")  # the name a job gives the stored text
        with self._lock:
            self._kept[dataset_id] = (dataset.content_sha256, kept)
            self._kept.move_to_end(dataset_id)
            while sum(len(d) for _, d in self._kept.values()) > self.max_rows:
                self._kept.popitem(last=False)

    def get(self, dataset_id: int, sha256: str) -> Dataset | None:
        """The data set kept for ``dataset_id`` when its content hash is ``sha256``, else None."""
        with self._lock:
            kept = self._kept.get(dataset_id)
            if kept is None or kept[0] != sha256:
                return None
            self._kept.move_to_end(dataset_id)
            return kept[1]

    def forget(self, dataset_id: int) -> None:
        with self._lock:
            self._kept.pop(dataset_id, None)


def check_upload(
    data: bytes,
    fmt: UploadFormat,
    name: str,
    limits: Any,
    kind: UploadKind,
    options: ReadOptions | None = None,
) -> CheckedUpload:
    """Parse and validate an upload against the robot's axis ``limits``; render and summarise it.

    ``name`` is the data set's name (a JSON ``{"name": …, "records": …}`` may give another);
    ``options`` how the file is written (the query's ``delimiter``, ``decimal_comma``, ``units``,
    ``euler``): what is stored is the converted data set, in mm and degrees. Raises
    :class:`UploadRefused`.
    """
    options = options or ReadOptions()
    campaign = None
    try:
        if fmt == "csv":
            as_kind = "any" if sniff_campaign(data, options.delimiter) is not None else kind
            ds = parse_dataset(
                data, source=name, limits_deg=limits, min_rows=1, kind=as_kind, options=options
            )
        else:
            doc = load_json_records(data, name)
            name = (doc.name or name)[:200]
            keys = set(doc.records[0]) if doc.records and isinstance(doc.records[0], dict) else set()
            as_kind = "any" if header_kind(keys) is not None else kind
            ds = dataset_from_json(
                doc, source=name, limits_deg=limits, min_rows=1, kind=as_kind, options=options
            )
        if campaign_kind(ds) is not None:
            campaign = campaign_of(ds)
    except DatasetError as exc:
        raise UploadRefused.of(exc) from None
    del data
    summary = ds.summary()
    if not options.is_default:
        summary["read_as"] = options.describe()
    if campaign is not None:
        summary["campaign"] = campaign_kind(ds)
    fit_ready = campaign is not None or (ds.a_deg is not None and ds.xyz_mm is not None)
    return CheckedUpload(
        name, dataset_to_csv(ds), ds.content_sha256, len(ds), summary, ds if fit_ready else None
    )


def _check_file(
    path: str, fmt: UploadFormat, name: str, limits: Any, kind: UploadKind, options: ReadOptions | None
) -> CheckedUpload:
    """:func:`check_upload` of a spooled body (in the checking process)."""
    with open(path, "rb") as f:
        data = f.read()
    return check_upload(data, fmt, name, limits, kind, options)


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


class UploadBudget:
    """Bytes of upload bodies in flight (being received or checked), at most ``limit_bytes``.

    An upload takes its declared ``Content-Length`` (the body limit when it declares none) before
    its body is read and gives it back once checked. One upload always fits when nothing else is
    in flight, so the limit never refuses a body the size limit allows.
    """

    def __init__(self, limit_bytes: int) -> None:
        self.limit_bytes = limit_bytes
        self.in_flight = 0
        self.uploads = 0

    def take(self, size: int) -> bool:
        """Count ``size`` bytes in flight, or False (nothing counted) when they do not fit."""
        if self.uploads and self.in_flight + size > self.limit_bytes:
            return False
        self.in_flight += size
        self.uploads += 1
        return True

    def give(self, size: int) -> None:
        self.in_flight -= size
        self.uploads -= 1


class UploadChecker:
    """Runs :func:`check_upload`: small bodies in a worker thread, spooled ones in a fresh process
    each (at most ``processes`` at once; more wait for one). :attr:`budget` bounds the bytes in
    flight."""

    def __init__(self, processes: int, bytes_in_flight: int) -> None:
        self.processes = processes
        self.budget = UploadBudget(bytes_in_flight)
        self._pool: ProcessPoolExecutor | None = None

    async def check(
        self,
        spool: Spool,
        fmt: UploadFormat,
        name: str,
        limits: Any,
        kind: UploadKind,
        options: ReadOptions | None = None,
    ) -> CheckedUpload:
        if spool.in_memory:
            return await asyncio.to_thread(check_upload, spool.data(), fmt, name, limits, kind, options)
        path = await asyncio.to_thread(spool.path)
        if self._pool is None:
            self._pool = ProcessPoolExecutor(
                max_workers=self.processes,
                mp_context=multiprocessing.get_context("spawn"),
                max_tasks_per_child=1,
                initializer=exit_with_parent,
                initargs=(os.getpid(),),
            )
        future = self._pool.submit(_check_file, path, fmt, name, limits, kind, options)
        return await asyncio.wrap_future(future)

    def shutdown(self) -> None:
        """End the checking processes (an upload still being checked fails)."""
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)
