"""A scriptable device on the master side of a real pseudo-terminal, for the hardening and fuzz
tests: it answers HELLO, TIME and PLAY like the firmware unless told to misbehave. Also the
host-side rig config and the short trial plan every device test plays."""

from __future__ import annotations

import contextlib
import os
import select
import threading
import tty
from collections.abc import Callable

from masking_lab.core.stimulus import parse_stimulus
from masking_lab.core.trial import TrialPlan
from masking_lab.device import protocol as proto

RIG = """\
schema_version: 1
channels:
  EV: {max_drive_v: 2.5}
  MV: {max_drive_v: 8}
serial:
  reply_timeout_s: 0.2
  done_margin_s: 0.3
  boot_timeout_s: 0
  hello_retry_s: 0.1
  max_garbage_lines: 4
  watchdog_s: 0.3
  virtual_hang_guard_s: 60
waveform: {sample_rate_hz: 10000, ramp_s: 0.002}
"""


def short_plan(**kw) -> TrialPlan:
    """EV270 at 0.5 V in interval 2 under MV120 at 0.3 V, 20 ms stimuli; ``kw`` overrides."""
    base = {
        "target": parse_stimulus("EV270"),
        "target_amplitude_v": 0.5,
        "target_interval": 2,
        "masker": parse_stimulus("MV120"),
        "masker_amplitude_v": 0.3,
        "stimulus_s": 0.02,
        "gap_s": 0.01,
        "lead_in_s": 0.01,
    }
    base.update(kw)
    return TrialPlan(**base)


#: The same rig with a short virtual-time hang guard, for tests whose peer never answers.
QUICK_RIG = RIG.replace("virtual_hang_guard_s: 60", "virtual_hang_guard_s: 0.3")

HELLO = {
    "proto": 2,
    "fw": "fw-2.0.0",
    "build": "0123456789ab",
    "clk": "host",
    "rst": "power",
    # 24 bits over 10 V: an LSB of 1.2 µV, so a peer that echoes the request plays it.
    "bits_ev": 24,
    "bits_mv": 24,
    "fsv_ev": 10.0,
    "fsv_mv": 10.0,
    "att": "0",
    "model": "FAKE",
    "sn": "F1",
    "max_ev": 5.0,
    "max_mv": 10.0,
    "wd_ms": 0,
    "fs": 20000.0,
    "vt": 1,
}


def standard(frame: proto.Frame, events: list[int]) -> list[bytes]:
    """The firmware's answer to ``frame`` (HELLO, TIME, PLAY with its DONE, anything: OK)."""
    if frame.name == "HELLO":
        return [proto.encode_ok(frame.seq, HELLO)]
    if frame.name == "TIME":
        return [proto.encode_ok(frame.seq, {"t": 0.0})]
    if frame.name == "PLAY":
        events[0] += 1
        at = float(frame.fields["at"])
        step = float(frame.fields["stim"]) + float(frame.fields["gap"])
        onsets = [at + float(frame.fields["lead"]) + i * step for i in range(3)]
        done = {
            "seq": frame.seq,
            "on": onsets,
            "end": onsets[-1] + float(frame.fields["stim"]),
            "tamp": float(frame.fields["tamp"]),
            "mamp": float(frame.fields["mamp"]),
        }
        return [proto.encode_ok(frame.seq), proto.encode_event(events[0], "DONE", done)]
    return [proto.encode_ok(frame.seq)]


Responder = Callable[[proto.Frame, list[int]], "list[bytes] | None"]


class ScriptedPeer:
    """Runs ``respond(frame, event_counter)`` for each frame the host sends; None from it
    means the standard answer. Raw bytes in the returned list go out as they are."""

    def __init__(self, respond: Responder | None = None) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        tty.setraw(self.master)
        self.port = os.ttyname(self.slave)
        self.respond = respond or (lambda frame, events: None)
        self._events = [0]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        buf = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.05)
            if not ready:
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
                out = self.respond(frame, self._events)
                for chunk in standard(frame, self._events) if out is None else out:
                    with contextlib.suppress(OSError):
                        os.write(self.master, chunk)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)


def raw_frame(body: str) -> bytes:
    """A frame with a valid checksum around any body (fields the encoder would refuse)."""
    data = body.encode("ascii")
    return data + b"*" + f"{proto.crc16(data):04X}".encode("ascii") + b"\n"
