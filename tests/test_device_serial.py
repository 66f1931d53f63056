"""SerialDevice (host side) over a real pseudo-terminal: the emulator or a hand-written peer on
the master side, pyserial on the slave side. Every fault path ends with both outputs at 0 V."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
import tty

import pytest
from hardening_support import HELLO as V2_HELLO
from hardening_support import QUICK_RIG, short_plan
from hardening_support import RIG as HOST_RIG

from masking_lab.core.clock import RealClock, VirtualClock
from masking_lab.core.errors import (
    DeviceDisconnectedError,
    DeviceError,
    DeviceFaultError,
    DeviceProtocolError,
    DeviceTimeoutError,
    SafetyLimitError,
)
from masking_lab.core.stimulus import parse_stimulus
from masking_lab.device import protocol as proto
from masking_lab.device.config import load_device_config
from masking_lab.device.emulator import FirmwareEmulator
from masking_lab.device.serial_device import SerialDevice

EV270, MV120, MV180 = (parse_stimulus(n) for n in ("EV270", "MV120", "MV180"))


def write_rig(tmp_path, text=HOST_RIG, name="rig.yaml"):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


@pytest.fixture
def rig(tmp_path):
    return load_device_config(write_rig(tmp_path))


@pytest.fixture
def quick_rig(tmp_path):
    """The rig with a 0.3 s virtual-time hang guard: for peers that never answer."""
    return load_device_config(write_rig(tmp_path, QUICK_RIG, "quick.yaml"))


@pytest.fixture
def closing():
    """Collects emulators, devices and fds; closes them all at teardown."""
    items: list = []
    yield items
    for item in reversed(items):
        if isinstance(item, int):
            with contextlib.suppress(OSError):
                os.close(item)
        else:
            item.close()


@pytest.fixture
def connect(rig, closing):
    """connect(clock, host_config=rig, **emulator_kwargs) -> (SerialDevice, FirmwareEmulator)."""

    def make(clock=None, host_config=None, emulator_config=None, **emu_kwargs):
        clock = clock or VirtualClock()
        emu_kwargs.setdefault("virtual_time", clock.virtual)
        emu = FirmwareEmulator(emulator_config or rig, **emu_kwargs).start()
        closing.append(emu)
        dev = SerialDevice(emu.port, host_config or rig, clock)
        closing.append(dev)
        return dev, emu

    return make


def wait_until(predicate, timeout=3.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


# ---------------------------------------------------------------------------- handshake


def test_handshake_identity_and_the_stricter_limits_win(tmp_path, connect):
    firmware = load_device_config(
        write_rig(
            tmp_path,
            HOST_RIG.replace("{max_drive_v: 2.5}", "{max_drive_v: 1.0}").replace(
                "{max_drive_v: 8}", "{max_drive_v: 9}"
            ),
            "fw.yaml",
        )
    )
    dev, emu = connect(emulator_config=firmware)
    ident = dev.identity
    assert (ident.backend, ident.port, ident.firmware_version) == ("serial", emu.port, "fw-2.0.0")
    # EV: firmware 1.0 V is stricter than host 2.5 V; MV: host 8 V is stricter than firmware 9 V
    assert dict(ident.limits.max_drive_v) == {"EV": 1.0, "MV": 8.0}
    assert dev.watchdog_s == pytest.approx(0.3)
    with pytest.raises(SafetyLimitError, match="EV limit of 1 V"):
        dev.play_trial(short_plan(target_amplitude_v=1.5), 0.0)


def test_over_limit_is_refused_on_the_host_and_nothing_is_sent(connect):
    dev, emu = connect()
    before = emu.commands_received
    cases = [
        short_plan(target_amplitude_v=2.6),
        short_plan(masker_amplitude_v=8.5),
        short_plan(target=MV180, target_amplitude_v=5.0, masker_amplitude_v=4.0),  # sum on MV
        short_plan(target_amplitude_v=float("nan")),
        short_plan(target_amplitude_v=-0.1),
        short_plan(target_interval=4),
        short_plan(masker=None, masker_amplitude_v=0.2),
    ]
    for plan in cases:
        with pytest.raises(SafetyLimitError):
            dev.play_trial(plan, 0.0)
    with pytest.raises(SafetyLimitError, match="exceeds the EV limit"):
        dev.set_amplitude("EV", EV270, 3.0)
    with pytest.raises(SafetyLimitError, match="not MV"):
        dev.set_amplitude("MV", EV270, 0.1)
    assert emu.commands_received == before
    assert emu.outputs().zero


def test_firmware_refusal_is_a_safety_error_and_zeroes(connect):
    dev, emu = connect()
    dev.set_amplitude("MV", MV120, 1.0)
    # Bypass the host check, as a buggy or tampered host would: the firmware still refuses.
    with pytest.raises(SafetyLimitError, match=r"refused SETUP .* LIMIT"):
        dev._command("SETUP", {"ch": "EV", "car": 270.0, "env": 0.0, "amp": 4.0})
    assert emu.outputs().zero


def test_a_board_that_resets_on_open_is_waited_for(tmp_path, closing, rig):
    host = load_device_config(
        write_rig(tmp_path, HOST_RIG.replace("boot_timeout_s: 0", "boot_timeout_s: 3"), "h.yaml")
    )
    emu = FirmwareEmulator(rig, virtual_time=True, boot_delay_s=0.4).start()
    closing.append(emu)
    dev = SerialDevice(emu.port, host, VirtualClock())
    closing.append(dev)
    assert dev.garbage_lines >= 1  # the bootloader's chatter was discarded, not fatal
    # 0.5 V on the emulator's 12-bit, 10 V converter at 0 dB: within one LSB (4.9 mV)
    assert dev.play_trial(short_plan(), 1.0).played_target_v == pytest.approx(0.5, abs=0.0049)


def test_a_board_that_boots_too_slowly_is_reported(tmp_path, closing, rig):
    host = load_device_config(
        write_rig(tmp_path, QUICK_RIG.replace("boot_timeout_s: 0", "boot_timeout_s: 0.3"), "h.yaml")
    )
    emu = FirmwareEmulator(rig, virtual_time=True, boot_delay_s=5.0).start()
    closing.append(emu)
    with pytest.raises(
        DeviceTimeoutError, match=rf"no answer to HELLO from {emu.port}.*boot_timeout"
    ):
        SerialDevice(emu.port, host, VirtualClock())


def test_time_mode_mismatch_is_refused(connect):
    with pytest.raises(DeviceError, match="runs in real time"):
        connect(clock=VirtualClock(), virtual_time=False)
    with pytest.raises(DeviceError, match="runs in virtual time"):
        connect(clock=RealClock(), virtual_time=True)


def test_missing_port_is_reported(rig, tmp_path):
    with pytest.raises(DeviceError, match=r"cannot open serial port .*check the cable"):
        SerialDevice(str(tmp_path / "ttyNOPE"), rig, VirtualClock())


def test_a_port_in_use_is_reported(connect, rig):
    dev, _ = connect()
    with pytest.raises(DeviceError, match="another program"):
        SerialDevice(dev.port, rig, VirtualClock())


# ---------------------------------------------------------------------------- playing


def test_virtual_time_trials_advance_the_session_clock(connect):
    clock = VirtualClock(100.0)
    dev, emu = connect(clock=clock)
    plan = short_plan(stimulus_s=1.8, gap_s=0.6, lead_in_s=1.2)
    for k in range(50):
        start = clock.now() + 0.5
        result = dev.play_trial(plan, start)
        assert clock.now() == pytest.approx(start + plan.duration_s)
        assert result.planned_onsets_s == pytest.approx([start + 1.2, start + 3.6, start + 6.0])
        late = [a - p for a, p in zip(result.actual_onsets_s, result.planned_onsets_s, strict=True)]
        assert all(-1e-5 <= d < 0.002 for d in late), (k, late)
        # quantised to the emulator's 12-bit, 10 V converter (one LSB: 4.9 mV)
        played = (result.played_target_v, result.played_masker_v)
        assert played == pytest.approx((0.5, 0.3), abs=0.0049) and played != (0.5, 0.3)
        assert (result.extra["requested_target_v"], result.extra["target_att_db"]) == (0.5, 0.0)
    assert emu.outputs().zero


def test_real_time_trial_returns_after_it_ended_with_onsets_in_session_time(connect):
    clock = RealClock()
    dev, emu = connect(clock=clock)
    start = clock.now() + 0.02
    plan = short_plan()
    result = dev.play_trial(plan, start)
    assert clock.now() >= start + plan.duration_s
    assert len(result.actual_onsets_s) == 3
    # onsets map to the session clock: never before the plan (beyond the sync error), in order
    assert all(
        a > p - 0.002 for a, p in zip(result.actual_onsets_s, result.planned_onsets_s, strict=True)
    )
    assert result.actual_onsets_s == sorted(result.actual_onsets_s)
    snap = emu.outputs()
    assert snap.zero and dict(snap.last_sample_v) == {"EV": 0.0, "MV": 0.0}


def test_long_real_time_trial_keeps_the_watchdog_fed(connect):
    clock = RealClock()
    dev, emu = connect(clock=clock, watchdog_s=0.15)  # the trial lasts 3× the watchdog period
    result = dev.play_trial(short_plan(stimulus_s=0.12, gap_s=0.05), clock.now())
    assert len(result.actual_onsets_s) == 3
    assert not any("WATCHDOG" in line for line in emu.log_lines())


def test_streamed_amplitudes_setup_once_then_amp(connect):
    dev, emu = connect()
    dev.set_amplitude("EV", EV270, 0.4)
    dev.set_amplitude("EV", EV270, 0.6)
    dev.set_amplitude("MV", parse_stimulus("MV120am40"), 2.0)
    # streams play whole converter codes (12 bits, 10 V full scale: 4.88 mV per LSB)
    lsb = 20.0 / 4096
    played = dict(emu.outputs().amplitude_v)
    assert played == pytest.approx(
        {"EV": round(0.6 / lsb) * lsb, "MV": round(2.0 / lsb) * lsb}, abs=1e-6
    )
    dev.keepalive()
    dev.stop()
    assert emu.outputs().zero
    dev.set_amplitude("EV", EV270, 0.2)  # after STOP the channel is set up again
    assert emu.outputs().amplitude_v["EV"] == pytest.approx(0.2, abs=20.0 / 4096)  # whole codes


def test_stop_from_another_thread_aborts_a_trial_in_progress(connect):
    clock = RealClock()
    dev, emu = connect(clock=clock)
    outcome = []

    def play():
        try:
            dev.play_trial(short_plan(stimulus_s=1.0, lead_in_s=0.0), clock.now())
            outcome.append("finished")
        except DeviceError as exc:
            outcome.append(exc)

    worker = threading.Thread(target=play)
    worker.start()
    assert wait_until(lambda: emu.outputs().amplitude_v["MV"] > 0)
    dev.stop()  # e.g. the experimenter aborts while the trial plays
    worker.join(timeout=5)
    assert emu.outputs().zero
    assert isinstance(outcome[0], DeviceFaultError) and "aborted" in str(outcome[0])


def test_close_sends_stop_and_is_idempotent(connect):
    dev, emu = connect()
    dev.set_amplitude("EV", EV270, 1.0)
    dev.close()
    dev.close()
    assert emu.outputs().zero
    assert any("STOP" in line for line in emu.log_lines())
    with pytest.raises(DeviceError, match="closed"):
        dev.play_trial(short_plan(), 0.0)


# ---------------------------------------------------------------------------- faults


def test_no_reply_is_a_timeout_and_the_watchdog_zeroes(connect):
    clock = RealClock()
    dev, emu = connect(clock=clock)
    dev.set_amplitude("EV", EV270, 1.0)
    emu.inject("mute", 100)  # firmware hangs: neither PLAY, PING nor STOP is answered
    with pytest.raises(DeviceTimeoutError) as info:
        dev.play_trial(short_plan(), clock.now())
    msg = str(info.value)
    assert emu.port in msg and "stopped answering after 0.2 s" in msg and "resume" in msg
    assert dev.fault_log[0]["kind"] == "DeviceTimeoutError"
    assert wait_until(lambda: emu.outputs().zero)  # the firmware's watchdog, 0.3 s later
    assert any("WATCHDOG" in line for line in emu.log_lines())


def test_a_few_garbled_lines_are_discarded_and_counted(connect):
    dev, emu = connect()
    emu.inject("garbage", 3)
    result = dev.play_trial(short_plan(), 1.0)
    assert result.extra["garbage_lines"] == dev.garbage_lines == 3


def test_a_flood_of_garbage_is_a_protocol_fault_and_zeroes(connect):
    dev, emu = connect()
    dev.set_amplitude("MV", MV120, 1.0)
    emu.inject("garbage", 10)
    with pytest.raises(DeviceProtocolError, match=rf"{emu.port} sent 5 unframed or corrupted"):
        dev.keepalive()
    assert wait_until(lambda: emu.outputs().zero)
    assert dev.fault_log[-1]["kind"] == "DeviceProtocolError"


def test_a_corrupted_reply_is_discarded_then_times_out(connect, quick_rig):
    dev, emu = connect(host_config=quick_rig)
    emu.inject("bad_crc", 1)
    with pytest.raises(DeviceTimeoutError, match="after 1 garbled line"):
        dev.keepalive()
    assert dev.garbage_lines == 1
    dev.keepalive()  # the link is fine again


def test_a_late_reply_is_not_taken_for_the_next_one(closing, quick_rig):
    pings = []

    def respond(frame):
        if frame.name == "PING":
            pings.append(frame.seq)
            if len(pings) == 1:
                return []  # first PING: silence (the reply comes late, below)
            return [proto.encode_ok(pings[0], {"t": 1.0}), proto.encode_ok(frame.seq, {"t": 2.0})]
        return None

    peer = FakePeer(respond)
    closing.append(peer)
    dev = SerialDevice(peer.port, quick_rig, VirtualClock())
    closing.append(dev)
    with pytest.raises(DeviceTimeoutError):
        dev.keepalive()
    dev.keepalive()
    assert dev.stale_replies == 1


def test_unplugged_mid_trial(connect):
    clock = RealClock()
    dev, emu = connect(clock=clock)
    emu.inject("unplug_on_play")
    with pytest.raises(DeviceDisconnectedError, match=rf"{emu.port} disconnected.*resume"):
        dev.play_trial(short_plan(stimulus_s=0.2), clock.now())
    snap = emu.outputs()
    assert snap.zero and not snap.connected
    assert any("UNPLUG" in line for line in emu.log_lines())
    with pytest.raises(DeviceDisconnectedError, match="reconnect"):
        dev.play_trial(short_plan(), clock.now())
    dev.close()  # no STOP can be sent, but closing does not raise


def test_unplugged_between_trials_in_virtual_time(connect):
    dev, emu = connect()
    dev.play_trial(short_plan(), 1.0)
    emu.unplug()
    with pytest.raises(DeviceDisconnectedError):
        dev.play_trial(short_plan(), 2.0)


def test_watchdog_trip_is_reported_at_the_next_command(connect):
    dev, emu = connect(watchdog_s=0.1)
    dev.set_amplitude("EV", EV270, 1.0)
    assert wait_until(lambda: emu.outputs().zero)  # host quiet: the firmware zeroed
    with pytest.raises(DeviceFaultError, match="watchdog tripped") as info:
        dev.keepalive()
    assert info.value.kind == "watchdog"
    dev.keepalive()  # reported once; the device is usable again


def test_a_command_corrupted_on_the_way_is_reported(connect):
    dev, emu = connect()
    dev.set_amplitude("EV", EV270, 1.0)
    dev._ser.write(b"1 AMP ch=EV amp=0.7*0000\n")  # line noise flipped the checksum
    with pytest.raises(DeviceFaultError, match="corrupted command"):
        dev.keepalive()
    assert emu.outputs().zero


# ---------------------------------------------------------------------------- other peers


class FakePeer:
    """A hand-written device on the master side of a raw pty: ``respond(frame)`` returns the
    lines to write back (None: the standard HELLO/TIME answers, [] : silence)."""

    def __init__(self, respond=None, *, garbage_every_s: float | None = None) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        tty.setraw(self.master)
        self.port = os.ttyname(self.slave)
        self.respond = respond or (lambda frame: None)
        self.garbage_every_s = garbage_every_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        import select

        buf = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], self.garbage_every_s or 0.05)
            if not ready:
                if self.garbage_every_s:
                    os.write(self.master, b"\x1b[0m$GPGGA,123519,4807.038,N*47\r\n")
                continue
            try:
                buf += os.read(self.master, 4096)
            except OSError:
                return
            while b"\n" in buf:
                line, _, buf = buf.partition(b"\n")
                try:
                    frame = proto.decode(line)
                except proto.FrameError:
                    continue
                out = self.respond(frame)
                if out is None:
                    out = [self.standard(frame)]
                for chunk in out:
                    os.write(self.master, chunk)

    @staticmethod
    def standard(frame, **hello):
        if frame.name == "HELLO":
            fields = dict(V2_HELLO)
            fields.update(hello)
            return proto.encode_ok(frame.seq, fields)
        return proto.encode_ok(frame.seq, {"t": 0.0})

    def close(self):
        self._stop.set()
        self._thread.join(timeout=2)
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)


@pytest.mark.parametrize("fw", ["fw-2.0.0", "fw-2.0.0+stm32", "fw-2.1.0+qemu", "fw-10.0.0"])
def test_current_firmware_with_a_board_suffix_is_accepted(closing, rig, fw):
    peer = FakePeer(lambda f: [FakePeer.standard(f, fw=fw)] if f.name == "HELLO" else None)
    closing.append(peer)
    dev = SerialDevice(peer.port, rig, VirtualClock())
    closing.append(dev)
    assert dev.identity.firmware_version == fw


def test_a_silent_port_times_out_at_hello(closing, quick_rig):
    peer = FakePeer(lambda frame: [])
    closing.append(peer)
    with pytest.raises(DeviceTimeoutError, match=rf"no answer to HELLO from {peer.port}"):
        SerialDevice(peer.port, quick_rig, VirtualClock())


def test_a_port_that_only_talks_garbage_is_not_a_device(closing, quick_rig):
    peer = FakePeer(lambda frame: [], garbage_every_s=0.01)
    closing.append(peer)
    with pytest.raises(DeviceProtocolError, match=r"not masking-lab frames.*baud rate"):
        SerialDevice(peer.port, quick_rig, VirtualClock())


@pytest.mark.parametrize(
    ("hello", "message"),
    [
        ({"proto": 1}, r"protocol version 1 is not 2.*flash firmware >= fw-2\.0\.0"),
        ({"fw": "fw-1.9.12"}, r"fw-1\.9\.12 is older than fw-2\.0\.0.*flash firmware"),
        ({"fw": "emu-1.0.0"}, r"not of the form fw-X\.Y\.Z.*flash firmware"),
        ({"fw": "fw-2.0.0-rc1+stm32"}, r"fw-2\.0\.0-rc1\+stm32 is older than fw-2\.0\.0"),
        ({"bits_ev": 0}, "incomplete HELLO"),
        ({"att": "20,0"}, "must ascend from 0 dB"),
        ({"rst": "cosmic"}, "incomplete HELLO"),
        ({"max_ev": 0.0}, "limit must be > 0 V"),
        ({"max_mv": "x"}, "incomplete HELLO"),
    ],
)
def test_an_incompatible_firmware_is_refused(closing, rig, hello, message):
    peer = FakePeer(lambda f: [FakePeer.standard(f, **hello)] if f.name == "HELLO" else None)
    closing.append(peer)
    with pytest.raises(DeviceProtocolError, match=message):
        SerialDevice(peer.port, rig, VirtualClock())


def test_a_device_that_plays_other_amplitudes_is_caught(closing, rig):
    def respond(frame):
        if frame.name == "PLAY":
            on = [0.01, 0.04, 0.07]
            done = {"seq": frame.seq, "on": on, "end": 0.09, "tamp": 0.9, "mamp": 0.3}
            return [proto.encode_ok(frame.seq, {"start": 0.0}), proto.encode_event(1, "DONE", done)]
        return None

    peer = FakePeer(respond)
    closing.append(peer)
    dev = SerialDevice(peer.port, rig, VirtualClock())
    closing.append(dev)
    with pytest.raises(DeviceProtocolError, match=r"played target amplitude 0\.9 V differs"):
        dev.play_trial(short_plan(), 0.0)


def test_a_leftover_end_of_trial_report_is_not_taken_for_a_new_trial(closing, rig):
    def respond(frame):
        if frame.name == "PING":  # a stale DONE numbered like the *next* command
            stale = {
                "seq": proto.next_seq(frame.seq),
                "on": [9.0, 9.1, 9.2],
                "end": 9.3,
                "tamp": 0.9,
                "mamp": 0.3,
            }
            return [proto.encode_ok(frame.seq), proto.encode_event(1, "DONE", stale)]
        if frame.name == "PLAY":
            at = frame.number("at")
            on = [at + 0.01, at + 0.04, at + 0.07]
            done = {"seq": frame.seq, "on": on, "end": at + 0.09, "tamp": 0.5, "mamp": 0.3}
            return [proto.encode_ok(frame.seq, {"start": at}), proto.encode_event(2, "DONE", done)]
        return None

    peer = FakePeer(respond)
    closing.append(peer)
    dev = SerialDevice(peer.port, rig, VirtualClock())
    closing.append(dev)
    dev.keepalive()
    result = dev.play_trial(short_plan(), 5.0)
    assert result.actual_onsets_s == pytest.approx(result.planned_onsets_s, abs=1e-6)


def test_a_device_that_never_reports_done_times_out(closing, quick_rig):
    def respond(frame):
        if frame.name == "PLAY":
            return [proto.encode_ok(frame.seq, {"start": 0.0})]
        return None

    peer = FakePeer(respond)
    closing.append(peer)
    dev = SerialDevice(peer.port, quick_rig, VirtualClock())
    closing.append(dev)
    with pytest.raises(DeviceTimeoutError, match="did not report the end of trial"):
        dev.play_trial(short_plan(), 0.0)


def test_a_device_that_reboots_mid_session_is_reported(closing, rig):
    def respond(frame):
        if frame.name == "PING":
            return [proto.encode_event(1, "BOOT", {"fw": "fake"}), proto.encode_ok(frame.seq)]
        return None

    peer = FakePeer(respond)
    closing.append(peer)
    dev = SerialDevice(peer.port, rig, VirtualClock())
    closing.append(dev)
    with pytest.raises(DeviceFaultError, match="rebooted"):
        dev.keepalive()


# ---------------------------------------------------------------------------- exit paths

CHILD = textwrap.dedent(
    """
    import os, signal, sys, time
    from masking_lab.core.clock import RealClock
    from masking_lab.device.config import load_device_config
    from masking_lab.device.serial_device import SerialDevice
    from masking_lab.core.stimulus import parse_stimulus

    port, config, how = sys.argv[1:4]
    dev = SerialDevice(port, load_device_config(config), RealClock())
    dev.set_amplitude("EV", parse_stimulus("EV270"), 1.0)
    print("playing", flush=True)
    sys.stdin.readline()  # the test checks the output is on, then lets us go
    if how == "exit":
        sys.exit(0)  # forgot to close: atexit must zero
    if how == "exception":
        raise RuntimeError("runner crashed")
    while True:  # wait for SIGTERM or SIGKILL, feeding the watchdog
        dev.keepalive()
        time.sleep(0.05)
    """
)


@pytest.mark.parametrize(
    ("how", "zeroed_by"),
    [("exit", "STOP"), ("exception", "STOP"), ("SIGTERM", "STOP"), ("SIGKILL", "WATCHDOG")],
)
def test_outputs_never_stay_on_after_the_host_program_ends(tmp_path, closing, how, zeroed_by):
    # Long watchdog unless the host is SIGKILLed: then only the watchdog can zero.
    fw = "watchdog_s: 0.3" if how == "SIGKILL" else "watchdog_s: 30"
    cfg = write_rig(tmp_path, HOST_RIG.replace("watchdog_s: 0.3", fw), "child.yaml")
    emu = FirmwareEmulator(load_device_config(cfg)).start()
    closing.append(emu)
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, emu.port, str(cfg), how],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout.readline().strip() == "playing"
        assert emu.outputs().amplitude_v["EV"] == pytest.approx(1.0, abs=20.0 / 4096)  # whole codes
        proc.stdin.write("go\n")
        proc.stdin.flush()
        if how in ("SIGTERM", "SIGKILL"):
            proc.send_signal(getattr(signal, how))
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert wait_until(lambda: emu.outputs().zero, timeout=3.0)
    log = "\n".join(emu.log_lines())
    assert zeroed_by in log, log
    if zeroed_by == "STOP":
        assert "WATCHDOG" not in log
