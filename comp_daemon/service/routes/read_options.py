"""How an uploaded file is written: the reader options of the command line as query parameters.

``delimiter`` (``,``, ``;`` or ``tab``), ``decimal_comma`` (``true``/``false``), ``units``
(``LENGTH,ANGLE``, e.g. ``m,rad``) and ``euler`` (a convention, e.g. ``intrinsic-zyx``) mean what
``--delimiter``, ``--decimal-comma``, ``--units`` and ``--euler`` mean to ``data check``
(:mod:`comp_daemon.data.options`, :mod:`comp_daemon.data.euler`); a multipart upload may give them
as form fields of the same names instead. A value the command line refuses is answered 422 with the
command line's sentence and ``column`` naming the parameter.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated

from fastapi import Depends, Query

from comp_daemon.data.options import ReadOptions
from comp_daemon.service.state import ApiError

__all__ = ["OPTION_FIELDS", "ReadingQuery", "merged", "options_of", "read_options_query"]

#: the parameters (and multipart form fields) that say how the file is written
OPTION_FIELDS: tuple[str, ...] = ("delimiter", "decimal_comma", "units", "euler")
_TRUE = ("true", "1", "yes", "on")
_FALSE = ("false", "0", "no", "off", "")


def options_of(values: Mapping[str, str | bool | None]) -> ReadOptions:
    """The :class:`ReadOptions` of the parameters ``values`` (names of :data:`OPTION_FIELDS`);
    :class:`ApiError` 422 naming the parameter at fault."""
    comma = values.get("decimal_comma")
    if isinstance(comma, str):
        if comma.strip().lower() not in (*_TRUE, *_FALSE):
            raise ApiError(
                422,
                "invalid_request",
                f"decimal_comma {comma!r}: expected true or false",
                column="decimal_comma",
            )
        comma = comma.strip().lower() in _TRUE
    try:
        return ReadOptions.of(
            _text(values.get("delimiter")),
            bool(comma),
            _text(values.get("units")),
            _text(values.get("euler")),
        )
    except ValueError as exc:
        message = str(exc)
        named = message.split(" ", 1)[0].lstrip("-").replace("-", "_")
        raise ApiError(
            422, "invalid_request", message, column=named if named in OPTION_FIELDS else None
        ) from None


def merged(query: Mapping[str, str | bool | None], form: Mapping[str, str]) -> dict[str, str | bool | None]:
    """The query's options with a multipart form's fields of the same names; one given in both is
    refused (422), whatever the values."""
    out = dict(query)
    for name, value in form.items():
        if out.get(name) is not None:
            raise ApiError(
                422,
                "invalid_request",
                f"{name} is given as a query parameter and as a form field",
                column=name,
            )
        out[name] = value
    return out


def _text(value: str | bool | None) -> str | None:
    return value if isinstance(value, str) else None


def read_options_query(
    delimiter: Annotated[
        str | None,
        Query(max_length=8, description="field separator of a CSV file: ',' (default), ';' or tab"),
    ] = None,
    decimal_comma: Annotated[
        bool | None, Query(description="numbers with ',' as the decimal mark (fields then ';'-separated)")
    ] = None,
    units: Annotated[
        str | None, Query(max_length=20, description="LENGTH,ANGLE: mm or m, deg or rad (default mm,deg)")
    ] = None,
    euler: Annotated[
        str | None,
        Query(
            max_length=40,
            description="a 6-DOF probe's orientation as Euler angles e1, e2, e3 in this convention, e.g. "
            "intrinsic-zyx (R = Rz(e1) Ry(e2) Rx(e3))",
        ),
    ] = None,
) -> dict[str, str | bool | None]:
    """The query parameters as given (a multipart form may add its own): a FastAPI dependency."""
    return {"delimiter": delimiter, "decimal_comma": decimal_comma, "units": units, "euler": euler}


ReadingQuery = Annotated[dict[str, str | bool | None], Depends(read_options_query)]
