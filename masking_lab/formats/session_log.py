"""Session logs: append-only JSON Lines, one record per line; the one reader and the one writer.

The log is the source of truth of a session (schema: ``data_schema/session_log.schema.json``,
typed records: :mod:`masking_lab.formats.log_records`). Each record is one ``write`` of a
complete line carrying ``seq``, its line number, so deleted, repeated or reordered records are
found (:mod:`masking_lab.formats.log_integrity`). The writer holds an exclusive lock on the file
(:mod:`masking_lab.formats.log_lock`) for the life of the session.

When a record reaches the disk (``sync``): ``"record"`` fsyncs every record (a real-time rig:
trials are seconds apart and each is a participant's time); ``"set"`` fsyncs the header, every
``set_end``, ``fault``, ``resume`` and ``session_end`` (virtual time: simulation and emulation,
where the fsync would be half the run time). Either way a completed set is never lost, and a
killed process loses nothing: only a power cut can lose the trials of the set in progress.

On reading, a last line without its newline is a torn record (cut on reopen) unless it is a
whole record (kept, its newline added); a line that does not parse or is not valid UTF-8 is
reported in :attr:`SessionLog.problems` (never skipped silently).
"""

from __future__ import annotations

import contextlib
import functools
import json
import operator
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import msgspec

from masking_lab.core.errors import LogError, LogWriteError
from masking_lab.formats.log_bytes import (
    BadNumber,
    check_schema_version,
    loads_record,
    read_log_bytes,
    strip_bom,
)
from masking_lab.formats.log_integrity import (
    continuity_problems,
    interleaved,
    problems_of_keys,
    record_key,
    split_tail,
)
from masking_lab.formats.log_lock import LogLock
from masking_lab.formats.log_records import (
    ASetEnd,
    ASetStart,
    ATrial,
    check_record,
    view_keys,
)
from masking_lab.formats.records import encode_record
from masking_lab.formats.typed_layout import Layout, intact_layout, typed_structure_intact

__all__ = ["SessionLog", "SessionLogWriter", "SetRecords", "SyncPolicy", "parse_log", "read_log"]

SyncPolicy = Literal["record", "set"]
_SEQ = operator.attrgetter("seq")
SET_SYNC_RECORDS = frozenset({"header", "set_end", "fault", "resume", "session_end"})
_write = os.write  # the one place bytes reach the log (tests inject disk errors here)


@dataclass
class SetRecords:
    """The records of one set within a log.

    Attributes
    ----------
    start : dict
        The (last) ``set_start`` record of the set.
    trials : list[dict]
        Its ``trial`` records in order.
    end : dict or None
        Its ``set_end`` record, or None if the set did not finish.
    counted : bool
        The trials are known to be typed trial records whose ``trial_index`` counts 0, 1,
        2, … (an intact typed log's layout says so; the estimator need not check again).
    """

    start: Any
    trials: list[Any] = field(default_factory=list)
    end: Any | None = None
    counted: bool = False


@dataclass
class SessionLog:
    """A parsed session log.

    Attributes
    ----------
    path : Path
        File read.
    header : dict
        The ``header`` record (first record).
    records : list[dict]
        Every later record that parsed, in file order (dicts; or the typed analysis view's
        records, which answer ``[]`` and ``get`` alike).
    truncated_tail : str or None
        Text of a torn last line (a crash mid-write), if any.
    problems : list[str]
        Human-readable notes on lines not used (``"line 7: ..."``).
    lines : list[int]
        The 1-based line number of each of ``records``.
    header_line : int
        The header's line number (1 unless lines before it were unusable).
    missing_newline : bool
        The last line is a whole record without its newline (kept; reopen adds the newline).
    value_problems : list[str]
        Records kept whose values cannot be used (a non-finite number): the analysis refuses
        the set holding them (``"line N: ..."``).
    """

    path: Path
    header: Any
    records: list[Any]
    truncated_tail: str | None = None
    problems: list[str] = field(default_factory=list)
    lines: list[int] = field(default_factory=list)
    header_line: int = 1
    missing_newline: bool = False
    value_problems: list[str] = field(default_factory=list)

    def sets(self) -> dict[str, SetRecords]:
        """Records grouped by ``set_id`` in the order sets were started.

        A set restarted after a resume keeps its trials (the runner never restarts a set from
        scratch; a repeated ``set_start`` just replaces the start record).
        """
        if self.records and isinstance(self.records[0], msgspec.Struct):
            layout = self.intact_layout
            if layout is None:
                return _typed_sets(self.records)
            recs, unset = self.records, msgspec.UNSET
            out_typed: dict[Any, SetRecords] = {}
            for (a, b), ended in zip(layout.spans, layout.ended, strict=True):
                sid = recs[a].set_id
                out_typed[None if sid is unset else sid] = SetRecords(
                    recs[a], recs[a + 1 : b], recs[b] if ended else None, counted=True
                )
            return out_typed
        out: dict[str, SetRecords] = {}
        for rec in self.records:
            kind = rec.get("record")
            sid = rec.get("set_id")
            if kind == "set_start":
                if sid in out:
                    out[sid].start = rec
                else:
                    out[sid] = SetRecords(start=rec)
            elif kind == "trial" and sid in out:
                out[sid].trials.append(rec)
            elif kind == "set_end" and sid in out:
                out[sid].end = rec
        return out

    @property
    def ended(self) -> bool:
        """True if the log has a ``session_end`` record."""
        # Looked for from the end, where a finished session's is: one record, not all of them.
        return any(r.get("record") == "session_end" for r in reversed(self.records))

    def continuity_problems(self) -> list[str]:
        """Deleted, repeated or reordered records, bad trial indices and set boundaries.

        Returns ``"line N: ..."`` notes (empty for an intact log); see
        :func:`masking_lab.formats.log_integrity.continuity_problems`.
        """
        if self.records and isinstance(self.records[0], msgspec.Struct):
            # Every counter equal to its line, checked in bulk: no gap, repeat or step back.
            intact = (
                self.header.get("seq") == self.header_line
                and list(map(_SEQ, self.records)) == self.lines
            )
            if (
                intact
                and not interleaved(self.header)
                and (self.intact_layout is not None or typed_structure_intact(self.records))
            ):
                return []
            # The keys only for a log the shortcut cannot clear (they cost more than the check).
            keys = [(self.header_line, *record_key(self.header))]
            keys += view_keys(self.lines, self.records)
            return problems_of_keys(
                keys, interleaved=interleaved(self.header), counter_intact=intact
            )
        entries = [(self.header_line, self.header), *zip(self.lines, self.records, strict=True)]
        return continuity_problems(entries)

    @functools.cached_property
    def intact_layout(self) -> Layout | None:
        """Where the sets of a typed log of the common intact shape lie, else None.

        Found once (:func:`~masking_lab.formats.typed_layout.intact_layout`) for
        :meth:`sets`, :meth:`continuity_problems` and the played-level check alike; None
        for a log of dicts (the general reader's).
        """
        if self.records and isinstance(self.records[0], msgspec.Struct):
            return intact_layout(self.records)
        return None


def _typed_sets(records: list[Any]) -> dict[str, SetRecords]:
    """:meth:`SessionLog.sets` for the typed analysis view, by class and attribute."""
    out: dict[Any, SetRecords] = {}
    unset = msgspec.UNSET
    for rec in records:
        cls = type(rec)
        if cls is ATrial:
            sid = None if rec.set_id is unset else rec.set_id
            group = out.get(sid)
            if group is not None:
                group.trials.append(rec)
        elif cls is ASetStart:
            sid = None if rec.set_id is unset else rec.set_id
            if sid in out:
                out[sid].start = rec
            else:
                out[sid] = SetRecords(start=rec)
        elif cls is ASetEnd:
            sid = None if rec.set_id is unset else rec.set_id
            if sid in out:
                out[sid].end = rec
    return out


def parse_log(raw: bytes, path: str | Path) -> SessionLog:
    """Parse a session log's bytes (pure: ``path`` only names it in messages).

    Raises
    ------
    LogError
        If the first record is not a ``header`` or there is none.

    Examples
    --------
    >>> log = parse_log(b'{"record":"header","seq":1}\\n{"record":"trial","set_id":"A"}\\n', "x")
    >>> log.header["seq"], log.records[0]["set_id"], log.lines
    (1, 'A', [2])
    """
    p = Path(path)
    raw = strip_bom(raw)
    tail = split_tail(raw)
    body = raw[: tail.complete_end] + (tail.tail + b"\n" if tail.whole_record else b"")
    lines = body.split(b"\n")
    lines.pop()  # after the last newline: empty
    problems: list[str] = []
    value_problems: list[str] = []
    records: list[Any] = []
    numbers: list[int] = []
    header: dict[str, Any] | None = None
    header_line = 1
    for lineno, line in enumerate(lines, start=1):
        if not line.strip():
            problems.append(f"line {lineno}: blank line; ignored")
            continue
        try:
            rec, non_finite = loads_record(line.decode("utf-8"))
        except UnicodeDecodeError:
            problems.append(f"line {lineno}: not valid UTF-8; line skipped")
            continue
        except json.JSONDecodeError as exc:
            problems.append(f"line {lineno}: not valid JSON ({exc.msg}); line skipped")
            continue
        except BadNumber as exc:
            problems.append(f"line {lineno}: {exc}; line skipped")
            continue
        except RecursionError:
            problems.append(f"line {lineno}: nested too deeply to be a log record; line skipped")
            continue
        if not isinstance(rec, dict) or "record" not in rec:
            problems.append(f"line {lineno}: not a log record (no 'record' key); line skipped")
            continue
        if not isinstance(rec.get("set_id"), str | None):
            problems.append(f"line {lineno}: set_id is not text; line skipped")
            continue
        if non_finite is not None:
            # Kept, so the set it belongs to is refused as a whole (analysis.thresholds), the
            # same way for every estimator; said here so validate and resume show it too.
            value_problems.append(
                f"line {lineno}: a non-finite number ({non_finite}) in a {str(rec['record'])[:40]}"
                " record; a set holding it is refused"
            )
        if header is None:
            if rec["record"] != "header":
                before = f" (before it, {problems[0]})" if problems else ""
                raise LogError(
                    f"{p}: line {lineno}: the first record must be the session header, found "
                    f"{str(rec['record'])[:40]!r}{before}; is this a masking_lab session log?"
                )
            check_schema_version(rec, p)
            header, header_line = rec, lineno
            continue
        records.append(rec)
        numbers.append(lineno)
    truncated_tail = None
    if tail.tail.strip() and not tail.whole_record:
        truncated_tail = tail.tail.decode("utf-8", errors="replace")
        problems.append(
            f"line {len(lines) + 1}: truncated last line ({len(tail.tail)} bytes, no newline),"
            " probably a crash while writing; it is ignored"
        )
    if header is None:
        why = f" ({problems[0]})" if problems else ""
        raise LogError(f"{p}: no session header found{why}; the file is empty or not a session log")
    return SessionLog(
        p,
        header,
        records,
        truncated_tail,
        problems,
        numbers,
        header_line,
        tail.whole_record,
        value_problems,
    )


def read_log(path: str | Path) -> SessionLog:
    """Read a session log, tolerating a torn last line (see :func:`parse_log`).

    Raises
    ------
    LogError
        If the file cannot be read or its first record is not a ``header``.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "log.jsonl"
    >>> _ = p.write_bytes(b'{"record":"header","seq":1}\\n{"record":"set_start","set_id":"A"')
    >>> log = read_log(p)
    >>> log.records, log.truncated_tail
    ([], '{"record":"set_start","set_id":"A"')
    """
    p = Path(path)
    return parse_log(read_log_bytes(p), p)


class SessionLogWriter:
    """Append records to a session log, one line each, under the log's lock.

    Use :meth:`create` for a new session and :meth:`reopen` to continue one (``resume``).

    Attributes
    ----------
    path : Path
        The log.
    sync : {"record", "set"}
        When records are fsynced (module docstring).
    """

    def __init__(self, lock: LogLock, next_seq: int, sync: SyncPolicy = "record") -> None:
        if sync not in ("record", "set"):
            raise ValueError(f"sync must be 'record' or 'set', got {sync!r}")
        self.path = lock.path
        self.sync = sync
        self._lock = lock
        self._seq = next_seq
        self._size = os.fstat(lock.fd).st_size
        self._dirty = False

    @classmethod
    def create(
        cls, path: str | Path, header: Mapping[str, Any], *, sync: SyncPolicy = "record"
    ) -> SessionLogWriter:
        """Create ``path`` (must not exist), lock it and write the header record.

        Raises
        ------
        LogError
            If the file exists already (a log is never overwritten) or cannot be written.
        """
        p = Path(path)
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:  # a file where a folder belongs, no permission, a full disk
            raise LogError(
                f"{p.parent}: cannot make the folder for the session log "
                f"({exc.strerror or exc}); choose a --data folder you can write to"
            ) from exc
        try:
            lock = LogLock.create(p)
        except FileExistsError as exc:
            raise LogError(
                f"{p}: a session log with this name exists already; use `masking-lab resume {p}`"
                " to continue it, or choose another --data folder"
            ) from exc
        except OSError as exc:
            raise LogError(
                f"{p}: cannot create the session log ({exc.strerror or exc}); choose a --data "
                "folder you can write to"
            ) from exc
        _fsync_dir(p.parent)
        writer = cls(lock, 1, sync)
        try:
            writer.append({**header, "record": "header"})
        except BaseException:
            writer.close()
            raise
        return writer

    @classmethod
    def reopen(
        cls, path: str | Path, *, lock: LogLock | None = None, sync: SyncPolicy = "record"
    ) -> tuple[SessionLogWriter, SessionLog]:
        """Lock an existing log (unless ``lock`` holds it already) and open it for appending.

        A torn last line is cut, on bytes, back to the end of the last complete line; a whole
        last record without its newline gets the newline. Returns the writer and the log as
        read (whose ``truncated_tail`` says what was cut).

        Raises
        ------
        LogLockedError
            Another process is writing the log.
        LogError
            Unreadable, not a log, or the repair could not be written.
        """
        held = lock or LogLock.acquire(path)
        try:
            raw = _read_all(held)
            log = parse_log(raw, held.path)
            tail = split_tail(raw)
            try:
                if tail.whole_record:
                    _write_all(held.fd, b"\n")
                elif tail.tail:
                    os.ftruncate(held.fd, tail.complete_end)
                if tail.tail:
                    os.fsync(held.fd)
            except OSError as exc:
                raise LogWriteError(
                    f"{held.path}: cannot repair the log's last line ({exc.strerror or exc}); "
                    "check the disk, then resume again"
                ) from exc
            size = tail.complete_end + (len(tail.tail) + 1 if tail.whole_record else 0)
            next_seq = raw[:size].count(b"\n") + (1 if tail.whole_record else 0) + 1
            return cls(held, next_seq, sync), log
        except BaseException:
            if lock is None:
                held.release()
            raise

    def append(self, record: Mapping[str, Any]) -> None:
        """Write ``record`` (and its ``seq``) as one line; fsync as :attr:`sync` says.

        Raises
        ------
        ValueError
            A NaN or infinite number, or a field of the wrong type (a bug in the caller).
        LogWriteError
            The disk refused the write (full, I/O error); the partial line is removed when the
            disk allows, so the log stays readable.
        """
        line = encode_record({**record, "seq": self._seq}) + "\n"
        check_record(record)
        data = line.encode("utf-8")
        try:
            _write_all(self._lock.fd, data)
        except OSError as exc:
            with contextlib.suppress(OSError):  # no torn line left behind, if the disk allows
                os.ftruncate(self._lock.fd, self._size)
            raise LogWriteError(
                f"{self.path}: cannot write the session log ({exc.strerror or exc}); free disk "
                f"space or fix the disk, then continue with `masking-lab resume {self.path}`"
            ) from exc
        self._size += len(data)
        self._seq += 1
        self._dirty = True
        if self.sync == "record" or record.get("record") in SET_SYNC_RECORDS:
            self.flush()

    def append_many(self, records: Sequence[Mapping[str, Any]]) -> None:
        """Append ``records`` in one write (synthetic logs, written whole), then sync once.

        The lines are exactly those :meth:`append` would write one by one; the sync follows
        :attr:`sync` as if they had been (one fsync covers them all).

        Raises
        ------
        ValueError, LogWriteError
            As :meth:`append`; nothing is left of the batch on a write error.
        """
        lines = []
        for k, record in enumerate(records):
            lines.append(encode_record({**record, "seq": self._seq + k}) + "\n")
            check_record(record)
        data = "".join(lines).encode("utf-8")
        try:
            _write_all(self._lock.fd, data)
        except OSError as exc:
            with contextlib.suppress(OSError):
                os.ftruncate(self._lock.fd, self._size)
            raise LogWriteError(
                f"{self.path}: cannot write the session log ({exc.strerror or exc}); free disk "
                "space or fix the disk"
            ) from exc
        self._size += len(data)
        self._seq += len(lines)
        self._dirty = True
        if self.sync == "record" or any(r.get("record") in SET_SYNC_RECORDS for r in records):
            self.flush()

    def flush(self) -> None:
        """Fsync what was written since the last sync.

        Raises
        ------
        LogWriteError
            The disk reported an error.
        """
        if not self._dirty or self._lock.fd < 0:
            return
        try:
            os.fsync(self._lock.fd)
        except OSError as exc:
            raise LogWriteError(
                f"{self.path}: cannot sync the session log to disk ({exc.strerror or exc}); "
                f"check the disk, then continue with `masking-lab resume {self.path}`"
            ) from exc
        self._dirty = False

    @property
    def closed(self) -> bool:
        """True once :meth:`close` ran."""
        return self._lock.fd < 0

    def close(self) -> None:
        """Sync what is pending, close the file and release the lock (idempotent)."""
        if self.closed:
            return
        try:
            self.flush()
        except LogWriteError:
            pass  # closing must not hide the real outcome; the next resume reads what is there
        finally:
            self._lock.release()

    def __enter__(self) -> SessionLogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        n = _write(fd, view)
        if n <= 0:
            raise OSError(28, os.strerror(28))  # a 0-byte write: no space
        view = view[n:]


def _read_all(lock: LogLock) -> bytes:
    return read_log_bytes(lock.path)


def _fsync_dir(directory: Path) -> None:
    # Make the new directory entry durable too, so a crash right after create keeps the file.
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
