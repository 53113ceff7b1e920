"""A command's options built from the fields of a settings model that the HTTP request body shares.

:func:`add_settings` adds one option per field of a pydantic settings model
(:class:`comp_daemon.preparation.options.FitSettings`,
:class:`comp_daemon.preparation.options.DiagnosisSettings`): ``probe_sigma_deg`` becomes
``--probe-sigma-deg``, a flag that is on by default ``--no-…`` (``infer_dir``: ``--no-infer-dir``),
one that is off ``--…`` (``--ridge``), a choice of words ``choices``; the help is the field's
description with its default. Each value is checked by the model's own field (its range, its
validator) as it is read, so a bad value is refused in the sentence the HTTP door answers with
(``argument --probe-sigma-deg: Input should be greater than 0, got '-1'``).
:func:`settings_of` gathers the parsed values into the model.
"""

from __future__ import annotations

import argparse
import typing
from collections.abc import Callable, Collection
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

__all__ = ["add_settings", "settings_of"]

Settings = TypeVar("Settings", bound=BaseModel)


def add_settings(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    model: type[BaseModel],
    *,
    skip: Collection[str] = (),
) -> None:
    """One option per field of ``model`` but those in ``skip`` (module docstring)."""
    for name, field in model.model_fields.items():
        if name in skip:
            continue
        flag = "--" + name.replace("_", "-")
        text = (field.description or "").replace("%", "%%")
        if field.annotation is bool:
            if field.default:
                parser.add_argument(f"--no-{flag[2:]}", dest=name, action="store_false", help=text)
            else:
                parser.add_argument(flag, dest=name, action="store_true", help=text)
            continue
        words = _words(field.annotation)
        shown = ",".join(field.default) if isinstance(field.default, tuple) else field.default
        said = "" if shown is None else f" (default {shown})"  # None: the description says
        parser.add_argument(
            flag,
            dest=name,
            type=_checked(model, name),
            default=field.default,
            choices=words,
            metavar=None if words else _metavar(name, field.annotation),
            help=text + said,
        )


def settings_of(args: argparse.Namespace, model: type[Settings]) -> Settings:
    """The model of the parsed options (each already checked as it was read); the fields ``args``
    lacks (skipped) keep their defaults."""
    return model.model_validate({n: getattr(args, n) for n in model.model_fields if hasattr(args, n)})


def _checked(model: type[BaseModel], name: str) -> Callable[[str], Any]:
    """argparse's ``type``: the text read by ``model``'s field ``name``, or its refusal."""

    def read(text: str) -> Any:
        try:
            return getattr(model.model_validate({name: text}), name)
        except ValidationError as exc:
            problem = exc.errors()[0]["msg"].removeprefix("Value error, ")
            raise argparse.ArgumentTypeError(f"{problem}, got {text!r}") from None

    return read


def _words(annotation: Any) -> tuple[str, ...] | None:
    """The words of a ``Literal[...]`` annotation (None for any other)."""
    if typing.get_origin(annotation) is typing.Literal:
        return tuple(typing.get_args(annotation))
    return None


def _metavar(name: str, annotation: Any) -> str:
    unit = name.rsplit("_", 1)[-1]
    if unit in ("deg", "mm"):
        return unit.upper()
    return "N" if annotation is int else name.upper()
