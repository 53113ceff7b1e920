"""The HTTP server of the service: uvicorn over one listening socket, guarded against idle clients.

:func:`build_http_server(app, settings.http) <build_http_server>` returns an :class:`HttpServer`
whose :meth:`~HttpServer.serve` runs until ``server.should_exit`` is set. What it adds to plain
uvicorn (which has no connection cap and no time limit for a request that never completes — its
keep-alive timer starts only after a response):

- **The listening socket** is made from ``getaddrinfo`` with ``IPPROTO_TCP``: accepted sockets
  inherit the protocol number, and asyncio sets ``TCP_NODELAY`` only on sockets that report
  ``IPPROTO_TCP`` (with protocol 0 every keep-alive request waited ~40 ms on the delayed ACK).
- **Request time limits**, per connection: ``header_timeout_s`` to send a request's headers (from
  the connection's opening or the end of the previous response; answered 408 and closed), and
  ``body_timeout_s`` to send the whole body after the headers (closed). A request being answered
  (the application has its whole body) has no limit, so event streams stay open.
- **A connection cap**, ``max_connections``: a connection opened beyond it closes the oldest
  connection that is still sending its headers or idling between requests (a half-sent request
  costs an attacker nothing, an answered one does), or, when every connection is busy with a
  request, is itself answered 503 and closed. The descriptors the HTTP side holds are thus bounded
  by about ``max_connections + 2 * listen_backlog`` (asyncio accepts up to a backlog's worth before
  the first of them is seen), whatever clients do, so the process never reaches its file limit on
  their account.
- **The accept error** asyncio logs for every pending connection once the process is out of file
  descriptors ("socket.accept() out of system resource", thousands of lines a second) is let
  through once per :data:`ACCEPT_ERROR_LOG_INTERVAL_S`, with the number held back.

:class:`GuardStats` counts what the guard did (``server.guard``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import socket
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, ClassVar

import h11
import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol

from comp_daemon.common.logs import get_logger
from comp_daemon.service.config import HttpSettings

__all__ = [
    "ACCEPT_ERROR_LOG_INTERVAL_S",
    "AcceptErrorFilter",
    "GuardStats",
    "HttpServer",
    "build_http_server",
    "listening_socket",
]

_log = get_logger("comp_daemon.http")

ACCEPT_ERROR_LOG_INTERVAL_S = 10.0
_ACCEPT_ERROR = "socket.accept() out of system resource"


def _raw_response(status: str, code: str, message: str, *headers: str) -> bytes:
    """A complete HTTP/1.1 response that closes the connection, body ``{"error", "message"}``."""
    body = json.dumps({"error": code, "message": message}).encode()
    head = [f"HTTP/1.1 {status}", "connection: close", "content-type: application/json", *headers]
    head.append(f"content-length: {len(body)}")
    return ("\r\n".join(head) + "\r\n\r\n").encode("ascii") + body


_TIMEOUT_408 = _raw_response("408 Request Timeout", "timeout", "request headers not received in time")
_BUSY_503 = _raw_response(
    "503 Service Unavailable", "busy", "too many connections; try again", "retry-after: 1"
)
_HEADERS, _BODY, _APP = "headers", "body", "app"


class AcceptErrorFilter(logging.Filter):
    """Passes asyncio's "socket.accept() out of system resource" once per ``interval_s`` (the
    message then says how many were held back); every other record passes."""

    def __init__(self, interval_s: float = ACCEPT_ERROR_LOG_INTERVAL_S) -> None:
        super().__init__()
        self.interval_s = interval_s
        self.held_back = 0
        self._last = -float("inf")

    def filter(self, record: logging.LogRecord) -> bool:
        if not isinstance(record.msg, str) or not record.msg.startswith(_ACCEPT_ERROR):
            return True
        now = time.monotonic()
        if now - self._last < self.interval_s:
            self.held_back += 1
            return False
        self._last = now
        if self.held_back:
            first, _, rest = record.getMessage().partition("\n")
            record.msg = (
                f"{first} ({self.held_back} more held back in the last {self.interval_s:g} s)\n{rest}"
            )
            record.args = None
            self.held_back = 0
        return True


def install_accept_error_filter(interval_s: float = ACCEPT_ERROR_LOG_INTERVAL_S) -> AcceptErrorFilter:
    """Put one :class:`AcceptErrorFilter` on the ``asyncio`` logger (again: the one already there)."""
    logger = logging.getLogger("asyncio")
    for existing in logger.filters:
        if isinstance(existing, AcceptErrorFilter):
            return existing
    flt = AcceptErrorFilter(interval_s)
    logger.addFilter(flt)
    return flt


@dataclass(slots=True)
class GuardStats:
    """What the connection guard did since the server started."""

    header_timeouts: int = 0  # connections answered 408: headers not complete in time
    body_timeouts: int = 0  # connections closed: body not complete in time
    evicted: int = 0  # connections closed to make room for a new one (they were sending headers)
    refused: int = 0  # new connections answered 503: every connection was busy with a request
    write_timeouts: int = 0  # connections aborted: the client stopped reading its answer
    max_open: int = 0  # most connections open at once
    logged_at: float = -float("inf")

    def note(self) -> None:
        """Log the counts (a warning, at most once per :data:`ACCEPT_ERROR_LOG_INTERVAL_S`)."""
        now = time.monotonic()
        if now - self.logged_at >= ACCEPT_ERROR_LOG_INTERVAL_S:
            self.logged_at = now
            _log.warning(
                "http connections closed by the guard",
                header_timeouts=self.header_timeouts,
                body_timeouts=self.body_timeouts,
                evicted=self.evicted,
                refused=self.refused,
                write_timeouts=self.write_timeouts,
                max_open=self.max_open,
            )


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with a time limit on each phase of a request (headers, body) and on
    writing its answer, and a cap on open connections; :func:`_guarded_protocol` gives it the
    settings and the counters."""

    guard_settings: ClassVar[HttpSettings]
    guard_stats: ClassVar[GuardStats]
    _phase = ""
    _phase_since = 0.0
    _deadline: asyncio.TimerHandle | None = None
    _stalled: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._enter(_HEADERS)
        open_now = len(self.connections)
        self.guard_stats.max_open = max(self.guard_stats.max_open, open_now)
        if open_now > self.guard_settings.max_connections:
            self._make_room()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        self._writable()
        self._phase = ""
        super().connection_lost(exc)

    def handle_events(self) -> None:
        super().handle_events()
        self._follow()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._follow()

    # ---- the request's phase and its deadline

    def _follow(self) -> None:
        if self.transport.is_closing():
            self._disarm()
            return
        state = self.conn.their_state
        if state is h11.SEND_BODY:
            self._enter(_BODY)
        elif state is h11.IDLE:
            if self._phase != _HEADERS and (self.cycle is None or self.cycle.response_complete):
                self._enter(_HEADERS)
        else:
            self._enter(_APP)

    def _enter(self, phase: str) -> None:
        if phase == self._phase:
            return
        self._disarm()
        self._phase, self._phase_since = phase, self.loop.time()
        settings = self.guard_settings
        limit = {_HEADERS: settings.header_timeout_s, _BODY: settings.body_timeout_s}.get(phase)
        if limit is not None:
            self._deadline = self.loop.call_later(limit, self._expire, phase)

    def _disarm(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None

    def _expire(self, phase: str) -> None:
        self._deadline = None
        if self._phase != phase or self.transport.is_closing():
            return
        if phase == _HEADERS:
            self.guard_stats.header_timeouts += 1
            self._close(_TIMEOUT_408)
        else:
            self.guard_stats.body_timeouts += 1
            self._close(None)
        self.guard_stats.note()

    def _close(self, answer: bytes | None) -> None:
        self._disarm()
        self._phase = ""
        if answer is not None:
            with contextlib.suppress(Exception):
                self.transport.write(answer)
        self.transport.close()

    # ---- the write time limit

    def pause_writing(self) -> None:
        super().pause_writing()
        if self._stalled is None:
            self._stalled = self.loop.call_later(self.guard_settings.write_timeout_s, self._write_expired)

    def resume_writing(self) -> None:
        super().resume_writing()
        self._writable()

    def _writable(self) -> None:
        if self._stalled is not None:
            self._stalled.cancel()
            self._stalled = None

    def _write_expired(self) -> None:
        self._stalled = None
        if self.transport.is_closing() and not self.transport.get_write_buffer_size():
            return
        self.guard_stats.write_timeouts += 1
        self.guard_stats.note()
        self._disarm()
        self._phase = ""
        self.transport.abort()  # close() would wait for the unsent bytes; abort frees them

    # ---- the cap

    def _make_room(self) -> None:
        waiting = [
            c
            for c in self.connections
            if c is not self and isinstance(c, GuardedH11Protocol) and c._phase == _HEADERS
        ]
        if waiting:
            oldest = min(waiting, key=lambda c: c._phase_since)
            self.guard_stats.evicted += 1
            oldest._close(None)
        else:
            self.guard_stats.refused += 1
            self._close(_BUSY_503)
        self.guard_stats.note()


def _guarded_protocol(settings: HttpSettings, stats: GuardStats) -> type[H11Protocol]:
    """:class:`GuardedH11Protocol` with the time limits and the connection cap of ``settings``,
    counting into ``stats``."""
    return type(
        "GuardedH11Protocol", (GuardedH11Protocol,), {"guard_settings": settings, "guard_stats": stats}
    )


def _addresses(host: str, port: int) -> Iterator[tuple[Any, ...]]:
    yield from socket.getaddrinfo(
        host, port, type=socket.SOCK_STREAM, proto=socket.IPPROTO_TCP, flags=socket.AI_PASSIVE
    )


def listening_socket(host: str, port: int, backlog: int) -> socket.socket:
    """A bound, listening TCP socket for ``host``:``port`` (0: a free port), protocol ``IPPROTO_TCP``
    so that accepted connections get ``TCP_NODELAY``. Raises OSError if it cannot bind."""
    error: OSError | None = None
    for family, type_, proto, _, address in _addresses(host, port):
        sock = socket.socket(family, type_, proto or socket.IPPROTO_TCP)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if family == socket.AF_INET6 and host in ("::", ""):
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 0)
            sock.bind(address)
            sock.listen(backlog)
        except OSError as exc:
            sock.close()
            error = exc
            continue
        sock.set_inheritable(True)
        return sock
    raise error if error is not None else OSError(f"no address to listen on for {host!r}")


class _Server(uvicorn.Server):
    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:  # the daemon owns the signals
        yield


@dataclass(slots=True)
class HttpServer:
    """A uvicorn server and its listening socket; ``port`` is the bound port."""

    server: uvicorn.Server
    sock: socket.socket
    guard: GuardStats
    port: int

    @property
    def started(self) -> bool:
        return bool(self.server.started)

    def stop(self) -> None:
        """Ask :meth:`serve` to finish (open requests get ``timeout_graceful_shutdown``)."""
        self.server.should_exit = True

    async def serve(self) -> None:
        """Serve until :meth:`stop`; the socket is closed on return. A failed start (uvicorn exits
        the process there) is raised as RuntimeError."""
        try:
            await self.server.serve(sockets=[self.sock])
        except SystemExit as exc:
            raise RuntimeError(f"the HTTP service failed to start ({exc})") from None
        finally:
            self.sock.close()


def build_http_server(app: Any, settings: HttpSettings, *, graceful_shutdown_s: int = 3) -> HttpServer:
    """Bind ``settings.host``:``settings.port`` and build the guarded uvicorn server for ``app``.

    Binding happens here (an address in use raises OSError now, not in :meth:`HttpServer.serve`);
    uvicorn's own log configuration, access log, signal handlers and ``server`` header are off.
    """
    install_accept_error_filter()
    sock = listening_socket(settings.host, settings.port, settings.listen_backlog)
    stats = GuardStats()
    config = uvicorn.Config(
        app,
        http=_guarded_protocol(settings, stats),
        log_config=None,
        access_log=False,
        lifespan="on",
        timeout_graceful_shutdown=graceful_shutdown_s,
        timeout_keep_alive=settings.keep_alive_s,
        backlog=settings.listen_backlog,
        server_header=False,
    )
    return HttpServer(_Server(config), sock, stats, int(sock.getsockname()[1]))
