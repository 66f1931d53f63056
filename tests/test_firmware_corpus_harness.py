"""The corpus harness says what happened when an implementation stops answering.

The real-time corpus waits on real ptys (QEMU runs on ``-icount auto``); once it failed beside
a full test suite with a bare "no sentinel within 60 s". The wait now ends only after a
stretch of silence, and the error names the implementation and tells a process that exited,
one the machine starved of CPU (here: stopped with SIGSTOP) and one that ran but sent nothing
(a busy loop behind a pty nobody answers) apart. Silence is real time here by nature; nothing
asserts how long anything took.
"""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import threading
import time
import tty

import pytest
from adversarial_corpus import SENTINEL_SEQ, Port, cpu_seconds
from firmware_support import start

from masking_lab.device import protocol as proto

SILENCE_S = 1.5


def _silent_pty() -> tuple[int, str]:
    """A pty whose other end nobody serves: (master fd to keep open, slave path)."""
    master, slave = os.openpty()
    path = os.ttyname(slave)
    os.close(slave)
    return master, path


def _slow_device(
    master: int, delay_s: float, stop: threading.Event, lose: int | None = None
) -> None:
    """Answer every command line on ``master`` with OK after ``delay_s``, one at a time;
    the command numbered ``lose`` is never answered (its bytes lost on the way)."""
    buf = b""
    while not stop.is_set():
        ready, _, _ = select.select([master], [], [], 0.05)
        if ready:
            buf += os.read(master, 4096)
        while b"\n" in buf:
            line, _, buf = buf.partition(b"\n")
            time.sleep(delay_s)  # a device that is slow, but makes progress
            seq = proto.decode(line + b"\n").seq
            if seq != lose:
                os.write(master, proto.encode_ok(seq))


def _fake(delay_s: float, lose: int | None = None):
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    stop = threading.Event()
    server = threading.Thread(target=_slow_device, args=(master, delay_s, stop, lose), daemon=True)
    server.start()

    def close() -> None:
        stop.set()
        server.join()
        os.close(master)
        os.close(slave)

    return os.ttyname(slave), close


def test_a_slow_but_progressing_device_is_waited_for_past_the_silence_limit():
    path, close = _fake(0.3)
    port = Port(path, "slow")
    try:
        # 11 answers 0.3 s apart: longer in all than the 2 s silence limit, never silent as long
        frames = port.batch([proto.encode_command(k, "PING") for k in range(1, 12)], 2.0)
        assert [f.seq for f in frames] == list(range(1, 12))
        assert len(port.stalls) == 1 and port.stalls[0] < 2.0
    finally:
        port.close()
        close()


def test_a_device_alive_but_missing_the_sentinel_is_reported_as_losing_bytes():
    path, close = _fake(0.0, lose=SENTINEL_SEQ)
    port = Port(path, "qemu", os.getpid())  # a live process behind the pty
    try:
        with pytest.raises(TimeoutError) as info:
            port.batch([proto.encode_command(1, "PING")], SILENCE_S)
        assert "(1 answers of this batch read); it answers a fresh PING" in str(info.value)
        assert "sentinel was lost on the way" in str(info.value)
    finally:
        port.close()
        close()


def test_a_starved_process_is_reported_as_starved():
    dev = start("host")
    port = Port(dev.port, "host", dev.proc.pid)
    os.kill(dev.proc.pid, signal.SIGSTOP)  # as a machine that gives it no CPU
    try:
        with pytest.raises(TimeoutError) as info:
            port.batch([], SILENCE_S)
        text = str(info.value)
        assert text.startswith("host: no sentinel reply after")
        assert "starved: the machine gave it almost no CPU" in text and "0 answers" in text
    finally:
        os.kill(dev.proc.pid, signal.SIGCONT)
        port.close()
        dev.close()


def test_a_process_that_runs_but_sends_nothing_is_reported_as_hung():
    master, path = _silent_pty()
    spinner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    port = Port(path, "qemu", spinner.pid)
    try:
        with pytest.raises(TimeoutError, match=r"^qemu: .*\(hung: it ran but sent nothing\)"):
            port.batch([], SILENCE_S * 2)
    finally:
        spinner.kill()
        spinner.wait()
        port.close()
        os.close(master)


def test_an_exited_process_is_reported_as_exited():
    master, path = _silent_pty()
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    assert cpu_seconds(gone.pid) is None
    port = Port(path, "host-asan", gone.pid)
    try:
        with pytest.raises(TimeoutError, match=r"^host-asan: .*its process has exited"):
            port.batch([], SILENCE_S)
    finally:
        port.close()
        os.close(master)
