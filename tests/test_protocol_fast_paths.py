"""The frame codec's shortcuts for a trial's frames accept and refuse exactly what the
general checks do."""

from __future__ import annotations

import enum

import pytest

from masking_lab.device import protocol as proto


def test_every_trial_key_is_a_valid_field_name() -> None:
    assert all(proto._KEY.match(k) for k in proto._TRIAL_KEYS)


class _Mode(enum.IntEnum):
    TWO = 2


def test_whole_numbers_and_flags_are_written_as_before() -> None:
    fields = {"ti": 2, "n": _Mode.TWO, "vt": True, "il": False, "neg": -5, "at": 1.25}
    assert proto.encode_command(3, "PLAY", fields).split(b"*")[0] == (
        b"3 PLAY ti=2 n=2 vt=1 il=0 neg=-5 at=1.25"
    )
    with pytest.raises(proto.FrameError, match="bad field name"):
        proto.encode_command(3, "PLAY", {"Tch": "EV"})


def test_decoding_a_trial_frame_still_refuses_bad_and_repeated_fields() -> None:
    good = proto.encode_event(9, "DONE", {"seq": 17, "on": [1.2, 3.6], "end": 7.4})
    assert proto.decode(good).fields == {"seq": "17", "on": "1.2,3.6", "end": "7.4"}
    for body in (b"9 OK start=1 start=2", b"9 OK Start=1", b"9 OK start=", b"9 OK 1x=2"):
        line = body + b"*" + f"{proto.crc16(body):04X}".encode() + b"\n"
        with pytest.raises(proto.FrameError, match="bad field"):
            proto.decode(line)
