"""The store's vocabulary: states, errors, the records it returns, and the JSON helpers of its columns."""

from __future__ import annotations

import dataclasses
import json
import math
import sqlite3
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal, TypeVar

__all__ = [
    "JOB_FINAL_STATES",
    "JOB_STATES",
    "STATS_DETAIL_PATHS",
    "TARGET_ACTIVE_STATES",
    "TARGET_FINAL_STATES",
    "TARGET_STATES",
    "TARGET_TRANSITIONS",
    "BatchRecord",
    "ConflictError",
    "DatasetRecord",
    "EventListener",
    "EventRecord",
    "IdempotencyConflict",
    "JobRecord",
    "ModelDraft",
    "ModelRecord",
    "NotFoundError",
    "RecoveryReport",
    "StoreDamagedError",
    "StoreError",
    "StoreFullError",
    "TargetRecord",
    "dumps",
    "finite",
    "loads",
    "record_of",
    "without_details",
]

TARGET_STATES: tuple[str, ...] = (
    "queued",
    "compensating",
    "moving",
    "settling",
    "done",
    "failed",
    "cancelled",
    "interrupted",
)
TARGET_ACTIVE_STATES: tuple[str, ...] = ("compensating", "moving", "settling")
TARGET_FINAL_STATES: tuple[str, ...] = ("done", "failed", "cancelled")
JOB_STATES: tuple[str, ...] = ("queued", "running", "done", "failed", "cancelled")
JOB_FINAL_STATES: tuple[str, ...] = ("done", "failed", "cancelled")

# allowed moves of a target: from -> to
TARGET_TRANSITIONS: dict[str, frozenset[str]] = {
    "queued": frozenset({"compensating", "cancelled"}),
    "compensating": frozenset({"moving", "failed", "interrupted"}),
    "moving": frozenset({"settling", "failed", "interrupted"}),
    "settling": frozenset({"done", "failed", "interrupted"}),
    "interrupted": frozenset({"queued", "cancelled"}),
    "done": frozenset(),
    "failed": frozenset(),
    "cancelled": frozenset(),
}


class StoreError(Exception):
    """Base of the errors a caller can act on."""


class StoreFullError(StoreError):
    """A write could not be stored: the disk that holds ``path`` is full. Nothing stored is lost:
    the transaction that failed was rolled back whole."""

    def __init__(self, path: object, free_bytes: int | None) -> None:
        self.path = str(path)
        self.free_bytes = free_bytes
        free = "unknown" if free_bytes is None else f"{free_bytes} bytes"
        super().__init__(
            f"disk full: cannot write {self.path} ({free} free on its disk); nothing stored was lost; "
            "free space on that disk"
        )


class StoreDamagedError(StoreError):
    """The store's file is damaged, or empty or missing where a store existed; the message says
    what, where and how to recover. Nothing was changed."""


class NotFoundError(StoreError):
    def __init__(self, what: str, ident: object) -> None:
        self.what = what
        self.ident = ident
        super().__init__(f"{what} {ident} not found")


class ConflictError(StoreError):
    """The request does not fit the current state (a transition that is not allowed, a thing in use)."""


class IdempotencyConflict(ConflictError):
    """The idempotency key was used before with a different request."""


# --------------------------------------------------------------------------------------------- records


@dataclass(frozen=True, slots=True)
class DatasetRecord:
    id: int
    name: str
    format: Literal["csv", "json"]
    sha256: str
    rows: int
    summary: dict[str, Any]
    created_at: float
    content: str | None = None


@dataclass(frozen=True, slots=True)
class JobRecord:
    id: int
    kind: str
    params: dict[str, Any]
    dataset_id: int | None
    state: str
    progress: float
    message: str | None
    result: dict[str, Any] | None
    error: str | None
    created_at: float
    started_at: float | None
    finished_at: float | None


@dataclass(frozen=True, slots=True)
class ModelDraft:
    """A model about to be stored (the result of a fit)."""

    kind: str
    order: int | None
    artifact: dict[str, Any]
    stats: dict[str, Any]
    dataset_id: int | None


@dataclass(frozen=True, slots=True)
class ModelRecord:
    id: int
    kind: str
    order: int | None
    stats: dict[str, Any]
    dataset_id: int | None
    job_id: int | None
    active: bool
    created_at: float
    artifact: dict[str, Any] | None = None


@dataclass(frozen=True, slots=True)
class BatchRecord:
    id: int
    idempotency_key: str
    request_sha256: str
    source: str | None
    size: int
    created_at: float


@dataclass(frozen=True, slots=True)
class TargetRecord:
    id: int
    batch_id: int
    seq: int
    idempotency_key: str
    queue_pos: int
    request: dict[str, Any]
    state: str
    reason: str | None
    commanded_axes_deg: list[float] | None
    final_joint_errors_deg: dict[str, float | None] | None
    created_at: float
    updated_at: float
    started_at: float | None
    finished_at: float | None


@dataclass(frozen=True, slots=True)
class EventRecord:
    id: int
    time: float
    kind: str
    target_id: int | None
    job_id: int | None
    message: dict[str, Any]


@dataclass(frozen=True, slots=True)
class RecoveryReport:
    interrupted_targets: list[int]
    queued_targets: int
    failed_jobs: list[int]


EventListener = Callable[[EventRecord], None]


def dumps(value: Any) -> str:
    """Compact, key-sorted JSON of a column; NaN refused."""
    return json.dumps(value, separators=(",", ":"), sort_keys=True, allow_nan=False)


#: The bulky entries of fit statistics (per check row, per parameter), left out of list pages by
#: SQLite itself (``json_remove`` runs without Python's GIL, so the real-time thread need not wait
#: for ~1 MB of JSON to be decoded per page of 100 fits).
STATS_DETAIL_PATHS: tuple[str, ...] = (
    "$.errors_3d_mm",
    "$.fit.identifiability",
    "$.fit.identified",
    "$.fit.order_selection",
    "$.fit.range_deg",
    "$.fit.solver",
    "$.fit.effects",
)


def without_details(column: str, prefix: str = "$") -> str:
    """SQL for ``column`` without :data:`STATS_DETAIL_PATHS` (below ``prefix``)."""
    paths = ", ".join(f"'{prefix}{p[1:]}'" for p in STATS_DETAIL_PATHS)
    return f"json_remove({column}, {paths})"


def loads(text: str | None) -> Any:
    """A JSON column's value (None stays None)."""
    return None if text is None else json.loads(text)


def finite(value: float) -> float:
    """``value`` as a float; ValueError for NaN or infinity."""
    if not math.isfinite(value):
        raise ValueError("not a finite number")
    return float(value)


_R = TypeVar("_R")
_FIELD_NAMES: dict[type, tuple[str, ...]] = {}  # a record class -> its fields' names


def record_of(cls: type[_R], row: sqlite3.Row, **decoded: Any) -> _R:
    """A record of dataclass ``cls`` from a store row: each field from the column of its name, but
    those ``decoded`` gives (JSON columns, flags, columns the query did not read)."""
    names = _FIELD_NAMES.get(cls)
    if names is None:
        names = _FIELD_NAMES[cls] = tuple(f.name for f in dataclasses.fields(cls))  # type: ignore[arg-type]
    return cls(**{name: decoded[name] if name in decoded else row[name] for name in names})
