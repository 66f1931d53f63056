"""The firmware emulator over a real pseudo-terminal, driven with raw frames through pyserial.

These tests bypass the host's SerialDevice on purpose: they check what the *firmware* does on its
own (limits, faults, watchdog, timing), whatever the host sends.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest
import serial
from firmware_support import Link

from masking_lab.device import protocol as proto
from masking_lab.device.config import load_device_config
from masking_lab.device.emulator import FirmwareEmulator
from masking_lab.device.emulator_checks import Converter
from masking_lab.formats.resources import shipped

DAC = Converter(12, 10_000_000)  # the emulator's default converter: 12 bits over ±10 V


def played(code: int) -> float:
    """V a code amplitude plays with no attenuation (1 LSB = 4.8828125 mV), to the µV."""
    return DAC.played_uv(code, 0) / 1e6


RIG = """\
schema_version: 1
channels:
  EV: {max_drive_v: 2.5}
  MV: {max_drive_v: 8}
serial: {reply_timeout_s: 0.3, watchdog_s: 0.3}
waveform: {sample_rate_hz: 10000, ramp_s: 0.002}
emulator: {model: TEST-EMU, serial_number: T-42, onset_jitter_s: 0.0001}
"""

PLAY = {
    "tch": "EV",
    "tcar": 270.0,
    "tenv": 0.0,
    "tamp": 0.5,
    "ti": 2,
    "mch": "MV",
    "mcar": 120.0,
    "menv": 0.0,
    "mamp": 0.3,
    "stim": 0.03,
    "gap": 0.02,
    "lead": 0.02,
    "n": 3,
}


@pytest.fixture
def rig(tmp_path):
    path = tmp_path / "rig.yaml"
    path.write_text(RIG, encoding="utf-8")
    return load_device_config(path)


@pytest.fixture
def emulator_factory(rig):
    made: list[FirmwareEmulator] = []
    links: list[Link] = []

    def make(**kwargs) -> tuple[FirmwareEmulator, Link]:
        emu = FirmwareEmulator(kwargs.pop("config", rig), **kwargs).start()
        made.append(emu)
        link = Link(emu.port)
        links.append(link)
        return emu, link

    yield make
    for link in links:
        link.ser.close()
    for emu in made:
        emu.close()


def wait_until(predicate, timeout: float = 2.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return predicate()


def test_hello_reports_identity_limits_watchdog_and_time_mode(emulator_factory):
    emu, link = emulator_factory(virtual_time=True)
    hello = link.reply(link.send("HELLO"))
    assert hello.ok
    assert hello.fields["model"] == "TEST-EMU" and hello.fields["sn"] == "T-42"
    assert (hello.number("max_ev"), hello.number("max_mv")) == (2.5, 8.0)
    assert hello.number("wd_ms") == 300 and hello.fields["vt"] == "1"
    assert int(hello.number("proto")) == proto.PROTOCOL_VERSION
    assert emu.port.startswith("/dev/")


def test_pty_is_raw_no_echo_and_no_newline_translation(emulator_factory):
    _, link = emulator_factory()
    seq = link.send("PING")
    reply_bytes = link.quiet_for(0.15)
    # only the reply comes back: no echo of our command, and \n is not turned into \r\n
    assert reply_bytes.count(b"\n") == 1 and b"\r" not in reply_bytes
    assert proto.decode(reply_bytes).seq == seq


def test_over_limit_raw_frame_is_refused_and_zeroes_both_outputs(emulator_factory):
    emu, link = emulator_factory()
    assert link.reply(link.send("SETUP", ch="MV", car=120.0, env=0.0, amp=1.0)).ok
    assert link.reply(link.send("SETUP", ch="EV", car=270.0, env=0.0, amp=0.5)).ok
    assert dict(emu.outputs().amplitude_v) == {"EV": played(102), "MV": played(205)}
    # 3 V on EV is within the host's idea of nothing here: the frame bypasses any host check
    refused = link.reply(link.send("AMP", ch="EV", amp=3.0))
    assert not refused.ok and refused.code == "LIMIT"
    assert emu.outputs().zero  # MV, which was fine, is zeroed too
    assert any("LIMIT" in line and "refused" in line for line in emu.log_lines())


def test_over_limit_play_is_refused_before_anything_plays(emulator_factory):
    emu, link = emulator_factory()
    # each amplitude alone is legal on its channel, but target and masker share MV: 5 + 4 > 8 V
    fields = dict(PLAY, tch="MV", tcar=250.0, tamp=5.0, mamp=4.0)
    refused = link.reply(link.send("PLAY", at=0.0, **fields))
    assert refused.code == "LIMIT"
    assert emu.outputs().zero
    assert link.quiet_for(0.2) == b""  # no DONE: nothing was played


@pytest.mark.parametrize(
    "raw",
    [
        b"1 SETUP ch=EV car=270 env=0 amp=0.5*0000\n",  # bad checksum
        b"\x00\xff\x13random bytes\n",  # line noise
        b"x" * 400,  # no newline at all
        b"7 OK*" + f"{proto.crc16(b'7 OK'):04X}".encode() + b"\n",  # a reply sent to the device
    ],
    ids=["bad_crc", "noise", "overlong", "wrong_direction"],
)
def test_corrupted_command_zeroes_outputs_and_reports_a_fault(emulator_factory, raw):
    emu, link = emulator_factory()
    assert link.reply(link.send("SETUP", ch="MV", car=120.0, env=0.0, amp=1.0)).ok
    link.ser.write(raw)
    fault = link.frames_until(lambda f: f.kind == "event")[-1]
    assert (fault.name, fault.fields["code"]) == ("FAULT", "FRAME")
    assert emu.outputs().zero
    assert any("FAULT FRAME" in line for line in emu.log_lines())
    if not raw.endswith(b"\n"):
        link.ser.write(b"\n")  # like the firmware, the rest of an over-long line is skipped
    assert link.reply(link.send("PING")).ok  # the firmware keeps serving


def test_watchdog_zeroes_outputs_when_the_host_goes_quiet(emulator_factory):
    emu, link = emulator_factory(watchdog_s=0.15)
    assert link.reply(link.send("SETUP", ch="EV", car=270.0, env=0.0, amp=1.0)).ok
    event = link.frames_until(lambda f: f.kind == "event", timeout=3.0)[-1]
    assert event.name == "WATCHDOG" and event.number("quiet_ms") >= 150
    assert emu.outputs().zero
    assert any("WATCHDOG" in line for line in emu.log_lines())


def test_pings_keep_the_watchdog_fed_and_an_idle_device_never_trips(emulator_factory):
    emu, link = emulator_factory(watchdog_s=0.3)
    assert link.reply(link.send("SETUP", ch="EV", car=270.0, env=0.0, amp=1.0)).ok
    for _ in range(8):  # 0.4 s of pings every 50 ms, longer than the 0.3 s period
        assert link.reply(link.send("PING")).ok
        time.sleep(0.05)
    assert emu.outputs().amplitude_v["EV"] == played(205)  # 1 V quantised
    assert link.reply(link.send("STOP")).ok
    assert link.quiet_for(0.45) == b""  # outputs at 0 V: nothing to guard, no WATCHDOG
    assert not any("WATCHDOG" in line for line in emu.log_lines())


def test_unplug_closes_the_port_and_zeroes_outputs(emulator_factory):
    emu, link = emulator_factory()
    assert link.reply(link.send("SETUP", ch="MV", car=120.0, env=0.0, amp=2.0)).ok
    emu.unplug()
    snapshot = emu.outputs()
    assert snapshot.zero and not snapshot.connected
    with pytest.raises((serial.SerialException, OSError)):
        for _ in range(50):  # the first read may still return buffered bytes
            link.ser.read(1)
    assert any("UNPLUG" in line for line in emu.log_lines())


def test_a_board_that_resets_on_open_ignores_input_until_booted(emulator_factory):
    _, link = emulator_factory(boot_delay_s=0.3)
    link.send("HELLO")
    early = link.quiet_for(0.15)
    assert early == b""  # swallowed by the booting board
    seen = []
    deadline = time.monotonic() + 2
    while not any(b"BOOT" in chunk for chunk in seen) and time.monotonic() < deadline:
        seen.append(link.ser.read(max(1, link.ser.in_waiting)))
    raw = b"".join(seen)
    assert b"bootloader" in raw  # unframed chatter a host must discard
    hello = link.reply(link.send("HELLO"))
    assert hello.ok


def test_reset_zeroes_and_reboots(emulator_factory):
    emu, link = emulator_factory(boot_delay_s=0.05)
    assert link.frames_until(lambda f: f.kind == "event" and f.name == "BOOT", timeout=2.0)
    assert link.reply(link.send("SETUP", ch="EV", car=270.0, env=0.0, amp=1.0)).ok
    emu.reset()
    assert emu.outputs().zero
    assert any("RESET" in line for line in emu.log_lines())


def _play(seed: int, rig) -> tuple[int, list[proto.Frame]]:
    """One virtual-time PLAY on a fresh emulator: its seq and the frames up to its DONE."""
    emu = FirmwareEmulator(rig, virtual_time=True, seed=seed).start()
    try:
        link = Link(emu.port)
        try:
            seq = link.send("PLAY", at=5.0, **PLAY)
            return seq, link.frames_until(lambda f: f.kind == "event" and f.name == "DONE")
        finally:
            link.ser.close()
    finally:
        emu.close()


def _done_line(seed: int, rig) -> proto.Frame:
    seq, frames = _play(seed, rig)
    assert any(f.kind == "reply" and f.seq == seq and f.number("start") == 5.0 for f in frames)
    return frames[-1]


def test_virtual_time_play_reports_planned_onsets_plus_small_seeded_lateness(rig):
    done = _done_line(1, rig)
    planned = [5.02, 5.07, 5.12]  # at + lead + k·(stim + gap)
    onsets = done.numbers("on")
    assert all(0 <= a - p < 0.002 for a, p in zip(onsets, planned, strict=True))
    assert done.number("end") == pytest.approx(5.0 + 0.02 + 3 * 0.03 + 2 * 0.02)
    # played after quantisation: 12 bits over ±10 V, 1 LSB = 4.8828125 mV
    assert (done.number("tamp"), done.number("mamp")) == (played(102), played(61))
    assert done.numbers("on") == _done_line(1, rig).numbers("on")  # same seed, same lateness
    assert done.numbers("on") != _done_line(2, rig).numbers("on")


def test_virtual_time_play_answers_ok_and_done_in_one_write(rig, monkeypatch):
    # The host then gets both from one read: one wake-up per simulated trial, not two.
    import masking_lab.device.emulator as emulator_module

    writes: list[bytes] = []

    class CountingOs:
        def __getattr__(self, name):
            return getattr(os, name)

        @staticmethod
        def write(fd: int, data: bytes) -> int:
            writes.append(bytes(data))
            return os.write(fd, data)

    monkeypatch.setattr(emulator_module, "os", CountingOs())
    seq, frames = _play(1, rig)
    replies = [w for w in writes if f"{seq} OK".encode() in w]
    assert len(replies) == 1 and b" DONE seq=" in replies[0]
    assert [f.kind for f in frames[-2:]] == ["reply", "event"]  # OK first, then DONE


def test_real_time_play_is_hardware_timed_and_ends_on_zero(emulator_factory):
    emu, link = emulator_factory()
    now = link.reply(link.send("TIME")).number("t")
    at = now + 0.05
    seq = link.send("PLAY", at=at, **PLAY)
    assert link.reply(seq).ok
    assert wait_until(lambda: emu.outputs().playing, 1.0)
    done = link.frames_until(lambda f: f.kind == "event" and f.name == "DONE")[-1]
    assert done.number("seq") == seq
    onsets = done.numbers("on")
    planned = [at + 0.02, at + 0.07, at + 0.12]
    # a hardware-timed device is never early, and keeps the order of the intervals
    assert all(a >= p for a, p in zip(onsets, planned, strict=True))
    assert onsets == sorted(onsets)
    snap = emu.outputs()
    assert snap.zero and dict(snap.last_sample_v) == {"EV": 0.0, "MV": 0.0}


def test_stop_aborts_a_trial_in_progress(emulator_factory):
    emu, link = emulator_factory(watchdog_s=0)
    now = link.reply(link.send("TIME")).number("t")
    seq = link.send("PLAY", at=now, **dict(PLAY, stim=2.0, lead=0.0))
    assert link.reply(seq).ok
    assert wait_until(lambda: emu.outputs().amplitude_v["MV"] == played(61), 1.0)
    stop = link.send("STOP")
    frames = link.frames_until(lambda f: f.kind == "reply" and f.seq == stop)
    aborted = [f for f in frames if f.kind == "event" and f.name == "ABORTED"]
    assert aborted and aborted[0].number("seq") == seq and aborted[0].fields["why"] == "STOP"
    assert emu.outputs().zero


@pytest.mark.parametrize(
    ("name", "fields", "code"),
    [
        ("AMP", {"ch": "EV", "amp": 0.1}, "STATE"),
        ("BLINK", {}, "UNKNOWN"),
        ("SETUP", {"ch": "EV", "car": 270.0}, "ARGS"),
        ("SETUP", {"ch": "XX", "car": 270.0, "env": 0.0, "amp": 0.1}, "ARGS"),
        ("SETUP", {"ch": "EV", "car": 9000.0, "env": 0.0, "amp": 0.1}, "ARGS"),
        ("PLAY", dict(PLAY, ti=4, at=0.0), "ARGS"),
        ("PLAY", dict(PLAY, stim=0.0, at=0.0), "ARGS"),
    ],
)
def test_bad_commands_get_err_and_zero_outputs(emulator_factory, name, fields, code):
    emu, link = emulator_factory()
    assert link.reply(link.send("SETUP", ch="MV", car=120.0, env=0.0, amp=1.0)).ok
    if name == "AMP":
        assert link.reply(link.send("STOP")).ok
    reply = link.reply(link.send(name, **fields))
    assert not reply.ok and reply.code == code
    assert emu.outputs().zero


def test_play_while_playing_is_busy(emulator_factory):
    emu, link = emulator_factory(watchdog_s=0)
    now = link.reply(link.send("TIME")).number("t")
    assert link.reply(link.send("PLAY", at=now + 1.0, **PLAY)).ok
    busy = link.reply(link.send("PLAY", at=now + 2.0, **PLAY))
    assert busy.code == "BUSY"
    assert emu.outputs().zero  # and the first trial is aborted


def test_muted_firmware_stops_answering_but_its_watchdog_still_zeroes(emulator_factory):
    emu, link = emulator_factory(watchdog_s=0.15)
    assert link.reply(link.send("SETUP", ch="EV", car=270.0, env=0.0, amp=1.0)).ok
    emu.inject("mute", 2)
    link.send("PING")
    link.send("STOP")
    event = link.frames_until(lambda f: True, timeout=3.0)[-1]
    assert event.name == "WATCHDOG"  # no reply to PING or STOP, only the watchdog's report
    assert emu.outputs().zero


def test_unknown_fault_kind_is_refused(emulator_factory):
    emu, _ = emulator_factory()
    with pytest.raises(ValueError, match="unknown fault"):
        emu.inject("lightning")


def test_event_log_file_is_written(tmp_path, rig):
    log = tmp_path / "emu.log"
    emu = FirmwareEmulator(rig, log_path=log).start()
    link = Link(emu.port)
    try:
        link.ser.write(b"noise\n")
        link.frames_until(lambda f: f.kind == "event")
    finally:
        link.ser.close()
        emu.close()
    text = log.read_text()
    assert "START" in text and "FAULT FRAME" in text and "CLOSE" in text


def test_emulate_command_prints_its_port_serves_it_and_zeroes_on_sigterm(tmp_path):
    cfg = tmp_path / "rig.yaml"
    cfg.write_text(RIG, encoding="utf-8")
    log = tmp_path / "emu.log"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "masking_lab.commands.cli",
            "emulate",
            "--config",
            str(cfg),
            "--virtual-time",
            "--watchdog-ms",
            "200",
            "--log",
            str(log),
            "--bits",
            "16",
            "--fsv",
            "5",
            "--att",
            "0,20",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        first = proc.stdout.readline()
        assert first.startswith("emulator listening on /dev/"), first
        port = first.split()[-1]
        link = Link(port)
        try:
            hello = link.reply(link.send("HELLO"))
            assert hello.fields["vt"] == "1" and hello.number("wd_ms") == 200
            f = hello.fields  # the converter and attenuator options reach HELLO
            assert (f["bits_ev"], f["fsv_mv"], f["att"], f["fw"]) == ("16", "5", "0,20", "fw-2.0.0")
            assert link.reply(link.send("SETUP", ch="EV", car=270.0, env=0.0, amp=1.0)).ok
        finally:
            link.ser.close()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0
    assert "outputs zeroed" in err
    text = log.read_text()
    assert "CLOSE" in text


@pytest.mark.parametrize(
    ("option", "value"), [("--att", "0,10,5"), ("--att", "20"), ("--bits", "40"), ("--fsv", "nan")]
)
def test_emulate_command_refuses_a_bad_converter_option(option, value):
    proc = subprocess.run(
        [sys.executable, "-m", "masking_lab.commands.cli", "emulate", option, value],
        capture_output=True,
        text=True,
        timeout=20,
    )
    assert proc.returncode == 2
    assert option in proc.stderr and "Traceback" not in proc.stderr


def test_emulate_command_reports_a_bad_config(tmp_path):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("schema_version: 1\nchannels: {EV: {max_drive_v: 99}}\n", encoding="utf-8")
    proc = subprocess.run(
        [sys.executable, "-m", "masking_lab.commands.cli", "emulate", "--config", str(cfg)],
        capture_output=True,
        text=True,
        timeout=20,
    )
    assert proc.returncode == 2
    assert str(cfg) in proc.stderr and "Traceback" not in proc.stderr


def test_emulate_with_an_open_interlock_refuses_a_session_until_it_closes(tmp_path):
    """The safety chain from the CLI: `emulate --interlock-open`, then SIGUSR1 closes it."""
    cli = [sys.executable, "-m", "masking_lab.commands.cli"]
    proc = subprocess.Popen(
        [*cli, "emulate", "--virtual-time", "--interlock-open"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        port = proc.stdout.readline().split()[-1]
        run = [
            *cli,
            "run",
            str(shipped("protocols", "baseline.yaml")),
            "--participant",
            "S01",
            "--device",
            f"serial:{port}",
            "--responder",
            "sim",
            "--data",
            str(tmp_path / "data"),
            "--seed",
            "3",
            "--sets",
            "EV270",
        ]
        refused = subprocess.run(run, capture_output=True, text=True, timeout=60)
        assert refused.returncode == 3, refused.stderr
        assert "interlock" in refused.stderr and "Traceback" not in refused.stderr
        assert "wristband" in refused.stderr  # says what to check
        assert not list((tmp_path / "data").rglob("*.jsonl"))  # nothing was logged or played
        assert "interlock open;" in proc.stderr.readline()
        proc.send_signal(signal.SIGUSR1)
        assert proc.stderr.readline().strip() == "interlock closed"
        ran = subprocess.run(run, capture_output=True, text=True, timeout=120)
        assert ran.returncode == 0, ran.stderr
        assert len(list((tmp_path / "data").rglob("*.jsonl"))) == 1
        proc.send_signal(signal.SIGUSR1)
        assert proc.stderr.readline().strip() == "interlock open: outputs zeroed"
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0
