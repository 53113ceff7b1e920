"""RSI codec: whole telegrams, every truncation, junk, hostile XML, fuzzing, exact reply bytes."""

from __future__ import annotations

import math

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from comp_daemon.rt.rsi_codec import (
    RobTelegram,
    RsiProtocolError,
    SenReply,
    _parse_rob_fast,
    _parse_rob_full,
    build_rob,
    build_sen,
    parse_rob,
    parse_sen,
)

# A KR C4 telegram as captured (one line), with an element the daemon does not know.
KRC4 = (
    b'<Rob Type="KUKA"><RIst X="445.0000" Y="0.0000" Z="890.0000" A="180.0000" B="0.0000" C="180.0000"/>'
    b'<RSol X="445.0000" Y="0.0000" Z="890.0000" A="180.0000" B="0.0000" C="180.0000"/>'
    b'<AIPos A1="0.0000" A2="-90.0000" A3="90.0000" A4="0.0000" A5="90.0000" A6="0.0000"/>'
    b'<ASPos A1="0.0000" A2="-90.0000" A3="90.0000" A4="0.0000" A5="90.0000" A6="0.0000"/>'
    b'<Delay D="0"/><Digout o1="0" o2="1"/><IPOC>5490270</IPOC></Rob>'
)


def test_parse_whole_krc4_telegram() -> None:
    t = parse_rob(KRC4)
    assert t.ipoc == 5490270
    assert t.aipos_deg == (0.0, -90.0, 90.0, 0.0, 90.0, 0.0)
    assert t.aspos_deg == (0.0, -90.0, 90.0, 0.0, 90.0, 0.0)
    assert t.rist == (445.0, 0.0, 890.0, 180.0, 0.0, 180.0)
    assert t.rsol == t.rist
    assert t.delay == 0
    assert t.rob_type == "KUKA"
    assert t.extra_element("Digout") == ({"o1": "0", "o2": "1"}, "")
    assert t.extra_element("Nothing") is None


def test_type_or_TYPE_and_optional_elements() -> None:
    t = parse_rob(b'<Rob TYPE="SIM"><IPOC>12</IPOC></Rob>')
    assert t == RobTelegram(ipoc=12, rob_type="SIM")
    t = parse_rob(b"<Rob><AIPos A1='1' A2='2' A3='3' A4='4' A5='5' A6='-6.5e-1'/><IPOC> 24 </IPOC></Rob>")
    assert t.aipos_deg == (1.0, 2.0, 3.0, 4.0, 5.0, -0.65)
    assert t.rob_type == "" and t.aspos_deg is None and t.delay is None


def test_whitespace_between_elements_and_xml_declaration_accepted() -> None:
    t = parse_rob(b'<?xml version="1.0"?>\n<Rob Type="KUKA">\n  <Delay D="3"/>\n  <IPOC>36</IPOC>\n</Rob>\n')
    assert (t.ipoc, t.delay) == (36, 3)


def test_every_truncation_is_a_protocol_error() -> None:
    for n in range(len(KRC4)):
        with pytest.raises(RsiProtocolError):
            parse_rob(KRC4[:n])


@pytest.mark.parametrize(
    "junk",
    [b"x", b"<", b"\x00", b"<Rob/>", KRC4, b"<Sen/>", b"\xff\xfe", b"</Rob>"],
    ids=["char", "lt", "nul", "second-root", "second-telegram", "other-root", "binary", "close-tag"],
)
def test_junk_after_telegram_is_a_protocol_error(junk: bytes) -> None:
    with pytest.raises(RsiProtocolError):
        parse_rob(KRC4 + junk)


@pytest.mark.parametrize(
    ("data", "reason"),
    [
        (b"", "not well-formed"),
        (b"hello", "not well-formed"),
        (b'<Sen Type="ImFree"><IPOC>1</IPOC></Sen>', "root element is <Sen>"),
        (b'<Rob Type="KUKA"><Delay D="0"/></Rob>', "no <IPOC>"),
        (b"<Rob><IPOC>12a</IPOC></Rob>", "IPOC is not an unsigned integer"),
        (b"<Rob><IPOC>-12</IPOC></Rob>", "IPOC is not an unsigned integer"),
        (b"<Rob><IPOC>1</IPOC><IPOC>2</IPOC></Rob>", "appears twice"),
        (
            b'<Rob><AIPos A1="1" A2="2" A3="3" A4="4" A5="5"/><IPOC>1</IPOC></Rob>',
            "AIPos attribute A6 is missing",
        ),
        (
            b'<Rob><AIPos A1="1" A2="x" A3="3" A4="4" A5="5" A6="6"/><IPOC>1</IPOC></Rob>',
            "AIPos attribute A2",
        ),
        (
            b'<Rob><ASPos A1="nan" A2="0" A3="3" A4="4" A5="5" A6="6"/><IPOC>1</IPOC></Rob>',
            "ASPos attribute A1",
        ),
        (b'<Rob><RIst X="inf" Y="0" Z="0" A="0" B="0" C="0"/><IPOC>1</IPOC></Rob>', "RIst attribute X"),
        (b'<Rob><RSol X="1e999" Y="0" Z="0" A="0" B="0" C="0"/><IPOC>1</IPOC></Rob>', "overflows"),
        (b'<Rob><RIst X="1_0" Y="0" Z="0" A="0" B="0" C="0"/><IPOC>1</IPOC></Rob>', "RIst attribute X"),
        (b'<Rob><Delay D="-1"/><IPOC>1</IPOC></Rob>', "Delay attribute D"),
        (b"<Rob>junk<IPOC>1</IPOC></Rob>", "stray text"),
        (b"<Rob><IPOC>1<x/></IPOC></Rob>", "must not contain elements"),
        (b'<!DOCTYPE Rob [<!ENTITY a "1">]><Rob><IPOC>&a;</IPOC></Rob>', "markup declarations"),
        (b"<Rob><!-- hi --><IPOC>1</IPOC></Rob>", "markup declarations"),
        (b"<Rob><IPOC><![CDATA[1]]></IPOC></Rob>", "markup declarations"),
        (b"<Rob><IPOC>&undefined;</IPOC></Rob>", "not well-formed"),
        (b'<?xml version="1.0" encoding="klingon"?><Rob><IPOC>1</IPOC></Rob>', "XML"),
        (b"<Rob><IPOC>1</IPOC></Rob>" + b" " * 20000, "larger than"),
        (b"<Rob><IPOC>" + b"7" * 5000 + b"</IPOC></Rob>", "IPOC is beyond 64 bits \\(5000 digits\\)"),
        (b"<Rob><IPOC>" + b"0" * 5000 + b"18446744073709551616</IPOC></Rob>", "IPOC is beyond 64 bits"),
        (
            b'<Rob><Delay D="' + b"9" * 4400 + b'"/><IPOC>1</IPOC></Rob>',
            "Delay attribute D is beyond 64 bits",
        ),
    ],
)
def test_garbage_is_named(data: bytes, reason: str) -> None:
    with pytest.raises(RsiProtocolError, match=reason):
        parse_rob(data)


def test_largest_64_bit_ipoc_and_leading_zeros_are_accepted() -> None:
    assert parse_rob(b"<Rob><IPOC>18446744073709551615</IPOC></Rob>").ipoc == 2**64 - 1
    assert parse_rob(b"<Rob><IPOC>" + b"0" * 5000 + b"12</IPOC></Rob>").ipoc == 12


def test_billion_laughs_rejected_before_parsing() -> None:
    bomb = (
        b'<?xml version="1.0"?><!DOCTYPE lolz [<!ENTITY lol "lol">'
        + b"".join(
            b'<!ENTITY lol%d "%s">' % (i, (b"&lol%d;" % (i - 1) if i > 1 else b"&lol;") * 10)
            for i in range(1, 10)
        )
        + b"]><Rob><IPOC>&lol9;</IPOC></Rob>"
    )
    with pytest.raises(RsiProtocolError, match="markup declarations"):
        parse_rob(bomb)


def test_build_sen_exact_spec_form() -> None:
    reply = SenReply(ipoc=5490270, ak_deg=(0.0, 0.001, -0.002, 1.2345674, -1e-9, 12.5), stop=False)
    assert build_sen(reply) == (
        b'<Sen Type="ImFree"><Stop>0</Stop><AK A1="0.000000" A2="0.001000" A3="-0.002000" '
        b'A4="1.234567" A5="0.000000" A6="12.500000"/><IPOC>5490270</IPOC></Sen>'
    )
    stop = build_sen(SenReply(ipoc=12, stop=True, sen_type="Cell_7"))
    assert stop.startswith(b'<Sen Type="Cell_7"><Stop>1</Stop><AK A1="0.000000"')
    assert b"\n" not in stop and b" />" not in stop


@pytest.mark.parametrize(
    ("reply", "match"),
    [
        (SenReply(1, (0.0, math.nan, 0.0, 0.0, 0.0, 0.0)), "AK A2 is not finite"),
        (SenReply(1, (0.0, 0.0, 0.0, 0.0, 0.0, math.inf)), "AK A6 is not finite"),
        (SenReply(1, (0.0,) * 5), "AK needs 6 values"),
        (SenReply(-1), "IPOC"),
        (SenReply(1, sen_type='a"b'), "sen_type"),
        (SenReply(1, sen_type=""), "sen_type"),
    ],
)
def test_build_sen_rejects_our_own_bugs_with_value_error(reply: SenReply, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        build_sen(reply)


def test_rob_round_trip_and_sen_round_trip() -> None:
    data = build_rob(
        17,
        (1, 2, 3, 4, 5, 6),
        (0.5,) * 6,
        (1.0, 2.0, 3.0, 4.0, 5.0, 6.0),
        None,
        4,
        rob_type="TYPE2",
        decimals=6,
    )
    t = parse_rob(data)
    assert t == RobTelegram(17, (1, 2, 3, 4, 5, 6), (0.5,) * 6, (1, 2, 3, 4, 5, 6), None, 4, "TYPE2")
    r = SenReply(99, (0.000001, -0.5, 0.0, 0.0, 0.0, 3.0), True, "ImFree")
    assert parse_sen(build_sen(r)) == r


def test_parse_sen_requires_ak_and_ipoc_and_checks_stop() -> None:
    with pytest.raises(RsiProtocolError, match="no <AK>"):
        parse_sen(b'<Sen Type="ImFree"><Stop>0</Stop><IPOC>1</IPOC></Sen>')
    with pytest.raises(RsiProtocolError, match="Stop is"):
        parse_sen(
            b'<Sen Type="x"><Stop>2</Stop><AK A1="0" A2="0" A3="0" A4="0" A5="0" A6="0"/><IPOC>1</IPOC></Sen>'
        )
    r = parse_sen(
        b'<Sen Type="x"><RKorr X="1"/><AK A1="0" A2="0" A3="0" A4="0" A5="0" A6="1"/><IPOC>1</IPOC></Sen>'
    )
    assert r == SenReply(1, (0, 0, 0, 0, 0, 1), False, "x")


@pytest.mark.parametrize(
    ("element", "reason"),
    [
        (b"<IPOC>2</IPOC>", "element <IPOC> appears twice"),
        (b'<AK A1="0" A2="0" A3="0" A4="0" A5="0" A6="2"/>', "element <AK> appears twice"),
        (b"<Stop>0<x/></Stop>", "<Stop> must not contain elements"),
        (b"<Stop>0</Stop>junk", "stray text 'junk' after <Stop>"),
    ],
)
def test_parse_sen_refuses_a_repeated_or_nested_element(element: bytes, reason: str) -> None:
    sen = b'<Sen Type="x"><AK A1="0" A2="0" A3="0" A4="0" A5="0" A6="1"/><IPOC>1</IPOC>' + element + b"</Sen>"
    with pytest.raises(RsiProtocolError, match=reason):
        parse_sen(sen)


# ------------------------------------------------------------------------------------------ fuzzing

_FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _telegram_or_protocol_error(data: bytes) -> None:
    try:
        t = parse_rob(data)
    except RsiProtocolError:
        return
    assert isinstance(t, RobTelegram) and isinstance(t.ipoc, int) and t.ipoc >= 0
    for six in (t.aipos_deg, t.aspos_deg, t.rist, t.rsol):
        assert six is None or (len(six) == 6 and all(math.isfinite(v) for v in six))


@_FUZZ
@given(st.binary(max_size=700))
def test_fuzz_random_bytes(data: bytes) -> None:
    _telegram_or_protocol_error(data)


@_FUZZ
@given(st.data())
def test_fuzz_mutated_telegrams(data: st.DataObject) -> None:
    raw = bytearray(KRC4)
    for _ in range(data.draw(st.integers(1, 6))):
        op = data.draw(st.sampled_from(["flip", "delete", "insert", "truncate"]))
        i = data.draw(st.integers(0, max(0, len(raw) - 1)))
        if op == "flip" and raw:
            raw[i] = data.draw(st.integers(0, 255))
        elif op == "delete" and raw:
            del raw[i : i + data.draw(st.integers(1, 20))]
        elif op == "insert":
            raw[i:i] = data.draw(
                st.sampled_from([b"<", b">", b'"', b"/", b"&", b"<!", b"<IPOC>1</IPOC>", b"\x00"])
            )
        else:
            del raw[i:]
    _telegram_or_protocol_error(bytes(raw))


_finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)


@_FUZZ
@given(
    st.integers(0, 2**40),
    st.tuples(*[_finite] * 6),
    st.one_of(st.none(), st.tuples(*[_finite] * 6)),
    st.integers(0, 1000),
)
def test_round_trip_property(
    ipoc: int, aipos: tuple[float, ...], rist: tuple[float, ...] | None, delay: int
) -> None:
    t = parse_rob(build_rob(ipoc, aipos, aipos, rist, rist, delay))
    assert t.ipoc == ipoc and t.delay == delay
    assert t.aipos_deg is not None
    assert all(abs(a - b) <= 0.5e-4 + 1e-12 * abs(b) for a, b in zip(t.aipos_deg, aipos, strict=True))
    reply = SenReply(ipoc, aipos, bool(delay % 2))
    back = parse_sen(build_sen(reply))
    assert back.ipoc == ipoc and back.stop == reply.stop
    assert all(abs(a - b) <= 0.5e-6 + 1e-12 * abs(b) for a, b in zip(back.ak_deg, aipos, strict=True))


def _fast_agrees_with_full(data: bytes) -> bool:
    """The fast path either declines or gives exactly the full parser's telegram; True if it took it."""
    fast = _parse_rob_fast(data)
    try:
        full = _parse_rob_full(data)
    except RsiProtocolError:
        assert fast is None, data  # the fast path never accepts what the full parser refuses
        return False
    assert fast is None or fast == full, data
    return fast is not None


@_FUZZ
@given(
    st.integers(0, 2**40),
    st.lists(st.one_of(st.none(), st.tuples(*[_finite] * 6)), min_size=4, max_size=4),
    st.one_of(st.none(), st.integers(0, 10**6)),
    st.integers(0, 8),
    st.sampled_from(["KUKA", "ImFree", "Rob_1.x-2"]),
)
def test_fast_path_is_the_full_parser_on_the_spec_form(
    ipoc: int, sixes: list[tuple[float, ...] | None], delay: int | None, decimals: int, rob_type: str
) -> None:
    aipos, aspos, rist, rsol = sixes
    data = build_rob(ipoc, aipos, aspos, rist, rsol, delay, rob_type=rob_type, decimals=decimals)
    assert _fast_agrees_with_full(data)  # the spec's form always takes the fast path
    assert parse_rob(data) == _parse_rob_full(data)


@_FUZZ
@given(st.data())
def test_fast_path_declines_what_it_does_not_know(data: st.DataObject) -> None:
    raw = bytearray(KRC4)
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(0, max(0, len(raw) - 1)))
        raw[i:i] = data.draw(
            st.sampled_from(
                [b" ", b"\n", b"1e5", b"<X/>", b"-", b"0", b".", b"<IPOC>1</IPOC>", b'"', b"\xff"]
            )
        )
    _fast_agrees_with_full(bytes(raw))


@pytest.mark.parametrize(
    "data",
    [
        b'<Rob Type="KUKA"><IPOC>1</IPOC><IPOC>2</IPOC></Rob>',
        b'<Rob Type="KUKA"><AIPos A1="1e3" A2="0" A3="0" A4="0" A5="0" A6="0"/><IPOC>1</IPOC></Rob>',
        b'<Rob Type="KUKA"><AIPos A1="'
        + b"9" * 400
        + b'" A2="0" A3="0" A4="0" A5="0" A6="0"/><IPOC>1</IPOC></Rob>',
        b'<Rob Type="KUKA"><ASPos A1="0" A2="0" A3="0" A4="0" A5="0" A6="0"/><AIPos A1="0" A2="0" A3="0"'
        b' A4="0" A5="0" A6="0"/><IPOC>1</IPOC></Rob>',  # order other than the KR C4's: full parser
        b'<Rob Type="KUKA">\n<IPOC>1</IPOC></Rob>',
        b'<Rob TYPE="KUKA"><IPOC>1</IPOC></Rob>',
    ],
)
def test_fast_path_leaves_the_unusual_to_the_full_parser(data: bytes) -> None:
    assert _parse_rob_fast(data) is None
    _fast_agrees_with_full(data)
