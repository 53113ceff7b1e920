"""What the routes share: :class:`ServiceState` (``app.state.svc``) and :class:`ApiError`."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ParamSpec, TypeVar

from fastapi import Request

from comp_daemon.robot.description import RobotDescription
from comp_daemon.service.auth import TokenTable
from comp_daemon.service.config import Settings
from comp_daemon.service.daemon_view import DaemonView
from comp_daemon.service.events import EventBus
from comp_daemon.service.jobs import JobRunner
from comp_daemon.service.store import Store
from comp_daemon.service.uploads import ParsedDatasets

__all__ = ["ApiError", "ServiceState", "get_state"]

P = ParamSpec("P")
T = TypeVar("T")


class ApiError(Exception):
    """An error answered as ``{"error": code, "message": message, **extra}`` with ``status``."""

    def __init__(self, status: int, code: str, message: str, **extra: Any) -> None:
        self.status = status
        self.code = code
        self.message = message
        self.extra = extra
        super().__init__(message)


@dataclass(slots=True)
class ServiceState:
    settings: Settings
    store: Store
    daemon: DaemonView
    bus: EventBus
    tokens: TokenTable
    runner: JobRunner
    robot: RobotDescription
    parsed: ParsedDatasets = field(default_factory=ParsedDatasets)  # uploads as parsed, for the fits

    async def run(self, fn: Callable[P, T], *args: P.args, **kwargs: P.kwargs) -> T:
        """Run a blocking call (a store method, a parser) in a worker thread."""
        return await asyncio.to_thread(fn, *args, **kwargs)


def get_state(request: Request) -> ServiceState:
    state: ServiceState = request.app.state.svc
    return state
