"""One row per trial of every session (pure): the long table R's ``glmer`` and pandas expect.

``analyze`` writes it as ``trials.csv`` (and ``trials.parquet`` when pyarrow is installed);
the columns are described in ``data_schema/trials.csv.json``. Rows keep the log's order
(sessions in the order read, then sets, then trials). Each row carries the status that
``thresholds.csv`` gives its set attempt (``set_status``), so a model can keep the completed,
not superseded sets with one filter.

Levels are dB: ``level_db`` is in the unit the set's track ran in (``level_unit``: ``db_sl``
above the participant's unmasked AL of the target for masked sets, ``db_v`` re 1 V for baseline
sets); ``level_db_sl`` and ``level_db_v`` give both. Times are seconds on the session clock.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from typing import Any

from masking_lab.formats.session_log import SessionLog

__all__ = ["TRIAL_COLUMNS", "trial_rows"]

TRIAL_COLUMNS = [
    "participant",
    "session_id",
    "created_utc",
    "experiment",
    "protocol_path",
    "set_id",
    "set_position",
    "target",
    "masker",
    "masker_level_db_sl",
    "procedure",
    "level_unit",
    "trial",
    "level_db",
    "level_db_sl",
    "level_db_v",
    "correct",
    "target_interval",
    "response_interval",
    "reversal",
    "response_time_s",
    "planned_onset_1_s",
    "planned_onset_2_s",
    "planned_onset_3_s",
    "actual_onset_1_s",
    "actual_onset_2_s",
    "actual_onset_3_s",
    "posterior_mean_db",
    "posterior_sd_db",
    "at_bound",
    "set_status",
    "log",
    "line",
]


def _num(v: Any) -> float | None:
    """A finite float, or None (non-finite numbers never reach an output)."""
    # The exact types a parsed log holds first: this runs ~12 times per trial row.
    kind = type(v)
    if kind is float:
        return v if math.isfinite(v) else None
    if kind is bool or not isinstance(v, int | float):
        return None
    f = float(v)
    return f if math.isfinite(f) else None


def _int(v: Any) -> int | None:
    return v if type(v) is int or (isinstance(v, int) and not isinstance(v, bool)) else None


def _flag(v: Any) -> int | None:
    """A logged boolean as 1/0 (what ``glmer(family = binomial)`` and pandas sums take)."""
    return int(v) if isinstance(v, bool) else None


def _onsets(v: Any) -> list[float | None]:
    if type(v) is list and len(v) == 3:  # a 3IFC trial's onsets: the common case
        return [_num(v[0]), _num(v[1]), _num(v[2])]
    vals = list(v) if isinstance(v, list) else []
    return [_num(vals[i]) if i < len(vals) else None for i in range(3)]


def _procedure(start: Mapping[str, Any]) -> str:
    proc = start.get("procedure")
    if isinstance(proc, Mapping):
        return str(proc.get("kind", "procedure"))
    return "staircase"


def trial_rows(
    log: SessionLog, log_name: str, set_status: Mapping[tuple[str, str], str] | None = None
) -> Iterator[list[Any]]:
    """The trial rows of one parsed session log, in :data:`TRIAL_COLUMNS` order.

    Parameters
    ----------
    log : SessionLog
        A log parsed by the general reader (records as dicts).
    log_name : str
        How the log is named (path relative to the data folder, as in ``thresholds.csv``).
    set_status : mapping, optional
        ``(log_name, set_id)`` → the set attempt's status in ``thresholds.csv``.

    Yields
    ------
    list
        One row per ``trial`` record that belongs to a started set; levels in dB, times in s,
        ``correct``/``reversal`` as 1/0, absent or non-finite values as None.

    Examples
    --------
    >>> from pathlib import Path
    >>> from masking_lab.formats.session_log import parse_log
    >>> raw = (b'{"record":"header","participant":"P1","session_id":"s1",'
    ...        b'"protocol":{"experiment":"e1","path":"p.yaml"}}\\n'
    ...        b'{"record":"set_start","set_id":"A","target":"EV270","masker":"MV120",'
    ...        b'"masker_level_db_sl":10,"level_unit":"db_sl"}\\n'
    ...        b'{"record":"trial","set_id":"A","trial_index":0,"level_db_sl":12.0,'
    ...        b'"level_db_v":-20.0,"correct":true,"reversal":false,"target_interval":2,'
    ...        b'"response_interval":2,"response_time_s":0.8,'
    ...        b'"planned_onsets_s":[1,2,3],"actual_onsets_s":[1,2,3.001]}\\n')
    >>> row = dict(zip(TRIAL_COLUMNS, next(trial_rows(parse_log(raw, "x"), "x.jsonl"))))
    >>> row["participant"], row["trial"], row["level_db"], row["correct"], row["line"]
    ('P1', 0, 12.0, 1, 3)
    """
    h = log.header if isinstance(log.header, Mapping) else {}
    raw_protocol = h.get("protocol")
    protocol = raw_protocol if isinstance(raw_protocol, Mapping) else {}
    base = [
        str(h.get("participant", "")),
        str(h.get("session_id", log_name)),
        str(h.get("created_utc", "")),
        str(protocol.get("experiment", "")),
        str(protocol.get("path", "")),
    ]
    status = set_status or {}
    starts: dict[str, tuple[list[Any], str]] = {}
    lines = log.lines or [0] * len(log.records)
    for rec, line in zip(log.records, lines, strict=False):
        kind = rec.get("record")
        sid = rec.get("set_id")
        if kind == "set_start" and isinstance(sid, str):
            unit = "db_sl" if rec.get("level_unit") == "db_sl" else "db_v"
            position = starts[sid][0][1] if sid in starts else len(starts)
            masker = rec.get("masker")
            starts[sid] = (
                [
                    sid,
                    position,
                    rec.get("target"),
                    masker if isinstance(masker, str) else None,
                    _num(rec.get("masker_level_db_sl")),
                    _procedure(rec),
                    unit,
                ],
                unit,
            )
        elif kind == "trial" and isinstance(sid, str) and sid in starts:
            head, unit = starts[sid]
            level = _num(rec.get("level_" + unit))
            post = rec.get("posterior")
            if not isinstance(post, Mapping):
                post = {}
            bound = rec.get("at_bound")
            yield [
                *base,
                *head,
                _int(rec.get("trial_index")),
                level,
                _num(rec.get("level_db_sl")),
                _num(rec.get("level_db_v")),
                _flag(rec.get("correct")),
                _int(rec.get("target_interval")),
                _int(rec.get("response_interval")),
                _flag(rec.get("reversal")),
                _num(rec.get("response_time_s")),
                *_onsets(rec.get("planned_onsets_s")),
                *_onsets(rec.get("actual_onsets_s")),
                _num(post.get("mean_db")),
                _num(post.get("sd_db")),
                bound if bound in ("upper", "lower") else None,
                status.get((log_name, sid)),
                log_name,
                line,
            ]
