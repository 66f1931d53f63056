"""Firmware emulator: our device protocol served on a real pseudo-terminal.

The emulator behaves like the rig's microcontroller: it answers every command with OK/ERR,
enforces its own amplitude limits (independently of the host), plays three-interval trials on
its own clock and reports the actual onsets, streams amplitude updates, zeroes both outputs on
any fault (corrupted frame, over-limit request, any ERR, watchdog, STOP, unplug, close) and
reports faults as framed events. It runs in a background thread (tests, ``--device emulator``)
or as a process (``masking-lab emulate``), and can imitate a board that resets when the port is
opened (``boot_delay_s``) and a set of injected faults (:meth:`FirmwareEmulator.inject`).

Two time modes:

- real time: PLAY is hardware-timed: the emulator waits until each onset and reports when it
  switched the output on (real onset jitter), and renders each trial's buffers with
  :mod:`masking_lab.core.waveforms` like a DAC would;
- virtual time: PLAY completes at once and reports the planned onsets plus a small seeded
  lateness (the documented xorshift32 generator, integer µs, identical to the C firmware's),
  so a simulated study runs thousands of trials through the pty in seconds.

It also models the interlock input (:meth:`FirmwareEmulator.set_interlock`) and answers the
read-only ``DIAG`` command, like ``firmware/`` does.

The host side of the same protocol is :mod:`masking_lab.device.serial_device`.
"""

from __future__ import annotations

import contextlib
import os
import select
import threading
import time
import tty
from pathlib import Path
from types import MappingProxyType
from typing import Any

from masking_lab.core.stimulus import CHANNELS
from masking_lab.device import protocol as proto
from masking_lab.device.config import DeviceConfig, default_device_config
from masking_lab.device.emulator_checks import (
    ONE,
    Checker,
    Converter,
    LimitError,
)
from masking_lab.device.emulator_commands import FIRMWARE_VERSION, EmulatorCommands
from masking_lab.device.emulator_state import (
    OnsetLateness,
    OutputSnapshot,
    PlayState,
    build_hash,
    interlock_text,
)

MAX_FIELDS = 24  # FRAME_MAX_FIELDS of firmware/core/frame.h
HARD_MAX_DRIVE_V = 10.0  # the DAC's range: no config can raise a limit above it
BOOT_BANNER = b"\r\nML bootloader v0.3 ... starting application\r\n"
__all__ = ["FirmwareEmulator", "OutputSnapshot"]

FAULT_KINDS = ("garbage", "bad_crc", "mute", "unplug_on_play")
_OUT_CAP = 1 << 16  # bytes queued for a host that is not reading before output is dropped


class FirmwareEmulator(EmulatorCommands):
    """Emulated two-channel (EV, MV) firmware on a pseudo-terminal.

    Parameters
    ----------
    config : DeviceConfig, optional
        Firmware limits (``channels.*.max_drive_v``), watchdog period, sample rate, model and
        serial number; the reference rig if None.
    virtual_time : bool
        Complete PLAY at once with planned onsets plus seeded lateness (see module doc).
    watchdog_s : float, optional
        Overrides ``config.serial.watchdog_s`` (s; 0 disables).
    boot_delay_s : float
        Imitate a board that resets when opened: for this long after start (and after
        :meth:`reset`) input is discarded, then a bootloader banner is sent.
    seed : int
        Seed of the simulated onset lateness (virtual time; see :class:`OnsetLateness`).
    render_buffers : bool, optional
        Build each trial's sample buffers (default: in real-time mode only).
    log_path : str or Path, optional
        Also append the emulator's event log to this file (fsynced per line).
    interlock_open : bool
        Start with the interlock input open (HV enable off, E-stop pressed or wristband off).
    bits : int
        Converter resolution of both channels, bits (HELLO ``bits_ev``/``bits_mv``).
    fsv_v : float
        Converter full scale of both channels at the amplifier input, V peak.
    att_db : tuple of int
        Attenuator steps the board switches, dB, ascending, first 0 (HELLO ``att``).
    linear_codes : int, optional
        Largest |code| around mid-scale the output stage plays linearly, both channels (HELLO
        ``lin``); None = the reference DAC's fraction 1798/2048 of the half range (1798 codes
        at 12 bits), as the host build and the STM32 image.
    overdrive : float
        Fault injection for tests: scale every rendered sample by this factor after the level
        checks, so the per-sample limit check (``FAULT code=LIMIT``) can be exercised.
    """

    def __init__(
        self,
        config: DeviceConfig | None = None,
        *,
        virtual_time: bool = False,
        watchdog_s: float | None = None,
        boot_delay_s: float = 0.0,
        seed: int = 0,
        render_buffers: bool | None = None,
        log_path: str | Path | None = None,
        interlock_open: bool = False,
        bits: int = 12,
        fsv_v: float = 10.0,
        att_db: tuple[int, ...] = (0, 20, 40),
        linear_codes: int | None = None,
        overdrive: float = 1.0,
    ) -> None:
        self.config = config or default_device_config()
        self.virtual_time = bool(virtual_time)
        self.watchdog_s = float(self.config.serial.watchdog_s if watchdog_s is None else watchdog_s)
        self.boot_delay_s = float(boot_delay_s)
        self.render_buffers = (not virtual_time) if render_buffers is None else render_buffers
        self.limits = {
            ch: min(HARD_MAX_DRIVE_V, self.config.limits.max_drive_v[ch]) for ch in CHANNELS
        }
        top = (1 << (int(bits) - 1)) - 1
        if linear_codes is not None and not 1 <= linear_codes <= top:
            raise ValueError(
                f"linear_codes={linear_codes} must be a whole number of codes in 1..{top} "
                f"for a {bits}-bit converter (omit it for the reference 1798/2048 of the range)"
            )
        self.checker = Checker(
            {ch: round(v * ONE) for ch, v in self.limits.items()},
            {
                ch: Converter(int(bits), round(fsv_v * ONE), int(linear_codes or 0))
                for ch in CHANNELS
            },
            att_db,
            round(self.config.waveform.sample_rate_hz),
        )
        self.overdrive = float(overdrive)
        self.build = build_hash()
        self._lateness = OnsetLateness(seed, round(self.config.emulator.onset_jitter_s * 1e6))
        self._interlock_open = bool(interlock_open)
        self._lock = threading.Lock()
        self._log: list[str] = []
        self._log_file = open(log_path, "a", encoding="utf-8") if log_path else None  # noqa: SIM115
        self._t0 = time.perf_counter()
        self._vt_us = 0  # virtual device clock, integer µs like the C firmware
        self._amp = dict.fromkeys(CHANNELS, 0.0)
        self._stream: dict[str, tuple[float, float | None]] = {}
        self._last_sample = dict.fromkeys(CHANNELS, 0.0)
        self._peak = dict.fromkeys(CHANNELS, 0.0)  # largest |rendered sample| since start, V
        self._play: PlayState | None = None
        self._faults: dict[str, int] = {}
        self._wd_trips = 0
        self._event_no = 0
        self.commands_received = 0  # valid commands handled (tests: "nothing was sent")
        hello = self._hello_fields()
        try:
            proto.encode_ok(proto.SEQ_MODULO - 1, hello)  # the longest seq
        except proto.FrameError:
            raise ValueError(
                f"HELLO would exceed {proto.MAX_FRAME_BYTES} bytes: shorten [emulator] "
                f"serial_number ({hello['sn']!r}) or model, or use fewer att steps"
            ) from None
        self._rx = bytearray()
        self._rx_discard = False  # skipping the tail of an over-long line
        # While the lines of one read are handled, replies queue and go out in one write at
        # the end: in virtual time a PLAY's OK and DONE reach the host in one read.
        self._holding_out = False
        self._out = bytearray()
        self._last_rx = time.perf_counter()
        self._booting_until: float | None = None
        self._requests: list[str] = []
        self._done_requests = threading.Condition(self._lock)
        self._connected = False
        self._running = False
        self._thread: threading.Thread | None = None
        self._master = self._slave = -1
        self._wake_r = self._wake_w = -1
        self.port = ""

    # ---------------------------------------------------------------- public (any thread)

    def start(self) -> FirmwareEmulator:
        """Open the pseudo-terminal (raw mode) and start serving it in a background thread."""
        master, slave = os.openpty()
        tty.setraw(slave)  # a fresh pty echoes and turns \n into \r\n until set raw
        tty.setraw(master)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self._wake_r, self._wake_w = os.pipe()
        self.port = os.ttyname(slave)
        self._connected = self._running = True
        if self.boot_delay_s > 0:
            self._booting_until = time.perf_counter() + self.boot_delay_s
        mode = "virtual" if self.virtual_time else "real"
        self._note(
            f"START port={self.port} fw={FIRMWARE_VERSION} time={mode} "
            f"max_ev={self.limits['EV']:g} max_mv={self.limits['MV']:g} wd_s={self.watchdog_s:g}"
        )
        self._thread = threading.Thread(target=self._serve, name="firmware-emulator", daemon=True)
        self._thread.start()
        return self

    def outputs(self) -> OutputSnapshot:
        """A consistent snapshot of the outputs (thread-safe)."""
        with self._lock:
            return OutputSnapshot(
                MappingProxyType(dict(self._amp)),
                self._play is not None,
                MappingProxyType(dict(self._last_sample)),
                self._connected,
                self._interlock_open,
            )

    def set_interlock(self, open: bool) -> None:
        """Open (True) or close the interlock input; opening zeroes both outputs at once.

        Each change is reported to the host as ``!n INTERLOCK state=open|closed``; while open,
        PLAY, SETUP and AMP get ``ERR INTERLOCK``.
        """
        with self._lock:
            if bool(open) == self._interlock_open:
                return
            self._interlock_open = bool(open)
            state = interlock_text(open)
            if open:
                self._zero("interlock open", aborted_why="INTERLOCK")
            self._note(f"INTERLOCK {state}")
            self._send_event("INTERLOCK", {"state": state})

    def log_lines(self) -> list[str]:
        """The emulator's event log so far: ``"<device s> <EVENT> details"`` lines."""
        with self._lock:
            return list(self._log)

    def inject(self, fault: str, count: int = 1) -> None:
        """Arm a fault for the next ``count`` opportunities.

        ``garbage``: send ``count`` unframed lines before the next reply; ``bad_crc``: corrupt
        the checksum of the next ``count`` frames sent; ``mute``: ignore the next ``count``
        commands, like a hung firmware (the watchdog still runs); ``unplug_on_play``: close the
        port at the first onset of the next PLAY.
        """
        if fault not in FAULT_KINDS:
            raise ValueError(f"unknown fault {fault!r}; choose from {FAULT_KINDS}")
        with self._lock:
            self._faults[fault] = self._faults.get(fault, 0) + int(count)

    def unplug(self) -> None:
        """Close the port as if the cable were pulled (outputs zeroed); waits until done."""
        self._request("unplug")

    def reset(self) -> None:
        """Reset like a board whose port was reopened: outputs zeroed, boot delay, banner."""
        self._request("reset")

    def close(self) -> None:
        """Zero the outputs, close the port and stop the thread. Idempotent."""
        if self._thread is not None and self._thread.is_alive():
            self._request("close")
            self._thread.join(timeout=5)
        with self._lock:
            self._zero("close")
            if self.port and self._master >= 0:
                self._note("CLOSE port closed, outputs at 0 V")
            self._close_fds(wake=True)
            self._running = False
        if self._log_file is not None:
            self._log_file.close()
            self._log_file = None

    def __enter__(self) -> FirmwareEmulator:
        return self if self._running else self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---------------------------------------------------------------- serving thread

    def _request(self, what: str) -> None:
        with self._lock:
            if not self._running or self._thread is None or not self._thread.is_alive():
                if what == "unplug":
                    self._zero("unplug")
                    self._close_fds()
                return
            self._requests.append(what)
            with contextlib.suppress(OSError):
                os.write(self._wake_w, b"x")
            self._done_requests.wait_for(lambda: what not in self._requests, timeout=5)

    def _serve(self) -> None:
        try:
            while self._running:
                timeout = self._next_timeout()
                rlist = [self._wake_r] + ([self._master] if self._connected else [])
                wlist = [self._master] if self._connected and self._out else []
                try:
                    readable, writable, _ = select.select(rlist, wlist, [], timeout)
                except (OSError, ValueError):
                    break  # fds closed under us by close(): stop serving
                if self._wake_r in readable:
                    os.read(self._wake_r, 4096)
                    self._handle_requests()
                    if not self._running:
                        break
                if self._connected and self._master in readable:
                    self._receive()
                if self._connected and (writable or self._out):
                    self._flush()
                self._tick()
        finally:
            with self._lock:
                self._zero("serving thread ended")
                self._done_requests.notify_all()

    def _next_timeout(self) -> float | None:
        now = time.perf_counter()
        due: list[float] = []
        with self._lock:
            if self._play is not None and self._play.steps:
                due.append(self._play.steps[0][0] + self._t0)
            if self._armed() and self.watchdog_s > 0:
                due.append(self._last_rx + self.watchdog_s)
            if self._booting_until is not None:
                due.append(self._booting_until)
        if not due:
            return None
        return max(0.0, min(due) - now)

    def _handle_requests(self) -> None:
        with self._lock:
            requests, self._requests = self._requests, []
            for what in requests:
                if what == "close":
                    self._running = False
                elif what == "unplug":
                    self._unplug_locked("unplug requested")
                elif what == "reset":
                    self._zero("reset")
                    self._rx.clear()
                    self._rx_discard = False
                    self._booting_until = time.perf_counter() + self.boot_delay_s
                    self._note("RESET board reset: outputs zeroed, booting")
            self._done_requests.notify_all()

    def _receive(self) -> None:
        try:
            data = os.read(self._master, 4096)
        except BlockingIOError:
            return
        except OSError as exc:  # EIO: the slave side has gone away entirely
            with self._lock:
                self._unplug_locked(f"read failed ({exc.strerror})")
            return
        with self._lock:
            if self._booting_until is not None:
                return  # a resetting board hears nothing
            self._rx += data
            self._holding_out = True
            try:
                self._handle_lines()
            finally:
                self._holding_out = False
                self._flush_locked()

    def _handle_lines(self) -> None:
        """Handle every complete line received so far (lock held)."""
        while True:
            i = self._rx.find(b"\n")
            if self._rx_discard:  # the rest of a line already reported as too long
                if i < 0:
                    self._rx.clear()
                    break
                del self._rx[: i + 1]
                self._rx_discard = False
                continue
            if i < 0:
                # like the firmware: the 256th byte without a newline is garbage, once
                if len(self._rx) >= proto.MAX_FRAME_BYTES:
                    self._rx.clear()
                    self._rx_discard = True
                    self._fault("FRAME", "line too long without a newline")
                break
            line = bytes(self._rx[: i + 1])
            del self._rx[: i + 1]
            self._handle_line(line)
            if not self._connected:
                break

    def _tick(self) -> None:
        now = time.perf_counter()
        with self._lock:
            if self._booting_until is not None and now >= self._booting_until:
                self._booting_until = None
                self._rx.clear()
                self._rx_discard = False
                self._out += BOOT_BANNER
                self._send_event("BOOT", {"fw": FIRMWARE_VERSION, "rst": "power"})
                self._note("BOOT done")
            self._advance_play(now)
            if self._armed() and self.watchdog_s > 0 and now - self._last_rx > self.watchdog_s:
                quiet_ms = round((now - self._last_rx) * 1000)
                self._note(f"WATCHDOG host quiet for {quiet_ms} ms: outputs zeroed")
                self._wd_trips += 1
                self._zero("watchdog", aborted_why="WATCHDOG")
                self._send_event("WATCHDOG", {"quiet_ms": quiet_ms})

    # ---------------------------------------------------------------- protocol (lock held)

    def _handle_line(self, line: bytes) -> None:
        try:
            frame = proto.decode(line)
        except proto.FrameError as exc:
            self._fault("FRAME", str(exc))
            return
        if frame.kind != "command":
            self._fault("FRAME", f"expected a command, got a {frame.kind}")
            return
        if len(frame.fields) > MAX_FIELDS:  # the firmware's command_t holds no more
            self._fault("FRAME", f"more than {MAX_FIELDS} fields")
            return
        if self._take_fault("mute"):
            return  # a hung firmware neither answers nor feeds its watchdog
        self._last_rx = time.perf_counter()
        self.commands_received += 1
        handler = getattr(self, f"_cmd_{frame.name.lower()}", None)
        if handler is None:
            self._err(frame.seq, "UNKNOWN", f"unknown command {frame.name}")
            return
        try:
            handler(frame)
        except LimitError as exc:
            self._note(f"LIMIT #{frame.seq} {exc}: refused")
            self._err(frame.seq, "LIMIT", str(exc))
        except (proto.FrameError, ValueError) as exc:
            self._err(frame.seq, "ARGS", f"{frame.name}: {exc}")

    def _advance_play(self, now_real: float) -> None:
        play = self._play
        while play is not None and play.steps and play.steps[0][0] + self._t0 <= now_real:
            _, action, k = play.steps.pop(0)
            plan = play.plan
            if action == "on":
                if k + 1 == plan.target_interval:
                    self._amp[plan.target.channel] += plan.target_amplitude_v
                if plan.masker is not None:
                    self._amp[plan.masker.channel] += plan.masker_amplitude_v
                play.actual.append(self._device_now())
                if k == 0 and self._take_fault("unplug_on_play"):
                    self._unplug_locked("unplug injected during PLAY")
                    return
            else:
                self._amp = dict.fromkeys(CHANNELS, 0.0)
            if not play.steps:
                self._play = None
                self._send_done(play, self._device_now())

    # ---------------------------------------------------------------- helpers (lock held)

    def _armed(self) -> bool:
        return self._play is not None or any(v > 0 for v in self._amp.values())

    def _device_now(self) -> float:
        return self._vt_us / 1e6 if self.virtual_time else time.perf_counter() - self._t0

    def _zero(self, why: str, aborted_why: str | None = None) -> None:
        if self._play is not None and aborted_why is not None:
            self._send_event("ABORTED", {"seq": self._play.seq, "why": aborted_why})
        if self._play is not None or any(self._amp.values()):
            self._note(f"ZERO outputs ({why})")
        self._play = None
        self._stream.clear()
        self._amp = dict.fromkeys(CHANNELS, 0.0)

    def _fault(self, code: str, why: str) -> None:
        self._note(f"FAULT {code} {why}: outputs zeroed")
        self._zero(f"fault {code}", aborted_why=code)
        self._send_event("FAULT", {"code": code})

    def _unplug_locked(self, why: str) -> None:
        self._zero(why)
        self._note(f"UNPLUG {why}: port closed, outputs zeroed")
        if self._holding_out:  # what was sent before the cable went reaches the host, as before
            self._flush_locked()
        self._close_fds()

    def _close_fds(self, *, wake: bool = False) -> None:
        self._connected = False
        names = ("_master", "_slave") + (("_wake_r", "_wake_w") if wake else ())
        for name in names:
            fd = getattr(self, name)
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
                setattr(self, name, -1)

    def _take_fault(self, kind: str) -> bool:
        if self._faults.get(kind, 0) > 0:
            self._faults[kind] -= 1
            return True
        return False

    def _ok(self, seq: int, fields: dict[str, Any] | None = None) -> None:
        try:
            frame = proto.encode_ok(seq, fields)
        except proto.FrameError:  # too long: say so rather than go silent (as the C core)
            frame = proto.encode_err(seq, "SIZE", proto.SIZE_TEXT)
        self._send(frame)

    def _err(self, seq: int, code: str, text: str) -> None:
        self._note(f"ERR #{seq} {code} {text}: outputs zeroed")
        self._zero(f"ERR {code}", aborted_why=code)
        self._send(proto.encode_err(seq, code, text))

    def _send_event(self, name: str, fields: dict[str, Any]) -> None:
        self._event_no = proto.next_seq(self._event_no)
        try:
            frame = proto.encode_event(self._event_no, name, fields)
        except proto.FrameError:  # too long: a FAULT rather than silence (as the C core)
            self._event_no = proto.next_seq(self._event_no)
            frame = proto.encode_event(self._event_no, "FAULT", {"code": "SIZE"})
        self._send(frame)

    def _send(self, frame: bytes) -> None:
        while self._take_fault("garbage"):
            self._out += b"\x00\xffnoise " + os.urandom(4).hex().encode() + b"\n"
        if self._take_fault("bad_crc"):
            frame = frame[:-5] + (b"0000" if frame[-5:-1] != b"0000" else b"FFFF") + b"\n"
        if len(self._out) + len(frame) > _OUT_CAP:
            return  # nobody is reading: drop rather than block the firmware loop
        self._out += frame
        if not self._holding_out:
            self._flush_locked()

    def _flush(self) -> None:
        with self._lock:
            self._flush_locked()

    def _flush_locked(self) -> None:
        if not self._connected or not self._out:
            return
        try:
            n = os.write(self._master, self._out)
        except BlockingIOError:
            return
        except OSError:
            self._out.clear()
            return
        del self._out[:n]

    def _note(self, text: str) -> None:
        line = f"{self._device_now():.6f} {text}"
        self._log.append(line)
        if self._log_file is not None:
            self._log_file.write(line + "\n")
            self._log_file.flush()
            os.fsync(self._log_file.fileno())
