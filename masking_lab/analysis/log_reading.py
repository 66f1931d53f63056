"""Reading many session logs for ``analyze`` (*shell*): one read per log, typed, in parallel.

Each log is read once: the same bytes are hashed (provenance) and parsed. Parsing uses the
typed analysis view of :mod:`masking_lab.formats.log_records` (only the fields the analysis
uses, decoded by msgspec without a dict per record); a log the view cannot take as a whole (a
torn last line, a line that is not a record, an unexpected type) is parsed by the general
reader :func:`masking_lab.formats.session_log.parse_log` instead, which reports every line it
cannot use. Both give the same rows. With many logs, the work is spread over processes.

Every log yields a :class:`LogResult`: its hash, header, threshold rows, line problems and
record-continuity problems (:mod:`masking_lab.formats.log_integrity`), or why it is unreadable.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, get_args

import msgspec
import numpy as np

from masking_lab.analysis.played_levels import played_level_problems
from masking_lab.analysis.procedure_estimates import places_masker
from masking_lab.analysis.study_status import SessionInfo, session_of
from masking_lab.analysis.thresholds import EstimatorSettings, packed, session_rows
from masking_lab.core.errors import LogError
from masking_lab.core.worker_processes import cancel_pool, rest_here, worker_pool
from masking_lab.formats.log_bytes import check_schema_version, read_log_bytes, strip_bom
from masking_lab.formats.log_records import (
    ANALYSIS_DECODER,
    AHeader,
    AnalysisRecord,
    ASetStart,
)
from masking_lab.formats.session_log import SessionLog, parse_log

__all__ = [
    "LogResult",
    "fast_parse",
    "names_masker_placing_set",
    "read_logs",
]

PARALLEL_FROM = 64  # fewer logs than this are read in-process (workers cost ~0.3 s to start)
_CHUNK = 32
_NEWLINE = ord("\n")


@dataclass
class LogResult:
    """What one log contributes to the analysis.

    Attributes
    ----------
    path : Path
        The log file.
    rel : str
        Its name relative to the data folder (``/``-separated).
    error : str or None
        Why it could not be read at all (then every other field is empty).
    sha256 : str
        Hex digest of the bytes parsed.
    header : dict
        The header's fields the analysis uses.
    rows : list[tuple]
        One raw threshold row per set (:func:`~masking_lab.analysis.thresholds.session_rows`),
        :func:`~masking_lab.analysis.thresholds.packed` (a third of the memory of dicts, which
        matters at 100,000 sets).
    line_problems : list[str]
        Lines not used (``"line N: ..."``).
    continuity : list[str]
        Deleted, repeated or reordered records, bad trial indices or set boundaries.
    value_problems : list[str]
        Records kept whose values the analysis refuses (a non-finite number): their sets are
        ``invalid``.
    n_bytes : int
        Size of the log, bytes.
    completed : bool
        The log ends with a ``session_end`` record of status ``completed``.
    session : tuple or None
        Its session, the participant's ``info`` and the protocol's ``info`` fields
        (:func:`~masking_lab.analysis.study_status.session_of`), so the study matrix and
        ``participants.tsv`` need no second read of the log.
    may_hold_functional : bool
        A ``set_start`` of its records runs a procedure that places the masker level: only
        such logs are read again for the functional outputs (:func:`names_masker_placing_set`).
    """

    path: Path
    rel: str
    error: str | None = None
    sha256: str = ""
    header: dict[str, Any] = field(default_factory=dict)
    rows: list[tuple[Any, ...]] = field(default_factory=list)
    line_problems: list[str] = field(default_factory=list)
    continuity: list[str] = field(default_factory=list)
    value_problems: list[str] = field(default_factory=list)
    n_bytes: int = 0
    completed: bool = False
    session: tuple[SessionInfo, Mapping[str, Any] | None, list[dict[str, Any]]] | None = None
    may_hold_functional: bool = True


def fast_parse(raw: bytes, path: str | Path) -> SessionLog | None:
    """The log's typed analysis view, or None when only the general reader can take it.

    None for: no final newline, a blank line, a line that is not a known record with fields of
    the expected types, or a first record that is not the header.

    Examples
    --------
    >>> log = fast_parse(b'{"record":"header","participant":"P1"}\\n{"record":"fault"}\\n', "x")
    >>> log.header["participant"], log.lines
    ('P1', [2])
    >>> fast_parse(b'{"record":"header"}\\n{"record":"tri', "x") is None
    True
    """
    raw = strip_bom(raw)
    if not raw.endswith(b"\n"):
        return None
    try:
        recs = ANALYSIS_DECODER.decode_lines(raw)
    # a bad byte inside a decoded string, or nesting deeper than msgspec recurses: the general
    # reader (its own depth limit) says what is wrong and where
    except (msgspec.DecodeError, UnicodeDecodeError, RecursionError):
        return None
    if not recs or len(recs) != _newlines(raw) or not isinstance(recs[0], AHeader):
        return None
    check_schema_version(recs[0], path)
    return SessionLog(Path(path), recs[0].as_dict(), recs[1:], lines=list(range(2, len(recs) + 1)))


def _newlines(raw: bytes) -> int:
    """``raw.count(b"\\n")`` in under half its time (numpy compares 64 bytes at once): ~35 µs
    against ~80 µs for a ~300 kB log: a reading worker's time per log falls by 4 %.

    Examples
    --------
    >>> _newlines(b'{"a":1}\\n\\n{"b":2}\\n')
    3
    """
    return int(np.count_nonzero(np.frombuffer(raw, dtype=np.uint8) == _NEWLINE))


def read_one(path: Path, rel: str, settings: EstimatorSettings) -> LogResult:
    """Read, hash and parse one log and compute its threshold rows.

    Examples
    --------
    >>> read_one(Path("/nonexistent.jsonl"), "x.jsonl", EstimatorSettings()).error
    '/nonexistent.jsonl: cannot read session log (No such file or directory)'
    """
    try:
        raw = read_log_bytes(path)
        log = fast_parse(raw, path)
    except LogError as exc:
        return LogResult(path, rel, error=str(exc))
    digest = hashlib.sha256(raw).hexdigest()
    rows = None
    if log is not None:
        try:
            rows = session_rows(log, rel, settings)
        except AttributeError:  # the view lacks a field newer analysis code asks for
            log = None
    if log is None:
        try:
            log = parse_log(raw, path)
        except LogError as exc:
            return LogResult(path, rel, error=str(exc))
        rows = session_rows(log, rel, settings)
    header = log.header if isinstance(log.header, dict) else {}
    layout = log.intact_layout
    if layout is None:
        played = played_level_problems(log.records, log.lines)
        may_hold_functional = names_masker_placing_set(log.records)
    else:
        # An intact typed log: its one pass found whether any trial reports a played level
        # (most do not: nothing to compare), and its set_starts are at the spans' starts.
        played = played_level_problems(log.records, log.lines) if layout.played else []
        starts = [log.records[a] for a, _ in layout.spans]
        may_hold_functional = names_masker_placing_set(starts)
    return LogResult(
        path,
        rel,
        sha256=digest,
        header=_analysis_header(header),
        rows=packed(rows or []),
        line_problems=list(log.problems),
        continuity=[*log.continuity_problems(), *played],
        value_problems=list(log.value_problems),
        n_bytes=len(raw),
        completed=_completed(log),
        session=session_of(header, rel, log.ended),
        may_hold_functional=may_hold_functional,
    )


_TYPED_NOT_SET_START = frozenset(get_args(AnalysisRecord)) - {ASetStart}


def names_masker_placing_set(records: Sequence[Any]) -> bool:
    """Whether any ``set_start`` among a log's parsed records (typed view or dicts) runs a
    procedure that places the masker level (the registry's ``places_masker`` kinds).

    Read off the records the one read decoded anyway (escapes already decoded), so finding
    no functional set is neither a second read of the study nor a second scan of its bytes.

    Examples
    --------
    >>> start = {"record": "set_start", "procedure": {"kind": "quest_plus"}}
    >>> names_masker_placing_set([start])
    False
    >>> names_masker_placing_set([{**start, "procedure": {"kind": "functional_ramp"}}])
    True
    """
    for rec in records:
        cls = type(rec)
        if cls in _TYPED_NOT_SET_START:  # most records of a typed log: one test, not two
            continue
        if cls is ASetStart:
            procedure = rec.procedure
        elif isinstance(rec, dict) and rec.get("record") == "set_start":  # the general reader's
            procedure = rec.get("procedure")
        else:
            continue
        if isinstance(procedure, Mapping) and places_masker(procedure):
            return True
    return False


#: The header fields a run reads of every log after its read (skipping, the cross-log and rig
#: checks, the creation time); of ``protocol``, only ``experiment``.
HEADER_FIELDS = ("participant", "session_id", "created_utc", "kind", "rig", "protocol")


def _analysis_header(header: dict[str, Any]) -> dict[str, Any]:
    """The :data:`HEADER_FIELDS` of ``header``: the whole header (its protocol above all) of
    every log at once was ~20 MB at 10,000 sessions."""
    kept = {k: header[k] for k in HEADER_FIELDS if k in header}
    protocol = kept.get("protocol")
    if isinstance(protocol, dict):
        kept["protocol"] = {k: protocol[k] for k in ("experiment",) if k in protocol}
    return kept


def _completed(log: SessionLog) -> bool:
    """Whether the log ends with ``session_end`` of status ``completed`` (nothing may follow
    it, so only the last record is looked at)."""
    if not log.records:
        return False
    last = log.records[-1]
    return last.get("record") == "session_end" and last.get("status") == "completed"


def _read_chunk(args: tuple[list[tuple[Path, str]], EstimatorSettings]) -> list[LogResult]:
    jobs, settings = args
    results = [read_one(path, rel, settings) for path, rel in jobs]
    _share_values(results)
    return results


def _share_values(results: list[LogResult]) -> None:
    """Make equal strings and equal floats in the results' rows one object each. Every log's
    set, target and masker names and its quantised levels and ALs are decoded anew; shared,
    pickle sends each once per chunk and the analysing process keeps one copy (at 10,000
    sessions ~35 MB less). Values are unchanged: a float is shared only with an equal one of
    the same bits (zeros, whose sign equality ignores, and NaN are left as they are)."""
    strings: dict[str, str] = {}
    floats: dict[float, float] = {}
    share_str, share_float = strings.setdefault, floats.setdefault
    for res in results:
        # inline, not a function call per value: ~300 values per log
        res.rows = [
            tuple(
                [
                    share_str(v, v)
                    if type(v) is str
                    else share_float(v, v)
                    if type(v) is float and v == v and v != 0.0
                    else v
                    for v in row
                ]
            )
            for row in res.rows
        ]


def read_logs(
    paths: Sequence[Path],
    data_dir: Path,
    settings: EstimatorSettings,
    *,
    workers: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Iterator[LogResult]:
    """Every log's :class:`LogResult`, in the order of ``paths``.

    Parameters
    ----------
    paths : sequence of Path
        Logs under ``data_dir``.
    data_dir : Path
        The data folder (names in the results are relative to it).
    settings : EstimatorSettings
        How ALs are re-estimated.
    workers : int, optional
        Processes; default: the CPU count when there are at least ``PARALLEL_FROM`` logs,
        else 1 (in-process).
    progress : callable, optional
        Called with (logs read, logs found).

    Examples
    --------
    >>> list(read_logs([], Path("."), EstimatorSettings()))
    []
    """
    jobs = [(p, p.relative_to(data_dir).as_posix()) for p in paths]
    n = len(jobs)
    if workers is None:
        workers = (os.cpu_count() or 1) if n >= PARALLEL_FROM else 1
    if workers <= 1 or n < 2:
        return _read_here(jobs, settings, progress)
    # Every chunk is handed to the workers now, not at the first result asked for: the caller
    # loads the rest of the analysis while they read.
    chunks = [(jobs[i : i + _CHUNK], settings) for i in range(0, n, _CHUNK)]
    pool = worker_pool(min(workers, len(chunks)))
    try:
        parts = pool.map(_read_chunk, chunks)
    except BaseException:
        cancel_pool(pool)
        raise
    # the chunks of a worker that died (killed for memory, say) are read here
    return _gathered(pool, rest_here(parts, _read_chunk, chunks), n, progress)


def _read_here(
    jobs: list[tuple[Path, str]],
    settings: EstimatorSettings,
    progress: Callable[[int, int], None] | None,
) -> Iterator[LogResult]:
    for done, (path, rel) in enumerate(jobs, 1):
        yield read_one(path, rel, settings)
        if progress:
            progress(done, len(jobs))


def _gathered(
    pool: ProcessPoolExecutor,
    parts: Iterator[list[LogResult]],
    n: int,
    progress: Callable[[int, int], None] | None,
) -> Iterator[LogResult]:
    """The workers' results in order; the pool is shut down when they are all in, or, when the
    caller stops early, once the chunks being read are done (the queued ones are cancelled)."""
    done = 0
    try:
        for results in parts:
            for result in results:
                yield result
                done += 1
                if progress:
                    progress(done, n)
    finally:
        pool.shutdown(wait=True, cancel_futures=done < n)
