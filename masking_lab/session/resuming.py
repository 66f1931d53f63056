"""Resuming a session: header checks, the continued clock, the resume and unclean-stop records.

A resumed session takes everything from its log's header (never from files that may have changed
since); the frame (:mod:`masking_lab.session.frame`) calls these in order.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from masking_lab import __version__
from masking_lab.core.clock import Clock, RealClock, VirtualClock
from masking_lab.core.errors import LogError, MaskingLabError
from masking_lab.device.base import DeviceIdentity
from masking_lab.formats.reader import excerpt
from masking_lab.formats.schemas import describe, key_path, schema_errors
from masking_lab.formats.session_log import SessionLog, SessionLogWriter
from masking_lab.session.opening import check_participant, observer_record
from masking_lab.session.progress import ProgressLine
from masking_lab.session.shell import device_record, drop_none, utc_now


def check_header(header: Mapping[str, Any], path: Path) -> None:
    """Raise :class:`LogError` if ``header`` breaks the session-log schema."""
    errors = schema_errors(dict(header), "session_log")
    if errors:
        raise LogError(
            f"{path}: line 1: the header breaks the session-log schema at "
            f"{excerpt(key_path(errors[0]), 80)}: {describe(errors[0])}; this log cannot be "
            "resumed"
        )
    try:  # the id names folders and files: hold it to what `run` accepts
        check_participant(header.get("participant"))
    except MaskingLabError as exc:
        raise LogError(
            f"{path}: line 1: the header's participant id is not one `run` accepts ({exc}); this "
            "log cannot be resumed"
        ) from None


def refuse_finished(log: SessionLog, path: Path) -> None:
    """Raise :class:`LogError` if the log has a ``session_end`` record: nothing to resume."""
    if log.ended:
        raise LogError(
            f"{path}: this session has finished (it has a session_end record); there is nothing "
            "to resume. Start a new session with `masking-lab run`"
        )


def refuse_damaged(log: SessionLog, path: Path) -> None:
    """Raise :class:`LogError` if lines are unusable or records are missing, repeated or moved.

    A torn last line is not damage (a crash mid-write; it is cut and its trial re-run). Every
    other problem is listed with its line, so the experimenter can compare with a backup.

    Examples
    --------
    >>> from masking_lab.formats.session_log import parse_log
    >>> log = parse_log(b'{"record":"header","seq":1}\\n{"record":"fault","seq":3}\\n', "x.jsonl")
    >>> try:
    ...     refuse_damaged(log, Path("x.jsonl"))
    ... except LogError as exc:
    ...     print(str(exc)[:77])
    x.jsonl: the log is damaged, so resuming could repeat or lose trials: line 2:
    """
    damage = [p for p in log.problems if "truncated last line" not in p]
    damage += log.continuity_problems()
    if damage:
        shown = "; ".join(damage[:5]) + (f"; and {len(damage) - 5} more" if len(damage) > 5 else "")
        raise LogError(
            f"{path}: the log is damaged, so resuming could repeat or lose trials: {shown}. "
            "Restore the log from a backup copy, or start a new session with `masking-lab run` "
            "(`masking-lab analyze` reports what this log holds)"
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
    """``device_config`` if given; the reference rig if the session started with it.

    A log header is data, never a path to open: a session that started with a rig config of
    its own is resumed only with ``--device-config`` naming a file again (a crafted header
    could otherwise make ``resume`` read, and quote, any file it names).

    Raises
    ------
    LogError
        The session started with a rig config and none is given now.
    """
    if device_config is not None:
        return device_config
    logged = header_device_config(header)
    if logged is not None:
        raise LogError(
            f"this session started with the rig config {excerpt(str(logged), 80)}; resume opens no "
            "file the log names by itself: pass --device-config with that file (or the rig "
            "config to use now)"
        )
    return None


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
    backend = str(dev.get("backend", "sim")) if isinstance(dev, Mapping) else "?"
    if backend in ("sim", "emulator"):
        return backend
    if backend == "serial":
        # A port named by the log is never opened by itself: a crafted header could name any
        # path (a file, a FIFO) as the serial port.
        port = excerpt(str(dev.get("port") or "?"), 60)
        raise LogError(
            f"the session ran on serial port {port}; pass --device serial:PORT naming the port "
            "to reopen (resume opens no path the log names by itself)"
        )
    raise LogError(
        f"the log's device back-end {excerpt(backend)} cannot be reopened; pass --device"
    )


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


def _finite(v: object) -> bool:
    # An int beyond float range (a crafted record) is not a time either.
    return (
        isinstance(v, int | float)
        and not isinstance(v, bool)
        and abs(v) <= 1e300
        and (math.isfinite(v))
    )


def last_time_s(log: SessionLog) -> float:
    """The latest session time (s) in the log's records: ``t_s`` and presentation onsets."""
    last = 0.0
    for rec in log.records:
        for key in ("t_s",):
            v = rec.get(key)
            if _finite(v):
                last = max(last, float(v))
        for key in ("planned_onsets_s", "actual_onsets_s"):
            for v in rec.get(key) or ():
                if _finite(v):
                    last = max(last, float(v))
    return last
