"""The second read of ``analyze`` (*shell*): each analysed log parsed by the general reader for
the fields the analysis view leaves out (intervals, response times, onsets, the participant's
``info``), in parallel for many logs.

Each log gives a :class:`LogPart`: its session for the study matrix, the participant's
``info``, its sets' trials for the psychometric fits, and its ``trials.csv`` lines already
formatted (the formatting, a cell at a time, is the costly part, so it runs where the log was
read). Parts come back in the order of the logs, so the outputs keep their bytes however many
processes read them.
"""

from __future__ import annotations

import importlib.util
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from masking_lab.analysis.log_reading import PARALLEL_FROM
from masking_lab.analysis.pf_table import SetTrials, set_trials
from masking_lab.analysis.study_status import SessionInfo, session_of
from masking_lab.analysis.trials_table import TRIAL_COLUMNS, trial_rows
from masking_lab.core.errors import LogError
from masking_lab.core.worker_processes import rest_here, worker_pool
from masking_lab.formats.csv_table import csv_text_columns
from masking_lab.formats.session_log import read_log

__all__ = ["LogPart", "ParquetSink", "StudyLogs", "read_parts", "trial_batch"]

_CHUNK = 16  # logs per worker task


@dataclass
class LogPart:
    """What one analysed log gives the per-participant outputs.

    Attributes
    ----------
    session : SessionInfo
        Its session (participant, experiment, log, planned sets, how it ended).
    info : mapping or None
        The header's ``info`` (the participant's answers), if any.
    info_specs : list of dict
        The protocol's ``info`` field specifications.
    sets : dict
        Set id → :class:`~masking_lab.analysis.pf_table.SetTrials` (levels in dB).
    trials_csv : str
        Its ``trials.csv`` lines without the header ('' unless asked for).
    trial_batch : pyarrow.RecordBatch or None
        Its trial rows as columns, for ``trials.parquet`` (None unless asked for).
    """

    session: SessionInfo
    info: Mapping[str, Any] | None
    info_specs: list[dict[str, Any]]
    sets: dict[str, SetTrials]
    trials_csv: str = ""
    trial_batch: Any = None  # pyarrow.RecordBatch


@dataclass
class StudyLogs:
    """The analysed logs as the per-participant outputs need them."""

    sessions: list[SessionInfo] = field(default_factory=list)
    sets: dict[tuple[str, str], SetTrials] = field(default_factory=dict)
    info: dict[str, dict[str, Any]] = field(default_factory=dict)
    info_fields: dict[str, dict[str, Any]] = field(default_factory=dict)
    sessions_of: dict[str, int] = field(default_factory=dict)

    def add(self, part: LogPart) -> None:
        """Take in one log (in the order the logs are listed)."""
        s = part.session
        self.sessions.append(s)
        self.sessions_of[s.participant] = self.sessions_of.get(s.participant, 0) + 1
        if part.info is not None:
            self.info.setdefault(s.participant, {}).update(part.info)
        for spec in part.info_specs:
            self.info_fields.setdefault(spec["name"], spec)
        for sid, st in part.sets.items():
            self.sets[(s.log, sid)] = st


def read_part(
    path: Path,
    rel: str,
    set_status: Mapping[tuple[str, str], str] | None = None,
    *,
    csv: bool = False,
    rows: bool = False,
) -> LogPart | None:
    """One log's :class:`LogPart`, or None when it cannot be read (the analysis' own read
    has reported it already).

    Examples
    --------
    >>> read_part(Path("/nonexistent.jsonl"), "x.jsonl") is None
    True
    """
    try:
        log = read_log(path)
    except LogError:
        return None
    h = log.header if isinstance(log.header, Mapping) else {}
    session, info, specs = session_of(h, rel, log.ended)
    part = LogPart(session, info, specs, set_trials(log))
    if csv or rows:
        table = list(trial_rows(log, rel, set_status))
        if csv:
            # Formatted a column at a time (the same bytes as row by row, csv_table's tests):
            # a study's trials.csv has millions of cells.
            columns = [list(c) for c in zip(*table, strict=True)] or [[] for _ in TRIAL_COLUMNS]
            part.trials_csv = csv_text_columns(TRIAL_COLUMNS, columns).split("\n", 1)[1]
        if rows:
            part.trial_batch = trial_batch(table)
    return part


def _read_chunk(
    args: tuple[list[tuple[Path, str]], dict[tuple[str, str], str], bool, bool],
) -> list[LogPart | None]:
    jobs, status, csv, rows = args
    return [read_part(path, rel, status, csv=csv, rows=rows) for path, rel in jobs]


def read_parts(
    data: Path,
    logs: Sequence[str],
    set_status: Mapping[tuple[str, str], str] | None = None,
    *,
    csv: bool = False,
    rows: bool = False,
    workers: int | None = None,
) -> Iterator[LogPart | None]:
    """Every log's :func:`read_part`, in the order of ``logs`` (relative paths under ``data``).

    Parameters
    ----------
    data : Path
        The data folder.
    logs : sequence of str
        The analysed logs.
    set_status : mapping, optional
        ``(log, set_id)`` → status in ``thresholds.csv``, for the trial rows.
    csv, rows : bool
        Format each log's ``trials.csv`` lines; keep its trial rows (for ``trials.parquet``).
    workers : int, optional
        Processes; default: the CPU count from ``PARALLEL_FROM`` logs on, else in-process.

    Examples
    --------
    >>> list(read_parts(Path("."), []))
    []
    """
    status = set_status or {}
    if workers is None:
        workers = (os.cpu_count() or 1) if len(logs) >= PARALLEL_FROM else 1
    if workers <= 1 or len(logs) < 2:
        for rel in logs:
            yield read_part(data / rel, rel, status, csv=csv, rows=rows)
        return
    by_log: dict[str, dict[tuple[str, str], str]] = {}
    for key, value in status.items():
        by_log.setdefault(key[0], {})[key] = value
    chunks = []
    for i in range(0, len(logs), _CHUNK):
        names = logs[i : i + _CHUNK]
        sub = {k: v for rel in names for k, v in by_log.get(rel, {}).items()}
        chunks.append(([(data / rel, rel) for rel in names], sub, csv, rows))
    with worker_pool(min(workers, len(chunks))) as pool:
        # the chunks of a worker that died (killed for memory, say) are read here
        for parts in rest_here(pool.map(_read_chunk, chunks), _read_chunk, chunks):
            yield from parts


def trial_batch(rows: list[list[Any]]) -> Any:
    """Trial rows (:data:`~masking_lab.analysis.trials_table.TRIAL_COLUMNS` order) as a
    ``pyarrow.RecordBatch`` of the ``trials.parquet`` column types (needs pyarrow).

    Examples
    --------
    >>> trial_batch([]).num_rows  # doctest: +SKIP
    0
    """
    import pyarrow as pa

    cols: list[Sequence[Any]] = (
        list(zip(*rows, strict=True)) if rows else [[] for _ in TRIAL_COLUMNS]
    )
    return pa.record_batch(
        [pa.array(list(v), type=_ARROW[c]()) for c, v in zip(TRIAL_COLUMNS, cols, strict=True)],
        names=TRIAL_COLUMNS,
    )


class ParquetSink:
    """``trials.parquet`` written in row groups when pyarrow is installed; else nothing.

    Each log's rows come as one record batch (columns, a fraction of the memory of rows); a
    row group is written once 200,000 rows are held, so the row groups fall where they fell
    when rows were gathered one log at a time.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.batches: list[Any] = []
        self.n_rows = 0
        self.writer: Any = None
        self.enabled = importlib.util.find_spec("pyarrow") is not None

    def add(self, batch: Any) -> None:
        """Hold one log's rows (a record batch from :func:`trial_batch`)."""
        if self.enabled:
            self.batches.append(batch)
            self.n_rows += batch.num_rows
            if self.n_rows >= 200_000:
                self._flush()

    def _flush(self) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        batches = self.batches or [trial_batch([])]
        table = pa.Table.from_batches(batches).combine_chunks()
        if self.writer is None:
            self.writer = pq.ParquetWriter(self.path, table.schema)
        self.writer.write_table(table)
        self.batches, self.n_rows = [], 0

    def close(self) -> list[Path]:
        """Write what is held and close the file; the files written."""
        if not self.enabled:
            return []
        if self.batches or self.writer is None:
            self._flush()
        self.writer.close()
        return [self.path]


def _arrow_types() -> dict[str, Callable[[], Any]]:
    def t(name: str) -> Callable[[], Any]:
        def make() -> Any:
            import pyarrow as pa

            return getattr(pa, name)()

        return make

    ints = {"set_position", "trial", "correct", "target_interval", "response_interval",
            "reversal", "line"}  # fmt: skip
    strs = {"participant", "session_id", "created_utc", "experiment", "protocol_path",
            "set_id", "target", "masker", "procedure", "level_unit", "at_bound", "set_status",
            "log"}  # fmt: skip
    return {c: t("int64") if c in ints else t("string") if c in strs else t("float64")
            for c in TRIAL_COLUMNS}  # fmt: skip


_ARROW = _arrow_types()
