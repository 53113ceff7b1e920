"""What the routes take from every request: the service state, the caller's role, a list's page.

A list endpoint takes ``limit`` (1-1000, default 100) and ``offset`` (0-2^31) and never returns more
than ``http.max_page_items`` rows, whatever ``limit`` asks for.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Query

from comp_daemon.service.auth import Principal, require
from comp_daemon.service.config import Role
from comp_daemon.service.state import ServiceState, get_state

__all__ = ["Engineer", "Operator", "Page", "Paging", "State", "Viewer", "page"]

State = Annotated[ServiceState, Depends(get_state)]
Viewer = Annotated[Principal, Depends(require(Role.viewer, read=True))]
Operator = Annotated[Principal, Depends(require(Role.operator))]
Engineer = Annotated[Principal, Depends(require(Role.engineer))]


@dataclass(frozen=True, slots=True)
class Page:
    """One page of a list: at most ``limit`` rows after the first ``offset``."""

    limit: int
    offset: int


def page(
    svc: State,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    offset: Annotated[int, Query(ge=0, le=2**31)] = 0,
) -> Page:
    """The page a list request asks for, its ``limit`` cut to ``http.max_page_items``."""
    return Page(limit=min(limit, svc.settings.http.max_page_items), offset=offset)


Paging = Annotated[Page, Depends(page)]
