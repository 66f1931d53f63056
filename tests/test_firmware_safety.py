"""Issue 23: limits on what is played, a clock that never steps back, a modelled IWDG.

One regression test per defect the issue lists, on every implementation that can show it:
the Python emulator, the C host build (the sanitizer build where overflow is the point) and,
for the frame-level checks, the STM32 image under QEMU. Virtual-time trials are rendered in
full through the output stage (host build ``--vt-render``, emulator ``render_buffers``), so
DIAG's ``pk_ev``/``pk_mv`` (largest sample output) covers every sample of a trial.
"""

from __future__ import annotations

import re
import time

import pytest
from firmware_support import REPO, TARGETS, EmulatorDevice, Link, played, start
from firmware_support import RIG as RIG_TEXT

from masking_lab.device import protocol as proto
from masking_lab.device.config import parse_device_config
from masking_lab.device.emulator import FirmwareEmulator
from masking_lab.device.emulator_state import build_hash

PLAY = dict(tch="EV", tcar=270, tenv=0, tamp=0.5, ti=1, mch="MV", mcar=120, menv=0, mamp=0.3)
PLAY.update(stim=0.05, gap=0.03, lead=0.02, n=3, at=0)
VT_RENDER = {"emulator": {"render_buffers": True}, "host": {"host_args": ("--vt-render",)}}
VT_RENDER["host-asan"] = VT_RENDER["host"]


def _open(target: str, **kwargs):
    dev = start(target, **kwargs)
    return dev, Link(dev.port)


def _close(dev, link) -> str:
    link.close()
    return dev.close() or ""


@pytest.mark.parametrize("target", TARGETS)
def test_negative_target_on_the_masker_channel_is_refused_not_summed(target):
    # issue 23: tamp=-3.9 with mamp=8.9 on EV summed to 5 V and passed; EV then played 8.9 V
    dev, link = _open(target)
    try:
        frame = dict(PLAY, tch="EV", tamp=-3.9, mch="EV", mamp=8.9)
        assert link.call("PLAY", **frame).code == "ARGS"
        assert link.call("SETUP", ch="EV", car=270, env=0, amp=-0.1).code == "ARGS"
        diag = link.call("DIAG")
        assert (diag.number("ev"), diag.number("mv"), diag.fields["playing"]) == (0, 0, "0")
    finally:
        _close(dev, link)


@pytest.mark.parametrize("target", TARGETS)
def test_an_over_long_line_split_across_reads_is_one_fault(target):
    # found by the corpus: the emulator faulted twice when a > 256-byte line arrived in two
    # pieces (once for the head, once for the tail); the firmware discards the tail
    dev, link = _open(target)
    try:
        link.ser.write(b"7 PING pad=" + b"9" * 290)
        link.ser.flush()
        time.sleep(0.2)  # the head is read (and refused) before the tail arrives
        link.ser.write(b"9" * 40 + b"*0000\n")
        assert link.call("PING").ok
        faults = [e for e in link.events if e.name == "FAULT"]
        assert [f.fields["code"] for f in faults] == ["FRAME"], link.events
    finally:
        _close(dev, link)


@pytest.mark.parametrize("target", ["emulator", "host"])
def test_a_slow_envelope_over_a_long_stimulus_never_exceeds_the_request(target):
    # issue 23: the peak was scanned over the first 2 s only; a 0.05 Hz envelope peaks at
    # t = 10 s, and a 1 V request played 10.3 V at t = 10.5 s. Now every sample of a 12 s
    # stimulus goes through the output stage and the largest one is the played amplitude.
    dev, link = _open(target, virtual_time=True, **VT_RENDER[target])
    try:
        slow = dict(PLAY, tenv=0.05, tamp=1.0, mch="-", n=1, stim=12.0, lead=0, gap=0)
        seq = link.send("PLAY", **slow)
        assert link.reply(seq).ok
        done = link.event("DONE")
        assert done.number("tamp") == played(1.0)
        peak = link.call("DIAG").number("pk_ev")
        assert 0.99 * played(1.0) <= peak <= played(1.0), peak
    finally:
        _close(dev, link)


@pytest.mark.parametrize("target", ["emulator", "host-asan"])
def test_duration_arithmetic_cannot_overflow_past_the_60_s_limit(target):
    # issue 23: UBSan reported signed overflow in trial.c and the 60 s limit was skipped
    dev, link = _open(target, virtual_time=True)
    huge = "999999999999.999999"
    frames = [
        dict(PLAY, stim=huge),
        dict(PLAY, gap=huge, n=9, ti=9),
        dict(PLAY, lead=huge),
        dict(PLAY, stim=60, gap=60, n=9),
        dict(PLAY, stim=6.7, gap=0, n=9, ti=1),  # 60.3 s in total
        dict(PLAY, at=huge),
        dict(PLAY, at=-1),
        dict(PLAY, n=huge, ti=huge),
        dict(PLAY, n="-" + huge),
    ]
    try:
        for frame in frames:
            reply = link.call("PLAY", **frame)
            assert (reply.name, reply.code) == ("ERR", "ARGS"), frame
        assert link.call("PLAY", **dict(PLAY, stim=6.6, gap=0, n=9, ti=1)).ok  # 59.4 s
        assert link.event("DONE").number("end") == pytest.approx(59.42)  # + 20 ms lead
    finally:
        stderr = _close(dev, link)
    assert "runtime error" not in stderr and "Sanitizer" not in stderr, stderr


def test_phase_arithmetic_cannot_overflow_on_long_tones_at_high_rates():
    # found while fixing issue 23: carrier x sample index overflowed int64 past 1.8e7 samples
    # of a near-Nyquist carrier at 1 MHz (UBSan); a 20 s tone renders clean now
    dev, link = _open("host-asan", virtual_time=True, host_args=("--vt-render", "--fs", "1000000"))
    try:
        tone = dict(PLAY, tcar=499999.9, tamp=1.0, mch="-", n=1, stim=20, gap=0, lead=0)
        assert link.call("PLAY", **tone).ok
        assert link.event("DONE", timeout=120).number("tamp") == played(1.0)
    finally:
        stderr = _close(dev, link)
    assert "runtime error" not in stderr and "Sanitizer" not in stderr, stderr
    assert "IWDG" not in stderr  # the rendering feeds the modelled watchdog as a board would


@pytest.mark.parametrize(
    ("target", "options"),
    [("emulator", {"overdrive": 3.0}), ("host", {"host_args": ("--test-overdrive-pct", "300")})],
)
def test_a_sample_over_the_limit_is_a_fault_never_clipped(target, options):
    # fault injection scales every synthesised sample by 3 after the level checks: the
    # output stage's own check must refuse the first sample over the 2.5 V EV limit
    extra = VT_RENDER[target]
    if target == "host":
        options = {"host_args": (*extra["host_args"], *options["host_args"])}
    else:
        options = {**extra, **options}
    dev, link = _open(target, virtual_time=True, **options)
    try:
        seq = link.send("PLAY", **dict(PLAY, tamp=1.0, mamp=0.1))
        assert link.reply(seq).ok
        aborted, fault = link.event("ABORTED"), link.event("FAULT")
        assert (aborted.number("seq"), aborted.fields["why"]) == (seq, "LIMIT")
        assert fault.fields["code"] == "LIMIT"
        diag = link.call("DIAG")
        assert diag.number("pk_ev") <= 2.5 and diag.fields["playing"] == "0"
        assert (diag.number("ev"), diag.number("mv")) == (0, 0)
    finally:
        _close(dev, link)


def expected_build(target: str) -> str:
    """The build id a target reports: the host build's is the Makefile's hash of the sources in
    this checkout; the emulator's is the same recipe run wherever the package is installed."""
    return build_hash(REPO) if target == "host" else build_hash()


@pytest.mark.parametrize("target", ["emulator", "host"])
def test_levels_are_quantised_and_attenuators_checked(target):
    dev, link = _open(target, virtual_time=True)
    try:
        hello = link.call("HELLO")
        assert hello.fields["att"] == "0,20,40" and hello.fields["build"] == expected_build(target)
        # 1 mV behind 40 dB: the converter plays 0.1 V = 20.48 LSB -> 20 LSB = 0.977 mV
        assert link.call("PLAY", **dict(PLAY, tamp=0.001, tatt=40)).ok
        done = link.event("DONE")
        assert (done.number("tamp"), done.number("mamp")) == (0.000977, played(0.3))
        assert done.number("tamp") == played(0.001, 40)
        assert link.call("PLAY", **dict(PLAY, tatt=10)).code == "ARGS"  # not a board step
        shared = dict(PLAY, mch="EV", tatt=20, matt=0)
        assert link.call("PLAY", **shared).code == "ARGS"  # one channel, one attenuator
        # 0.5 V behind 40 dB needs 50 V from a ±10 V converter
        assert link.call("PLAY", **dict(PLAY, tatt=40)).code == "LIMIT"
        # the EV limit, 2.5 V, is exactly 512 LSB: playable, and reported as such
        assert link.call("SETUP", ch="EV", car=270, env=0, amp=2.5).ok
        assert link.call("DIAG").number("ev") == 2.5
    finally:
        _close(dev, link)


@pytest.mark.parametrize("target", ["emulator", "host"])
def test_a_request_within_the_limit_that_quantises_over_it_is_refused(target):
    # EV limit 2.503 V is 512.6 LSB: 2.503 V rounds to 513 LSB = 2.504883 V, over the limit
    if target == "host":
        dev = start("host", host_args=("--max-ev", "2.503"))
    else:
        rig = RIG_TEXT.replace("max_drive_v: 2.5}", "max_drive_v: 2.503}")
        dev = EmulatorDevice.from_config(parse_device_config(rig, "quantising rig"))
    link = Link(dev.port)
    try:
        assert link.call("HELLO").number("max_ev") == 2.503
        refused = link.call("SETUP", ch="EV", car=270, env=0, amp=2.503)
        assert refused.code == "LIMIT" and "quantised" in refused.text
        assert link.call("PLAY", **dict(PLAY, tamp=2.503)).code == "LIMIT"
        assert link.call("SETUP", ch="EV", car=270, env=0, amp=2.502).ok  # 512 LSB = 2.5 V
        assert link.call("DIAG").number("ev") == 2.5
    finally:
        _close(dev, link)


def test_emulator_and_host_build_report_the_same_v2_identity():
    emu_dev, emu = _open("emulator")
    host_dev, host = _open("host")
    try:
        a, b = emu.call("HELLO").fields, host.call("HELLO").fields
        keys = ("proto", "fw", "clk", "rst", "bits_ev", "bits_mv", "fsv_ev", "fsv_mv")
        assert {k: a[k] for k in keys} == {k: b[k] for k in keys}
        # the same build recipe in Python and in the Makefile (an installed emulator, with no
        # firmware tree beside it, says 000000000000)
        assert (a["build"], b["build"]) == (expected_build("emulator"), expected_build("host"))
        assert build_hash(REPO) == b["build"] != "000000000000"
        assert (a["att"], a["rst"], a["clk"]) == (b["att"], "power", "host")
    finally:
        _close(emu_dev, emu)
        _close(host_dev, host)


def test_emulator_converter_options_show_in_hello_and_in_levels():
    with FirmwareEmulator(virtual_time=True, bits=16, fsv_v=2.5, att_db=(0, 20)) as emu:
        link = Link(emu.port)
        try:
            f = link.call("HELLO").fields
            assert (f["bits_ev"], f["fsv_mv"], f["att"]) == ("16", "2.5", "0,20")
            # 1 LSB = 5 V / 65536 = 76.29 µV: 0.1 V is 1310.72 LSB -> 1311 LSB = 0.100021 V
            assert link.call("PLAY", **dict(PLAY, tamp=0.1, tatt=0)).ok
            assert link.event("DONE").number("tamp") == 0.100021
            assert link.call("PLAY", **dict(PLAY, tatt=40)).code == "ARGS"
        finally:
            link.close()


def test_a_starved_main_loop_is_a_watchdog_reset_on_the_host_build():
    # the modelled IWDG: one iteration burning 300 ms of CPU against a 100 ms period resets
    dev, link = _open("host", host_args=("--iwdg-ms", "100", "--test-stall-ms", "300"))
    try:
        now = link.call("TIME").number("t")
        assert link.call("PLAY", **dict(PLAY, at=now)).ok
        boot = link.event("BOOT", timeout=10)
        if boot.fields["rst"] == "power":  # the power-on BOOT of this process came first
            boot = link.event("BOOT", timeout=10)
        assert boot.fields["rst"] == "watchdog"
        hello = link.call("HELLO")
        assert hello.fields["rst"] == "watchdog"
        diag = link.call("DIAG")
        assert (diag.number("ev"), diag.number("mv"), diag.fields["playing"]) == (0, 0, "0")
    finally:
        _close(dev, link)


def test_a_paper_length_masked_am_trial_never_trips_the_modelled_watchdog():
    # 1.8 s AM target on EV (20 Hz envelope) masked on MV, rendered in real time at 10 kHz
    dev, link = _open("host", host_args=("--iwdg-ms", "100"))
    try:
        now = link.call("TIME").number("t")
        am = dict(PLAY, tcar=270, tenv=20, mcar=120, menv=10, stim=1.8, n=1, lead=0.05, at=now)
        seq = link.send("PLAY", **am)
        assert link.reply(seq).ok
        done = link.event("DONE", timeout=20, keepalive=True)
        assert done.number("seq") == seq
        resets = [e for e in link.events if e.name == "BOOT" and e.fields["rst"] != "power"]
        assert not resets and not [e for e in link.events if e.name in ("WATCHDOG", "FAULT")]
        assert link.call("DIAG").number("pk_ev") <= played(0.5)
    finally:
        _close(dev, link)


def test_the_device_clock_runs_on_across_the_32_bit_timer_wrap():
    # the counter starts 0.4 s before 2^32 µs: times stay monotonic, differences saturate,
    # and the 300 ms host watchdog does not trip while the host keeps pinging
    start_us = str(2**32 - 400_000)
    dev, link = _open("host", host_args=("--clock-start-us", start_us))
    try:
        assert link.call("SETUP", ch="EV", car=270, env=0, amp=0.2).ok
        times = []
        for _ in range(24):  # 1.2 s of pings every 50 ms, across the wrap
            times.append(link.call("PING").number("t"))
            time.sleep(0.05)
        assert times == sorted(times) and times[-1] > 2**32 / 1e6
        assert not [e for e in link.events if e.name == "WATCHDOG"]
        assert link.call("DIAG").number("ev") == played(0.2)
    finally:
        _close(dev, link)


def test_a_counter_that_steps_back_holds_the_clock_instead_of_tripping_the_watchdog():
    # issue 23: the device clock stepped back ~1 ms, `mono - last_rx` wrapped and the
    # watchdog tripped. Fault injection: every other 250 ms the 32-bit counter reads 20 ms low.
    dev, link = _open("host", host_args=("--test-clock-stepback-us", "20000"))
    try:
        assert link.call("SETUP", ch="EV", car=270, env=0, amp=0.2).ok
        times = []
        for _ in range(24):  # 1.2 s of pings every 50 ms: four step-backs
            times.append(link.call("PING").number("t"))
            time.sleep(0.05)
        assert times == sorted(times) and times[-1] < 60, times  # no step back, no 2^32 jump
        assert not [e for e in link.events if e.name == "WATCHDOG"]
        assert link.call("DIAG").number("ev") == played(0.2)
    finally:
        _close(dev, link)


def test_boot_event_carries_the_reset_cause():
    frame = proto.encode_event(1, "BOOT", {"fw": "fw-2.0.0", "rst": "power"})
    assert re.fullmatch(rb"!1 BOOT fw=fw-2\.0\.0 rst=power\*[0-9A-F]{4}\n", frame)
