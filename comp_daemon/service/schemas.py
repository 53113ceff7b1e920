"""Request and response bodies of the HTTP API (pydantic; they make the OpenAPI description).

Times are ISO 8601 strings in UTC; angles in degrees (``_deg``), lengths in mm (``_mm``).
Errors have one shape, :class:`ErrorOut`: ``error`` (a stable code), ``message`` (for a person)
and, for a refused data set or target batch, ``row`` / ``column`` naming the place (``path`` for a
value in a JSON upload).
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import re
from collections.abc import Iterable, Mapping
from typing import Annotated, Any, Literal

from fastapi.responses import Response
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationInfo, field_validator

from comp_daemon.data.columns import AXIS_COLUMNS as _AXES
from comp_daemon.data.columns import TARGET_ABC_COLUMNS as _ABC
from comp_daemon.data.columns import TARGET_XYZ_COLUMNS as _TCP
from comp_daemon.data.target import BOTH_FORMS, FORMS, NO_FORM, Target, missing_fields
from comp_daemon.models.effects import EFFECTS, effect_by_name
from comp_daemon.models.registry import KINDS, MAX_ORDER
from comp_daemon.preparation.options import DiagnosisSettings, FitSettings
from comp_daemon.service.store import (
    STATS_DETAIL_PATHS,
    BatchRecord,
    DatasetRecord,
    EventRecord,
    JobRecord,
    ModelRecord,
    TargetRecord,
)

__all__ = [
    "MAX_ID",
    "BatchIn",
    "BatchOut",
    "DatasetOut",
    "DiagnosisIn",
    "ErrorOut",
    "EventOut",
    "FitIn",
    "GratingCalibrationIn",
    "JobOut",
    "ModelOut",
    "ReadyOut",
    "TargetIn",
    "TargetOut",
    "iso",
]


#: The largest id the API takes: 2**53 - 1, the largest integer a JSON number (an IEEE double) holds
#: exactly, so that a schema bound and the server's check agree for every client.
MAX_ID = 2**53 - 1


def iso(t: float | None) -> str | None:
    """UNIX seconds as an ISO 8601 UTC string (None stays None)."""
    if t is None:
        return None
    return dt.datetime.fromtimestamp(t, tz=dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _iso_of(value: Any) -> Any:
    return iso(value) if isinstance(value, int | float) else value


#: a time the store keeps as UNIX seconds, answered as an ISO 8601 UTC string (:func:`iso`)
Time = Annotated[str | None, BeforeValidator(_iso_of)]


def record_fields(record: Any, **changes: Any) -> dict[str, Any]:
    """A store record's fields by name (the values themselves, not copies) with ``changes`` over
    them: what a response model is validated from (the fields it does not name are ignored)."""
    return {**{f.name: getattr(record, f.name) for f in dataclasses.fields(record)}, **changes}


class _Out(BaseModel):
    model_config = ConfigDict(frozen=True)


def json_array(items: Iterable[BaseModel]) -> Response:
    """A JSON array response serialised one item at a time.

    FastAPI would validate and serialise a whole page in two calls into pydantic-core, each holding
    the interpreter lock for the whole page (milliseconds for a page of fits); the RSI reply on the
    real-time thread waits for the lock. One item per call gives it a turn between items. The
    routes keep their ``response_model`` for the OpenAPI description; the bytes are the same.
    """
    body = b"[" + b",".join(item.__pydantic_serializer__.to_json(item) for item in items) + b"]"
    return Response(content=body, media_type="application/json")


class ErrorOut(_Out):
    error: str = Field(description="stable error code, e.g. not_found, conflict, invalid_dataset")
    message: str
    row: int | None = Field(None, description="1-based row (header = row 1) or record number at fault")
    column: str | None = Field(None, description="column or field at fault")
    row_label: str | None = Field(
        None, description="'row' (CSV), 'record' (JSON record), 'line' (JSON text) or 'target' (batch)"
    )
    path: str | None = Field(
        None, description="JSON uploads: the path of the value at fault, e.g. $.records[3].a1 or $[0].note"
    )
    retry_after_s: int | None = Field(
        None, description="503 busy: seconds to wait before trying again (also the Retry-After header)"
    )
    error_id: str | None = Field(None, description="for internal errors: the id under which it was logged")
    details: list[dict[str, Any]] | None = None


class DatasetOut(_Out):
    id: int
    name: str
    format: Literal["csv", "json"]
    sha256: str
    rows: int
    summary: dict[str, Any]
    created_at: Time

    @classmethod
    def of(cls, r: DatasetRecord) -> DatasetOut:
        return cls.model_validate(record_fields(r))


#: Top-level entries of fit statistics that lists leave out (the store's STATS_DETAIL_PATHS).
_DETAIL_KEYS = frozenset(p[2:] for p in STATS_DETAIL_PATHS if p.count(".") == 1)


def stats_summary(stats: dict[str, Any]) -> dict[str, Any]:
    """Fit statistics for a list: without the per-check-row errors (``errors_3d_mm``) and with only
    the scalar entries of ``fit`` (the identifiability and per-parameter tables stay in the single
    views). The store already strips :data:`STATS_DETAIL_PATHS` in SQL for list pages; this is the
    list's shape, and it also holds for any other nested entry a model kind may put under ``fit``."""
    out = {k: v for k, v in stats.items() if k not in _DETAIL_KEYS}
    fit = out.get("fit")
    if isinstance(fit, dict):
        out["fit"] = {k: v for k, v in fit.items() if v is None or isinstance(v, str | int | float | bool)}
    return out


def _result_summary(result: dict[str, Any] | None) -> dict[str, Any] | None:
    if result is None or not isinstance(result.get("stats"), dict):
        return result
    return {**result, "stats": stats_summary(result["stats"])}


class JobOut(_Out):
    id: int
    kind: str
    state: Literal["queued", "running", "done", "failed", "cancelled"]
    progress: float = Field(description="0..1")
    message: str | None
    params: dict[str, Any]
    dataset_id: int | None
    result: dict[str, Any] | None = Field(
        description="result statistics; omitted for diagnoses (see the report)"
    )
    error: str | None
    created_at: Time
    started_at: Time
    finished_at: Time

    @classmethod
    def of(cls, r: JobRecord, *, with_result: bool = True, summary: bool = False) -> JobOut:
        """``summary``: the result's statistics as in a list (:func:`stats_summary`)."""
        result = r.result if with_result else None
        if summary:
            result = _result_summary(result)
        return cls.model_validate(record_fields(r, result=result))


class ModelOut(_Out):
    id: int
    kind: str
    order: int | None
    active: bool
    dataset_id: int | None
    job_id: int | None
    stats: dict[str, Any]
    created_at: Time

    @classmethod
    def of(cls, r: ModelRecord, *, summary: bool = False) -> ModelOut:
        """``summary``: the statistics as in a list (:func:`stats_summary`)."""
        return cls.model_validate(record_fields(r, stats=stats_summary(r.stats) if summary else r.stats))


#: one pose: the six axis values A1..A6 (deg)
Pose = Annotated[list[float], Field(min_length=6, max_length=6)]


class GratingCalibrationIn(BaseModel):
    """Poses for the grating calibration (axis values A1..A6, deg); omitted: the daemon's own
    (six poses sweeping every grating joint ±20° around the robot's position)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    poses: list[Pose] | None = Field(None, min_length=3, max_length=50)


_NEIGHBOURS = r"k=(?:[4-9]|[1-9][0-9]{1,4}|100000)"  # k=N, N in 4..100000 (registry.MAX_NEIGHBOURS)


def _model_name_pattern() -> str:
    """A regular expression of the model names the registry takes, for the OpenAPI description: a
    kind; its order (``:0``..``:8``, ``:cv``) or its options (each once, in the registry's order);
    then the robot's joint effects it offers (each once, ``ratio`` first, then the registry's order).
    It is documentation only: the server also takes other orders of options and effects, and blanks
    around the parts (:func:`~comp_daemon.models.registry.parse_model_name` decides)."""
    effects = sorted(
        (e for e in EFFECTS if effect_by_name(e).of_the_robot), key=lambda e: e != "ratio"
    )  # seed 001's order: kinematic+ratio+backlash
    words = [k.name for k in KINDS.values()] + effects + [w for k in KINDS.values() for w in k.option_words]
    assert all(re.fullmatch(r"[a-z0-9=-]+|k=N", w) for w in words), words  # nothing to escape
    forms = []
    for kind in KINDS.values():
        form = kind.name
        if kind.takes_order:
            form += rf"(?::(?:[0-{MAX_ORDER}]|cv))?"
        for word in kind.option_words:
            form += "(?::" + (_NEIGHBOURS if word == "k=N" else word) + ")?"
        if kind.takes_effects:
            form += "".join(rf"(?:\+{e})?" for e in effects)
        forms.append(form)
    return "^(?:" + "|".join(forms) + ")$"


MODEL_NAME_PATTERN = _model_name_pattern()


class FitIn(FitSettings):
    """A fit job: the data set, the model, and the fit's settings as ``comp-daemon fit`` takes them
    (:class:`~comp_daemon.preparation.options.FitSettings`: ``frame``, ``folds``, ``seed``,
    ``infer_dir``, ``probe_sigma_deg``, and for a ballbar or cross-bar campaign
    ``fix_near_dependent`` and ``ridge``)."""

    dataset_id: int = Field(ge=1, le=MAX_ID)
    model: str = Field(
        json_schema_extra={"pattern": MODEL_NAME_PATTERN},
        description=f"a model kind of GET /api/fits/kinds ({', '.join(KINDS)}); "
        "kinematic+ratio+backlash adds seed 001's joint effects; "
        "chebyshev:m or chebyshev:cv; kriging:k=64 (local neighbourhoods), kriging:aniso (per-joint "
        "ranges), kriging-backlash+compliance (an effect on the kriging's base)",
        min_length=1,
        max_length=100,
    )
    order: int | None = Field(
        None, ge=0, le=8, description="Chebyshev order; omitted: the model name's (default 3, seed 000)"
    )

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={  # an order apart from the name goes with a plain 'chebyshev' only
            "if": {"required": ["order"], "properties": {"order": {"type": "integer"}}},
            "then": {"properties": {"model": {"const": "chebyshev"}}},
        },
    )

    def settings(self) -> FitSettings:
        """The fit's settings alone (what the job carries to the pipeline)."""
        return FitSettings.model_validate(self.model_dump(include=set(FitSettings.model_fields)))


def _diagnosis_schema(schema: dict[str, Any]) -> None:
    """The names a diagnosis takes, in its JSON schema: effects of the catalogue (at least one) and
    model names of the registry (:data:`MODEL_NAME_PATTERN`). A comma-separated string, which the
    server also takes, is left out of the description."""
    properties = schema["properties"]
    properties["effects"]["anyOf"] = [
        {"type": "array", "items": {"enum": list(EFFECTS)}, "minItems": 1},
        {"type": "null"},
    ]
    properties["compare_models"]["items"] = {"type": "string", "pattern": MODEL_NAME_PATTERN}


class DiagnosisIn(DiagnosisSettings):
    """A diagnosis job: the data set and the diagnosis's settings as ``comp-daemon diagnose`` takes
    them (:class:`~comp_daemon.preparation.options.DiagnosisSettings`)."""

    model_config = ConfigDict(json_schema_extra=_diagnosis_schema)
    dataset_id: int = Field(ge=1, le=MAX_ID)

    def settings(self) -> DiagnosisSettings:
        """The diagnosis's settings alone (what the job carries)."""
        return DiagnosisSettings.model_validate(self.model_dump(include=set(DiagnosisSettings.model_fields)))


#: a JSON number, never a bool or a string (strict); finite (the model's allow_inf_nan)
Number = Annotated[float, Field(strict=True)]
#: a TCP coordinate (mm): no robot reaches 100 m; bounded so that a huge number is refused by name
#: instead of overflowing the inverse kinematics
Millimetres = Annotated[float, Field(strict=True, ge=-100_000.0, le=100_000.0)]
#: an orientation angle (deg, KUKA A, B, C)
Degrees = Annotated[float, Field(strict=True, ge=-360.0, le=360.0)]


def _target_schema(schema: dict[str, Any]) -> None:
    """The JSON schema of :class:`TargetIn` as tight as its validation: exactly one form, axis
    values (all six, nothing of a TCP) or a TCP (tx, ty, tz, no axis value; ta, tb, tc all or none).
    A value given as ``null`` counts as absent for the server; the schema simply asks for numbers."""
    properties = schema["properties"]
    for name in (*_AXES, *_TCP, *_ABC):
        given: dict[str, Any] = next(
            (f for f in properties[name].get("anyOf", []) if f.get("type") == "number"), {}
        )
        bounds = {k: v for k, v in given.items() if k in ("minimum", "maximum")}
        properties[name] = {"type": "number", "title": properties[name].get("title", name), **bounds}

    def none_of(names: tuple[str, ...]) -> dict[str, Any]:
        return {"not": {"anyOf": [{"required": [n]} for n in names]}}

    schema["oneOf"] = [
        {"required": list(_AXES), **none_of((*_TCP, *_ABC))},
        {
            "required": list(_TCP),
            **none_of(_AXES),
            "dependentRequired": {n: [m for m in _ABC if m != n] for n in _ABC},
        },
    ]


class TargetIn(BaseModel):
    """One drilling point in exactly one form: axis values ``a1..a6`` (deg), or the wanted TCP
    ``tx, ty, tz`` (mm, robot base frame) with optional orientation ``ta, tb, tc`` (deg, KUKA A, B,
    C), as in a target file (docs/data-format.md). Values are JSON numbers (``true`` or ``"20"`` are
    refused, not converted). Whether the robot reaches the point is checked when the batch is posted.
    The route works on the :class:`~comp_daemon.data.target.Target` it gives (:meth:`target`)."""

    model_config = ConfigDict(
        extra="forbid", allow_inf_nan=False, validate_default=True, json_schema_extra=_target_schema
    )
    pose_id: str | None = Field(None, min_length=1, max_length=64, strict=True)
    a1: Number | None = None
    a2: Number | None = None
    a3: Number | None = None
    a4: Number | None = None
    a5: Number | None = None
    a6: Number | None = None
    tx: Millimetres | None = None
    ty: Millimetres | None = None
    tz: Millimetres | None = None
    ta: Degrees | None = None
    tb: Degrees | None = None
    tc: Degrees | None = None
    payload_kg: Number | None = Field(None, ge=0, le=10000)

    @field_validator(*_AXES, *_TCP, *_ABC, mode="after")
    @classmethod
    def _one_form(cls, value: float | None, info: ValidationInfo) -> float | None:
        """Exactly one form, checked field by field (in field order) so that the error names the
        field at fault: the first one missing from a partly given group, the first TCP field given
        next to axis values, or ``tz`` when no form is given at all."""
        name, data = info.field_name, info.data  # data: the earlier fields that validated
        assert name is not None
        group, form = next((g, f) for g, f in FORMS if name in g)
        earlier = group[: group.index(name)]
        if value is None:
            if any(data.get(k) is not None for k in earlier):
                raise ValueError(f"{name} is missing: {form} all of {', '.join(group)}")
            if name == "tz" and all(k in data and data[k] is None for k in (*_AXES, "tx", "ty")):
                raise ValueError(NO_FORM)
            return value
        missing = [k for k in earlier if k in data and data[k] is None]
        if missing:
            raise ValueError(missing_fields(missing, group, form))
        if group is not _AXES and any(data.get(k) is not None for k in _AXES):
            raise ValueError(BOTH_FORMS)
        return value

    def target(self) -> Target:
        """The validated request as the one target type (its record is this model without nulls)."""
        return Target.from_record(self.model_dump())


class BatchIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    targets: list[TargetIn] = Field(min_length=1)


#: Store event of a target's move to ``moving``; its ``compensation`` holds the model, the mapping,
#: the nominal solution, the predicted residual and, for a model with an uncertainty,
#: ``predicted_sigma_mm`` (the executor's record of how the commanded axes came about).
TARGET_MOVING = "target.moving"


class TargetOut(_Out):
    id: int
    batch_id: int
    seq: int = Field(description="1-based position in its batch")
    state: Literal[
        "queued", "compensating", "moving", "settling", "done", "failed", "cancelled", "interrupted"
    ]
    reason: str | None
    request: dict[str, Any]
    commanded_axes_deg: list[float] | None
    final_joint_errors_deg: dict[str, float | None] | None
    created_at: Time
    updated_at: Time
    started_at: Time
    finished_at: Time
    model_id: int | None = Field(None, description="the model that compensated the commanded axes")
    predicted_sigma_mm: float | None = Field(
        None,
        description="3-D 1-σ uncertainty (mm) of the model's predicted TCP at the commanded axes "
        "(the norm of its x, y, z standard deviations); null without a compensation or for a model "
        "without an uncertainty (nominal)",
    )

    @classmethod
    def of(cls, r: TargetRecord, compensation: Mapping[str, Any] | None = None) -> TargetOut:
        """``compensation``: the ``compensation`` of the target's latest :data:`TARGET_MOVING` event."""
        comp = compensation or {}
        sigma = comp.get("predicted_sigma_mm")
        model_id = comp.get("model_id")
        return cls.model_validate(
            record_fields(
                r,
                model_id=None if model_id is None else int(model_id),
                predicted_sigma_mm=None if sigma is None else float(sigma),
            )
        )


class BatchOut(_Out):
    id: int
    idempotency_key: str
    size: int
    source: str | None
    created_at: Time
    targets: list[TargetOut]

    @classmethod
    def of(
        cls,
        b: BatchRecord,
        targets: list[TargetRecord],
        compensations: Mapping[int, Mapping[str, Any]] | None = None,
    ) -> BatchOut:
        out = [TargetOut.of(t, (compensations or {}).get(t.id)) for t in targets]
        return cls.model_validate(record_fields(b, targets=out))


class EventOut(_Out):
    id: int
    time: Time
    kind: str
    target_id: int | None
    job_id: int | None
    message: dict[str, Any]

    @classmethod
    def of(cls, e: EventRecord) -> EventOut:
        return cls.model_validate(record_fields(e))


class ReadyOut(_Out):
    ready: bool
    reasons: list[str]
