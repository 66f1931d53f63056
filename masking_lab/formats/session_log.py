"""Session logs: append-only JSON Lines, one record per line, fsynced per record.

The log is the source of truth of a session (schema: ``data_schema/session_log.schema.json``).
A crash at any instant loses at most the record being written: each record is one ``write`` of a
complete line followed by ``fsync``. On reading, a last line without its newline (or that does not
parse) is reported as a truncated tail, not treated as fatal; an unparseable line in the middle is
reported in :attr:`SessionLog.problems` and skipped.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from masking_lab.core.errors import LogError
from masking_lab.formats.records import encode_record


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
    """

    start: dict[str, Any]
    trials: list[dict[str, Any]] = field(default_factory=list)
    end: dict[str, Any] | None = None


@dataclass
class SessionLog:
    """A parsed session log.

    Attributes
    ----------
    path : Path
        File read.
    header : dict
        The ``header`` record (first line).
    records : list[dict]
        Every later record that parsed, in file order.
    truncated_tail : str or None
        Text of an incomplete last line (a crash mid-write), if any.
    problems : list[str]
        Human-readable notes on skipped lines (``"line 7: ..."``).
    """

    path: Path
    header: dict[str, Any]
    records: list[dict[str, Any]]
    truncated_tail: str | None = None
    problems: list[str] = field(default_factory=list)

    def sets(self) -> dict[str, SetRecords]:
        """Records grouped by ``set_id`` in the order sets were started.

        A set restarted after a resume keeps its trials (the runner never restarts a set from
        scratch; a repeated ``set_start`` just replaces the start record).
        """
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
        return any(r.get("record") == "session_end" for r in self.records)


def read_log(path: str | Path) -> SessionLog:
    """Read a session log, tolerating a truncated last line.

    Raises
    ------
    LogError
        If the file cannot be read or its first line is not a ``header`` record.
    """
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise LogError(f"{p}: cannot read session log ({exc.strerror or exc})") from exc
    text = raw.decode("utf-8", errors="replace")
    lines = text.split("\n")
    # A complete file ends with "\n", so the last split element is "" unless the tail is partial.
    tail = lines.pop()
    truncated_tail = tail if tail.strip() else None
    problems: list[str] = []
    records: list[dict[str, Any]] = []
    header: dict[str, Any] | None = None
    for lineno, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError as exc:
            problems.append(f"line {lineno}: not valid JSON ({exc.msg}); line skipped")
            continue
        if not isinstance(rec, dict) or "record" not in rec:
            problems.append(f"line {lineno}: not a log record (no 'record' key); line skipped")
            continue
        if header is None:
            if rec["record"] != "header":
                raise LogError(
                    f"{p}: line {lineno}: the first record must be the session header, found "
                    f"{rec['record']!r}; is this a masking_lab session log?"
                )
            header = rec
            continue
        records.append(rec)
    if truncated_tail is not None:
        problems.append(
            f"line {len(lines) + 1}: truncated last line ({len(truncated_tail)} bytes, no newline),"
            " probably a crash while writing; it is ignored"
        )
    if header is None:
        raise LogError(f"{p}: no session header found; the file is empty or not a session log")
    return SessionLog(p, header, records, truncated_tail, problems)


class SessionLogWriter:
    """Append records to a session log, one fsynced line each.

    Use :meth:`create` for a new session and :meth:`reopen` to continue one (``resume``).
    """

    def __init__(self, path: Path, fh: Any) -> None:
        self.path = path
        self._fh = fh

    @classmethod
    def create(cls, path: str | Path, header: dict[str, Any]) -> SessionLogWriter:
        """Create ``path`` (must not exist) and write the header record.

        Raises
        ------
        LogError
            If the file exists already (a log is never overwritten).
        """
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        try:
            fh = open(p, "x", encoding="utf-8")  # noqa: SIM115 - owned by the writer
        except FileExistsError as exc:
            raise LogError(
                f"{p}: a session log with this name exists already; use `masking-lab resume {p}`"
                " to continue it, or choose another --data folder"
            ) from exc
        _fsync_dir(p.parent)
        writer = cls(p, fh)
        writer.append({**header, "record": "header"})
        return writer

    @classmethod
    def reopen(cls, path: str | Path) -> tuple[SessionLogWriter, SessionLog]:
        """Open an existing log for appending, cutting off a truncated last line first.

        Returns the writer and the log as read (whose ``truncated_tail`` says what was cut).
        """
        p = Path(path)
        log = read_log(p)
        if log.truncated_tail is not None:
            size = p.stat().st_size
            with open(p, "r+b") as fh:
                fh.truncate(size - len(log.truncated_tail.encode("utf-8")))
                fh.flush()
                os.fsync(fh.fileno())
        fh = open(p, "a", encoding="utf-8")  # noqa: SIM115 - owned by the writer
        return cls(p, fh), log

    def append(self, record: dict[str, Any]) -> None:
        """Write ``record`` as one line and fsync before returning."""
        self._fh.write(encode_record(record) + "\n")
        self._fh.flush()
        os.fsync(self._fh.fileno())

    def close(self) -> None:
        """Close the file (idempotent)."""
        if not self._fh.closed:
            self._fh.close()

    def __enter__(self) -> SessionLogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


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
