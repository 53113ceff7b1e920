"""KUKA RSI (Ethernet) telegram codec, without I/O.

Conventions (the loop that uses them: ``docs/daemon.md``, "The loop, per telegram"):

- Robot → daemon: one ``<Rob …>`` telegram per UDP datagram. ``AIPos``/``ASPos`` are axis values in
  degrees (``A1``..``A6``), ``RIst``/``RSol`` Cartesian poses (``X``, ``Y``, ``Z`` in mm; ``A``, ``B``,
  ``C`` in degrees), ``Delay D`` the controller's count of late replies, ``IPOC`` a millisecond
  timestamp that grows by the cycle time. Unknown elements are kept in ``extra`` and otherwise
  ignored; the root's ``Type``/``TYPE`` attribute is recorded but never relied on.
- Daemon → robot: ``<Sen Type="…"><Stop>0|1</Stop><AK A1="…" … A6="…"/><IPOC>…</IPOC></Sen>`` with
  six decimals; ``AK`` is the axis correction in degrees, ``IPOC`` echoed as received.

Errors: :class:`RsiProtocolError` means the peer sent something that is not a valid telegram
(not XML, DTD/entities, wrong root, missing or non-numeric field, an IPOC or Delay beyond 64 bits,
two telegrams in one datagram); no other exception escapes :func:`parse_rob` for bytes input.
A :class:`ValueError` from a builder means the caller (our side) passed a bad value, e.g. a
non-finite correction.

:func:`parse_rob` first tries a fast path, one precompiled pattern for the spec's own form (one
line, no whitespace, the known elements in the KR C4's order with their attributes in order, plain
decimals of at most 15 digits either side of the point). A datagram it matches to the last byte
becomes the same :class:`RobTelegram` the full parser would give; anything else — other spacing,
unknown elements, exponents, duplicates, garbage — goes to the full parser, which decides and
explains. The fast path shortens the real-time reply (it takes about a third of the full parser's
time); it is never a second opinion: a property test holds it to the full parser's result.

The full parser is expat (``xml.etree``) behind a pre-scan that rejects every markup declaration
(``<!`` — DOCTYPE, ENTITY, comments, CDATA) and datagrams above :data:`MAX_TELEGRAM_BYTES`; without
a DTD there can be no entity expansion or external entity, so the usual XML attacks cannot occur.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass

__all__ = [
    "AXIS_NAMES",
    "CARTESIAN_NAMES",
    "MAX_TELEGRAM_BYTES",
    "RobTelegram",
    "RsiProtocolError",
    "SenReply",
    "build_rob",
    "build_sen",
    "parse_rob",
    "parse_sen",
]

#: Attribute names of AIPos/ASPos/AK, in axis order.
AXIS_NAMES: tuple[str, ...] = ("A1", "A2", "A3", "A4", "A5", "A6")
#: Attribute names of RIst/RSol (mm, mm, mm, deg, deg, deg).
CARTESIAN_NAMES: tuple[str, ...] = ("X", "Y", "Z", "A", "B", "C")
#: Largest datagram accepted as a telegram (a full KR C4 telegram is about 600 bytes).
MAX_TELEGRAM_BYTES = 16384

_NUMBER_CHARS = "0123456789+-.eE \t\r\n"
_MAX_UNSIGNED = 2**64 - 1  # IPOC and Delay D: counters the controller keeps in 64 bits at most
_MAX_UNSIGNED_DIGITS = len(str(_MAX_UNSIGNED))
_TYPE_NAME = re.compile(r"[A-Za-z0-9_.\-]+\Z")
_AXIS_ELEMENTS = frozenset({"AIPos", "ASPos"})
_KNOWN_ROB = frozenset({"IPOC", "AIPos", "ASPos", "RIst", "RSol", "Delay"})
_KNOWN_SEN = frozenset({"IPOC", "AK", "Stop"})


class RsiProtocolError(Exception):
    """The peer sent a datagram that is not a valid RSI telegram."""

    def __init__(self, message: str, data: bytes = b"") -> None:
        more = "…" if len(data) > 80 else ""
        super().__init__(f"{message} (datagram of {len(data)} bytes: {data[:80]!r}{more})")
        self.reason = message


ExtraElement = tuple[str, tuple[tuple[str, str], ...], str]


@dataclass(frozen=True, slots=True)
class RobTelegram:
    """One ``<Rob>`` telegram. Missing optional elements are ``None``."""

    ipoc: int
    aipos_deg: tuple[float, ...] | None = None
    aspos_deg: tuple[float, ...] | None = None
    rist: tuple[float, ...] | None = None
    rsol: tuple[float, ...] | None = None
    delay: int | None = None
    rob_type: str = ""
    #: Unknown elements in order: (tag, sorted attribute items, stripped text).
    extra: tuple[ExtraElement, ...] = ()

    def extra_element(self, tag: str) -> tuple[dict[str, str], str] | None:
        """Attributes and text of the first unknown element named ``tag``, or None."""
        for name, attrs, text in self.extra:
            if name == tag:
                return dict(attrs), text
        return None


@dataclass(frozen=True, slots=True)
class SenReply:
    """One ``<Sen>`` reply: axis correction ``ak_deg`` (6 values, deg) for telegram ``ipoc``."""

    ipoc: int
    ak_deg: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    stop: bool = False
    sen_type: str = "ImFree"


# ---------------------------------------------------------------------------------------------- parse


def _root(data: bytes, expected: str) -> ET.Element:
    if not isinstance(data, bytes | bytearray | memoryview):
        raise TypeError(f"an RSI telegram is bytes, got {type(data).__name__}")
    data = bytes(data)
    if len(data) > MAX_TELEGRAM_BYTES:
        raise RsiProtocolError(f"datagram larger than {MAX_TELEGRAM_BYTES} bytes", data)
    if b"<!" in data:
        raise RsiProtocolError("markup declarations (DOCTYPE, ENTITY, comment, CDATA) are not allowed", data)
    try:
        root = ET.fromstring(data)
    except ET.ParseError as exc:
        raise RsiProtocolError(f"not well-formed XML: {exc}", data) from None
    except (ValueError, LookupError) as exc:  # e.g. an XML declaration naming an unsupported encoding
        raise RsiProtocolError(f"not decodable XML: {exc}", data) from None
    if root.tag != expected:
        raise RsiProtocolError(f"root element is <{root.tag}>, expected <{expected}>", data)
    if root.text is not None and root.text.strip():
        raise RsiProtocolError(f"stray text {root.text.strip()[:20]!r} inside <{expected}>", data)
    return root


def _number(value: str | None, tag: str, name: str, data: bytes) -> float:
    if value is None:
        raise RsiProtocolError(f"{tag} attribute {name} is missing", data)
    try:
        if value.strip(_NUMBER_CHARS):  # only digits, sign, point, exponent (and surrounding blanks)
            raise ValueError
        number = float(value)
    except ValueError:
        raise RsiProtocolError(
            f"{tag} attribute {name} is not a finite decimal number: {value[:20]!r}", data
        ) from None
    if number - number != 0.0:  # inf or nan, e.g. an exponent beyond a double
        raise RsiProtocolError(f"{tag} attribute {name} overflows a double: {value[:20]!r}", data)
    return number


def _unsigned(value: str | None, where: str, data: bytes) -> int:
    if value is None:
        raise RsiProtocolError(f"{where} is missing", data)
    text = value.strip()
    if not (text.isascii() and text.isdigit()):
        raise RsiProtocolError(f"{where} is not an unsigned integer: {value[:20]!r}", data)
    significant = text.lstrip("0") or "0"
    if len(significant) > _MAX_UNSIGNED_DIGITS or int(significant) > _MAX_UNSIGNED:
        raise RsiProtocolError(f"{where} is beyond 64 bits ({len(significant)} digits): {value[:20]!r}", data)
    return int(significant)


def _six(element: ET.Element, names: tuple[str, ...], data: bytes) -> tuple[float, ...]:
    get = element.attrib.get
    tag = element.tag
    return tuple([_number(get(n), tag, n, data) for n in names])


def _check_leaf(element: ET.Element, data: bytes) -> None:
    if len(element):
        raise RsiProtocolError(f"<{element.tag}> must not contain elements", data)
    if element.tail is not None and element.tail.strip():
        raise RsiProtocolError(f"stray text {element.tail.strip()[:20]!r} after <{element.tag}>", data)


def _take_leaf(element: ET.Element, seen: set[str], data: bytes) -> None:
    """Check ``element`` is a leaf not met before in its telegram (tags in ``seen``), and note its tag."""
    _check_leaf(element, data)
    if element.tag in seen:
        raise RsiProtocolError(f"element <{element.tag}> appears twice", data)
    seen.add(element.tag)


_FAST_NUM = rb"(-?\d{1,15}(?:\.\d{1,15})?)"


def _fast_six(tag: str, names: tuple[str, ...]) -> bytes:
    attrs = b" ".join(n.encode() + b'="' + _FAST_NUM + b'"' for n in names)
    return b"(?:<" + tag.encode() + b" " + attrs + b"/>)?"


#: The spec's form: ``<Rob Type="…">`` then RIst, RSol, AIPos, ASPos, Delay (each optional, in this
#: order), IPOC and ``</Rob>``, no whitespace. Groups: type, 6 × 4 values (or None), D, IPOC.
_FAST_ROB = re.compile(
    rb'<Rob Type="([A-Za-z0-9_.\-]{1,64})">'
    + _fast_six("RIst", CARTESIAN_NAMES)
    + _fast_six("RSol", CARTESIAN_NAMES)
    + _fast_six("AIPos", AXIS_NAMES)
    + _fast_six("ASPos", AXIS_NAMES)
    + rb'(?:<Delay D="(\d{1,18})"/>)?<IPOC>(\d{1,18})</IPOC></Rob>'
)


def _parse_rob_fast(data: bytes) -> RobTelegram | None:
    """The spec's own form of ``<Rob>`` (module docstring), or None to leave it to the full parser."""
    m = _FAST_ROB.fullmatch(data)
    if m is None:
        return None
    g = m.groups()
    six: list[tuple[float, ...] | None] = [
        None if g[i] is None else (float(g[i]), float(g[i + 1]), float(g[i + 2]),
                                   float(g[i + 3]), float(g[i + 4]), float(g[i + 5]))
        for i in (1, 7, 13, 19)
    ]  # fmt: skip
    return RobTelegram(
        ipoc=int(g[26]),
        aipos_deg=six[2],
        aspos_deg=six[3],
        rist=six[0],
        rsol=six[1],
        delay=None if g[25] is None else int(g[25]),
        rob_type=g[0].decode("ascii"),
    )


def parse_rob(data: bytes) -> RobTelegram:
    """Parse one ``<Rob>`` telegram (robot → daemon). Raises :class:`RsiProtocolError` on garbage."""
    if type(data) is bytes and len(data) <= MAX_TELEGRAM_BYTES:
        fast = _parse_rob_fast(data)
        if fast is not None:
            return fast
    return _parse_rob_full(data)


def _parse_rob_full(data: bytes) -> RobTelegram:
    """:func:`parse_rob` through expat, with every check (the fast path's reference)."""
    root = _root(data, "Rob")
    seen: set[str] = set()
    axes: dict[str, tuple[float, ...]] = {}
    extra: list[ExtraElement] = []
    ipoc: int | None = None
    delay: int | None = None
    for child in root:
        tag = child.tag
        if tag not in _KNOWN_ROB:
            if child.tail is not None and child.tail.strip():
                raise RsiProtocolError(f"stray text {child.tail.strip()[:20]!r} after <{tag}>", data)
            extra.append((tag, tuple(sorted(child.attrib.items())), (child.text or "").strip()))
            continue
        _take_leaf(child, seen, data)
        if tag == "IPOC":
            ipoc = _unsigned(child.text, "IPOC", data)
        elif tag == "Delay":
            delay = _unsigned(child.attrib.get("D"), "Delay attribute D", data)
        elif tag in _AXIS_ELEMENTS:
            axes[tag] = _six(child, AXIS_NAMES, data)
        else:
            axes[tag] = _six(child, CARTESIAN_NAMES, data)
    if ipoc is None:
        raise RsiProtocolError("no <IPOC> element", data)
    return RobTelegram(
        ipoc=ipoc,
        aipos_deg=axes.get("AIPos"),
        aspos_deg=axes.get("ASPos"),
        rist=axes.get("RIst"),
        rsol=axes.get("RSol"),
        delay=delay,
        rob_type=root.attrib.get("Type", root.attrib.get("TYPE", "")),
        extra=tuple(extra),
    )


def parse_sen(data: bytes) -> SenReply:
    """Parse one ``<Sen>`` reply (daemon → robot; the simulated controller's side).

    ``AK`` and ``IPOC`` are required, ``Stop`` defaults to 0; unknown elements are ignored.
    """
    root = _root(data, "Sen")
    seen: set[str] = set()
    ipoc: int | None = None
    ak: tuple[float, ...] | None = None
    stop = False
    for child in root:
        tag = child.tag
        if tag not in _KNOWN_SEN:
            continue
        _take_leaf(child, seen, data)
        if tag == "IPOC":
            ipoc = _unsigned(child.text, "IPOC", data)
        elif tag == "AK":
            ak = _six(child, AXIS_NAMES, data)
        else:
            value = (child.text or "").strip()
            if value not in ("0", "1"):
                raise RsiProtocolError(f"Stop is {value[:20]!r}, expected 0 or 1", data)
            stop = value == "1"
    if ipoc is None:
        raise RsiProtocolError("no <IPOC> element", data)
    if ak is None:
        raise RsiProtocolError("no <AK> element", data)
    sen_type = root.attrib.get("Type", root.attrib.get("TYPE", ""))
    return SenReply(ipoc=ipoc, ak_deg=ak, stop=stop, sen_type=sen_type)


# ---------------------------------------------------------------------------------------------- build

_checked_types: set[str] = set()


def _check_type(value: str, what: str) -> None:
    if value in _checked_types:
        return
    if not isinstance(value, str) or _TYPE_NAME.match(value) is None:
        raise ValueError(f"{what} must be a non-empty name of letters, digits, '_', '.', '-': {value!r}")
    _checked_types.add(value)


def _check_ipoc(ipoc: int) -> None:
    if not isinstance(ipoc, int) or isinstance(ipoc, bool) or ipoc < 0:
        raise ValueError(f"IPOC must be a non-negative int, got {ipoc!r}")


def _format_six(tag: str, names: tuple[str, ...], values: Sequence[float], decimals: int) -> str:
    if len(values) != 6:
        raise ValueError(f"{tag} needs 6 values, got {len(values)}")
    parts = []
    for name, v in zip(names, values, strict=True):
        if not math.isfinite(v):
            raise ValueError(f"{tag} {name} is not finite: {v!r}")
        text = f"{v:.{decimals}f}"
        if text[0] == "-" and text.strip("-0.") == "":
            text = text[1:]  # never send "-0.000000"
        parts.append(f'{name}="{text}"')
    return f"<{tag} {' '.join(parts)}/>"


def build_sen(reply: SenReply) -> bytes:
    """The ``<Sen>`` datagram for ``reply``, exactly in the spec's form (six decimals, one line).

    Raises ValueError for a reply our side should never build (non-finite AK, bad type, bad IPOC).
    """
    _check_type(reply.sen_type, "sen_type")
    _check_ipoc(reply.ipoc)
    ak = _format_six("AK", AXIS_NAMES, reply.ak_deg, 6)
    stop = 1 if reply.stop else 0
    text = f'<Sen Type="{reply.sen_type}"><Stop>{stop}</Stop>{ak}<IPOC>{reply.ipoc}</IPOC></Sen>'
    return text.encode("ascii")


def build_rob(
    ipoc: int,
    aipos_deg: Sequence[float] | None = None,
    aspos_deg: Sequence[float] | None = None,
    rist: Sequence[float] | None = None,
    rsol: Sequence[float] | None = None,
    delay: int | None = 0,
    *,
    rob_type: str = "KUKA",
    decimals: int = 4,
) -> bytes:
    """A ``<Rob>`` datagram as a KR C4 sends it (the simulated controller's side).

    Elements given as None are left out (they depend on the controller's SEND list). Values are
    written with ``decimals`` decimals (4 like the KR C4).
    """
    _check_type(rob_type, "rob_type")
    _check_ipoc(ipoc)
    parts = [f'<Rob Type="{rob_type}">']
    if rist is not None:
        parts.append(_format_six("RIst", CARTESIAN_NAMES, rist, decimals))
    if rsol is not None:
        parts.append(_format_six("RSol", CARTESIAN_NAMES, rsol, decimals))
    if aipos_deg is not None:
        parts.append(_format_six("AIPos", AXIS_NAMES, aipos_deg, decimals))
    if aspos_deg is not None:
        parts.append(_format_six("ASPos", AXIS_NAMES, aspos_deg, decimals))
    if delay is not None:
        if not isinstance(delay, int) or delay < 0:
            raise ValueError(f"Delay must be a non-negative int, got {delay!r}")
        parts.append(f'<Delay D="{delay}"/>')
    parts.append(f"<IPOC>{ipoc}</IPOC></Rob>")
    return "".join(parts).encode("ascii")
