"""Structured logs: one JSON object per line (or a readable console form), through structlog.

Every record carries ``timestamp`` (ISO 8601, UTC), ``level``, ``logger`` and ``event`` (the
message), plus whatever is bound: use ``bound(target_id=…, job_id=…)`` around work on one target or
job, and everything logged inside it (by any module, in that task or thread) carries those keys.
Standard-library loggers (uvicorn, asyncio) go through the same renderer.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterator, MutableMapping
from contextlib import contextmanager
from typing import IO, Any, Literal

import structlog

__all__ = ["bound", "configure_logging", "get_logger", "plain_line"]

_HANDLER_MARK = "_comp_daemon_handler"


def _shared_processors() -> list[Any]:
    return [
        structlog.contextvars.merge_contextvars,
        structlog.stdlib.add_log_level,
        structlog.stdlib.add_logger_name,
        structlog.processors.TimeStamper(fmt="iso", utc=True),
        structlog.processors.StackInfoRenderer(),
    ]


def configure_logging(
    level: str = "INFO", fmt: Literal["json", "console"] = "json", stream: IO[str] | None = None
) -> None:
    """Route structlog and the standard library to one handler on ``stream`` (stderr by default)."""
    shared = _shared_processors()
    structlog.configure(
        processors=[*shared, structlog.stdlib.ProcessorFormatter.wrap_for_formatter],
        logger_factory=structlog.stdlib.LoggerFactory(),
        wrapper_class=structlog.stdlib.BoundLogger,
        cache_logger_on_first_use=False,
    )
    renderer: Any
    if fmt == "json":
        renderer = structlog.processors.JSONRenderer(default=repr)
        final = [structlog.processors.format_exc_info, renderer]
    else:
        final = [
            structlog.dev.ConsoleRenderer(colors=False, exception_formatter=structlog.dev.plain_traceback)
        ]
    formatter = structlog.stdlib.ProcessorFormatter(
        foreign_pre_chain=shared,
        processors=[structlog.stdlib.ProcessorFormatter.remove_processors_meta, *final],
    )
    handler = logging.StreamHandler(stream if stream is not None else sys.stderr)
    handler.setFormatter(formatter)
    setattr(handler, _HANDLER_MARK, True)
    root = logging.getLogger()
    for old in [h for h in root.handlers if getattr(h, _HANDLER_MARK, False)]:
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(level.upper())
    for name in ("uvicorn", "uvicorn.error", "uvicorn.access"):
        lg = logging.getLogger(name)
        lg.handlers.clear()
        lg.propagate = True


def plain_line(_logger: Any, _name: str, event_dict: MutableMapping[str, Any]) -> str:
    """A structlog processor: the event, then its keys as ``key=value``, then any traceback, as one
    text (the record's message before :func:`configure_logging`, and in the real-time child)."""
    exception = event_dict.pop("exception", None)
    event = str(event_dict.pop("event", ""))
    keys = " ".join(f"{k}={v}" for k, v in event_dict.items())
    text = f"{event} {keys}" if keys else event
    return f"{text}\n{exception}" if exception else text


def _route_to_stdlib() -> None:
    """Before :func:`configure_logging` (in tests, in a library use), structlog records still go
    through the standard library, as one plain line each, so its handlers and levels apply."""
    if not structlog.is_configured():
        structlog.configure(
            processors=[
                structlog.stdlib.filter_by_level,
                structlog.contextvars.merge_contextvars,
                structlog.processors.format_exc_info,
                plain_line,
            ],
            logger_factory=structlog.stdlib.LoggerFactory(),
            wrapper_class=structlog.stdlib.BoundLogger,
            cache_logger_on_first_use=False,
        )


def get_logger(name: str | None = None, **initial: Any) -> Any:
    """A structlog logger (``.info(event, **kv)`` etc.), optionally with keys bound."""
    _route_to_stdlib()
    logger = structlog.get_logger(name)
    return logger.bind(**initial) if initial else logger


@contextmanager
def bound(**keys: Any) -> Iterator[None]:
    """Bind ``keys`` (e.g. ``target_id``, ``job_id``) to every log record inside the block."""
    with structlog.contextvars.bound_contextvars(**keys):
        yield
