"""Device implementations behind one interface, for the conformance tests (no tests here).

Three implementations of docs/device-protocol.md: the Python emulator on its pty, the C
firmware built for the host (``firmware/build/host/masking-fw``) and the STM32 image under
``qemu-system-arm -M netduinoplus2``. Each is started fresh, reached through a real pty, and
can open/close its interlock input. The firmware is built once per test session with make;
a missing compiler or QEMU skips those targets locally but fails under CI (``CI`` set).
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import os
import re
import shutil
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial

from masking_lab.device import protocol as proto
from masking_lab.device.config import parse_device_config
from masking_lab.device.emulator import FirmwareEmulator
from masking_lab.device.emulator_checks import Converter

REPO = Path(__file__).resolve().parents[1]
FIRMWARE = REPO / "firmware"
HOST_FW = FIRMWARE / "build" / "host" / "masking-fw"
HOST_ASAN_FW = FIRMWARE / "build" / "host-asan" / "masking-fw"  # ASan + UBSan
QEMU_FW = FIRMWARE / "build" / "qemu" / "masking-fw.elf"
# The QEMU image built with the shared rig's limits and the 0/20/40 dB attenuator steps of the
# emulator and the host build (target "qemu-att"): the three are then configured alike, so the
# linear-range frames at the deepest steps must get the same answers (HELLO lin 1798 each).
QEMU_ATT_BUILD = FIRMWARE / "build" / "att"
QEMU_ATT_FW = QEMU_ATT_BUILD / "qemu" / "masking-fw.elf"
QEMU_ATT_OPTIONS = {
    "ATT_STEPS_DB": "0,20,40",
    "LIMIT_EV_UV": "2500000",
    "LIMIT_MV_UV": "8000000",
    # longer than the rig's 300 ms: under -icount auto a host that deschedules QEMU makes its
    # clock jump on resuming, which tripped the host-quiet watchdog mid-episode in the rt corpus
    # (a real-time artefact, 3-4 per 20,000 frames, that could turn an AMP into ERR STATE)
    "WATCHDOG_MS": "2000",
    "SERIAL_NUMBER": "T-42",
}
TARGETS = ("emulator", "host", "qemu")
# How long a test waits for a frame before calling the device hung (wall clock): a hang guard,
# not a timing check. QEMU starved of CPU by a busy suite took over 2 s to finish a frame.
REPLY_WAIT_S = 10.0
# -icount: the guest clock follows executed instructions, so device-reported times are
# consistent even when the host is loaded; serial0 = host link, serial1 = interlock line.
# nice -5 (as root; GNU nice runs the command unchanged where it may not): the emulated board is
# a real-time device, and a CPU-bound test worker beside it stretched its frames past the board's
# host watchdog in CI. Idle, QEMU uses ~20 % of a core, so the others keep theirs.
QEMU_CMD = ["nice", "-n", "-5", "qemu-system-arm", "-M", "netduinoplus2", "-icount", "shift=auto"]
QEMU_CMD += ["-display", "none", "-monitor", "none", "-serial", "pty", "-serial", "pty"]

# The emulator and the host build get the same limits; the QEMU image has the compiled-in
# reference limits (EV 5 V, MV 10 V) and watchdog (500 ms).
RIG = """\
schema_version: 1
channels:
  EV: {max_drive_v: 2.5}
  MV: {max_drive_v: 8}
serial: {reply_timeout_s: 0.5, watchdog_s: 0.3}
waveform: {sample_rate_hz: 10000, ramp_s: 0.002}
emulator: {model: TEST-EMU, serial_number: T-42, onset_jitter_s: 0.00005}
"""
HOST_ARGS = ["--wd-ms", "300", "--max-ev", "2.5", "--max-mv", "8", "--fs", "10000"]
HOST_ARGS += ["--ramp-us", "2000", "--sn", "T-42"]


def played(volts: float, att_db: int = 0) -> float:
    """What a request plays on every implementation's default converter (12 bits, ±10 V), V.

    The amplitude in whole LSBs (1 LSB = 4.8828125 mV at 0 dB) and back, to the µV: what
    DONE's tamp/mamp and DIAG's ev/mv report for a request of ``volts``.
    """
    dac = Converter(12, 10_000_000)
    return dac.played_uv(dac.code(round(volts * 1e6), att_db), att_db) / 1e6


def rig_config():
    return parse_device_config(RIG, "conformance rig")


def _missing(tools: list[str]) -> str | None:
    absent = [t for t in tools if shutil.which(t) is None]
    return ", ".join(absent) or None


@contextlib.contextmanager
def build_lock() -> Iterator[None]:
    """Hold the firmware build folder's lock: parallel test workers (pytest-xdist) share it."""
    lock = FIRMWARE / "build" / ".lock"
    lock.parent.mkdir(parents=True, exist_ok=True)
    with lock.open("w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        yield


@functools.cache
def _make(target: str) -> str | None:
    """Build one firmware target; the reason it cannot be built, or None."""
    tools = {"host": ["make", "gcc"], "host-asan": ["make", "gcc"]}
    tools["qemu"] = tools["qemu-att"] = ["make", "arm-none-eabi-gcc", "qemu-system-arm"]
    absent = _missing(tools[target])
    if absent:
        return f"{absent} not installed (apt-get install gcc-arm-none-eabi qemu-system-arm make)"
    args = [target]
    if target == "qemu-att":
        args = [
            f"BUILD={QEMU_ATT_BUILD}",
            "qemu",
            *(f"{k}={v}" for k, v in QEMU_ATT_OPTIONS.items()),
        ]
    with build_lock():
        proc = subprocess.run(
            ["make", "-C", str(FIRMWARE), "-j2", *args],
            capture_output=True,
            text=True,
            timeout=300,
        )
    if proc.returncode != 0:
        pytest.fail(f"make -C firmware {target} failed:\n{proc.stdout}\n{proc.stderr}")
    return None


def require_build(target: str) -> None:
    """Build ``target`` (host/qemu) or skip — or fail under CI, where the tools must exist."""
    if target == "emulator":
        return
    why = _make(target)
    if why:
        if os.environ.get("CI"):
            pytest.fail(f"CI must run the {target} firmware tests, but {why}")
        pytest.skip(f"{target} firmware not testable here: {why}")


class Device:
    """One running implementation: its port, interlock control and cleanup."""

    name: str
    port: str
    vt: bool

    def set_interlock(self, is_open: bool) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class EmulatorDevice(Device):
    def __init__(self, *, virtual_time: bool = False, seed: int = 0, **options) -> None:
        self.name, self.vt = "emulator", virtual_time
        self.emu = FirmwareEmulator(
            rig_config(), virtual_time=virtual_time, seed=seed, **options
        ).start()
        self.port = self.emu.port

    @classmethod
    def from_config(cls, config, **options) -> EmulatorDevice:
        """An emulator with another device config than the shared rig's."""
        dev = cls.__new__(cls)
        dev.name, dev.vt = "emulator", bool(options.get("virtual_time"))
        dev.emu = FirmwareEmulator(config, **options).start()
        dev.port = dev.emu.port
        return dev

    def set_interlock(self, is_open: bool) -> None:
        self.emu.set_interlock(is_open)

    def close(self) -> None:
        self.emu.close()


class HostFirmware(Device):
    def __init__(self, *args: str, binary: Path = HOST_FW) -> None:
        self.name, self.vt = "host", "--virtual-time" in args
        self.proc = subprocess.Popen(
            [str(binary), *HOST_ARGS, *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.port = self.proc.stdout.readline().strip()
        assert self.port.startswith("/dev/"), self.proc.stderr.read()

    def set_interlock(self, is_open: bool) -> None:
        self.proc.send_signal(signal.SIGUSR1 if is_open else signal.SIGUSR2)

    def close(self) -> str:
        """Stop the process; its stderr (sanitizer reports land there)."""
        if self.proc.poll() is None:
            self.proc.terminate()
        return self.proc.communicate(timeout=10)[1]


class QemuFirmware(Device):
    def __init__(self, elf: Path = QEMU_FW) -> None:
        self.name, self.vt = "qemu", False
        self.proc = subprocess.Popen(
            [*QEMU_CMD, "-kernel", str(elf)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        ports: list[str] = []
        while len(ports) < 2:
            line = self.proc.stdout.readline()
            assert line, "qemu-system-arm exited before opening its serial ports"
            found = re.search(r"(/dev/pts/\d+)", line)
            if found:
                ports.append(found.group(1))
        self.port, interlock_port = ports
        # QEMU's serial1 is the image's interlock line: 'o' opens it, 'c' closes it.
        self.interlock = serial.Serial(interlock_port, timeout=0.05)
        _wait_until_answering(self.port)

    def set_interlock(self, is_open: bool) -> None:
        self.interlock.write(b"o" if is_open else b"c")

    def close(self) -> None:
        self.interlock.close()
        if self.proc.poll() is None:
            self.proc.terminate()
        self.proc.communicate(timeout=10)


def _wait_until_answering(port: str, timeout: float = 10.0) -> None:
    """QEMU's pty drops bytes until it notices the peer: PING until a reply comes back."""
    with serial.Serial(port, timeout=0.05) as ser:
        deadline = time.monotonic() + timeout
        buf = b""
        while time.monotonic() < deadline:
            ser.write(proto.encode_command(60000, "PING"))
            # The image answers ~0.4 s after QEMU opens its ports: asking every 50 ms instead
            # of every 300 ms halves the wait at each of the suite's ~60 QEMU starts.
            end = time.monotonic() + 0.05
            while time.monotonic() < end:
                buf += ser.read(256)
                if b"60000 OK" in buf:
                    time.sleep(0.1)
                    ser.reset_input_buffer()
                    return
        raise TimeoutError(f"QEMU firmware on {port} never answered")


def start(target: str, *, host_args: tuple[str, ...] = (), **kwargs) -> Device:
    """Start a fresh ``target`` (building it first); close it with ``.close()``.

    ``target`` is ``emulator``, ``host``, ``host-asan`` (the host build under ASan+UBSan),
    ``qemu`` or ``qemu-att`` (the QEMU image with the shared rig's limits and 0/20/40 dB
    steps); ``host_args`` go to the host builds only, other keyword options to the emulator
    (``virtual_time`` and ``seed`` to both).
    """
    require_build(target)
    if target == "emulator":
        return EmulatorDevice(**kwargs)
    if target in ("host", "host-asan"):
        args = ["--virtual-time"] if kwargs.get("virtual_time") else []
        if "seed" in kwargs:
            args += ["--seed", str(kwargs["seed"])]
        binary = HOST_FW if target == "host" else HOST_ASAN_FW
        return HostFirmware(*args, *host_args, binary=binary)
    if target == "qemu-att":
        return QemuFirmware(QEMU_ATT_FW)
    return QemuFirmware()


class Link:
    """The host end of a device's pty, raw: pyserial plus hand-built frames."""

    def __init__(self, port: str) -> None:
        self.ser = serial.Serial(port, timeout=0.02)
        self.seq = 0
        self.buf = b""
        self.events: list[proto.Frame] = []
        self.garbage: list[bytes] = []  # unframed lines (boot chatter), in order

    def send(self, name: str, **fields) -> int:
        self.seq += 1
        self.ser.write(proto.encode_command(self.seq, name, fields))
        return self.seq

    def frame(self, timeout: float = REPLY_WAIT_S) -> proto.Frame:
        deadline = time.monotonic() + timeout
        while True:
            while b"\n" not in self.buf:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"no frame within {timeout} s (buffer {self.buf!r})")
                self.buf += self.ser.read(max(1, self.ser.in_waiting))
            line, _, self.buf = self.buf.partition(b"\n")
            try:
                return proto.decode(line + b"\n")
            except proto.FrameError:
                self.garbage.append(line)

    def frames_until(self, predicate, timeout: float = REPLY_WAIT_S) -> list[proto.Frame]:
        """Frames up to and including the first for which ``predicate`` is true."""
        seen: list[proto.Frame] = []
        deadline = time.monotonic() + timeout
        while True:
            f = self.frame(max(0.01, deadline - time.monotonic()))
            seen.append(f)
            if predicate(f):
                return seen

    def quiet_for(self, seconds: float) -> bytes:
        """Everything the device sends in the next ``seconds`` (b"" if it stays quiet)."""
        end = time.monotonic() + seconds
        got = b""
        while time.monotonic() < end:
            got += self.ser.read(max(1, self.ser.in_waiting))
        return got

    def reply(self, seq: int, timeout: float = REPLY_WAIT_S) -> proto.Frame:
        """The reply to ``seq``; events seen on the way are kept in ``self.events``."""
        while True:
            f = self.frame(timeout)
            if f.kind == "event":
                self.events.append(f)
            elif f.seq == seq:
                return f

    def call(self, name: str, **fields) -> proto.Frame:
        return self.reply(self.send(name, **fields))

    def event(
        self, name: str, timeout: float = REPLY_WAIT_S, *, keepalive: bool = False
    ) -> proto.Frame:
        """The next ``name`` event (including one already seen by ``reply``).

        With ``keepalive`` the link PINGs every 50 ms while it waits, as a host must while a
        trial plays, so the device's watchdog stays fed.
        """
        for i, f in enumerate(self.events):
            if f.name == name:
                return self.events.pop(i)
        deadline = time.monotonic() + timeout
        next_ping = time.monotonic()
        while True:
            if keepalive and time.monotonic() >= next_ping:
                self.send("PING")
                next_ping = time.monotonic() + 0.05
            wait = 0.05 if keepalive else max(0.01, deadline - time.monotonic())
            try:
                f = self.frame(wait)
            except TimeoutError:
                if time.monotonic() > deadline:
                    raise
                continue
            if f.kind == "event" and f.name == name:
                return f
            if f.kind == "event":
                self.events.append(f)

    def close(self) -> None:
        self.ser.close()
