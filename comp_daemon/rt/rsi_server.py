"""The daemon's RSI endpoint: a thin asyncio UDP protocol over :mod:`comp_daemon.rt.rsi_codec`.

``datagram_received`` parses the telegram, calls the synchronous controller step
``handler(telegram) -> SenReply`` and sends the reply to the sender before returning — no task, no
queue, no await on the reply path.

Newest-only answering: asyncio's datagram transport reads *one* datagram per readiness callback, so
a backlog (the loop was busy for more than a cycle) would otherwise be answered telegram by telegram,
each answer later than the last. On every receive the protocol therefore drains the socket with
non-blocking ``recvfrom_into`` on a duplicate of the transport's socket (same kernel queue), parses
every datagram from the controller's address as it is read, and answers only the *newest valid
telegram of the session*: the one with the highest IPOC, not the last to arrive. Older fresh
telegrams of the same batch are counted as ``superseded``. Garbage is counted as ``garbled`` and
never displaces a valid telegram, so a flood of garbage from the controller's address (spoofed or
a broken device) costs parse time but no reply. When nothing is queued this costs one ``recvfrom``
returning EAGAIN.

The controller session: the source address (host and port) the telegrams come from, with an IPOC
that only grows. A telegram of the session whose IPOC is not above the highest one taken so far is
an older copy (a duplicate, or a copy the network delivered late) and is counted as ``stale`` and
never answered: answering it would send the controller a reply for a cycle it has left behind,
while the reply to the current cycle is missing — a late reply on its count. Telegrams from a
second sender on the controller's address while the session's sender is still sending are counted
as ``other_sender`` and never answered or passed to the loop: one loop, one controller. The session
is not handed over to the newcomer, because a robot in a running session must not be stopped by
whatever else sends on the cell network; a real second controller gets no reply and stops on its
own Timeout. A sender that has sent nothing for ``session_silence_ms`` (default: 10 cycles, the
ETHERNET object's default Timeout — by then a controller without replies has stopped RSI) no longer
holds the session: the next telegram begins a new session (counted as ``sessions``, logged with
both senders), as it does when the same sender comes back after such a silence with an IPOC that
went back (the controller restarted on the same port). The same sender resuming with a higher IPOC
keeps its session here (a controller unscheduled for a while does that too); that RSI stopped and
was re-armed in between is the daemon's judgement (:mod:`comp_daemon.daemon.rsi_sessions`). The
``on_new_session`` callback learns of each new session before its first telegram is handled.

Only datagrams from the configured controller address are accepted (host, and port if configured);
others are counted as ``foreign``, logged (rate-limited) and never answered. A garbled datagram is
logged (the first, then every ``log_every``-th) and not answered (the controller counts the missing
reply as late). If the handler
raises or returns a reply for another IPOC — our bug — the reply is zero correction with ``Stop=1``.

Times are integer nanoseconds from an injectable clock (``time.perf_counter_ns`` by default):
``latency`` is receive callback entry → ``sendto`` returned; ``jitter`` is the inter-arrival time of
answered telegrams minus the IPOC difference (the controller's own cycle), so skipped cycles do not
show up as jitter. A reply whose latency exceeds ``late_after_ms`` (default: ``cycle_ms``) is counted
as ``late``; the controller's own count arrives in ``Delay D`` and is kept as ``controller_delay``.
"""

from __future__ import annotations

import asyncio
import bisect
import contextlib
import socket
import time
from array import array
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, cast

import numpy as np

from comp_daemon.common.logs import get_logger
from comp_daemon.rt.cycle_trace import CycleTrace
from comp_daemon.rt.rsi_codec import RobTelegram, RsiProtocolError, SenReply, build_sen, parse_rob

__all__ = [
    "LATENCY_BUCKETS_NS",
    "RsiHandler",
    "RsiServerConfig",
    "RsiServerProtocol",
    "RsiServerStats",
    "SampleStats",
    "SessionHook",
    "start_rsi_server",
]

log = get_logger(__name__)

RsiHandler = Callable[[RobTelegram], SenReply]
Clock = Callable[[], int]
#: ``on_new_session(number, sender, what)``: a new controller session begins (``what``: in words)
SessionHook = Callable[[int, tuple[str, int], str], None]

#: Upper bucket bounds (ns) for latency and |jitter| histograms; the last bucket is open.
LATENCY_BUCKETS_NS: tuple[int, ...] = tuple(
    int(us * 1000) for us in (10, 20, 50, 100, 200, 500, 1000, 2000, 4000, 8000, 12000, 24000, 100000)
)

_ZERO_AK = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
_MAX_DRAIN = 256  # datagrams read per receive callback at most

_Valid = tuple[RobTelegram, tuple[str, int]]  # a parsed telegram from the controller and its sender


@dataclass(frozen=True, slots=True)
class RsiServerConfig:
    """Settings of the RSI endpoint. Hosts are IP literals (the controller's address is compared as text)."""

    controller_host: str
    controller_port: int | None = None  # None: any source port of controller_host
    bind_host: str = "0.0.0.0"
    bind_port: int = 49152
    cycle_ms: float = 12.0
    late_after_ms: float | None = None  # None: cycle_ms
    sen_type: str = "ImFree"  # used for the replies the server builds itself (handler failure)
    stop_on_handler_error: bool = True
    log_every: int = 1000  # after the first, log every n-th foreign/garbled/other-sender datagram
    #: a sender silent this long (ms) no longer holds the session (None: 10 cycles)
    session_silence_ms: float | None = None
    samples: int = 65536  # ring size for latency/jitter percentiles
    #: receive buffer asked of the kernel (SO_RCVBUF, capped by ``net.core.rmem_max``): room for a
    #: burst of garbage from the controller's address while this process is not scheduled, so that
    #: the kernel does not drop the valid telegrams arriving meanwhile (the usual default, 208 KiB,
    #: holds 25 datagrams of 5 KB)
    receive_buffer_bytes: int = 1 << 20


class SampleStats:
    """Count, min, max, sum, a fixed histogram of |value| and a ring of the last ``size`` values (ns)."""

    __slots__ = ("_i", "bounds", "count", "histogram", "max", "min", "ring", "sum")

    def __init__(self, size: int = 65536, bounds: tuple[int, ...] = LATENCY_BUCKETS_NS) -> None:
        self.bounds = bounds
        self.histogram = [0] * (len(bounds) + 1)
        self.ring = array("q", bytes(8 * size))
        self._i = 0
        self.count = 0
        self.sum = 0
        self.min: int | None = None
        self.max: int | None = None

    def record(self, value: int) -> None:
        ring = self.ring
        ring[self._i] = value
        self._i = (self._i + 1) % len(ring)
        self.count += 1
        self.sum += value
        self.histogram[bisect.bisect_left(self.bounds, abs(value))] += 1
        if self.max is None or value > self.max:
            self.max = value
        if self.min is None or value < self.min:
            self.min = value

    def recent(self) -> np.ndarray:
        """The retained values, oldest first."""
        n = min(self.count, len(self.ring))
        values = np.frombuffer(self.ring, dtype=np.int64)
        if self.count <= len(self.ring):
            return values[:n].copy()
        return np.concatenate([values[self._i :], values[: self._i]])

    def since(self, count: int) -> array[int]:
        """The values recorded after the ``count``-th, oldest first (at most the ring's size)."""
        ring = self.ring
        n = min(max(self.count - count, 0), len(ring))
        start = (self._i - n) % len(ring)
        if start + n <= len(ring):
            return ring[start : start + n]
        return ring[start:] + ring[: self._i]

    def percentiles(self, qs: tuple[float, ...] = (50.0, 99.0)) -> dict[str, float]:
        """Percentiles (ns) of the retained values; empty dict before the first value."""
        values = self.recent()
        if values.size == 0:
            return {}
        return {f"p{q:g}": float(v) for q, v in zip(qs, np.percentile(values, qs), strict=True)}

    def summary(self) -> dict[str, Any]:
        return {
            "count": self.count,
            "min_ns": self.min,
            "max_ns": self.max,
            "mean_ns": self.sum / self.count if self.count else None,
            **{f"{k}_ns": v for k, v in self.percentiles().items()},
            "histogram_le_ns": dict(zip([*map(str, self.bounds), "inf"], self.histogram, strict=True)),
        }


class RsiServerStats:
    """Counters of the RSI endpoint, written only by the loop that runs it; other threads read single
    counters and copies of the rings (the daemon's telemetry does, from the service loop)."""

    __slots__ = (
        "answered",
        "controller_delay",
        "foreign",
        "garbled",
        "handler_errors",
        "ipoc_skipped",
        "jitter",
        "late",
        "latency",
        "other_sender",
        "received",
        "send_errors",
        "session_sender",
        "sessions",
        "stale",
        "superseded",
    )

    def __init__(self, samples: int) -> None:
        self.received = 0  # datagrams taken from the socket
        self.answered = 0
        self.garbled = 0
        self.foreign = 0
        self.superseded = 0  # older telegrams drained and not answered
        self.stale = 0  # copies of telegrams older than the session's newest: never answered
        self.other_sender = 0  # telegrams of a second sender while the session's sender sends
        self.sessions = 0  # controller sessions begun (the first, and each restart)
        self.session_sender: str | None = None  # "host:port" of the session's sender
        self.handler_errors = 0
        self.late = 0  # replies whose latency exceeded late_after_ms
        self.ipoc_skipped = 0  # cycles missing between consecutive answered IPOCs
        self.send_errors = 0
        self.controller_delay: int | None = None  # last Delay D reported by the controller
        self.latency = SampleStats(samples)
        self.jitter = SampleStats(samples)

    def snapshot(self) -> dict[str, Any]:
        counts = {
            name: getattr(self, name)
            for name in self.__slots__
            if name not in ("latency", "jitter", "controller_delay", "session_sender")
        }
        return {
            **counts,
            "controller_delay": self.controller_delay,
            "session_sender": self.session_sender,
            "latency": self.latency.summary(),
            "jitter": self.jitter.summary(),
        }


class RsiServerProtocol(asyncio.DatagramProtocol):
    """Answers RSI telegrams from one controller in the receive callback. See the module docstring."""

    def __init__(
        self,
        handler: RsiHandler,
        config: RsiServerConfig,
        *,
        clock: Clock = time.perf_counter_ns,
        on_new_session: SessionHook | None = None,
        trace: CycleTrace | None = None,
    ):
        self.handler = handler
        self.trace = trace  # the per-cycle trace (comp_daemon.rt.cycle_trace), when asked for
        self.config = config
        self.clock = clock
        self.on_new_session = on_new_session
        self.stats = RsiServerStats(config.samples)
        self.transport: asyncio.DatagramTransport | None = None
        self._drain_sock: socket.socket | None = None
        self._buf = bytearray(65536)
        self._late_after_ns = int((config.late_after_ms or config.cycle_ms) * 1e6)
        self._last_rx_ns: int | None = None
        self._last_ipoc: int | None = None
        self._foreign_seen: set[tuple[str, int]] = set()
        self._others_seen: set[tuple[str, int]] = set()
        silence_ms = config.session_silence_ms
        self._silence_ns = int((10 * config.cycle_ms if silence_ms is None else silence_ms) * 1e6)
        # the session: its sender, the highest IPOC taken from it, when its last fresh telegram came
        self._sender: tuple[str, int] | None = None
        self._session_ipoc: int | None = None
        self._session_rx_ns = 0
        self.closed = asyncio.Event()  # set when the transport has gone

    # asyncio callbacks ---------------------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.DatagramTransport, transport)
        trsock = transport.get_extra_info("socket")
        if trsock is not None:
            with contextlib.suppress(OSError):  # a refusal leaves the system's default
                trsock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.config.receive_buffer_bytes)
            self._drain_sock = trsock.dup()  # same kernel receive queue; already non-blocking
            self._drain_sock.setblocking(False)
            if self.trace is not None:
                self.trace.attach(self._drain_sock)

    def connection_lost(self, exc: Exception | None) -> None:
        if self._drain_sock is not None:
            self._drain_sock.close()
            self._drain_sock = None
        self.transport = None
        self.closed.set()

    def error_received(self, exc: Exception) -> None:
        self.stats.send_errors += 1
        if self.stats.send_errors == 1 or self.stats.send_errors % self.config.log_every == 0:
            log.warning(f"rsi: socket error {exc!r} ({self.stats.send_errors} so far)")

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        t_rx = self.clock()
        trace = self.trace
        if trace is not None:
            entry, kernel_first = trace.entry(), trace.kernel_stamp()
        self.stats.received += 1
        batch: list[_Valid] = []
        self._take(data, addr, batch)
        if self._drain_sock is not None:
            self._drain(batch)
        if batch:
            newest = self._choose(batch, t_rx)
            if newest is not None and self._answer(newest[0], newest[1], t_rx) and trace is not None:
                trace.record(newest[0].ipoc, kernel_first, trace.kernel_stamp(), entry, len(batch))

    # internals -----------------------------------------------------------------------------------

    def _accept(self, addr: tuple[str | Any, int]) -> bool:
        cfg = self.config
        if addr[0] == cfg.controller_host and (cfg.controller_port is None or addr[1] == cfg.controller_port):
            return True
        stats = self.stats
        stats.foreign += 1
        key = (str(addr[0]), int(addr[1]))
        if key not in self._foreign_seen or stats.foreign % cfg.log_every == 0:
            if len(self._foreign_seen) < 1024:
                self._foreign_seen.add(key)
            log.warning(
                f"rsi: ignored datagram from foreign address {key[0]}:{key[1]} ({stats.foreign} so far)"
            )
        return False

    def _take(self, data: bytes, addr: tuple[str | Any, int], batch: list[_Valid]) -> None:
        """Append this datagram to ``batch`` if it is a telegram from the controller's address."""
        if not self._accept(addr):
            return
        try:
            telegram = parse_rob(data)
        except RsiProtocolError as exc:
            stats = self.stats
            stats.garbled += 1
            if stats.garbled == 1 or stats.garbled % self.config.log_every == 0:
                log.warning(f"rsi: garbled telegram from {addr[0]}:{addr[1]}: {exc} ({stats.garbled} so far)")
            return
        batch.append((telegram, (str(addr[0]), int(addr[1]))))

    def _drain(self, batch: list[_Valid]) -> None:
        sock = self._drain_sock
        assert sock is not None
        buf = self._buf
        for _ in range(_MAX_DRAIN):  # bounded: a flood must not keep the callback busy
            try:
                n, addr = sock.recvfrom_into(buf)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # e.g. ICMP port unreachable reported on the socket
                self.error_received(exc)
                continue
            self.stats.received += 1
            self._take(bytes(buf[:n]), addr, batch)

    def _choose(self, batch: list[_Valid], t_rx: int) -> _Valid | None:
        """The telegram to answer from one receive callback's valid telegrams: the session's newest
        fresh one; counts the rest (superseded, stale, other sender). See the module docstring."""
        stats = self.stats
        sender = self._sender
        silent = sender is None or t_rx - self._session_rx_ns >= self._silence_ns
        ours = [v for v in batch if v[1] == sender]
        if not ours and silent:  # the session's sender has gone quiet: the first one in the batch begins one
            sender = batch[0][1]
            ours = [v for v in batch if v[1] == sender]
            self._begin(sender, ours, "a new sender")
        elif ours and silent and self._session_ipoc is not None:
            if max(v[0].ipoc for v in ours) <= self._session_ipoc:  # restarted on the same port
                self._begin(ours[0][1], ours, "its IPOC went back")
        if len(ours) < len(batch):
            self._count_others(batch, sender)
        newest: _Valid | None = None
        top = self._session_ipoc
        for v in ours:
            ipoc = v[0].ipoc
            if top is not None and ipoc <= top:
                stats.stale += 1
                continue
            if newest is not None:
                stats.superseded += 1
            newest, top = v, ipoc
        if newest is not None:
            self._session_ipoc, self._session_rx_ns = top, t_rx
        return newest

    def _begin(self, sender: tuple[str, int], ours: list[_Valid], why: str) -> None:
        """A new controller session from ``sender`` (log, count, tell ``on_new_session``)."""
        stats = self.stats
        before, last_ipoc = self._sender, self._session_ipoc
        stats.sessions += 1
        stats.session_sender = f"{sender[0]}:{sender[1]}"
        first = max(v[0].ipoc for v in ours)
        if before is None:
            what = f"controller session {stats.sessions} from {stats.session_sender}, IPOC {first}"
            log.info(f"rsi: {what}")
        else:
            silent_ms = (self.clock() - self._session_rx_ns) / 1e6
            what = (
                f"controller session {stats.sessions} from {stats.session_sender} at IPOC {first} "
                f"({why}): the session of {before[0]}:{before[1]} ended at IPOC {last_ipoc}, "
                f"silent for {silent_ms:.0f} ms"
            )
            log.warning(f"rsi: {what}")
        self._sender, self._session_ipoc = sender, None
        self._last_ipoc = self._last_rx_ns = None  # no jitter across sessions
        if self.on_new_session is not None:
            try:
                self.on_new_session(stats.sessions, sender, what)
            except Exception:
                log.exception("rsi: the new-session hook failed")

    def _count_others(self, batch: list[_Valid], sender: tuple[str, int] | None) -> None:
        stats = self.stats
        for _, addr in batch:
            if addr == sender:
                continue
            stats.other_sender += 1
            if addr not in self._others_seen or stats.other_sender % self.config.log_every == 0:
                if len(self._others_seen) < 1024:
                    self._others_seen.add(addr)
                log.warning(
                    f"rsi: ignored telegram from a second sender {addr[0]}:{addr[1]} on the controller's "
                    f"address while the session of {stats.session_sender} runs ({stats.other_sender} so far)"
                )

    def _answer(self, telegram: RobTelegram, addr: tuple[str, int], t_rx: int) -> bool:
        """Build and send the reply; False when the endpoint has closed."""
        stats = self.stats
        try:
            reply = self.handler(telegram)
            if reply.ipoc != telegram.ipoc:
                raise RuntimeError(f"handler replied for IPOC {reply.ipoc} to telegram IPOC {telegram.ipoc}")
            datagram = build_sen(reply)
        except Exception:
            stats.handler_errors += 1
            if stats.handler_errors == 1 or stats.handler_errors % self.config.log_every == 0:
                log.exception(f"rsi: controller step failed on IPOC {telegram.ipoc}; zero correction sent")
            datagram = build_sen(
                SenReply(telegram.ipoc, _ZERO_AK, self.config.stop_on_handler_error, self.config.sen_type)
            )
        transport = self.transport
        if transport is None:
            return False
        transport.sendto(datagram, addr)
        t_tx = self.clock()
        stats.answered += 1
        latency = t_tx - t_rx
        stats.latency.record(latency)
        if latency > self._late_after_ns:
            stats.late += 1
        if telegram.delay is not None:
            stats.controller_delay = telegram.delay
        last_ipoc, last_rx = self._last_ipoc, self._last_rx_ns
        if last_ipoc is not None and last_rx is not None:
            gap_ms = telegram.ipoc - last_ipoc
            cycles = round(gap_ms / self.config.cycle_ms)
            if 0 < gap_ms <= 16 * self.config.cycle_ms:
                stats.jitter.record((t_rx - last_rx) - int(gap_ms * 1_000_000))
                if cycles > 1:
                    stats.ipoc_skipped += cycles - 1
        self._last_ipoc, self._last_rx_ns = telegram.ipoc, t_rx
        return True


async def start_rsi_server(
    handler: RsiHandler,
    config: RsiServerConfig,
    *,
    clock: Clock = time.perf_counter_ns,
    on_new_session: SessionHook | None = None,
    trace: CycleTrace | None = None,
) -> tuple[asyncio.DatagramTransport, RsiServerProtocol]:
    """Bind the UDP endpoint (``bind_port`` 0 picks a free port) and return (transport, protocol)."""
    loop = asyncio.get_running_loop()
    protocol = RsiServerProtocol(handler, config, clock=clock, on_new_session=on_new_session, trace=trace)
    transport, _ = await loop.create_datagram_endpoint(
        lambda: protocol, local_addr=(config.bind_host, config.bind_port), family=socket.AF_INET
    )
    return transport, protocol
