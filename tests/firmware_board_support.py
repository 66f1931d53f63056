"""Helpers for the board-layer and build tests (no tests here).

``QemuBoard`` runs a firmware image under ``qemu-system-arm -M netduinoplus2`` with its host
link on a pty and the QEMU monitor on a unix socket, so a test can both talk the protocol and
read the image's RAM and peripheral registers (``read_word``) while the machine is stopped
(``paused``): two values read in one pause come from the same instant of virtual time.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial

from masking_lab.device import protocol as proto

REPO = Path(__file__).resolve().parents[1]
FIRMWARE = REPO / "firmware"


def require_tools(*tools: str) -> None:
    """Skip (locally) or fail (under CI, ``CI`` set) when a tool is not installed."""
    absent = [t for t in tools if shutil.which(t) is None]
    if absent:
        hint = "apt-get install gcc-arm-none-eabi qemu-system-arm"
        why = f"{', '.join(absent)} not installed ({hint})"
        if os.environ.get("CI"):
            pytest.fail(f"CI must run the firmware board tests, but {why}")
        pytest.skip(why)


def symbols(elf: Path) -> dict[str, int]:
    """Symbol name → address of an ELF image (arm-none-eabi-nm)."""
    out = subprocess.run(
        ["arm-none-eabi-nm", str(elf)], capture_output=True, text=True, check=True
    ).stdout
    table = {}
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 3:
            table[parts[2]] = int(parts[0], 16)
    return table


class QemuBoard:
    """One QEMU netduinoplus2 running ``elf``; use as a context manager."""

    def __init__(self, elf: Path, icount: str | None = "shift=auto") -> None:
        require_tools("qemu-system-arm", "arm-none-eabi-nm")
        self.elf = elf
        self.icount = icount
        self.symbols = symbols(elf)
        self._dir = Path(os.environ.get("TMPDIR", "/tmp"))
        self._mon_path = self._dir / f"ml-qemu-mon-{os.getpid()}-{id(self)}.sock"
        self.proc = subprocess.Popen(
            [
                *("nice", "-n", "-5"),  # as firmware_support.QEMU_CMD: a real-time device
                *("qemu-system-arm", "-M", "netduinoplus2"),
                *(("-icount", self.icount) if self.icount else ()),
                *("-display", "none", "-monitor", f"unix:{self._mon_path},server,nowait"),
                *("-serial", "pty", "-serial", "pty", "-kernel", str(elf)),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        try:
            self._start()
        except BaseException:
            self.close()
            raise

    def _start(self) -> None:
        ports: list[str] = []
        while len(ports) < 2:
            line = self.proc.stdout.readline()
            assert line, "qemu-system-arm exited before opening its serial ports"
            found = re.search(r"(/dev/pts/\d+)", line)
            if found:
                ports.append(found.group(1))
        self.ser = serial.Serial(ports[0], timeout=0.05)
        self.interlock = serial.Serial(ports[1], timeout=0.05)
        self.seq = 0
        self._buf = b""
        self.events: list[proto.Frame] = []
        self._connect_monitor()
        self._wait_answering()

    # --- protocol ---------------------------------------------------------------------------
    def _wait_answering(self, timeout: float = 20.0) -> None:
        """QEMU's pty drops bytes until it notices the peer: PING until a reply comes."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with contextlib.suppress(TimeoutError):
                self.call("PING", timeout=0.3)
                return
        raise TimeoutError(f"QEMU image {self.elf} never answered")

    def _frame(self, deadline: float, what: str) -> proto.Frame | None:
        """The next decodable frame (None for an unframed line)."""
        while b"\n" not in self._buf:
            if time.monotonic() > deadline:
                raise TimeoutError(f"no {what} in time")
            self._buf += self.ser.read(max(1, self.ser.in_waiting))
        line, _, self._buf = self._buf.partition(b"\n")
        try:
            return proto.decode(line + b"\n")
        except proto.FrameError:
            return None

    def call(self, name: str, timeout: float = 3.0, **fields) -> dict[str, str]:
        """Send a command; the fields of its OK reply (ERR fails the test).

        Events that arrive meanwhile are kept in ``self.events``.
        """
        frame = self.answer(name, timeout, **fields)
        assert frame.name == "OK", f"{name} answered {frame}"
        return dict(frame.fields)

    def answer(self, name: str, timeout: float = 3.0, **fields) -> proto.Frame:
        """Send a command; its reply, OK or ERR (events meanwhile go to ``self.events``)."""
        self.seq += 1
        self.ser.write(proto.encode_command(self.seq, name, fields))
        deadline = time.monotonic() + timeout
        while True:
            frame = self._frame(deadline, f"reply to {name}")
            if frame is not None and frame.kind == "event":
                self.events.append(frame)
            elif frame is not None and frame.kind == "reply" and frame.seq == self.seq:
                return frame

    def event(self, name: str, timeout: float = 10.0) -> proto.Frame:
        """The next ``name`` event (one seen already first), PINGing so the watchdog stays fed."""
        for i, frame in enumerate(self.events):
            if frame.name == name:
                return self.events.pop(i)
        deadline = time.monotonic() + timeout
        while True:
            self.call("PING", timeout=max(0.5, deadline - time.monotonic()))
            for i, frame in enumerate(self.events):
                if frame.name == name:
                    return self.events.pop(i)
            if time.monotonic() > deadline:
                raise TimeoutError(f"no {name} event within {timeout} s: {self.events}")
            time.sleep(0.05)

    # --- monitor ----------------------------------------------------------------------------
    def _connect_monitor(self) -> None:
        deadline = time.monotonic() + 10
        while True:
            try:
                self.mon = socket.socket(socket.AF_UNIX)
                self.mon.connect(str(self._mon_path))
                break
            except OSError:
                self.mon.close()
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.05)
        self._hmp("")  # banner and first prompt

    def _hmp(self, command: str) -> str:
        if command:
            self.mon.sendall(command.encode() + b"\n")
        out = b""
        while not out.endswith(b"(qemu) "):
            chunk = self.mon.recv(4096)
            assert chunk, "QEMU monitor closed"
            out += chunk
        return out.decode(errors="replace")

    def read_word(self, addr: int) -> int:
        """A 32-bit word of guest memory or a peripheral register (monitor ``xp``)."""
        out = self._hmp(f"xp /1wx {addr:#x}")
        return int(re.findall(r":\s*(0x[0-9a-fA-F]+)", out)[-1], 16)

    def read_cstring(self, addr: int, limit: int = 32) -> str:
        """A NUL-terminated ASCII string of guest memory."""
        out = self._hmp(f"xp /{limit}bx {addr:#x}")
        rows = re.findall(r"^[0-9a-fA-F]+:((?:\s+0x[0-9a-fA-F]{2})+)", out, re.MULTILINE)
        data = bytes(int(h, 16) for row in rows for h in row.split())
        return data.split(b"\0", 1)[0].decode("ascii")

    def symbol_word(self, name: str) -> int:
        return self.read_word(self.symbols[name])

    @contextlib.contextmanager
    def paused(self) -> Iterator[None]:
        """The virtual machine stopped: everything read inside is one instant."""
        self._hmp("stop")
        try:
            yield
        finally:
            self._hmp("cont")

    def close(self) -> None:
        for name in ("ser", "interlock", "mon"):
            with contextlib.suppress(OSError, AttributeError):
                getattr(self, name).close()
        if self.proc.poll() is None:
            self.proc.terminate()
        self.proc.communicate(timeout=10)
        with contextlib.suppress(FileNotFoundError):
            self._mon_path.unlink()

    def __enter__(self) -> QemuBoard:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
