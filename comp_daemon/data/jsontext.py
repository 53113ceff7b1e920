"""JSON text of a data set → its records, refusing what no data set may hold, by the value's path.

A JSON data set is a list of records (``[{...}, ...]``) or an object holding one
(``{"name": ..., "records": [...]}``). :func:`load_json_records` decodes UTF-8 (a byte order mark
is accepted), parses strictly and refuses, as a :class:`~comp_daemon.data.columns.DatasetError`
naming the ``path`` of the first bad value in document order (``$[3].a1``,
``$.records[0].note``) and, inside a record, its record number and column:

- a key given twice in one object (JSON allows it; the last value would silently win);
- a NUL character or a lone surrogate (``"\\ud800"``) in a string or a key;
- an integer of more than :data:`JSON_MAX_INT_DIGITS` digits (beyond any double; Python would
  otherwise refuse one over 4 300 digits with a ValueError of its own).

Text that is not UTF-8 or not JSON is refused with its line (``row_label="line"``).
:func:`record_path` gives the path of a fault the record checks
(:func:`comp_daemon.data.readers.dataset_from_records`) find later.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from comp_daemon.data.cells import printable, text_fault
from comp_daemon.data.columns import DatasetError

__all__ = ["JSON_MAX_INT_DIGITS", "JsonRecords", "json_path", "load_json_records", "record_path"]

JSON_MAX_INT_DIGITS = 309  # a longer integer is beyond every double (1.8e308)

PathPart = str | int
# only an escape can put a NUL or a surrogate into a parsed string (raw ones are not JSON, or not UTF-8)
_SUSPECT_ESCAPE = re.compile(r"\\u(?:0000|[dD][89a-fA-F])")


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
    return _LongInteger(text) if len(text.lstrip("-")) > JSON_MAX_INT_DIGITS else int(text)


def _first_fault(doc: Any) -> tuple[str, list[PathPart]] | None:
    """The first refused value in document order: (problem, path from the document's root)."""
    stack: list[tuple[Any, list[PathPart]]] = [(doc, [])]
    while stack:
        value, path = stack.pop()
        if isinstance(value, _LongInteger):
            return f"an integer of {len(value.lstrip('-'))} digits (beyond any number)", path
        if isinstance(value, str):
            problem = text_fault(value)
            if problem is not None:
                return problem, path
        elif isinstance(value, dict):
            duplicates = getattr(value, "duplicate_keys", ())
            if duplicates:
                return f"duplicate key {printable(duplicates[0])!r} (given twice)", [*path, duplicates[0]]
            for key in value:
                problem = text_fault(key)
                if problem is not None:
                    return f"{problem} (in a key)", [*path, key]
            stack.extend((v, [*path, k]) for k, v in reversed(value.items()))
        elif isinstance(value, list):
            stack.extend((v, [*path, i]) for i, v in reversed(list(enumerate(value))))
    return None


def json_path(parts: Sequence[PathPart]) -> str:
    """The JSONPath of a value: ``$``, then ``[i]`` per index and ``.key`` (or ``['key']``) per key."""
    out = "$"
    for part in parts:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if part.isidentifier() else f"[{part!r}]"
    return printable(out)


@dataclass(frozen=True, slots=True)
class JsonRecords:
    """The records of a JSON data set, the ``name`` it gives itself (if any), and where the records
    are in the document (``prefix``: ``()`` for a list, ``("records",)`` for the object form)."""

    records: list[Any]
    name: str | None
    prefix: tuple[PathPart, ...]


def record_path(doc: JsonRecords, record: int | None, column: str | None) -> str:
    """The path of a fault at 1-based ``record`` and ``column`` (a stripped key name): the value if
    the record has that key, else the record, else the list of records."""
    parts: list[PathPart] = list(doc.prefix)
    if record is None or not 0 < record <= len(doc.records):
        return json_path(parts)
    parts.append(record - 1)
    item = doc.records[record - 1]
    if column is not None and isinstance(item, dict):
        key = next((k for k in item if isinstance(k, str) and k.strip() == column), None)
        if key is not None:
            parts.append(key)
    return json_path(parts)


def load_json_records(data: bytes, source: str) -> JsonRecords:
    """Parse a JSON data set's bytes by the rules of this module; raises :class:`DatasetError`."""
    try:
        text = data.decode("utf-8").removeprefix("\ufeff")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise DatasetError(
            f"not UTF-8 text (byte 0x{data[exc.start]:02x})", source=source, row=line, row_label="line"
        ) from None
    marked: list[bool] = []  # a duplicate key or a long integer was parsed

    def object_pairs(pairs: list[tuple[str, Any]]) -> _Object:
        obj = _object_pairs(pairs)
        if obj.duplicate_keys:
            marked.append(True)
        return obj

    def parse_int(digits: str) -> int | _LongInteger:
        value = _parse_int(digits)
        if isinstance(value, _LongInteger):
            marked.append(True)
        return value

    try:
        doc = json.loads(text, object_pairs_hook=object_pairs, parse_int=parse_int)
    except json.JSONDecodeError as exc:
        raise DatasetError(
            f"not valid JSON (invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg})",
            source=source,
            row=exc.lineno,
            row_label="line",
        ) from None
    except RecursionError:
        raise DatasetError("not a list of records (JSON nested too deeply)", source=source) from None
    fault = _first_fault(doc) if marked or _SUSPECT_ESCAPE.search(text) else None
    if fault is not None:
        problem, parts = fault
        prefix: list[PathPart] = ["records"] if isinstance(doc, dict) else []
        row: int | None = None
        column: str | None = None
        inside = parts[len(prefix) :]
        if parts[: len(prefix)] == prefix and len(inside) >= 2 and isinstance(inside[0], int):
            row, column = inside[0] + 1, printable(str(inside[1]))
        raise DatasetError(
            problem,
            source=source,
            row=row,
            column=column,
            row_label="record",
            path=json_path(parts),
        )
    if isinstance(doc, list):
        return JsonRecords(doc, None, ())
    if isinstance(doc, dict) and isinstance(doc.get("records"), list):
        name = doc.get("name")
        return JsonRecords(
            doc["records"], name if isinstance(name, str) and name.strip() else None, ("records",)
        )
    raise DatasetError(
        "expected a list of records or an object with 'records' (a list)", source=source, path="$"
    )
