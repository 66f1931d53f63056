"""Nothing in virtual time depends on a quiet machine (issue 21, item 8).

A virtual-time session waits for its device's replies without a load-sized deadline (a slow
reply is still a reply), yet notices a dead peer at once (the pty closes: EIO), and the demo
passes with both cores saturated by busy processes. Real pseudo-terminals throughout."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import pytest
from hardening_support import HELLO, RIG, ScriptedPeer, short_plan, standard

from masking_lab.core.clock import RealClock, VirtualClock
from masking_lab.core.errors import DeviceDisconnectedError, DeviceTimeoutError
from masking_lab.device import protocol as proto
from masking_lab.device.config import parse_device_config
from masking_lab.device.serial_device import SerialDevice

SLOW_S = 0.6  # three times the rig's reply_timeout_s (0.2 s)


def slow_peer(delay_s: float, what: str = "PLAY") -> ScriptedPeer:
    """A board that answers ``what`` only after ``delay_s`` s, like one on a loaded machine."""

    def respond(frame, events):
        if frame.name == what:
            time.sleep(delay_s)
        return standard(frame, events)

    return ScriptedPeer(respond)


def test_a_reply_slower_than_the_reply_timeout_is_waited_for_in_virtual_time():
    peer = slow_peer(SLOW_S)
    try:
        device = SerialDevice(peer.port, parse_device_config(RIG, "rig"), VirtualClock())
        result = device.play_trial(short_plan(), 1.0)
        assert len(result.actual_onsets_s) == 3
        device.close()
    finally:
        peer.close()


def test_an_unanswered_command_is_still_a_timeout_in_real_time():
    # The control: in real time the reply timeout holds (a real board must answer in time).
    def respond(frame, events):
        if frame.name == "HELLO":
            return [proto.encode_ok(frame.seq, {**HELLO, "vt": 0})]
        if frame.name == "PING":
            return []  # never answered
        return None

    peer = ScriptedPeer(respond)
    try:
        device = SerialDevice(peer.port, parse_device_config(RIG, "rig"), RealClock())
        with pytest.raises(DeviceTimeoutError, match=r"stopped answering after 0\.2 s \(no"):
            device.keepalive()
        device.close()
    finally:
        peer.close()


def test_an_unanswered_command_in_virtual_time_ends_at_the_hang_guard_and_says_so():
    text = RIG.replace("virtual_hang_guard_s: 60", "virtual_hang_guard_s: 0.5")
    peer = ScriptedPeer(lambda frame, events: [] if frame.name == "PING" else None)
    try:
        device = SerialDevice(peer.port, parse_device_config(text, "rig"), VirtualClock())
        with pytest.raises(DeviceTimeoutError, match=r"hang guard serial\.virtual_hang_guard_s"):
            device.keepalive()
        device.close()
    finally:
        peer.close()


def test_a_dead_peer_ends_a_virtual_time_wait_at_once_not_at_the_hang_guard():
    # The hang guard is 60 s; the peer's side of the pty closes while the host waits for DONE.
    # The host notices the closed link (EIO) and reports a disconnect; it never waits 60 s
    # (the thread join below is the test's own hang guard, not a timing assertion).
    def respond(frame, events):
        if frame.name == "PLAY":
            threading.Timer(0.2, peer.close).start()
            return []
        return None

    peer = ScriptedPeer(respond)
    device = SerialDevice(peer.port, parse_device_config(RIG, "rig"), VirtualClock())
    errors: list[BaseException] = []

    def play() -> None:
        try:
            device.play_trial(short_plan(), 1.0)
        except BaseException as exc:
            errors.append(exc)

    worker = threading.Thread(target=play, daemon=True)
    worker.start()
    worker.join(30)
    assert not worker.is_alive(), "the host kept waiting on a closed link"
    (error,) = errors
    assert isinstance(error, DeviceDisconnectedError), error
    device.close()


def test_the_demo_passes_with_both_cores_saturated(tmp_path):
    busy = [
        subprocess.Popen([sys.executable, "-c", "while 1: pass"])
        for _ in range(os.cpu_count() or 2)
    ]
    try:
        proc = subprocess.run(
            [
                sys.executable,
                "-c",
                "import sys; from masking_lab.commands.cli import main; sys.exit(main())",
                "demo",
                "--out",
                str(tmp_path / "demo"),
                "--participants",
                "2",
                "--jobs",
                "2",
                "--n-boot",
                "100",
            ],
            capture_output=True,
            text=True,
            timeout=1800,  # a hang guard for the test itself, far beyond any run
        )
    finally:
        for p in busy:
            p.kill()
            p.wait()
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "stopped answering" not in proc.stderr
    assert len(list((tmp_path / "demo" / "data").rglob("*.jsonl"))) == 6
