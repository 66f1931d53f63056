"""Serial hardening (issue 11, item 3): every field of every frame is validated into a typed
value or a DeviceProtocolError; writes time out; the handshake is bounded by boot_timeout_s
whatever the board does; HELLO fields are range-checked. Real pseudo-terminals throughout."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import threading

import pytest
from hardening_support import (
    HELLO,
    QUICK_RIG,
    RIG,
    ScriptedPeer,
    raw_frame,
    short_plan,
    standard,
)

from masking_lab.core.clock import VirtualClock
from masking_lab.core.errors import DeviceProtocolError, DeviceTimeoutError
from masking_lab.device import protocol as proto
from masking_lab.device.config import parse_device_config
from masking_lab.device.serial_device import SerialDevice

PLAN = short_plan()


@pytest.fixture
def peers():
    made: list[ScriptedPeer] = []
    yield made
    for peer in made:
        peer.close()


def open_device(peers, respond) -> SerialDevice:
    peer = ScriptedPeer(respond)
    peers.append(peer)
    return SerialDevice(peer.port, parse_device_config(RIG, "rig"), VirtualClock())


def test_the_standard_peer_plays_a_trial(peers):
    # The control: the scripted peer is a working device, so the failures below are the fault's.
    device = open_device(peers, None)
    result = device.play_trial(PLAN, 1.0)
    assert len(result.actual_onsets_s) == 3 and result.played_target_v == 0.5
    device.close()


def done_with(body_fields: str):
    def respond(frame, events):
        if frame.name != "PLAY":
            return None
        events[0] += 1
        return [proto.encode_ok(frame.seq), raw_frame(f"!{events[0]} DONE {body_fields(frame)}")]

    return respond


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        (lambda f: f"seq={f.seq} tamp=0.5 mamp=0.3", "lacks field 'on'"),
        (lambda f: "seq=abc on=1,2,3 tamp=0.5 mamp=0.3", "seq='abc' is not a whole number"),
        (lambda f: f"seq={f.seq}.5 on=1,2,3 tamp=0.5 mamp=0.3", "is not a whole number"),
        (lambda f: f"seq={f.seq} on=1,x,3 tamp=0.5 mamp=0.3", "is not a number list"),
        (lambda f: f"seq={f.seq} on=1,2,3 tamp=nan mamp=0.3", "tamp='nan' is not finite"),
        (lambda f: f"seq={f.seq} on=1,2,3 tamp=0.5 mamp=-1", "negative"),
    ],
)
def test_a_malformed_done_is_a_protocol_fault(peers, fields, message):
    device = open_device(peers, done_with(fields))
    with pytest.raises(DeviceProtocolError, match=message) as info:
        device.play_trial(PLAN, 1.0)
    assert "malformed DONE event" in str(info.value)
    assert device.fault_log and device.fault_log[-1]["kind"] == "DeviceProtocolError"
    device.close()


@pytest.mark.parametrize(
    ("reply", "message"),
    [
        ({}, "lacks field 't'"),
        ({"t": "1e999"}, "is not finite"),
        ({"t": "0x10"}, "is not a number"),
        ({"t": -3.0}, "negative"),
    ],
)
def test_a_malformed_time_reply_is_a_protocol_fault(peers, reply, message):
    def respond(frame, events):
        if frame.name == "TIME":
            body = " ".join(f"{k}={v}" for k, v in reply.items())
            return [raw_frame(f"{frame.seq} OK {body}".rstrip())]
        return None

    with pytest.raises(DeviceProtocolError, match=rf"malformed TIME reply.*{message}"):
        open_device(peers, respond)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("wd_ms", "-5", "wd_ms='-5' is not a whole number in 0..60000"),
        ("wd_ms", "500.5", "is not a whole number"),
        ("wd_ms", "600000", "is not a whole number in 0..60000"),
        ("proto", "1.5", "proto='1.5' is not a whole number"),
        ("proto", "1.0", "proto='1.0' is not a whole number"),
        ("max_ev", "inf", "is not finite"),
        ("max_mv", "5000", "≤ 1000 V"),
        ("vt", "2", "vt='2' must be 0 or 1"),
        ("il", "ajar", "il='ajar' must be open or closed"),
    ],
)
def test_hello_fields_are_range_checked(peers, field, value, message):
    def respond(frame, events):
        if frame.name == "HELLO":
            fields = {**HELLO, field: value}
            body = " ".join(f"{k}={v}" for k, v in fields.items())
            return [raw_frame(f"{frame.seq} OK {body}")]
        return None

    with pytest.raises(DeviceProtocolError, match=message):
        open_device(peers, respond)


def test_malformed_abort_and_watchdog_events_are_protocol_faults(peers):
    def respond(frame, events):
        if frame.name == "PLAY":
            events[0] += 1
            return [proto.encode_ok(frame.seq), raw_frame(f"!{events[0]} ABORTED seq=x why=STOP")]
        return None

    device = open_device(peers, respond)
    with pytest.raises(DeviceProtocolError, match="malformed ABORTED event"):
        device.play_trial(PLAN, 1.0)
    device.close()


SPEWER = textwrap.dedent(
    """
    import os, sys, threading, tty
    from masking_lab.core.clock import VirtualClock
    from masking_lab.core.errors import DeviceError
    from masking_lab.device.config import parse_device_config
    from masking_lab.device.serial_device import SerialDevice

    rig = parse_device_config(sys.argv[1], "rig")
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)

    def spew():  # unframed chatter as fast as the pty takes it; never reads a byte
        while True:
            try:
                os.write(master, b"bootloader chatter, not a frame\\r\\n" * 50)
            except OSError:
                return

    threading.Thread(target=spew, daemon=True).start()
    try:
        SerialDevice(os.ttyname(slave), rig, VirtualClock())
    except DeviceError as exc:
        print(type(exc).__name__, exc)
        sys.exit(0)
    sys.exit("the device opened")
    """
)


def test_a_board_that_spews_and_never_reads_cannot_hang_the_handshake():
    # Before the fix the host filled the pty with HELLOs and blocked in write() forever.
    boot_s = 1.5
    # The short hang guard: in virtual time the handshake's budget is the larger of the two.
    rig = QUICK_RIG.replace("boot_timeout_s: 0", f"boot_timeout_s: {boot_s}")
    proc = subprocess.run(
        [sys.executable, "-c", SPEWER, rig], capture_output=True, text=True, timeout=boot_s + 20
    )
    assert proc.returncode == 0, proc.stderr
    kind, message = proc.stdout.split(" ", 1)
    # It ends because the boot budget ran out (the peer spews forever), naming the chatter;
    # the subprocess's own timeout is the hang guard.
    assert kind == "DeviceProtocolError", proc.stdout
    assert "are not masking-lab frames" in message and "bootloader chatter" in message
    assert f"never answered HELLO in {boot_s:.1f} s" in message


def test_a_write_that_blocks_times_out_as_a_device_fault(peers):
    # A peer that stops reading after the handshake: the link fills, and the host's write
    # must end in a DeviceTimeoutError within the write timeout instead of blocking.
    device = open_device(peers, None)
    peer = peers[-1]
    peer._stop.set()  # the peer stops reading entirely
    peer._thread.join(timeout=2)
    faults: list[Exception] = []

    def write_until_fault() -> None:
        try:
            for _ in range(100_000):  # far more PINGs than any pty buffer holds
                device._write(proto.encode_command(1, "PING"))
        except Exception as exc:
            faults.append(exc)

    writer = threading.Thread(target=write_until_fault, daemon=True)
    writer.start()
    writer.join(60)  # a hang guard: a blocking write would never return
    assert not writer.is_alive(), "the host's write blocked instead of timing out"
    (fault,) = faults
    assert isinstance(fault, DeviceTimeoutError), fault
    assert "does not read what the host sends" in str(fault)
    device._dead = "stalled"  # no STOP round trip on close: the peer is gone
    device.close()


def test_standard_answers_are_typed(peers):
    frame = proto.decode(standard(proto.decode(proto.encode_command(3, "HELLO")), [0])[0])
    hello = proto.parse_hello(frame)
    assert (hello.version, hello.watchdog_ms, hello.virtual) == (2, 0, True)
    assert dict(hello.max_v) == {"EV": 5.0, "MV": 10.0}
