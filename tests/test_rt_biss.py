"""BiSS-C frames against an independent bit-by-bit decoder; converter line protocol codec."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from comp_daemon.rt.biss import (
    BissFrame,
    BissProtocolError,
    LineReader,
    RequestKind,
    crc6,
    decode_frame,
    encode_frame,
    parse_count_reply,
    parse_frame_reply,
    parse_ident_reply,
    parse_ok_reply,
    parse_request,
    request_bit_length,
)


def independent_decode(hex16: str, bits: int) -> tuple[int, int, int, bool]:
    """Bit list from the hex digits; CRC by polynomial long division (x^6 + x + 1) on bit lists."""
    stream = [int(b) for ch in hex16 for b in format(int(ch, 16), "04b")]
    assert len(stream) == 64
    pos_bits = stream[:bits]
    n_e, n_w = stream[bits], stream[bits + 1]
    crc_sent = stream[bits + 2 : bits + 8]
    message = [*pos_bits, n_e, n_w] + [0] * 6  # multiply by x^6
    generator = [1, 0, 0, 0, 0, 1, 1]  # x^6 + x + 1, highest power first
    for i in range(len(message) - 6):
        if message[i]:
            for j, g in enumerate(generator):
                message[i + j] ^= g
    remainder = message[-6:]
    crc_ok = [1 - b for b in crc_sent] == remainder  # sent inverted
    position = int("".join(map(str, pos_bits)), 2)
    return position, n_e, n_w, crc_ok


def test_crc6_matches_the_published_table_start() -> None:
    # First entries of the CRC6 (0x43) table used by BiSS reference code: crc of one 6-bit chunk.
    assert [crc6(i, 6) for i in range(8)] == [0x00, 0x03, 0x06, 0x05, 0x0C, 0x0F, 0x0A, 0x09]
    assert crc6(0x10, 6) == 0x30


@pytest.mark.parametrize("bits", [26, 32])
def test_encode_agrees_with_independent_decoder(bits: int) -> None:
    rng = random.Random(1234)
    for _ in range(400):
        pos = rng.randrange(1 << bits)
        e_ok, w_ok = rng.random() < 0.8, rng.random() < 0.8
        text = encode_frame(pos, bits, error_ok=e_ok, warning_ok=w_ok)
        assert len(text) == 16 and text == text.upper()
        assert independent_decode(text, bits) == (pos, int(e_ok), int(w_ok), True)
        assert decode_frame(text, bits) == BissFrame(pos, e_ok, w_ok, True, bits)
        assert int(text, 16) & ((1 << (64 - bits - 8)) - 1) == 0  # left-aligned


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**64 - 1), st.sampled_from([26, 32]))
def test_decoder_agrees_with_independent_decoder_on_any_word(word: int, bits: int) -> None:
    text = f"{word:016X}"
    pos, n_e, n_w, crc_ok = independent_decode(text, bits)
    assert decode_frame(text.lower(), bits) == BissFrame(pos, bool(n_e), bool(n_w), crc_ok, bits)


def test_corrupted_crc_and_flipped_bits_are_detected() -> None:
    rng = random.Random(7)
    for _ in range(200):
        pos = rng.randrange(1 << 26)
        assert not decode_frame(encode_frame(pos, 26, crc_xor=rng.randrange(1, 64)), 26).crc_ok
        word = int(encode_frame(pos, 26), 16)
        flipped = word ^ (1 << rng.randrange(64 - 34 + 6, 64))  # a data bit (position, nE or nW)
        assert not decode_frame(f"{flipped:016X}", 26).crc_ok


@pytest.mark.parametrize(
    "bad", ["", "ERR", "0123456789ABCDE", "0123456789ABCDEF0", "0123456789ABCDEG", " 123456789ABCDEF"]
)
def test_decode_frame_rejects_non_frames(bad: str) -> None:
    with pytest.raises(BissProtocolError):
        parse_frame_reply(bad, 26)
    with pytest.raises(BissProtocolError):
        decode_frame(b"\xff" * 16, 26)


def test_builders_reject_our_own_bad_values() -> None:
    with pytest.raises(ValueError, match="does not fit"):
        encode_frame(1 << 26, 26)
    with pytest.raises(ValueError, match="bit length"):
        encode_frame(1, 24)
    with pytest.raises(ValueError, match="bit length"):
        request_bit_length(16)


def test_line_reader_whole_byte_by_byte_and_with_junk() -> None:
    stream = b"E201,1.07\rOK\r\n2F1853BC00000000\r\rSIM-J1\r"
    expected = ["E201,1.07", "OK", "2F1853BC00000000", "SIM-J1"]
    whole = LineReader()
    whole.feed(stream)
    assert [whole.next_line() for _ in range(5)] == [*expected, None]
    one = LineReader()
    got = []
    for b in stream:
        one.feed(bytes([b]))
        while (line := one.next_line()) is not None:
            got.append(line)
    assert got == expected
    junk = LineReader(max_line=16)
    junk.feed(b"\xff\xfeX\rOK\r" + b"Z" * 40)
    with pytest.raises(BissProtocolError, match="not ASCII"):
        junk.next_line()
    assert junk.next_line() == "OK"
    with pytest.raises(BissProtocolError, match="longer than"):
        junk.next_line()
    junk.feed(b"ZZZ\rOK\r")  # the rest of the overlong line is dropped silently
    assert junk.next_line() == "OK"
    assert junk.next_line() is None


def test_discard_pending_drops_a_late_reply_and_its_tail() -> None:
    lines = LineReader()
    lines.feed(b"OK\r2F1853BC000")  # a whole stale line and the start of a late reply
    lines.discard_pending()
    assert lines.next_line() is None
    lines.feed(b"00000\r2F1853BC00000000\r")  # the late reply's tail, then the reply to the new request
    assert lines.next_line() == "2F1853BC00000000"
    lines.feed(b"E201,1\r\n")
    lines.discard_pending()  # only complete lines: nothing pending afterwards
    lines.feed(b"OK\r")
    assert lines.next_line() == "OK"


def test_requests_and_replies() -> None:
    assert [parse_request(x).kind for x in ["v", "s", "4", "?", "1", "0", "B26", "B32", "B16", "x", ""]] == [
        RequestKind.IDENT,
        RequestKind.SERIAL,
        RequestKind.FRAME,
        RequestKind.COUNT,
        RequestKind.STREAM_ON,
        RequestKind.STREAM_OFF,
        RequestKind.BIT_LENGTH,
        RequestKind.BIT_LENGTH,
        RequestKind.UNKNOWN,
        RequestKind.UNKNOWN,
        RequestKind.UNKNOWN,
    ]
    assert parse_request("B32").bits == 32
    assert request_bit_length(26) == b"B26\r"
    assert parse_ident_reply("E201,2.3") == "2.3"
    for bad in ("E201,", "E200,1", "OK"):
        with pytest.raises(BissProtocolError):
            parse_ident_reply(bad)
    parse_ok_reply("OK")
    with pytest.raises(BissProtocolError):
        parse_ok_reply("ERR")
    assert parse_count_reply("123") == 123
    assert parse_count_reply("ERR") is None
    with pytest.raises(BissProtocolError):
        parse_count_reply("-5")
