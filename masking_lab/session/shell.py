"""The imperative shell both session runners share: entry-point checks, opening, resuming, faults.

:mod:`masking_lab.session.runner` (threshold sessions) and :mod:`masking_lab.usertest.runner` (the
user
test) differ in what a session plays, not in how it is framed: both check the participant id
and device spec, open a responder and a device (closing what is open if the next step fails),
create or reopen an fsynced JSON-lines log, continue a resumed session's clock where the log
stopped, hold SIGINT/SIGTERM/SIGHUP back while a record is written, and turn every way a session
can stop into a ``fault`` record, zeroed outputs and a resume hint. That frame lives here, once.

Exit codes: :data:`EXIT_COMPLETED` 0, :data:`EXIT_DEVICE_FAULT` 3, :data:`EXIT_INTERRUPTED` 130.
"""

from __future__ import annotations

import datetime as dt
import math
import re
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import Any, Generic, Protocol, TypeVar

import yaml

from masking_lab import __version__
from masking_lab.core.clock import Clock, RealClock, VirtualClock
from masking_lab.core.errors import DeviceError, LogError, MaskingLabError, ProtocolError
from masking_lab.device.base import Device, DeviceIdentity
from masking_lab.formats.schemas import key_path, schema_errors
from masking_lab.formats.session_log import SessionLog, SessionLogWriter
from masking_lab.session.progress import ProgressLine
from masking_lab.simulation.observer import ground_truth_from_dict

EXIT_COMPLETED = 0
EXIT_DEVICE_FAULT = 3
EXIT_INTERRUPTED = 130

_PARTICIPANT = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
_DEVICE_SPEC = re.compile(r"^(sim|emulator|serial:.+|nidaq(:.+)?)$")

DeviceOpener = Callable[[str, Clock], Device]


class Closable(Protocol):
    """Anything with ``close()``: both runners' responders (they share no other base)."""

    def close(self) -> None: ...


DeviceT = TypeVar("DeviceT", bound=Device)
ResponderT = TypeVar("ResponderT", bound=Closable)
ContextT = TypeVar("ContextT")
ResultT = TypeVar("ResultT")


# --------------------------------------------------------------------------------------------
# Entry-point checks


def check_participant(participant: str) -> str:
    """The participant id, if it can name a data folder.

    Raises
    ------
    MaskingLabError
        Empty, or characters other than letters, digits, ``_``, ``-`` and ``.``.
    """
    if not _PARTICIPANT.match(participant or ""):
        raise MaskingLabError(
            f"--participant {participant!r}: use letters, digits, '_', '-' and '.' only (it "
            "names the participant's data folder), e.g. S01"
        )
    return participant


def check_device_spec(spec: str) -> str:
    """The device spec without surrounding blanks.

    Raises
    ------
    MaskingLabError
        Not ``sim``, ``emulator``, ``serial:PORT`` or ``nidaq[:DEVICE]``.
    """
    if not _DEVICE_SPEC.match(spec.strip()):
        raise MaskingLabError(
            f"--device {spec!r}: choose sim, emulator, serial:PORT (e.g. serial:/dev/ttyACM0) "
            "or nidaq[:DEVICE]"
        )
    return spec.strip()


def use_virtual_clock(device: str, responder: str, real_time: bool) -> bool:
    """True if nothing real waits on the session: a sim responder on a simulated device.

    Then a virtual clock runs the session as fast as the computer can (``real_time`` forbids it).
    """
    if real_time or responder != "sim":
        return False
    return device == "sim" or device == "emulator"


def observer_record(ground_truth: Path | None) -> dict[str, Any]:
    """The simulated observer for the header: ground-truth path, population seed and truth.

    Parameters
    ----------
    ground_truth : Path or None
        A ground-truth YAML or JSON file; None: the shipped simulation ground truth.

    Raises
    ------
    ProtocolError
        Unreadable or malformed, or not a valid ground truth.
    """
    from masking_lab.formats.resources import shipped

    if ground_truth is None:
        text = shipped("protocols", "simulation/ground_truth.yaml").read_text(encoding="utf-8")
        source = "protocols/simulation/ground_truth.yaml"
    else:
        try:
            text = Path(ground_truth).read_text(encoding="utf-8")
        except OSError as exc:
            raise ProtocolError(
                str(ground_truth), "", f"cannot read the ground truth ({exc.strerror or exc})"
            ) from exc
        source = str(ground_truth)
    try:
        truth = yaml.safe_load(text)  # JSON is YAML too
    except yaml.YAMLError as exc:
        raise ProtocolError(source, "", f"malformed YAML or JSON: {exc}") from exc
    ground_truth_from_dict(truth, source)  # validate now, before the session starts
    return {"ground_truth_path": source, "population_seed": 0, "truth": truth}


# --------------------------------------------------------------------------------------------
# Opening the device and the responder, creating the log


def open_device_and_responder(
    make_responder: Callable[[str, ContextT], ResponderT],
    responder_name: str,
    context: ContextT,
    opener: Callable[[str, Clock], DeviceT],
    spec: str,
    clock: Clock,
) -> tuple[DeviceT, ResponderT]:
    """Build the responder, then open the device; close the responder if the device fails.

    Parameters
    ----------
    make_responder : callable
        ``(name, context) -> responder``.
    responder_name : str
        Responder name (``sim``, ``keys``, ``psychopy``).
    context : object
        What the responder factory needs (the runner's context dataclass).
    opener : callable
        ``(spec, clock) -> Device``.
    spec : str
        Checked device spec (see :func:`check_device_spec`).
    clock : Clock
        The session clock, handed to the device.

    Returns
    -------
    (Device, responder)
        Both open; the caller must close them (:func:`close_quietly`).
    """
    responder = make_responder(responder_name, context)
    try:
        device = opener(spec, clock)
    except BaseException:
        responder.close()
        raise
    return device, responder


@contextmanager
def close_on_failure(device: Device, responder: Closable) -> Iterator[None]:
    """Close ``device`` and ``responder`` if the block raises, then re-raise.

    For the steps between opening them and handing them to the session loop (which closes
    them itself), so a refused start never leaves a port or a window open.
    """
    try:
        yield
    except BaseException:
        close_quietly(device, responder)
        raise


def create_log(
    data_dir: Path, experiment: str, participant: str, header: Mapping[str, Any]
) -> SessionLogWriter:
    """Create a new session log under ``data_dir/<participant>/`` and write its header.

    Parameters
    ----------
    data_dir : Path
        The data folder.
    experiment, participant : str
        Name parts of the log file (see :func:`new_log_path`).
    header : mapping
        The header record; ``session_id`` (the file's stem) is added.

    Returns
    -------
    SessionLogWriter
        Open for appending; ``writer.path`` is the new log.
    """
    log_path = new_log_path(data_dir, experiment, participant)
    return SessionLogWriter.create(log_path, {**dict(header), "session_id": log_path.stem})


def new_log_path(data_dir: Path, experiment: str, participant: str) -> Path:
    """A new log path ``data_dir/<participant>/<experiment>-<participant>-<UTC>.jsonl``.

    A session started in the same second as an existing log gets ``-2``, ``-3``, … appended.
    """
    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    folder = data_dir / participant
    base = f"{experiment}-{participant}-{stamp}"
    path = folder / f"{base}.jsonl"
    n = 2
    while path.exists():  # two sessions in one second: never overwrite, number the newer one
        path = folder / f"{base}-{n}.jsonl"
        n += 1
    return path


# --------------------------------------------------------------------------------------------
# Resuming


def check_header(header: Mapping[str, Any], path: Path) -> None:
    """Raise :class:`LogError` if ``header`` breaks the session-log schema."""
    errors = schema_errors(dict(header), "session_log")
    if errors:
        raise LogError(
            f"{path}: line 1: the header breaks the session-log schema at {key_path(errors[0])}: "
            f"{errors[0].message}; this log cannot be resumed"
        )


def refuse_finished(log: SessionLog, path: Path) -> None:
    """Raise :class:`LogError` if the log has a ``session_end`` record: nothing to resume."""
    if log.ended:
        raise LogError(
            f"{path}: this session has finished (it has a session_end record); there is nothing "
            "to resume. Start a new session with `masking-lab run`"
        )


def resume_responder_name(
    header: Mapping[str, Any], responder: str | None, choices: tuple[str, ...]
) -> str:
    """The responder to resume with: ``responder`` if given, else the header's (``sim``).

    Raises
    ------
    MaskingLabError
        The name is not one of ``choices``.
    """
    name = responder or str(header.get("responder", "sim"))
    if name not in choices:
        raise MaskingLabError(f"responder {name!r}: choose one of {choices}")
    return name


def resume_clock(header: Mapping[str, Any], log: SessionLog) -> Clock:
    """A clock that continues the logged session's times (s since the session started).

    A virtual session's clock starts at the last logged time; a real one is offset by the wall
    time since the header's ``created_utc`` (never less than the last logged time), so times
    stay increasing across the stop.
    """
    last_t = last_time_s(log)
    if header["clock"] == "virtual":
        return VirtualClock(start=last_t)
    return OffsetClock(RealClock(), seconds_since(header["created_utc"], last_t))


def resume_observer(header: Mapping[str, Any], responder_name: str) -> dict[str, Any] | None:
    """The logged simulated observer; the shipped one for a sim responder if none was logged."""
    observer = header.get("simulated_observer")
    if responder_name == "sim" and observer is None:
        observer = observer_record(None)
    return observer


def resume_device_config(device_config: Path | None, header: Mapping[str, Any]) -> Path | None:
    """``device_config`` if given, else the rig config the session started with."""
    return device_config if device_config is not None else header_device_config(header)


def record_resume(
    writer: SessionLogWriter,
    log: SessionLog,
    identity: DeviceIdentity,
    out: ProgressLine,
    where: tuple[str | None, int | None],
) -> None:
    """Log how the session stopped (if it did not say) and that it resumes now.

    Says so if an incomplete last line was cut; appends an ``unclean_stop`` fault when the last
    record is not a fault (the process was killed or the machine went down), then the
    ``resume`` record with the device now used, and warns if that device differs.

    Parameters
    ----------
    writer : SessionLogWriter
        The reopened log.
    log : SessionLog
        The log as read before reopening.
    identity : DeviceIdentity
        The device opened for the continuation.
    out : ProgressLine
        Where messages go.
    where : (set_id, trial_index)
        The position the session stopped at, for the ``unclean_stop`` record.
    """
    path = writer.path
    dropped = log.truncated_tail is not None
    if dropped:
        out.message(
            f"{path}: cut an incomplete last line ({len(log.truncated_tail or '')} characters, "
            "a record being written when the session stopped); the trial it held is re-run"
        )
    last = log.records[-1] if log.records else None
    if last is None or last.get("record") != "fault":
        # Nothing in the log says why it stopped: it was killed or the machine went down.
        writer.append(
            drop_none(
                {
                    "record": "fault",
                    "kind": "unclean_stop",
                    "message": "the session stopped without recording why (killed, crashed or "
                    "power lost)" + ("; an incomplete last line was cut" if dropped else ""),
                    "set_id": where[0],
                    "trial_index": where[1],
                }
            )
        )
    writer.append(
        {
            "record": "resume",
            "resumed_utc": utc_now(),
            "software_version": __version__,
            "dropped_partial_line": dropped,
            "device": device_record(identity),
        }
    )
    warn_device_change(log.header.get("device", {}), identity, out)


def device_spec_from_header(header: Mapping[str, Any]) -> str:
    """The device spec to reopen the logged device with (``serial:<port>``, ``sim``, ``emulator``).

    Raises
    ------
    LogError
        A serial device without a port, or a back-end that cannot be reopened from the log.
    """
    dev = header.get("device") or {}
    backend = str(dev.get("backend", "sim"))
    if backend == "serial":
        if not dev.get("port"):
            raise LogError("the log's device has no port; pass --device serial:PORT")
        return f"serial:{dev['port']}"
    if backend in ("sim", "emulator"):
        return backend
    raise LogError(f"the log's device back-end {backend!r} cannot be reopened; pass --device")


def header_device_config(header: Mapping[str, Any]) -> Path | None:
    """The rig config the session started with, or None."""
    value = header.get("device_config")
    return Path(value) if value else None


def warn_device_change(
    logged: Mapping[str, Any], identity: DeviceIdentity, out: ProgressLine
) -> None:
    """Say so if the device now opened differs from the ``logged`` one (the header's record)."""
    now = device_record(identity)
    changed = [
        k
        for k in ("backend", "model", "serial_number", "firmware_version", "max_drive_v")
        if k in logged and logged[k] != now[k]
    ]
    if changed:
        out.message(
            "note: the device differs from the one the session started with "
            f"({', '.join(changed)}); the resume record logs the new one"
        )


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

    def run_guarded(self, body: Callable[[], None]) -> ResultT:
        """Run ``body`` under :class:`SessionSignals`, then log ``session_end``.

        A device fault returns exit code 3 and an interruption 130, each after zeroing the
        outputs and logging a ``fault``; any other error is logged and re-raised. The device,
        the responder and the log are closed in every case.
        """
        path = self.writer.path
        try:
            with self.signals:
                body()
                self._append(
                    {"record": "session_end", "status": "completed", "ended_utc": utc_now()}
                )
            self.out.clear()
            return self._result(EXIT_COMPLETED, "")
        except DeviceError as exc:
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
                f"masking-lab resume {path}"
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
                f"Resume with: masking-lab resume {path}"
            )
            self.out.message(message)
            return self._result(EXIT_INTERRUPTED, message)
        except MaskingLabError as exc:
            self._stop_device()
            self._fault("error", str(exc))
            self.out.message(f"stopped: {exc}. Fix it, then resume with: masking-lab resume {path}")
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
        except (OSError, ValueError) as exc:  # the disk itself failed: say so, keep going down
            print(f"could not log the fault ({exc}): {message}", file=sys.stderr)

    def _stop_device(self) -> bool:
        """Zero the outputs; False if the device did not take the command."""
        try:
            self.device.stop()
            return True
        except Exception:  # a dead device cannot stop; its watchdog does
            return False


def fault_kind(exc: DeviceError) -> str:
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
    return {
        "backend": identity.backend,
        "model": identity.model,
        "serial_number": identity.serial_number,
        "firmware_version": identity.firmware_version,
        "port": identity.port,
        "max_drive_v": {k: float(v) for k, v in identity.limits.max_drive_v.items()},
    }


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

    def deferred(self) -> _Deferred:
        """A context in which signals wait: use it around each log write."""
        return _Deferred(self)


class _Deferred:
    """While active, a signal is remembered and raised when the block ends (unless it raised)."""

    def __init__(self, signals: SessionSignals) -> None:
        self.signals = signals

    def __enter__(self) -> None:
        self.signals._deferring = True

    def __exit__(self, exc_type: object, *rest: object) -> None:
        self.signals._deferring = False
        pending, self.signals._pending = self.signals._pending, None
        if pending is not None and exc_type is None:
            raise SessionInterrupted(pending)


# --------------------------------------------------------------------------------------------
# Clocks


class OffsetClock:
    """A real clock whose zero is the session's start, so a resumed session's times continue."""

    virtual = False

    def __init__(self, base: Clock, offset_s: float) -> None:
        self.base = base
        self.offset_s = float(offset_s)

    def now(self) -> float:
        return self.base.now() + self.offset_s

    def sleep_until(self, t: float) -> None:
        self.base.sleep_until(t - self.offset_s)


def seconds_since(created_utc: str, floor_s: float) -> float:
    """Seconds (s) from ``created_utc`` (ISO 8601) to now, and at least ``floor_s``.

    An unparsable time counts as 0 s, so ``floor_s`` (the last logged time) wins.
    """
    try:
        created = dt.datetime.fromisoformat(created_utc.replace("Z", "+00:00"))
        elapsed = (dt.datetime.now(dt.UTC) - created).total_seconds()
    except ValueError:
        elapsed = 0.0
    return max(elapsed, floor_s)


def last_time_s(log: SessionLog) -> float:
    """The latest session time (s) in the log's records: ``t_s`` and presentation onsets."""
    last = 0.0
    for rec in log.records:
        for key in ("t_s",):
            v = rec.get(key)
            if isinstance(v, int | float) and math.isfinite(v):
                last = max(last, float(v))
        for key in ("planned_onsets_s", "actual_onsets_s"):
            for v in rec.get(key) or ():
                if isinstance(v, int | float) and math.isfinite(v):
                    last = max(last, float(v))
    return last


# --------------------------------------------------------------------------------------------
# Default device opener


def default_opener(device_config: Path | None) -> DeviceOpener:
    """``(spec, clock) -> Device`` through :func:`masking_lab.device.registry.open_device`.

    The factory is imported on first use, so the core runs without device drivers installed.
    """

    def opener(spec: str, clock: Clock) -> Device:
        from masking_lab.device import registry as factory

        return factory.open_device(spec, device_config, clock)

    return opener
