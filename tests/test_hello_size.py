"""HELLO always fits in one frame (docs/device-protocol.md, "Frame size").

A configuration whose HELLO would exceed MAX_FRAME_BYTES at the longest sequence number is
refused at start-up (host build) or construction (emulator), naming what to shorten; a reply
that still would not fit is answered ``ERR SIZE``, never dropped."""

from __future__ import annotations

import dataclasses
import subprocess
import time

import pytest
import serial
from firmware_board_support import require_tools
from firmware_support import FIRMWARE, HOST_FW, TARGETS, require_build, rig_config, start

from masking_lab.device import protocol as proto
from masking_lab.device.emulator import FirmwareEmulator

SN24 = "ABCDEFGHIJKLMNOPQRSTUVWX"  # the longest serial number the Makefile accepts
# A 24-character serial number, odd full scales (6 decimals), four attenuator steps: fits
# (253 bytes at seq 65535 with the rig's 2.5 V / 8 V limits) ...
LONG_HOST = ("--sn", SN24, "--fsv-ev", "3.333333", "--fsv-mv", "7.777777", "--att", "0,10,20,30")
# ... but odd limits too (6 decimals each) push HELLO past 256 bytes: refused at start-up.
WORST_HOST = (*LONG_HOST, "--max-ev", "2.123457", "--max-mv", "7.654321")


def raw_hello(port: str, seq: int = proto.SEQ_MODULO - 1, timeout: float = 5.0) -> bytes:
    """The raw line answering ``seq HELLO`` (events before it skipped)."""
    with serial.Serial(port, timeout=0.05) as ser:
        ser.write(proto.encode_command(seq, "HELLO"))
        buf, deadline = b"", time.monotonic() + timeout
        while time.monotonic() < deadline:
            buf += ser.read(max(1, ser.in_waiting))
            for line in buf.split(b"\n")[:-1]:
                if line.startswith(f"{seq} ".encode()):
                    return line + b"\n"
    raise TimeoutError(f"no reply to HELLO #{seq} on {port} (got {buf!r})")


@pytest.mark.parametrize("target", TARGETS)
def test_every_conformance_target_sends_a_hello_within_the_frame_limit(target):
    dev = start(target)
    try:
        line = raw_hello(dev.port)
    finally:
        dev.close()
    assert len(line) <= proto.MAX_FRAME_BYTES
    assert proto.decode(line).name == "OK"


def test_host_build_with_a_24_character_serial_number_starts_and_its_hello_fits():
    require_build("host")
    dev = start("host", host_args=LONG_HOST)
    try:
        line = raw_hello(dev.port)
    finally:
        dev.close()
    hello = proto.parse_hello(proto.decode(line))
    assert hello.serial_number == SN24
    assert len(line) <= proto.MAX_FRAME_BYTES


def test_host_build_refuses_to_start_when_its_hello_would_not_fit():
    require_build("host")
    done = subprocess.run([str(HOST_FW), *WORST_HOST], capture_output=True, text=True, timeout=20)
    assert done.returncode == 2
    assert done.stdout == ""  # no pty path: nothing to connect to
    assert "HELLO would exceed 256 bytes" in done.stderr and "--sn" in done.stderr


def _emulator_config(serial_number: str, model: str = "TEST-EMU"):
    cfg = rig_config()
    emu = dataclasses.replace(cfg.emulator, serial_number=serial_number, model=model)
    return dataclasses.replace(cfg, emulator=emu)


WORST_EMU = {"fsv_v": 3.333333, "att_db": (0, 10, 20, 30)}


def test_emulator_worst_case_constructs_and_its_hello_fits():
    emu = FirmwareEmulator(_emulator_config(SN24), **WORST_EMU).start()
    try:
        line = raw_hello(emu.port)
    finally:
        emu.close()
    assert proto.parse_hello(proto.decode(line)).serial_number == SN24
    assert len(line) <= proto.MAX_FRAME_BYTES


def test_emulator_refuses_a_configuration_whose_hello_would_not_fit():
    with pytest.raises(ValueError, match=r"HELLO would exceed 256 bytes: shorten \[emulator\]"):
        FirmwareEmulator(_emulator_config(SN24, model="M" * 40), **WORST_EMU)


def test_emulator_answers_err_size_for_a_reply_too_long_instead_of_nothing():
    emu = FirmwareEmulator(rig_config())
    emu._ok(7, {"x": "y" * 300})
    line = bytes(emu._out).splitlines(keepends=True)[-1]
    frame = proto.decode(line)
    assert (frame.seq, frame.name, frame.code, frame.text) == (7, "ERR", "SIZE", proto.SIZE_TEXT)


def test_emulator_sends_fault_size_for_an_event_too_long():
    emu = FirmwareEmulator(rig_config())
    emu._send_event("DONE", {"x": "y" * 300})
    frame = proto.decode(bytes(emu._out).splitlines(keepends=True)[-1])
    assert (frame.kind, frame.name, frame.fields) == ("event", "FAULT", {"code": "SIZE"})


# The QEMU image's model (ML-FW-2CH-QEMU) and its longest reset cause (watchdog) are longer
# than the host build's: the make-time check uses them, so this refuses while the same
# options on the host build (LONG_HOST, 253 bytes) start.
QEMU_WORST = ["SERIAL_NUMBER=" + SN24, "FSV_EV_UV=3333333", "FSV_MV_UV=7777777"]
QEMU_WORST += ["ATT_STEPS_DB=0,10,20,30", "LIMIT_EV_UV=2500000", "LIMIT_MV_UV=7000000"]


@pytest.mark.parametrize(("settings", "fits"), [(QEMU_WORST, False), (QEMU_WORST[:1], True)])
def test_make_refuses_an_image_whose_hello_would_not_fit(settings, fits, tmp_path):
    require_tools("make", "arm-none-eabi-gcc")
    cmd = ["make", "--no-print-directory", "-C", str(FIRMWARE), f"BUILD={tmp_path}", "qemu"]
    done = subprocess.run([*cmd, *settings], capture_output=True, text=True, timeout=600)
    assert (done.returncode == 0) is fits, done.stderr
    assert (tmp_path / "qemu" / "masking-fw.elf").exists() is fits
    if not fits:
        assert "shorten SERIAL_NUMBER" in done.stderr
