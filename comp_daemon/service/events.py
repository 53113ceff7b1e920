"""In-process publish/subscribe for live updates (served as server-sent events on ``/api/events``).

Publishers (the daemon's loop, the store's commit listener, the job runner) call
:meth:`EventBus.publish` — non-blocking, safe from any thread, O(subscribers). Each subscriber
has a bounded queue; a subscriber that falls behind loses its *oldest* events and is told how many
with a ``dropped`` count on the next event it receives, so the publisher never waits.

Events are ``(seq, kind, data, time)``; ``seq`` increases by one per published event in this process.
Kinds in use: ``loop`` (loop statistics, a few per second), ``joints`` (per-joint state),
``target.<state>``, ``batch.accepted``, ``job.<state>``, ``job.progress``, ``model.*``,
``dataset.*``, ``daemon.*``.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import threading
import time
from collections import deque
from collections.abc import AsyncIterator, Mapping
from dataclasses import dataclass, field
from typing import Any

__all__ = ["CLOSING", "BusEvent", "EventBus", "Subscription"]

CLOSING = "server.closing"


@dataclass(frozen=True, slots=True)
class BusEvent:
    seq: int
    kind: str
    data: Mapping[str, Any]
    time: float
    _encoded: list[str] = field(default_factory=list, compare=False, repr=False)

    def sse(self, dropped: int = 0) -> str:
        """The event as one server-sent-events message (``id``, ``event``, ``data`` lines)."""
        if not self._encoded:
            payload = {"seq": self.seq, "kind": self.kind, "time": self.time, "data": self.data}
            self._encoded.append(json.dumps(payload, separators=(",", ":"), default=str))
        body = self._encoded[0]
        if dropped:
            body = body[:-1] + f',"dropped":{dropped}}}'
        return f"id: {self.seq}\nevent: {self.kind}\ndata: {body}\n\n"


class Subscription:
    """One subscriber's queue; iterate with ``async for``; close with :meth:`close` or ``async with``."""

    def __init__(self, bus: EventBus, maxlen: int, kinds: frozenset[str] | None) -> None:
        self._bus = bus
        self._events: deque[BusEvent] = deque()
        self._maxlen = maxlen
        self._kinds = kinds
        self._wakeup = asyncio.Event()
        self.dropped = 0
        self.closed = False

    def _offer(self, event: BusEvent, *, force: bool = False) -> None:  # called in the loop thread
        if (
            not force
            and self._kinds is not None
            and event.kind not in self._kinds
            and event.kind.split(".")[0] not in self._kinds
        ):
            return
        if len(self._events) >= self._maxlen:
            self._events.popleft()
            self.dropped += 1
        self._events.append(event)
        self._wakeup.set()

    async def get(self, timeout: float | None = None) -> BusEvent | None:
        """The next event, or None after ``timeout`` seconds without one."""
        while not self._events:
            self._wakeup.clear()
            if timeout is None:
                await self._wakeup.wait()
            else:
                try:
                    await asyncio.wait_for(self._wakeup.wait(), timeout)
                except TimeoutError:
                    return None
        return self._events.popleft()

    def take_dropped(self) -> int:
        n, self.dropped = self.dropped, 0
        return n

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._bus._remove(self)

    async def __aenter__(self) -> Subscription:
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()

    def __aiter__(self) -> AsyncIterator[BusEvent]:
        return self._iterate()

    async def _iterate(self) -> AsyncIterator[BusEvent]:
        while not self.closed:
            event = await self.get()
            if event is not None:
                yield event


class EventBus:
    """Fan-out of events to subscribers living in one asyncio loop."""

    def __init__(self, queue_events: int = 256) -> None:
        self._queue_events = queue_events
        self._subscribers: list[Subscription] = []
        self._seq = itertools.count(1)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread: int | None = None
        self._lock = threading.Lock()
        self._closing: BusEvent | None = None

    def bind_loop(self, loop: asyncio.AbstractEventLoop | None = None) -> None:
        """Attach the loop that subscribers live in (done by the app at startup)."""
        self._loop = loop if loop is not None else asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()

    @property
    def subscriber_count(self) -> int:
        return len(self._subscribers)

    def subscribe(self, kinds: frozenset[str] | None = None) -> Subscription:
        """A new subscription (call inside the bus's loop); ``kinds`` filters by kind or kind prefix."""
        if self._loop is None:
            self.bind_loop()
        sub = Subscription(self, self._queue_events, kinds)
        self._subscribers.append(sub)
        if self._closing is not None:  # closed already: the new subscriber hears that at once
            sub._offer(self._closing, force=True)
        return sub

    def _remove(self, sub: Subscription) -> None:
        if sub in self._subscribers:
            self._subscribers.remove(sub)

    def publish(self, kind: str, data: Mapping[str, Any]) -> None:
        """Send ``data`` to every subscriber; never blocks, callable from any thread."""
        with self._lock:
            seq = next(self._seq)
        event = BusEvent(seq, kind, data, time.time())
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        if threading.get_ident() == self._loop_thread:
            self._deliver(event)
        else:
            try:
                loop.call_soon_threadsafe(self._deliver, event)
            except RuntimeError:  # loop closed between the check and the call
                pass

    def _deliver(self, event: BusEvent) -> None:
        for sub in list(self._subscribers):
            sub._offer(event)

    def close(self) -> None:
        """Tell every subscriber that the server is closing (a ``server.closing`` event, their last).

        Call it in the bus's loop *before* stopping the HTTP server: the server waits for open
        responses, and an event stream ends only when told. Later subscribers are told at once.
        """
        with self._lock:
            seq = next(self._seq)
        event = BusEvent(seq, CLOSING, {}, time.time())
        self._closing = event
        for sub in list(self._subscribers):
            sub._offer(event, force=True)
