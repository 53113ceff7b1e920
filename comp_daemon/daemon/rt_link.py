"""The link between the daemon and its real-time process: framed messages over a Unix socket pair.

A frame is a 4-byte big-endian length and a pickled Python object (protocol 5). Pickle is used
because both ends are this package, started by each other over a private ``socketpair`` that no
other process can reach: the messages are the package's own frozen dataclasses (the loop's core
state, encoder readings, safety events), and pickle carries them without a second schema.

:class:`FrameDecoder` is the protocol without I/O (bytes in, messages out); :class:`LinkProtocol` is
the thin asyncio adapter both ends use. ``send`` never blocks: it queues the frame on the transport.
"""

from __future__ import annotations

import asyncio
import pickle
import struct
from collections.abc import Callable
from typing import Any, cast

__all__ = ["MAX_FRAME_BYTES", "FrameDecoder", "LinkError", "LinkProtocol", "encode_frame"]

MAX_FRAME_BYTES = 64 * 1024 * 1024  # a grating calibration or a latency batch is far smaller
_HEADER = struct.Struct(">I")


class LinkError(RuntimeError):
    """A frame that cannot be read (too long, or not a pickled message)."""


def encode_frame(message: Any) -> bytes:
    payload = pickle.dumps(message, protocol=5)
    if len(payload) > MAX_FRAME_BYTES:
        raise LinkError(f"message of {len(payload)} bytes exceeds the frame limit of {MAX_FRAME_BYTES}")
    return _HEADER.pack(len(payload)) + payload


class FrameDecoder:
    """Bytes from the stream in, whole messages out (any split of the stream into chunks)."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[Any]:
        buf = self._buf
        buf += data
        out: list[Any] = []
        pos = 0
        while len(buf) - pos >= _HEADER.size:
            (n,) = _HEADER.unpack_from(buf, pos)
            if n > MAX_FRAME_BYTES:
                raise LinkError(f"frame of {n} bytes announced; the limit is {MAX_FRAME_BYTES}")
            end = pos + _HEADER.size + n
            if len(buf) < end:
                break
            try:
                out.append(pickle.loads(memoryview(buf)[pos + _HEADER.size : end]))
            except Exception as exc:
                raise LinkError(f"unreadable frame of {n} bytes: {exc}") from exc
            pos = end
        del buf[:pos]
        return out


class LinkProtocol(asyncio.Protocol):
    """Delivers each message to ``on_message``; ``on_lost`` once when the other end has gone."""

    def __init__(
        self,
        on_message: Callable[[Any], None],
        on_lost: Callable[[Exception | None], None],
    ) -> None:
        self.on_message = on_message
        self.on_lost = on_lost
        self.transport: asyncio.Transport | None = None
        self._decoder = FrameDecoder()
        self.closed = asyncio.Event()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.Transport, transport)

    def data_received(self, data: bytes) -> None:
        try:
            messages = self._decoder.feed(data)
        except LinkError as exc:
            if self.transport is not None:
                self.transport.abort()  # connection_lost follows with the error
            self._lost(exc)
            return
        for message in messages:
            self.on_message(message)

    def connection_lost(self, exc: Exception | None) -> None:
        self.transport = None
        self._lost(exc)

    def _lost(self, exc: Exception | None) -> None:
        if not self.closed.is_set():
            self.closed.set()
            self.on_lost(exc)

    @property
    def connected(self) -> bool:
        return self.transport is not None and not self.transport.is_closing()

    def send(self, message: Any) -> bool:
        """Queue one message; False when the link is down (the message is dropped)."""
        transport = self.transport
        if transport is None or transport.is_closing():
            return False
        transport.write(encode_frame(message))
        return True

    def buffered_bytes(self) -> int:
        transport = self.transport
        return 0 if transport is None else transport.get_write_buffer_size()

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()
