"""The session loop's frame: signals held back during writes, faults, zeroed outputs, closing.

Every session kind's loop (:mod:`masking_lab.session.runner` for thresholds,
:mod:`masking_lab.usertest.runner` for the user test) is a :class:`SessionShell`: it appends
fsynced records with SIGINT/SIGTERM/SIGHUP held back, and turns every way a session can stop into
a ``fault`` record, zeroed outputs and a resume hint. Opening and resuming are in
:mod:`masking_lab.session.opening` and :mod:`masking_lab.session.resuming`, called in order by
:mod:`masking_lab.session.frame`.

Exit codes: :data:`EXIT_COMPLETED` 0, :data:`EXIT_DEVICE_FAULT` 3, :data:`EXIT_INTERRUPTED` 130.
"""

from __future__ import annotations

import datetime as dt
import shlex
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import Any, Generic, Protocol, TypeVar

from masking_lab.core.clock import Clock
from masking_lab.core.errors import DeviceError, LogWriteError, MaskingLabError, ResponderError
from masking_lab.device.base import Device, DeviceIdentity
from masking_lab.formats.session_log import SessionLogWriter
from masking_lab.session.progress import ProgressLine

EXIT_COMPLETED = 0
EXIT_DEVICE_FAULT = 3
EXIT_INTERRUPTED = 130


class Closable(Protocol):
    """Anything with ``close()``: both runners' responders (they share no other base)."""

    def close(self) -> None: ...


ResultT = TypeVar("ResultT")


def resume_command(log_path: Path, device_spec: str, device_config: Path | None) -> str:
    """The command that resumes a session, with what resume cannot take from the log.

    A log header is data: resume never opens the serial port or the rig config it names, so
    the hint repeats them (quoted for a POSIX shell).

    Parameters
    ----------
    log_path : Path
        The session log.
    device_spec : str
        The device spec the session runs on.
    device_config : Path or None
        The rig config in force (None: the packaged reference rig).

    Examples
    --------
    >>> print(resume_command(Path("S01.jsonl"), "serial:/dev/ttyACM0", Path("my rig.yaml")))
    masking-lab resume S01.jsonl --device serial:/dev/ttyACM0 --device-config 'my rig.yaml'
    >>> resume_command(Path("log.jsonl"), "emulator", None)
    'masking-lab resume log.jsonl'
    """
    words = ["masking-lab", "resume", str(log_path)]
    if device_spec.startswith("serial:"):
        words += ["--device", device_spec]
    if device_config is not None:
        words += ["--device-config", str(device_config)]
    return " ".join(shlex.quote(w) for w in words)


# --------------------------------------------------------------------------------------------
# The session loop's frame: signals, faults, closing


class SessionShell(Generic[ResultT]):
    """Runs a session body and turns every way it can stop into a log record and a result.

    Subclasses set ``clock``, ``device``, ``responder``, ``writer`` and ``out`` (through
    ``__init__``) and provide :meth:`_result`, :meth:`_where_text` and :meth:`_position`; their
    ``run()`` calls :meth:`run_guarded` with the body.

    Attributes
    ----------
    signals : SessionSignals
        Installed while the body runs; :meth:`_append` holds signals back during a write.
    """

    def __init__(
        self,
        *,
        clock: Clock,
        device: Device,
        responder: Closable,
        writer: SessionLogWriter,
        out: ProgressLine,
    ) -> None:
        self.clock = clock
        self.device = device
        self.responder = responder
        self.writer = writer
        self.out = out
        self.signals = SessionSignals()
        self.resume_command = f"masking-lab resume {shlex.quote(str(writer.path))}"

    # -- what a subclass says ---------------------------------------------------------------

    def _result(self, code: int, message: str) -> ResultT:
        """The result for exit ``code`` with the experimenter's ``message`` ('' if completed)."""
        raise NotImplementedError

    def _where_text(self) -> str:
        """Where the session is, for messages: e.g. ``set A, trial 3``."""
        raise NotImplementedError

    def _position(self) -> tuple[str | None, int | None]:
        """``(set_id, trial_index)`` for fault records."""
        raise NotImplementedError

    # -- the frame --------------------------------------------------------------------------

    def run(self) -> ResultT:
        """Run the session to its end; a subclass calls :meth:`run_guarded` with its body."""
        raise NotImplementedError(f"{type(self).__name__} must define run()")

    def run_guarded(self, body: Callable[[], None]) -> ResultT:
        """Run ``body`` under :class:`SessionSignals`, then log ``session_end``.

        A device fault returns exit code 3 and an interruption 130, each after zeroing the
        outputs and logging a ``fault``; any other error is logged and re-raised. The device,
        the responder and the log are closed in every case.
        """
        try:
            with self.signals:
                body()
                self._append(
                    {"record": "session_end", "status": "completed", "ended_utc": utc_now()}
                )
            self.out.clear()
            return self._result(EXIT_COMPLETED, "")
        except (DeviceError, ResponderError) as exc:
            stopped = self._stop_device()
            kind = fault_kind(exc)
            note = (
                "outputs zeroed"
                if stopped
                else "the device did not take the stop command; its watchdog zeroes the outputs"
            )
            self._fault(kind, f"{exc} ({note})")
            message = (
                f"device fault ({kind}) in {self._where_text()}: {exc}. "
                f"{note[0].upper() + note[1:]}. Check the device and cable, then resume with: "
                f"{self.resume_command}"
            )
            self.out.message(message)
            return self._result(EXIT_DEVICE_FAULT, message)
        except KeyboardInterrupt as exc:
            self._stop_device()
            name = (
                exc.args[0]
                if isinstance(exc, SessionInterrupted)
                else "the keyboard (Ctrl-C, or Escape in the participant window)"
            )
            self._fault("interrupted", f"interrupted by {name}; outputs zeroed")
            message = (
                f"interrupted in {self._where_text()}; nothing logged is lost. "
                f"Resume with: {self.resume_command}"
            )
            self.out.message(message)
            return self._result(EXIT_INTERRUPTED, message)
        except MaskingLabError as exc:
            self._stop_device()
            self._fault("log_write" if isinstance(exc, LogWriteError) else "error", str(exc))
            self.out.message(f"stopped: {exc}. Fix it, then resume with: {self.resume_command}")
            raise
        except BaseException as exc:
            self._stop_device()
            self._fault("crash", f"{type(exc).__name__}: {exc}")
            raise
        finally:
            close_quietly(self.device, self.responder)
            self.writer.close()

    def _append(self, record: dict[str, Any]) -> None:
        """Append ``record`` to the log; SIGINT/SIGTERM wait until it is on disk."""
        with self.signals.deferred():
            self.writer.append(record)

    def _fault(self, kind: str, message: str) -> None:
        """Log a ``fault`` record at the current position and clock time (s)."""
        set_id, trial_index = self._position()
        record = drop_none(
            {
                "record": "fault",
                "kind": kind,
                "message": message,
                "set_id": set_id,
                "trial_index": trial_index,
                "t_s": self.clock.now(),
            }
        )
        try:
            self.writer.append(record)
        except (OSError, ValueError, LogWriteError) as exc:  # the disk failed: say so, go on
            print(f"could not log the fault ({exc}): {message}", file=sys.stderr)

    def _stop_device(self) -> bool:
        """Zero the outputs; False if the device did not take the command."""
        try:
            self.device.stop()
            return True
        except Exception:  # a dead device cannot stop; its watchdog does
            return False


def fault_kind(exc: DeviceError | ResponderError) -> str:
    """The fault record's ``kind`` for a device or responder error."""
    kind = getattr(exc, "kind", None)
    if isinstance(kind, str) and kind:
        return kind
    for cls in type(exc).__mro__:
        if cls.__name__ in _FAULT_KINDS:
            return _FAULT_KINDS[cls.__name__]
    return "device"


# Error classes (masking_lab.core.errors) → fault kinds in the log; most specific class first wins.
_FAULT_KINDS = {
    "SafetyLimitError": "safety_limit",
    "DeviceTimeoutError": "timeout",
    "DeviceDisconnectedError": "disconnected",
    "DeviceProtocolError": "garbage",
    "DeviceFaultError": "device_fault",
    "ResponderError": "responder",
}


def close_quietly(device: Device, responder: Closable) -> None:
    """Close the device, then the responder; report (not raise) errors while closing."""
    for close in (device.close, responder.close):
        try:
            close()
        except Exception as exc:  # closing must not hide the real outcome
            print(f"warning: while closing: {exc}", file=sys.stderr)


def drop_none(record: dict[str, Any]) -> dict[str, Any]:
    """``record`` without None values, except the keys whose null is meaningful in the log."""
    keep_null = {"level_db_sl", "at_bound", "set_id", "trial_index"}
    return {k: v for k, v in record.items() if v is not None or k in keep_null}


def device_record(identity: DeviceIdentity) -> dict[str, Any]:
    """The log's record of a device: back-end, model, serial, firmware, port, max drive (V)."""
    record = {
        "backend": identity.backend,
        "model": identity.model,
        "serial_number": identity.serial_number,
        "firmware_version": identity.firmware_version,
        "port": identity.port,
        "max_drive_v": {k: float(v) for k, v in identity.limits.max_drive_v.items()},
    }
    if identity.details:  # build hash, reset cause, converter (serial); watchdog support (NI)
        record["details"] = dict(identity.details)
    return record


def utc_now() -> str:
    """The current UTC time as ``YYYY-MM-DDTHH:MM:SSZ``."""
    return dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


# --------------------------------------------------------------------------------------------
# Signals


class SessionInterrupted(KeyboardInterrupt):
    """SIGINT, SIGTERM or SIGHUP arrived during a session."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(signal.Signals(signum).name)


class SessionSignals:
    """SIGINT/SIGTERM/SIGHUP raise :class:`SessionInterrupted`, except while a record is written.

    (SIGHUP: the experimenter's terminal closed.)
    """

    def __init__(self) -> None:
        self._previous: dict[int, Any] = {}
        self._deferring = False
        self._pending: int | None = None

    def __enter__(self) -> SessionSignals:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self._deferring:
            self._pending = signum
            return
        raise SessionInterrupted(signum)

    @contextmanager
    def deferred(self) -> Iterator[None]:
        """A context in which signals wait: use it around each log write. A signal is raised
        when the block ends (unless the block raised)."""
        self._deferring = True
        try:
            yield
        finally:
            self._deferring = False
            pending, self._pending = self._pending, None
        if pending is not None:
            raise SessionInterrupted(pending)


# --------------------------------------------------------------------------------------------
# Clocks
