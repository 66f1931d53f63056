"""Serial-frame fuzzing: a scripted device on a real pty answers the host with one mutated
frame (HELLO, TIME, the PLAY reply or its DONE event); the host must end in a DeviceError or a
played trial, never another exception and never a hang."""

from __future__ import annotations

import signal
import sys
import traceback
from pathlib import Path

from fuzz_corpus import NASTY_NUMBERS, Hang, Picker, _choice

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: hardening_support

import contextlib

from hardening_support import QUICK_RIG, ScriptedPeer, raw_frame, short_plan, standard

from masking_lab.core.clock import VirtualClock
from masking_lab.core.errors import DeviceError
from masking_lab.device import protocol as proto
from masking_lab.device.config import parse_device_config
from masking_lab.device.serial_device import SerialDevice

TARGETS = ("HELLO", "TIME", "PLAY", "DONE")
VALUES = (*(v.decode() for v in NASTY_NUMBERS if b" " not in v), "abc", "", "-5", "1.5", "=")
PLAN = short_plan()


def mutate_body(body: str, p: Picker) -> str:
    """One change to a frame body: a field dropped, doubled, renamed or given a bad value."""
    tokens = body.split(" ")
    head, fields = tokens[:2], tokens[2:]
    how = p.int(0, 5)
    if how == 0 and fields:
        del fields[p.int(0, len(fields) - 1)]
    elif how == 1 and fields:
        i = p.int(0, len(fields) - 1)
        key = fields[i].partition("=")[0]
        fields[i] = f"{key}={_choice(p, VALUES)}"
    elif how == 2 and fields:
        fields.append(fields[p.int(0, len(fields) - 1)])
    elif how == 3:
        fields.append(f"{_choice(p, ('on', 'seq', 'x', 'wd_ms', 't'))}={_choice(p, VALUES)}")
    elif how == 4:
        head[0] = _choice(p, ("!1", "0", "65535", "70000", "-1", "!x", head[0] + "0"))
    else:
        head[1] = _choice(p, ("DONE", "ABORTED", "WATCHDOG", "OK", "ERR", "BOOT", "lower"))
    return " ".join([*head, *fields])


def serial_trial(p: Picker, timeout_s: float = 15.0) -> tuple[str, str]:
    """Open a SerialDevice on a peer with one mutated answer and play a trial: (status, detail)."""
    target = _choice(p, TARGETS)
    fix_crc = p.int(0, 4) > 0  # mostly a valid checksum: the fields are what is tested
    choices = [p.int(0, 10_000) for _ in range(8)]

    class Replay:  # the mutation's choices, replayed inside the peer's thread
        def __init__(self) -> None:
            self.i = 0

        def int(self, lo: int, hi: int) -> int:
            value = choices[self.i % len(choices)]
            self.i += 1
            return lo + value % (hi - lo + 1)

    def respond(frame: proto.Frame, events: list[int]) -> list[bytes] | None:
        name = "DONE" if target == "DONE" and frame.name == "PLAY" else frame.name
        if name != target:
            return None
        out = standard(frame, events)
        k = len(out) - 1 if target == "DONE" else 0
        body = out[k][: out[k].rindex(b"*")].decode("ascii")
        bad = mutate_body(body, Replay())
        try:
            line = raw_frame(bad) if fix_crc else bad.encode("ascii", "replace") + b"*0000\n"
        except UnicodeEncodeError:
            line = b"garbage\n"
        return [*out[:k], line, *out[k + 1 :]]

    peer = ScriptedPeer(respond)

    def alarm(signum, frame):  # type: ignore[no-untyped-def]
        raise Hang

    # CPU time (ITIMER_PROF) bounds a spinning exchange whatever the machine's load; a wait
    # with no reply is bounded by a wall clock ten times longer.
    previous = signal.signal(signal.SIGALRM, alarm)
    previous_prof = signal.signal(signal.SIGPROF, alarm)
    signal.setitimer(signal.ITIMER_PROF, timeout_s)
    signal.setitimer(signal.ITIMER_REAL, 10 * timeout_s)
    device = None
    try:
        # a garbled reply is discarded and never answered again: in virtual time the host then
        # waits out the config's hang guard (no wall-clock reply timeout), here 0.3 s
        rig = parse_device_config(QUICK_RIG, "rig")
        device = SerialDevice(peer.port, rig, VirtualClock())
        device.play_trial(PLAN, 1.0)
        return "clean", ""
    except DeviceError:
        return "clean", ""
    except Hang:
        return "hang", f"{target}: no end within {timeout_s:g} s"
    except BaseException:  # any other escape is the finding
        return "traceback", f"{target}: {traceback.format_exc(limit=-3)}"
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.setitimer(signal.ITIMER_PROF, 0)
        signal.signal(signal.SIGALRM, previous)
        signal.signal(signal.SIGPROF, previous_prof)
        if device is not None:
            with contextlib.suppress(DeviceError):
                device.close()
        peer.close()
