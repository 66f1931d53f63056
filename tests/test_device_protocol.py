"""Device line protocol: checksum, framing, sequence numbers, corrupted lines (pure, no I/O)."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from masking_lab.device import protocol as proto


def crc_reference(data: bytes) -> int:
    """Bit-by-bit CRC-16/CCITT-FALSE, written from the algorithm's definition."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


def test_crc_matches_the_published_check_value():
    # CRC-16/CCITT-FALSE check value from the CRC catalogue: "123456789" -> 0x29B1.
    assert proto.crc16(b"123456789") == 0x29B1


@given(st.binary(max_size=300))
def test_crc_matches_a_bitwise_reference(data):
    assert proto.crc16(data) == crc_reference(data)


# Worked examples of docs/device-protocol.md; checksums computed with crc_reference above.
DOC_EXAMPLES = [
    b"1 HELLO*7DF0\n",
    b"7 PING*018E\n",
    b"12 PLAY tch=EV tcar=270 tenv=0 tamp=0.5 ti=2 mch=MV mcar=120 menv=0 mamp=0.3 stim=1.8 "
    b"gap=0.6 lead=1.2 n=3 at=10.25*6A40\n",
    b"12 OK start=10.25*A6BB\n",
    b"!4 DONE seq=12 on=11.450012,13.850009,16.250011 end=18.05 tamp=0.5 mamp=0.3*068D\n",
    b"13 ERR LIMIT EV amplitude 6 V exceeds the 5 V limit*C2A6\n",
]


@pytest.mark.parametrize("line", DOC_EXAMPLES)
def test_documented_examples_decode(line):
    frame = proto.decode(line)
    assert frame.seq in (1, 4, 7, 12, 13)


def test_documented_examples_are_what_the_encoders_produce():
    play = {
        "tch": "EV",
        "tcar": 270.0,
        "tenv": 0.0,
        "tamp": 0.5,
        "ti": 2,
        "mch": "MV",
        "mcar": 120.0,
        "menv": 0.0,
        "mamp": 0.3,
        "stim": 1.8,
        "gap": 0.6,
        "lead": 1.2,
        "n": 3,
        "at": 10.25,
    }
    assert proto.encode_command(1, "HELLO") == DOC_EXAMPLES[0]
    assert proto.encode_command(12, "PLAY", play) == DOC_EXAMPLES[2]
    assert proto.encode_ok(12, {"start": 10.25}) == DOC_EXAMPLES[3]
    done = {
        "seq": 12,
        "on": [11.450012, 13.850009, 16.250011],
        "end": 18.05,
        "tamp": 0.5,
        "mamp": 0.3,
    }
    assert proto.encode_event(4, "DONE", done) == DOC_EXAMPLES[4]
    err = proto.encode_err(13, "LIMIT", "EV amplitude 6 V exceeds the 5 V limit")
    assert err == DOC_EXAMPLES[5]


def test_kinds_are_told_apart():
    cmd = proto.decode(proto.encode_command(5, "STOP"))
    ok = proto.decode(proto.encode_ok(5, {"t": 1.5}))
    err = proto.decode(proto.encode_err(5, "ARGS", "missing amp"))
    event = proto.decode(proto.encode_event(5, "WATCHDOG", {"quiet_ms": 612}))
    assert (cmd.kind, cmd.name) == ("command", "STOP")
    assert ok.kind == "reply" and ok.ok and ok.number("t") == 1.5
    assert err.kind == "reply" and not err.ok and (err.code, err.text) == ("ARGS", "missing amp")
    assert event.kind == "event" and event.fields == {"quiet_ms": "612"}
    assert {f.seq for f in (cmd, ok, err, event)} == {5}


names = st.sampled_from(proto.COMMANDS)
keys = st.from_regex(r"[a-z][a-z0-9_]{0,5}", fullmatch=True)
values = st.one_of(
    st.from_regex(r"[A-Za-z0-9_.,\-]{1,8}", fullmatch=True),
    st.floats(-1e6, 1e6, allow_nan=False).map(lambda x: round(x, 6)),
    st.integers(0, 10**6),
)


@given(st.integers(0, 65535), names, st.dictionaries(keys, values, max_size=6))
def test_round_trip(seq, name, fields):
    frame = proto.decode(proto.encode_command(seq, name, fields))
    assert (frame.kind, frame.seq, frame.name) == ("command", seq, name)
    assert set(frame.fields) == set(fields)
    for key, value in fields.items():
        if isinstance(value, float):
            assert frame.number(key) == pytest.approx(value, abs=1e-6)
        else:
            assert frame.fields[key] == str(value)


@given(
    st.integers(0, 65535),
    st.dictionaries(keys, values, max_size=6),
    st.data(),
)
def test_any_single_byte_change_is_detected(seq, fields, data):
    line = proto.encode_command(seq, "PLAY", fields)
    i = data.draw(st.integers(0, len(line) - 1), label="position")
    new = data.draw(st.integers(0, 255).filter(lambda b: b != line[i]), label="byte")
    corrupted = line[:i] + bytes([new]) + line[i + 1 :]
    with pytest.raises(proto.FrameError):
        proto.decode(corrupted)


@pytest.mark.parametrize(
    ("line", "why"),
    [
        (b"hello there\n", "no '\\*' checksum"),
        (b"1 HELLO*7df0\n", "upper-case hex"),
        (b"1 HELLO*7DF1\n", "bad checksum"),
        (b"\x00\xff\xfe*0000\n", "non-ASCII|checksum"),
        (b"x" * 300 + b"\n", "longer than"),
    ],
)
def test_garbage_is_refused_with_a_reason(line, why):
    with pytest.raises(proto.FrameError, match=why):
        proto.decode(line)


def test_well_checksummed_but_malformed_bodies_are_refused():
    def framed(body: str) -> bytes:
        return body.encode() + b"*" + f"{crc_reference(body.encode()):04X}".encode() + b"\n"

    for body, why in [
        ("PING", "sequence number and a name"),
        ("x PING", "bad sequence number"),
        ("65536 PING", "bad sequence number"),
        ("007 PING", "bad sequence number"),
        ("1 ping", "bad frame name"),
        ("1 SETUP ch", "bad field"),
        ("1 SETUP ch=EV ch=MV", "bad field"),
        ("1 ERR", "without an error code"),
        ("1 SETUP\tch=EV", "control characters"),
    ]:
        with pytest.raises(proto.FrameError, match=why):
            proto.decode(framed(body))


def test_a_trailing_carriage_return_is_tolerated():
    assert proto.decode(b"7 PING*018E\r\n").name == "PING"


def test_sequence_numbers_wrap():
    assert proto.next_seq(65535) == 0
    assert proto.next_seq(0) == 1
    with pytest.raises(proto.FrameError):
        proto.encode_command(65536, "PING")


def test_err_text_is_made_safe_and_short():
    line = proto.encode_err(3, "ARGS", "bad *value*\nnext line é" + "x" * 400)
    frame = proto.decode(line)
    assert len(line) <= proto.MAX_FRAME_BYTES
    assert frame.text.startswith("bad ?value??next line ?")


def test_unsendable_values_are_refused():
    for bad in (float("nan"), float("inf")):
        with pytest.raises(proto.FrameError, match="non-finite"):
            proto.encode_command(1, "AMP", {"amp": bad})
    with pytest.raises(proto.FrameError, match="without spaces"):
        proto.encode_command(1, "SETUP", {"ch": "E V"})
    with pytest.raises(proto.FrameError, match="bad field name"):
        proto.encode_command(1, "SETUP", {"Ch": "EV"})
    with pytest.raises(proto.FrameError, match="replies"):
        proto.encode_command(1, "OK")


def test_number_fields_are_checked():
    frame = proto.decode(proto.encode_ok(1, {"t": "abc", "on": "1,x", "big": "inf"}))
    with pytest.raises(proto.FrameError, match="not a number"):
        frame.number("t")
    with pytest.raises(proto.FrameError, match="lacks field"):
        frame.number("missing")
    with pytest.raises(proto.FrameError, match="number list"):
        frame.numbers("on")
    with pytest.raises(proto.FrameError, match="not finite"):
        frame.number("big")


def test_a_lone_carriage_return_is_not_a_line_ending():
    with pytest.raises(proto.FrameError):
        proto.decode(b"7 PING*018E\r")
