"""BiSS-C frames and the grating converter's line protocol, without I/O.

Conventions (the converters' use in the cell: ``docs/daemon.md``, "Grating calibration"):

- A BiSS-C frame as the converter reports it: position (26 or 32 bits, MSB first), nE, nW, CRC6,
  left-aligned in 64 bits and written as 16 hex digits. nE and nW are active low (1 = no error /
  no warning). The CRC6 uses polynomial x⁶ + x + 1 (0x43), initial value 0, over the position, nE
  and nW bits, and is transmitted inverted. Bits to the right of the CRC are ignored.
- Position counts are in units of the scale resolution (:data:`RESOLUTION_NM`, 50 nm).
- Converter requests and replies are ASCII lines ending in ``\\r``; a ``\\n`` after the ``\\r`` is
  tolerated. Requests: ``v`` (identify), ``s`` (serial number), ``B26``/``B32`` (bit length),
  ``4`` (raw frame), ``?`` (checked count), ``1``/``0`` (streaming on/off); unknown ones answer ``ERR``.

Errors: :class:`BissProtocolError` means the peer sent something unusable (not hex, wrong length, a
line that is not ASCII or too long, an unexpected reply). A valid frame whose CRC or nE bit is bad
is *not* an exception: :func:`decode_frame` returns it with ``crc_ok``/``error_ok`` False so the
caller can count the fault. ValueError from a builder means our side passed a bad value.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

__all__ = [
    "CRC6_POLY",
    "FRAME_HEX_DIGITS",
    "MAX_LINE_BYTES",
    "REQ_COUNT",
    "REQ_FRAME",
    "REQ_IDENT",
    "REQ_SERIAL",
    "REQ_STREAM_OFF",
    "REQ_STREAM_ON",
    "RESOLUTION_NM",
    "SUPPORTED_BITS",
    "BissFrame",
    "BissProtocolError",
    "LineReader",
    "Request",
    "RequestKind",
    "crc6",
    "decode_frame",
    "encode_frame",
    "parse_count_reply",
    "parse_frame_reply",
    "parse_ident_reply",
    "parse_ok_reply",
    "parse_request",
    "request_bit_length",
]

#: Grating resolution: one position count is this many nanometres along the scale.
RESOLUTION_NM = 50.0
#: CRC6 generator polynomial x⁶ + x + 1, with the x⁶ term.
CRC6_POLY = 0x43
#: Supported position bit lengths.
SUPPORTED_BITS = (26, 32)
#: A frame reply is this many hex digits (64 bits).
FRAME_HEX_DIGITS = 16
#: Longest line accepted from a peer (without the terminator).
MAX_LINE_BYTES = 64

REQ_IDENT = b"v\r"
REQ_SERIAL = b"s\r"
REQ_FRAME = b"4\r"
REQ_COUNT = b"?\r"
REQ_STREAM_ON = b"1\r"
REQ_STREAM_OFF = b"0\r"


class BissProtocolError(Exception):
    """The converter (or, on the converter's side, the host) sent something unusable."""


def _crc6_table() -> tuple[int, ...]:
    # Byte-wise CRC with the 6-bit register kept in the top 6 bits of a byte (poly 0x43 << 2, x⁶ dropped).
    poly8 = (CRC6_POLY << 2) & 0xFF
    table = []
    for i in range(256):
        r = i
        for _ in range(8):
            r = ((r << 1) ^ poly8) & 0xFF if r & 0x80 else (r << 1) & 0xFF
        table.append(r)
    return tuple(table)


_CRC6_TABLE = _crc6_table()


def crc6(value: int, nbits: int) -> int:
    """CRC6 (x⁶ + x + 1, init 0, not inverted) over the low ``nbits`` of ``value``, MSB first.

    Leading zero bits do not change a CRC with initial value 0, so the value is processed in whole
    bytes from the most significant end.
    """
    if nbits <= 0 or value < 0 or value >> nbits:
        raise ValueError(f"value {value} does not fit in {nbits} bits")
    nbytes = (nbits + 7) // 8
    reg = 0
    table = _CRC6_TABLE
    for byte in value.to_bytes(nbytes, "big"):
        reg = table[reg ^ byte]
    return reg >> 2


@dataclass(frozen=True, slots=True)
class BissFrame:
    """A decoded BiSS-C frame. Only a frame with all three flags True is a valid position."""

    position_count: int
    error_ok: bool  # nE = 1: no error
    warning_ok: bool  # nW = 1: no warning
    crc_ok: bool
    bits: int = 26

    @property
    def valid(self) -> bool:
        """CRC right and no error bit (a warning alone leaves the position valid)."""
        return self.crc_ok and self.error_ok


def _check_bits(bits: int) -> None:
    if bits not in SUPPORTED_BITS:
        raise ValueError(f"position bit length must be one of {SUPPORTED_BITS}, got {bits!r}")


def encode_frame(
    position_count: int,
    bits: int = 26,
    *,
    error_ok: bool = True,
    warning_ok: bool = True,
    crc_xor: int = 0,
) -> str:
    """16 uppercase hex digits for a frame; ``crc_xor`` (1..63) corrupts the CRC for fault injection."""
    _check_bits(bits)
    if not 0 <= position_count < (1 << bits):
        raise ValueError(f"position count {position_count} does not fit in {bits} bits")
    if not 0 <= crc_xor < 64:
        raise ValueError(f"crc_xor must be in 0..63, got {crc_xor}")
    data = (position_count << 2) | (int(error_ok) << 1) | int(warning_ok)
    crc_tx = (~crc6(data, bits + 2) & 0x3F) ^ crc_xor
    word = ((data << 6) | crc_tx) << (64 - bits - 8)
    return f"{word:016X}"


def decode_frame(text: str | bytes, bits: int = 26) -> BissFrame:
    """Decode 16 hex digits; raises :class:`BissProtocolError` when they are not 16 hex digits."""
    _check_bits(bits)
    if isinstance(text, bytes | bytearray):
        raw = bytes(text)
        if not raw.isascii():
            raise BissProtocolError(f"frame is not ASCII: {raw[:20]!r}")
        text = raw.decode("ascii")
    if len(text) != FRAME_HEX_DIGITS:
        raise BissProtocolError(f"frame has {len(text)} characters, expected {FRAME_HEX_DIGITS} hex digits")
    try:
        if not text.isascii() or not text.isalnum():
            raise ValueError
        word = int(text, 16)
    except ValueError:
        raise BissProtocolError(f"frame is not hex: {text[:20]!r}") from None
    used = word >> (64 - bits - 8)
    crc_rx = (~used) & 0x3F
    data = used >> 6
    return BissFrame(
        position_count=data >> 2,
        error_ok=bool(data & 0b10),
        warning_ok=bool(data & 0b01),
        crc_ok=crc6(data, bits + 2) == crc_rx,
        bits=bits,
    )


# ------------------------------------------------------------------------------------- line protocol


class LineReader:
    """Splits a byte stream into ``\\r``-terminated ASCII lines (h11-style ``feed``/``next_line``).

    Empty lines and a ``\\n`` following ``\\r`` are skipped. A line that is not ASCII, or more than
    ``max_line`` bytes without a terminator, is consumed and reported once as
    :class:`BissProtocolError`; reading continues after it.
    """

    __slots__ = ("_buf", "_discarding", "max_line")

    def __init__(self, max_line: int = MAX_LINE_BYTES) -> None:
        self._buf = bytearray()
        self._discarding = False
        self.max_line = max_line

    def feed(self, data: bytes) -> None:
        self._buf += data

    def clear(self) -> None:
        """Forget everything buffered (e.g. a late reply before a new request)."""
        self._buf.clear()
        self._discarding = False

    def discard_pending(self) -> None:
        """Drop complete lines and a partial one, including the partial line's tail when it arrives.

        Used before a new request so that a reply that was still arriving when its request timed out
        is never taken for the reply to the next request.
        """
        buf = self._buf
        end = buf.rfind(b"\r")
        if end >= 0:
            del buf[: end + 1]
            self._discarding = False
        while buf[:1] == b"\n":
            del buf[:1]
        if buf:
            buf.clear()
            self._discarding = True

    @property
    def buffered(self) -> int:
        return len(self._buf)

    def next_line(self) -> str | None:
        """The next complete line without terminator, or None when none is complete yet."""
        buf = self._buf
        while True:
            while buf[:1] == b"\n" or buf[:1] == b"\r":
                del buf[:1]
            end = buf.find(b"\r")
            if end < 0:
                if len(buf) > self.max_line:
                    size = len(buf)
                    buf.clear()
                    self._discarding = True
                    raise BissProtocolError(f"line longer than {self.max_line} bytes ({size} without \\r)")
                return None
            raw = bytes(buf[:end])
            del buf[: end + 1]
            if self._discarding:  # the tail of an overlong line already reported
                self._discarding = False
                continue
            if len(raw) > self.max_line:
                raise BissProtocolError(f"line longer than {self.max_line} bytes: {raw[:20]!r}…")
            if not raw.isascii():
                raise BissProtocolError(f"line is not ASCII: {raw[:20]!r}")
            return raw.decode("ascii")


class RequestKind(enum.Enum):
    IDENT = "v"
    SERIAL = "s"
    BIT_LENGTH = "B"
    FRAME = "4"
    COUNT = "?"
    STREAM_ON = "1"
    STREAM_OFF = "0"
    UNKNOWN = ""


@dataclass(frozen=True, slots=True)
class Request:
    kind: RequestKind
    bits: int | None = None  # for BIT_LENGTH
    text: str = ""


_SIMPLE_REQUESTS = {
    "v": RequestKind.IDENT,
    "s": RequestKind.SERIAL,
    "4": RequestKind.FRAME,
    "?": RequestKind.COUNT,
    "1": RequestKind.STREAM_ON,
    "0": RequestKind.STREAM_OFF,
}


def parse_request(line: str) -> Request:
    """Classify a request line (the converter's side); anything else is ``UNKNOWN`` (answer ``ERR``)."""
    text = line.strip()
    kind = _SIMPLE_REQUESTS.get(text)
    if kind is not None:
        return Request(kind, text=text)
    if text in ("B26", "B32"):
        return Request(RequestKind.BIT_LENGTH, bits=int(text[1:]), text=text)
    return Request(RequestKind.UNKNOWN, text=text)


def request_bit_length(bits: int) -> bytes:
    _check_bits(bits)
    return f"B{bits}\r".encode("ascii")


def parse_ident_reply(line: str) -> str:
    """The firmware version from an identification reply ``E201,<fw>``."""
    if not line.startswith("E201,") or len(line) == 5:
        raise BissProtocolError(f"identification reply is {line[:30]!r}, expected 'E201,<firmware>'")
    return line[5:]


def parse_ok_reply(line: str) -> None:
    if line != "OK":
        raise BissProtocolError(f"reply is {line[:30]!r}, expected 'OK'")


def parse_frame_reply(line: str, bits: int = 26) -> BissFrame:
    """A ``4`` reply: 16 hex digits (``ERR`` or anything else raises :class:`BissProtocolError`)."""
    return decode_frame(line, bits)


def parse_count_reply(line: str) -> int | None:
    """A ``?`` reply: the count, or None when the converter answered ``ERR`` (its own CRC failed)."""
    if line == "ERR":
        return None
    if not line.isascii() or not line.isdigit():
        raise BissProtocolError(f"count reply is {line[:30]!r}, expected a decimal count or 'ERR'")
    return int(line)
