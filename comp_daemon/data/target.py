"""One drilling target, as the MES asks for it: the one type from the request to the executor.

A target is given in exactly one form (``docs/data-format.md``, target files):

- the axis values ``a1..a6`` of the nominal program (deg), or
- the wanted TCP ``tx, ty, tz`` (mm, robot base frame) with an optional orientation ``ta, tb, tc``
  (deg, KUKA A, B, C of the tool frame: :mod:`comp_daemon.kinematics.kuka_abc`),

with an optional ``pose_id`` and ``payload_kg``. :class:`Target` holds it; its **record** (the
fields above, only those given, in that order) is what ``POST /api/batches`` takes, what the store
keeps as a target's ``request`` and what the API shows. The HTTP schema
(:class:`comp_daemon.service.schemas.TargetIn`) validates a request field by field and builds a
:class:`Target`; a target file becomes targets through :func:`targets_of_dataset`; the executor reads a
stored request back with :meth:`Target.from_record` and hands the :class:`Target` to the compensator.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from comp_daemon.data.columns import AXIS_COLUMNS, TARGET_ABC_COLUMNS, TARGET_XYZ_COLUMNS, DatasetError
from comp_daemon.data.table import Dataset

__all__ = [
    "BOTH_FORMS",
    "FORMS",
    "NO_FORM",
    "TARGET_FIELDS",
    "Target",
    "TargetError",
    "missing_fields",
    "targets_of_dataset",
]

#: the fields of a target's record, in the order a record lists them
TARGET_FIELDS: tuple[str, ...] = (
    "pose_id",
    *AXIS_COLUMNS,
    *TARGET_XYZ_COLUMNS,
    *TARGET_ABC_COLUMNS,
    "payload_kg",
)


class TargetError(ValueError):
    """A target that is not one: the message names the field at fault."""


#: the target's forms, each a group of fields given whole or not at all, with what its sentence says
FORMS: tuple[tuple[tuple[str, ...], str], ...] = (
    (AXIS_COLUMNS, "axis values need"),
    (TARGET_XYZ_COLUMNS, "a TCP needs"),
    (TARGET_ABC_COLUMNS, "an orientation needs"),
)
BOTH_FORMS = "gives both axis values a1..a6 and a TCP; give exactly one form"
NO_FORM = "gives neither axis values a1..a6 nor a TCP tx, ty, tz"


def missing_fields(missing: list[str], names: tuple[str, ...], form: str) -> str:
    """The sentence for a group given in part: which of its fields are missing."""
    return f"{', '.join(missing)} missing: {form} all of {', '.join(names)}"


def _numbers(values: tuple[Any, ...] | None, names: tuple[str, ...]) -> tuple[float, ...] | None:
    if values is None:
        return None
    if len(values) != len(names):
        raise TargetError(f"{', '.join(names)}: {len(names)} values needed, got {len(values)}")
    out = []
    for name, v in zip(names, values, strict=True):
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise TargetError(f"{name} must be a number, got {v!r}")
        if not math.isfinite(float(v)):
            raise TargetError(f"{name} must be finite, got {v!r}")
        out.append(float(v))
    return tuple(out)


@dataclass(frozen=True, slots=True)
class Target:
    """One target in exactly one form; see the module docstring. Values are floats (deg, mm, kg)."""

    axes_deg: tuple[float, ...] | None = None  # a1..a6
    tcp_mm: tuple[float, ...] | None = None  # tx, ty, tz
    abc_deg: tuple[float, ...] | None = None  # ta, tb, tc (only with a TCP)
    payload_kg: float | None = None
    pose_id: str | None = None

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "axes_deg", _numbers(self.axes_deg, AXIS_COLUMNS))
        set_(self, "tcp_mm", _numbers(self.tcp_mm, TARGET_XYZ_COLUMNS))
        set_(self, "abc_deg", _numbers(self.abc_deg, TARGET_ABC_COLUMNS))
        if self.axes_deg is not None and (self.tcp_mm is not None or self.abc_deg is not None):
            raise TargetError(BOTH_FORMS)
        if self.abc_deg is not None and self.tcp_mm is None:
            raise TargetError("an orientation ta, tb, tc needs a TCP tx, ty, tz")
        if self.axes_deg is None and self.tcp_mm is None:
            raise TargetError(NO_FORM)
        if self.payload_kg is not None:
            (payload,) = _numbers((self.payload_kg,), ("payload_kg",)) or ()
            if payload < 0.0:
                raise TargetError(f"payload_kg must be ≥ 0, got {payload:g}")
            set_(self, "payload_kg", payload)
        if self.pose_id is not None and (not isinstance(self.pose_id, str) or not self.pose_id):
            raise TargetError(f"pose_id must be a non-empty string, got {self.pose_id!r}")

    @classmethod
    def from_record(cls, record: Mapping[str, Any]) -> Target:
        """The target of a record (the fields of :data:`TARGET_FIELDS`; ``None`` counts as absent)."""
        unknown = sorted(k for k in record if k not in TARGET_FIELDS)
        if unknown:
            raise TargetError(f"unknown field {unknown[0]!r}; a target has {', '.join(TARGET_FIELDS)}")
        given = {k: v for k, v in record.items() if v is not None}

        def group(names: tuple[str, ...], form: str) -> tuple[Any, ...] | None:
            present = [k for k in names if k in given]
            if not present:
                return None
            missing = [k for k in names if k not in given]
            if missing:
                raise TargetError(missing_fields(missing, names, form))
            return tuple(given[k] for k in names)

        axes, tcp, abc = (group(names, form) for names, form in FORMS)
        return cls(
            axes_deg=axes,
            tcp_mm=tcp,
            abc_deg=abc,
            payload_kg=given.get("payload_kg"),
            pose_id=given.get("pose_id"),
        )

    def to_record(self) -> dict[str, Any]:
        """The record of this target: the fields given, in the order of :data:`TARGET_FIELDS`."""
        record: dict[str, Any] = {}
        if self.pose_id is not None:
            record["pose_id"] = self.pose_id
        for names, values in (
            (AXIS_COLUMNS, self.axes_deg),
            (TARGET_XYZ_COLUMNS, self.tcp_mm),
            (TARGET_ABC_COLUMNS, self.abc_deg),
        ):
            if values is not None:
                record |= dict(zip(names, values, strict=True))
        if self.payload_kg is not None:
            record["payload_kg"] = self.payload_kg
        return record


def targets_of_dataset(dataset: Dataset) -> list[Target]:
    """The targets of a target file read with ``kind="targets"`` (a payload of 0 is no payload)."""
    if dataset.a_deg is not None and dataset.target_xyz_mm is not None:
        raise DatasetError(
            "a queued target gives either axis values a1..a6 or a TCP tx, ty, tz, not both",
            source=dataset.source,
            row=int(dataset.row_numbers[0]),
            column="tx",
        )
    payload = np.asarray(dataset.payload_kg, dtype=float)

    def row(values: np.ndarray | None, i: int) -> tuple[float, ...] | None:
        return None if values is None else tuple(float(v) for v in values[i])

    return [
        Target(
            axes_deg=row(dataset.a_deg, i),
            tcp_mm=row(dataset.target_xyz_mm, i),
            abc_deg=row(dataset.target_abc_deg, i),
            payload_kg=float(payload[i]) if payload.size and payload[i] != 0.0 else None,
            pose_id=str(dataset.pose_id[i]) if dataset.pose_id is not None and dataset.pose_id[i] else None,
        )
        for i in range(len(dataset))
    ]
