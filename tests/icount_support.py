"""Instruction counts of frames on the STM32 image under QEMU ``-icount shift=0``.

With ``-icount shift=0`` QEMU's virtual clock advances exactly 1 ns per guest instruction, so
the device clock (µs) that the firmware core reads around its own work measures instructions:
1 µs = 1000 instructions. DIAG reports, since the previous DIAG, the longest command handler
(``hmax_us``), the longest ``fw_poll`` (``pmax_us``) and the longest refill of the output
stage in one main-loop iteration (``omax_us``, over ``rnd_n`` samples rendered in all).
Used by ``tests/test_fw_icount.py`` and ``benchmarks/fw_icount.py``.
"""

from __future__ import annotations

import re
import subprocess
import time

import serial
from firmware_support import QEMU_FW, Link, _wait_until_answering, require_build

from masking_lab.device import protocol as proto

BUDGET = 840_000  # instructions: 5 ms at 168 MHz
QEMU_ICOUNT0 = ["qemu-system-arm", "-M", "netduinoplus2", "-icount", "shift=0"]
QEMU_ICOUNT0 += ["-display", "none", "-monitor", "none", "-serial", "pty", "-serial", "pty"]

AM = dict(tch="EV", tcar=270, tenv=20, tamp=1.5, ti=2, mch="MV", mcar=120, menv=10, mamp=4.0)
PAPER = dict(AM, stim=1.8, gap=0.6, lead=0.2, n=3, at=0)
LONGEST = dict(AM, ti=9, n=9, stim=6.6, gap=0, lead=0.02, at=0)
SHARED = dict(PAPER, mch="EV", tamp=2.0, mamp=2.5)


def _padded(fields: dict, seq: int) -> dict:
    """The same PLAY grown to the 256-byte frame limit with trailing zero decimals."""
    padded = {k: str(v) for k, v in fields.items()}
    keys = ["tcar", "mcar", "stim", "gap", "lead", "tamp", "mamp"]
    while True:
        for k in keys:
            trial = dict(padded)
            trial[k] = trial[k] + ("0" if "." in trial[k] else ".0")
            if len(_frame(seq, "PLAY", trial)) > proto.MAX_FRAME_BYTES:
                return padded
            padded = trial


def _frame(seq: int, name: str, fields: dict) -> bytes:
    body = f"{seq} {name}" + "".join(f" {k}={v}" for k, v in fields.items())
    data = body.encode("ascii")
    return data + b"*%04X\n" % proto.crc16(data)


PADDED = "PLAY 256-byte frame (paper trial)"
FRAMES = {
    "PLAY paper masked AM (3 x 1.8 s)": ("PLAY", PAPER),
    "PLAY longest trial (9 x 6.6 s, AM)": ("PLAY", LONGEST),
    "PLAY target+masker one channel": ("PLAY", SHARED),
    PADDED: ("PLAY", PAPER),  # grown to 256 bytes when sent (the length needs the seq)
    "SETUP AM stream": ("SETUP", dict(ch="MV", car=120, env=10, amp=4.0)),
    "HELLO": ("HELLO", {}),
    "PING": ("PING", {}),
    "STOP": ("STOP", {}),
}


class Qemu:
    def __init__(self) -> None:
        require_build("qemu")
        self.proc = subprocess.Popen(
            [*QEMU_ICOUNT0, "-kernel", str(QEMU_FW)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        ports: list[str] = []
        while len(ports) < 2:
            line = self.proc.stdout.readline()
            if not line:
                raise RuntimeError("qemu-system-arm exited before opening its serial ports")
            found = re.search(r"(/dev/pts/\d+)", line)
            if found:
                ports.append(found.group(1))
        self.port = ports[0]
        self.interlock = serial.Serial(ports[1])  # held open: QEMU blocks on a closed pty
        _wait_until_answering(self.port)
        self.link = Link(self.port)

    def close(self) -> None:
        self.link.close()
        self.interlock.close()
        self.proc.terminate()
        self.proc.communicate(timeout=10)


def measure(
    qemu: Qemu, name: str, fields: dict, *, pad: bool = False, device_s: float = 0.1
) -> dict[str, float]:
    """Counts for one frame, instructions: its handler, the longest fw_poll and refill.

    After the frame the output stage renders for ``device_s`` of the guest's own clock (the
    host keeps the watchdog fed), whatever the host's speed.
    """
    link = qemu.link
    link.call("STOP")
    link.call("DIAG")  # resets the counters
    link.seq += 1
    frame = _frame(link.seq, name, _padded(fields, link.seq) if pad else fields)
    assert len(frame) <= proto.MAX_FRAME_BYTES
    link.ser.write(frame)
    reply = link.reply(link.seq, timeout=10)
    assert reply.kind == "reply", reply
    handler = link.call("DIAG").number("hmax_us") * 1000  # this frame's handler alone
    start = link.call("TIME").number("t")
    while link.call("PING").number("t") - start < device_s:
        time.sleep(0.01)
    diag = link.call("DIAG")
    link.call("STOP")
    return {
        "ok": float(reply.ok),
        "handler": handler,
        "poll": diag.number("pmax_us") * 1000,
        "refill": diag.number("omax_us") * 1000,
        "samples": diag.number("rnd_n"),
    }
