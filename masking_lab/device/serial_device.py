"""Host side of the device protocol over pyserial: a :class:`~masking_lab.device.base.Device`.

:class:`SerialDevice` opens the port, waits through a board's reset-on-open with HELLO retries,
takes the stricter of its config limits and the firmware's, maps the device clock to the session
clock (TIME), and then plays trials (PLAY → OK → DONE with actual onsets), streams amplitudes
(SETUP/AMP), keeps the firmware watchdog fed while a trial plays (PING), and stops (STOP).

Every amplitude is checked on the host before it is sent (SafetyLimitError, nothing sent). Every
fault becomes a DeviceError subclass whose message names the port and says what to do; on a
fault the host sends a best-effort STOP and records the fault in :attr:`SerialDevice.fault_log`.
Every number the board sends is checked against its trial (``device.reply_checks``): a
violation is a DeviceProtocolError, nothing logged as played. Timeouts are real-time waits for
a real clock; with a VirtualClock replies are awaited without a deadline load could trip (a
closed link ends the wait at once; ``serial.virtual_hang_guard_s`` guards against a hung peer).
The session clock is only read (a VirtualClock advanced to each trial's end), never slept on.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Callable
from typing import Any, Literal

import serial

from masking_lab.core.clock import Clock, RealClock
from masking_lab.core.errors import (
    DeviceDisconnectedError,
    DeviceError,
    DeviceProtocolError,
    DeviceTimeoutError,
    SafetyLimitError,
)
from masking_lab.core.stimulus import Channel, Stimulus
from masking_lab.device import protocol as proto
from masking_lab.device import reply_checks, safety, serial_checks, serial_faults, serial_link
from masking_lab.device.base import DeviceIdentity, DeviceLimits, PlayResult, TrialPlan
from masking_lab.device.config import DeviceConfig, default_device_config

log = logging.getLogger("masking_lab.device")

RESUME_HINT = serial_faults.RESUME_HINT
#: A DONE onset or end may be this late (or serial.done_margin_s if larger), s.
LATE_TOLERANCE_S = 1.0


class SerialDevice:
    """A masking_lab device on a serial port (a microcontroller, or the emulator's pty).

    Parameters
    ----------
    port : str
        Serial port path, e.g. ``/dev/ttyACM0`` or an emulator's ``/dev/pts/7``.
    config : DeviceConfig, optional
        Host-side limits and serial settings (reference rig if None).
    clock : Clock, optional
        Session clock (a RealClock if None). With a VirtualClock the device must run in
        virtual time (``masking-lab emulate --virtual-time``).
    backend : str
        Recorded in :attr:`identity` (``"serial"`` or ``"emulator"``).
    on_close : callable, optional
        Called once by :meth:`close` after the port is closed (the factory stops its emulator).

    Raises
    ------
    DeviceError
        If the port cannot be opened, the device never answers HELLO within the boot timeout,
        speaks another protocol version, or runs in the other time mode than the clock.
    """

    def __init__(
        self,
        port: str,
        config: DeviceConfig | None = None,
        clock: Clock | None = None,
        *,
        backend: str = "serial",
        on_close: Callable[[], None] | None = None,
    ) -> None:
        self.port = port
        self.config = config or default_device_config()
        self.clock: Clock = clock or RealClock()
        self.fault_log: list[dict[str, Any]] = []
        self.garbage_lines = 0
        self.stale_replies = 0
        self._settings = self.config.serial
        self._on_close = on_close
        self._lock = threading.RLock()
        # Start numbering at random so a late reply meant for a previous session on the same
        # port (e.g. a runner killed mid-trial) cannot carry the number we are waiting for.
        self._seq = int.from_bytes(os.urandom(2), "little")
        self._buf = bytearray()
        self._checked: tuple[proto.Frame | None, Any] = (None, None)  # last event, parsed
        self._garbage_run = 0
        self._last_garbage = b""
        self._done: dict[int, proto.Done] = {}
        self._aborted: dict[int, proto.Frame] = {}
        self._streams: dict[str, tuple[float, float | None]] = {}
        self._offset_s = 0.0
        self._last_device_t = 0.0
        self._sync_rtt_s = math.inf
        self._dead: str | None = None
        self._closed = False
        self.watchdog_s = 0.0
        self.converters: dict[str, Any] = {}
        self.hello_details: dict[str, Any] = {}
        self.hello: proto.Hello | None = None
        self.emulator: Any = None  # set by the factory when it started an emulator for us
        self._ser = self._open()
        try:
            self.identity = self._handshake(backend)
            self._sync_clock(samples=1 if self.clock.virtual else 5)
        except BaseException:
            self._ser.close()
            if on_close is not None:
                on_close()
            raise
        safety.zero_on_exit(self)

    # ------------------------------------------------------------------ Device interface

    def play_trial(self, plan: TrialPlan, start_s: float) -> PlayResult:
        """Play ``plan`` starting at session time ``start_s`` (s); return after it has ended.

        Raises
        ------
        SafetyLimitError
            An amplitude exceeds the limits in force (nothing sent), or the firmware refused it.
        DeviceError
            Timeout, disconnect, garbage, watchdog or firmware fault (outputs zeroed).
        """
        safety.check_plan(plan, self.identity.limits)
        with self._lock:
            self._check_alive()
            return self._guarded("PLAY", lambda: self._play(plan, start_s))

    def set_amplitude(self, channel: Channel, stimulus: Stimulus, amplitude_v: float) -> None:
        """Stream ``stimulus`` on ``channel`` at peak ``amplitude_v`` V (SETUP once, then AMP).

        While any streamed amplitude is above 0 the firmware watchdog is armed: call this or
        :meth:`keepalive` at least every ``watchdog_s`` s.
        """
        if stimulus.channel != channel:
            raise SafetyLimitError(f"{stimulus} is a {stimulus.channel} stimulus, not {channel}")
        safety.check_amplitude(channel, amplitude_v, self.identity.limits, what=f"{stimulus}")
        with self._lock:
            self._check_alive()
            key = (stimulus.carrier_hz, stimulus.envelope_hz)
            if self._streams.get(channel) == key:
                self._guarded(
                    "AMP", lambda: self._command("AMP", {"ch": channel, "amp": amplitude_v})
                )
                return
            fields = {
                "ch": channel,
                "car": stimulus.carrier_hz,
                "env": stimulus.envelope_hz or 0.0,
                "amp": amplitude_v,
            }
            self._guarded("SETUP", lambda: self._command("SETUP", fields))
            self._streams[channel] = key

    def keepalive(self) -> None:
        """PING the device (feeds its watchdog while streaming)."""
        with self._lock:
            self._check_alive()
            self._guarded("PING", lambda: self._command("PING"))

    def stop(self) -> None:
        """Zero both outputs (STOP); safe to call from another thread during a trial.

        A no-op after a disconnect (the firmware zeroes itself when the link drops). Raises
        DeviceError if a connected device does not confirm.
        """
        if self._closed or self._dead:
            return
        if not self._lock.acquire(timeout=0.05):
            # Another thread is mid-transaction (e.g. a signal during a trial): send STOP without
            # waiting for its reply; that thread discards the reply as stale.
            self._write(proto.encode_command(proto.next_seq(self._seq + 1), "STOP"))
            return
        try:
            self._streams.clear()
            self._command("STOP", events="record")
        finally:
            self._lock.release()

    def close(self) -> None:
        """Zero both outputs (best effort) and release the port. Idempotent."""
        if self._closed:
            return
        try:
            self.stop()
        except DeviceError as exc:
            log.warning("could not send STOP to %s on close: %s", self.port, exc)
        finally:
            self._closed = True
            safety.forget(self)
            self._ser.close()
            if self._on_close is not None:
                self._on_close()

    def __enter__(self) -> SerialDevice:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ trial

    def _play(self, plan: TrialPlan, start_s: float) -> PlayResult:
        if not self.clock.virtual:
            self._sync_clock(samples=1)
        self._streams.clear()  # PLAY takes the outputs over from any stream
        masker = plan.masker
        steps = serial_checks.choose_steps(plan, self.converters, f"device on {self.port}")
        at = start_s + self._offset_s
        fields = serial_checks.play_fields(plan, at, steps)
        self._command("PLAY", fields)
        seq = self._seq
        done = self._wait_done(seq, plan, start_s)
        late = max(LATE_TOLERANCE_S, self._settings.done_margin_s)
        want = serial_checks.expected_done(plan, at, steps, self.converters, late)
        try:
            reply_checks.check_done(done.onsets_s, done.end_s, done.target_v, done.masker_v, want)
        except reply_checks.ReplyError as exc:
            raise DeviceProtocolError(
                f"device on {self.port} reported for PLAY #{seq} what the trial cannot have "
                f"done ({exc}); the trial is not logged as played: check the firmware "
                f"(docs/device-protocol.md), {RESUME_HINT}"
            ) from exc
        onsets = [t - self._offset_s for t in done.onsets_s]
        self.clock.sleep_until(start_s + plan.duration_s)  # jumps a VirtualClock; no-op if real
        return PlayResult(
            planned_onsets_s=plan.planned_onsets_s(start_s),
            actual_onsets_s=onsets,
            played_target_v=done.target_v,
            played_masker_v=done.masker_v,
            extra={
                "device_seq": seq,
                "garbage_lines": self.garbage_lines,
                "requested_target_v": plan.target_amplitude_v,
                "requested_masker_v": plan.masker_amplitude_v if masker else 0.0,
                "target_att_db": steps.target_db,
                "masker_att_db": steps.masker_db,
                # onset lateness in device time, µs: free of the host's clock-offset estimate
                "device_late_us": [
                    round((o - p) * 1e6) for o, p in zip(done.onsets_s, want.onsets_s, strict=True)
                ],
            },
        )

    def _wait_done(self, seq: int, plan: TrialPlan, start_s: float) -> proto.Done:
        """Wait for DONE of PLAY ``seq``, PINGing to keep the watchdog fed."""
        margin = self._settings.done_margin_s
        if self.clock.virtual:
            budget = self._reply_wait_s + margin
        else:
            budget = max(0.0, start_s + plan.duration_s - self.clock.now()) + margin
        deadline = time.monotonic() + budget
        ping_every = self.watchdog_s / 4 if self.watchdog_s > 0 else math.inf
        next_ping = time.monotonic() + ping_every
        while seq not in self._done:
            if seq in self._aborted:
                raise serial_faults.abort_error(self.port, seq, self._aborted.pop(seq))
            now = time.monotonic()
            if now >= deadline:
                raise DeviceTimeoutError(
                    f"device on {self.port} did not report the end of trial PLAY #{seq} within "
                    f"{budget:.2f} s{self._hang_note}: check the cable and power, {RESUME_HINT}"
                )
            if now >= next_ping:
                self._command("PING")
                next_ping = time.monotonic() + ping_every
                continue
            frame = self._read_frame(min(deadline, next_ping), f"DONE of PLAY #{seq}", quiet=True)
            if frame is not None:
                self._dispatch_unsolicited(frame)
        return self._done.pop(seq)

    # ------------------------------------------------------------------ link

    def _open(self) -> serial.Serial:
        poll = min(0.02, self._settings.reply_timeout_s / 4)
        try:
            # A write that blocks (a board that never reads fills the link's buffer) times
            # out rather than hanging the host.
            return serial.Serial(
                self.port,
                baudrate=self._settings.baud_rate,
                timeout=poll,
                write_timeout=self._write_timeout_s,
                exclusive=True,
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            busy = "lock" in str(exc).lower()
            hint = (
                "another program (another masking-lab session?) has it open: close it first"
                if busy
                else "check the cable, the port name (e.g. ls /dev/ttyACM* /dev/ttyUSB*) and "
                "that you may use it (Linux: the dialout group)"
            )
            raise DeviceError(f"cannot open serial port {self.port}: {exc}; {hint}") from exc

    def _handshake(self, backend: str) -> DeviceIdentity:
        s = self._settings
        with self._lock:
            try:
                self._ser.reset_input_buffer()  # bytes left by a previous session are stale
            except (serial.SerialException, OSError) as exc:
                raise self._disconnected("opening", exc) from exc
            boot = max(s.boot_timeout_s, self._reply_wait_s)  # the whole handshake's budget
            give_up = time.monotonic() + boot
            per_try = s.hello_retry_s if s.boot_timeout_s > 0 else self._reply_wait_s
            sent: set[int] = set()
            hello: proto.Frame | None = None
            last_problem: DeviceError | None = None
            while hello is None:
                try:
                    left = max(0.01, give_up - time.monotonic())  # no write outlasts the budget
                    self._set_write_timeout(min(self._write_timeout_s, left))
                    hello = self._command(
                        "HELLO",
                        timeout=min(per_try, max(0.01, give_up - time.monotonic())),
                        events="ignore",
                        accept=sent,
                    )
                except (DeviceTimeoutError, DeviceProtocolError) as exc:
                    last_problem = exc
                    if time.monotonic() >= give_up:
                        break
            self._set_write_timeout(self._write_timeout_s)
            if hello is None:
                raise serial_faults.no_hello_error(
                    self.port, boot, self._last_garbage, s.baud_rate, self._hang_note
                ) from last_problem
        return self._identity_from(hello, backend)

    def _identity_from(self, frame: proto.Frame, backend: str) -> DeviceIdentity:
        try:
            hello = proto.parse_hello(frame)
        except proto.FrameError as exc:
            raise serial_faults.malformed_error(self.port, "HELLO", exc) from exc
        self.hello = hello
        self.converters = serial_checks.accept_hello(
            self.port, hello, self.config, clock_virtual=self.clock.virtual
        )
        self.hello_details = serial_checks.hello_details(hello)
        self.watchdog_s = hello.watchdog_ms / 1000.0
        limits = safety.stricter_limits(self.config.limits, DeviceLimits(dict(hello.max_v)))
        return DeviceIdentity(
            backend=backend,
            model=hello.model,
            serial_number=hello.serial_number,
            firmware_version=hello.firmware,
            port=self.port,
            limits=limits,
            details=self.hello_details,
        )

    def _sync_clock(self, samples: int) -> None:
        """Estimate device time − session time from TIME round trips (keep the fastest)."""
        best_rtt = math.inf
        best_offset = self._offset_s
        for _ in range(samples):
            t0 = self.clock.now()
            frame = self._command("TIME")
            t1 = self.clock.now()
            try:
                device_t = proto.parse_time(frame)
                if device_t < self._last_device_t:  # a device clock never steps back
                    raise proto.FrameError(
                        f"TIME: t={device_t:.6f} s is before the {self._last_device_t:.6f} s "
                        "it reported earlier (the device clock stepped back)"
                    )
            except proto.FrameError as exc:
                raise serial_faults.malformed_error(self.port, "TIME reply", exc) from exc
            self._last_device_t = device_t
            if t1 - t0 < best_rtt:
                best_rtt, best_offset = t1 - t0, device_t - (t0 + t1) / 2
        # A slow round trip (scheduler hiccup) gives a poor estimate: keep the previous one.
        if best_rtt <= 2 * self._sync_rtt_s + 0.0005 or not math.isfinite(self._sync_rtt_s):
            self._offset_s = best_offset
            self._sync_rtt_s = min(self._sync_rtt_s, best_rtt)

    def _command(
        self,
        name: str,
        fields: dict[str, Any] | None = None,
        *,
        timeout: float | None = None,
        events: Literal["raise", "record", "ignore"] = "raise",
        accept: set[int] | None = None,
    ) -> proto.Frame:
        """Send one command and return its OK reply (ERR and faults raise)."""
        self._seq = proto.next_seq(self._seq)
        seq = self._seq
        if accept is not None:
            accept.add(seq)
        try:
            data = proto.encode_command(seq, name, fields)
        except proto.FrameError as exc:  # e.g. a time beyond the frame from a bad clock offset
            raise DeviceProtocolError(
                f"cannot send {name} to the device on {self.port} ({exc}): a value the device "
                f"reported earlier (TIME) is out of range; {RESUME_HINT}"
            ) from exc
        self._write(data)
        wait = self._reply_wait_s if timeout is None else timeout
        deadline = time.monotonic() + wait
        what = f"{name} #{seq}"
        while True:
            frame = self._read_frame(deadline, what, wait_s=wait)
            assert frame is not None
            if frame.kind == "event":
                self._dispatch_unsolicited(frame, events=events)
                continue
            if frame.seq != seq and not (accept and frame.seq in accept):
                self.stale_replies += 1  # the late answer to an earlier, timed-out command
                continue
            if frame.ok:
                # The device reports DONE/ABORTED only after this OK: anything filed under
                # this number before it is a leftover from an earlier session.
                self._done.pop(seq, None)
                self._aborted.pop(seq, None)
                return frame
            raise serial_faults.refusal_error(self.port, name, frame)

    def _dispatch_unsolicited(
        self, frame: proto.Frame, events: Literal["raise", "record", "ignore"] = "raise"
    ) -> None:
        if frame.kind == "reply":
            self.stale_replies += 1
            return
        if frame.name == "DONE":  # fields validated in _read_frame (proto.check_event)
            parsed = self._checked[1] if self._checked[0] is frame else None
            done = parsed if isinstance(parsed, proto.Done) else proto.parse_done(frame)
            self._done[done.seq] = done
            return
        if frame.name == "ABORTED":
            self._aborted[proto.parse_aborted(frame).seq] = frame
            return
        if events == "ignore":
            return
        exc = serial_faults.event_error(self.port, frame)
        if exc is None:
            return
        self._record(exc)
        if events == "raise":
            raise exc

    def _read_frame(
        self, deadline: float, what: str, *, wait_s: float = 0.0, quiet: bool = False
    ) -> proto.Frame | None:
        """Next valid frame before ``deadline`` (monotonic s); garbage is discarded and counted.

        Returns None on timeout if ``quiet``; otherwise raises DeviceTimeoutError.
        """
        while True:
            line = self._read_line(deadline)
            if line is None:
                if quiet:
                    return None
                garbage = (
                    f", after {self._garbage_run} garbled line(s)" if self._garbage_run else ""
                )
                raise DeviceTimeoutError(
                    f"device on {self.port} stopped answering after {wait_s:.2g} s"
                    f"{self._hang_note} (no reply to {what}{garbage}): "
                    f"check the cable and power, {RESUME_HINT}"
                )
            try:
                frame = proto.decode(line)
                if frame.kind == "command":
                    raise proto.FrameError("a device does not send commands")
            except proto.FrameError as exc:
                self._garbage(line, str(exc), what)
                continue
            self._garbage_run = 0
            if frame.kind == "event":
                try:
                    self._checked = (frame, proto.check_event(frame))
                except proto.FrameError as exc:
                    # A valid checksum around a malformed field is not line noise: the
                    # firmware is wrong, so the session stops with a device fault.
                    what = f"{frame.name} event (waiting for {what})"
                    raise serial_faults.malformed_error(self.port, what, exc) from exc
            return frame

    def _garbage(self, line: bytes, why: str, what: str) -> None:
        self.garbage_lines += 1
        self._garbage_run += 1
        self._last_garbage = line
        log.debug("discarded line from %s (%s): %r", self.port, why, line[:60])
        if self._garbage_run > self._settings.max_garbage_lines:
            raise serial_faults.garbage_error(self.port, self._garbage_run, what, line, why)

    def _read_line(self, deadline: float) -> bytes | None:
        while True:
            i = self._buf.find(b"\n")
            if i >= 0:
                line = bytes(self._buf[: i + 1])
                del self._buf[: i + 1]
                return line
            if len(self._buf) > proto.MAX_FRAME_BYTES:
                line, self._buf = bytes(self._buf), bytearray()
                return line  # decodes as too long: counted as garbage
            if time.monotonic() >= deadline:
                return None
            try:
                # pyserial returns b"" on timeout rather than raising: the deadline loop above
                # turns a silent device into a timeout, never into an empty reply.
                chunk = serial_link.read_some(self._ser)
            except (serial.SerialException, OSError, TypeError) as exc:
                raise self._disconnected("reading", exc) from exc
            self._buf += chunk

    @property
    def _reply_wait_s(self) -> float:
        """Reply wait, s: the reply timeout; in virtual time the hang guard (a closed link still
        ends any wait at once: EIO/EOF on read)."""
        s = self._settings
        return (
            max(s.reply_timeout_s, s.virtual_hang_guard_s)
            if self.clock.virtual
            else (s.reply_timeout_s)
        )

    @property
    def _hang_note(self) -> str:
        if not self.clock.virtual:
            return ""
        return " (virtual time: the hang guard serial.virtual_hang_guard_s ran out)"

    @property
    def _write_timeout_s(self) -> float:
        """Longest a write may block, s (the reply timeout: a device reads what it answers)."""
        return max(0.05, self._settings.reply_timeout_s)

    def _set_write_timeout(self, seconds: float) -> None:
        if self._ser.write_timeout != seconds:
            self._ser.write_timeout = seconds

    def _write(self, data: bytes) -> None:
        try:
            serial_link.write_all(self._ser, data)
        except serial.SerialTimeoutException as exc:
            raise serial_faults.write_timeout_error(self.port, self._ser.write_timeout) from exc
        except (serial.SerialException, OSError, TypeError) as exc:
            raise self._disconnected("writing", exc) from exc

    def _disconnected(self, doing: str, exc: BaseException) -> DeviceDisconnectedError:
        self._dead = f"disconnected while {doing} ({exc})"
        return serial_faults.disconnected_error(self.port, doing, exc)

    # ------------------------------------------------------------------ faults

    def _guarded(self, what: str, action: Callable[[], Any]) -> Any:
        """Run ``action``; on any fault make sure both outputs are zero, record it and re-raise."""
        try:
            return action()
        except DeviceError as exc:
            self._record(exc)
            self._emergency_stop()
            raise
        except BaseException:  # KeyboardInterrupt, SystemExit: zero before unwinding
            self._emergency_stop()
            raise

    def _emergency_stop(self) -> None:
        if self._dead:
            return
        try:
            self._streams.clear()
            self._command(
                "STOP", timeout=min(0.25, self._settings.reply_timeout_s), events="record"
            )
        except DeviceError as exc:
            log.error("could not confirm STOP on %s after a fault: %s", self.port, exc)

    def _record(self, exc: DeviceError) -> None:
        entry = {"t_s": self.clock.now(), "kind": type(exc).__name__, "message": str(exc)}
        if not self.fault_log or self.fault_log[-1]["message"] != entry["message"]:
            self.fault_log.append(entry)
            log.warning("%s: %s", entry["kind"], entry["message"])

    def _check_alive(self) -> None:
        if self._closed:
            raise DeviceError(f"device on {self.port} is closed; open it again")
        if self._dead:
            raise DeviceDisconnectedError(
                f"device on {self.port} is {self._dead}: reconnect it, {RESUME_HINT}"
            )
