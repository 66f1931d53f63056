"""Checks across the logs of one ``analyze`` run (pure: works on read results, no I/O).

A study folder gathered by hand holds surprises: a byte copy of a log beside it or deep in a
subfolder, a copy taken mid-session and the session continued afterwards, a participant who ran
one protocol twice to the end, a record holding NaN. Each is counted once and said out loud:

- :func:`duplicate_sessions` — logs sharing a ``session_id`` are one session: the longest log
  (most bytes; then the fewest folders deep, the shortest name, the first by path) is
  analysed, every other is skipped as its copy;
- :func:`repeated_sessions` — two or more *complete* sessions (``session_end`` with status
  ``completed``) of one experiment for one participant: the latest (by ``created_utc``, then
  session id, then path — the order :func:`~masking_lab.analysis.thresholds.thresholds_table`
  uses) counts; every set it completed again marks the earlier attempt ``superseded``;
- :func:`refused_sets` — records holding a non-finite number, whose sets are ``invalid``.

Each answer is a ``problems.csv`` row (``log``, ``problem``, ``action``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

__all__ = ["duplicate_sessions", "refused_sets", "repeated_sessions"]


class _Read(Protocol):
    """What these checks read of :class:`~masking_lab.analysis.log_reading.LogResult`."""

    rel: str
    error: str | None
    sha256: str
    header: dict
    n_bytes: int
    completed: bool
    value_problems: list[str]


def duplicate_sessions(results: Sequence[_Read]) -> dict[str, str]:
    """Logs to skip because another log holds the same session: relative path → reason.

    Examples
    --------
    >>> from types import SimpleNamespace as R
    >>> a = R(rel="a.jsonl", error=None, sha256="1", header={"session_id": "S"}, n_bytes=9)
    >>> b = R(rel="old/a.jsonl", error=None, sha256="1", header={"session_id": "S"}, n_bytes=9)
    >>> duplicate_sessions([a, b])
    {'old/a.jsonl': 'a byte copy of a.jsonl (session S); analysed once, from a.jsonl'}
    """
    groups: dict[str, list[_Read]] = {}
    for res in results:
        sid = res.header.get("session_id") if res.error is None else None
        if isinstance(sid, str) and sid:
            groups.setdefault(sid, []).append(res)
    out: dict[str, str] = {}
    for sid, group in groups.items():
        if len(group) < 2:
            continue
        keep = min(group, key=_original_first)
        for res in group:
            if res is keep:
                continue
            if res.sha256 == keep.sha256:
                what = f"a byte copy of {keep.rel} (session {sid})"
            else:
                what = (
                    f"the same session ({sid}) as {keep.rel}, which is longer (a copy taken "
                    "before the session went on)"
                )
            out[res.rel] = f"{what}; analysed once, from {keep.rel}"
    return out


def _original_first(res: _Read) -> tuple[int, int, int, str]:
    """Which of a session's logs is analysed: the longest (a copy taken mid-session is a
    prefix), then the shallowest and shortest name (copies land in backups and get suffixes
    like `` (1)``), then path order."""
    return (-res.n_bytes, res.rel.count("/"), len(res.rel), res.rel)


def repeated_sessions(results: Sequence[_Read]) -> list[dict[str, str]]:
    """A problem row for each complete session that a later complete one of the same
    participant and experiment outranks.

    Examples
    --------
    >>> from types import SimpleNamespace as R
    >>> h = {"participant": "P1", "protocol": {"experiment": "experiment1"}}
    >>> a = R(rel="a.jsonl", completed=True, header={**h, "created_utc": "2024-01-01T00:00:00Z"})
    >>> b = R(rel="b.jsonl", completed=True, header={**h, "created_utc": "2024-02-01T00:00:00Z"})
    >>> [(p["log"], p["action"]) for p in repeated_sessions([b, a])]
    [('a.jsonl', 'its sets completed again in b.jsonl are superseded')]
    """
    groups: dict[tuple[str, str], list[_Read]] = {}
    for res in results:
        protocol = res.header.get("protocol")
        experiment = protocol.get("experiment") if isinstance(protocol, dict) else None
        participant = res.header.get("participant")
        if res.completed and isinstance(participant, str) and isinstance(experiment, str):
            groups.setdefault((participant, experiment), []).append(res)
    out: list[dict[str, str]] = []
    for (participant, experiment), group in sorted(groups.items()):
        if len(group) < 2:
            continue
        group = sorted(group, key=_session_order)
        latest = group[-1]
        names = ", ".join(r.rel for r in group)
        for res in group[:-1]:
            out.append(
                {
                    "log": res.rel,
                    "problem": f"participant {participant} has {len(group)} complete sessions of "
                    f"{experiment} ({names}); the latest, {latest.rel}, counts",
                    "action": f"its sets completed again in {latest.rel} are superseded",
                }
            )
    return out


def _session_order(res: _Read) -> tuple[str, str, str]:
    h = res.header
    created = h.get("created_utc")
    sid = h.get("session_id")
    return (
        created if isinstance(created, str) else "",
        sid if isinstance(sid, str) else "",
        res.rel,
    )


def refused_sets(res: _Read) -> list[dict[str, str]]:
    """A problem row for each record of ``res`` holding a non-finite number.

    Examples
    --------
    >>> from types import SimpleNamespace as R
    >>> refused_sets(R(rel="a.jsonl", value_problems=["line 9: a non-finite number (NaN)"]))
    [{'log': 'a.jsonl', 'problem': 'line 9: a non-finite number (NaN)', 'action': 'set refused'}]
    """
    return [{"log": res.rel, "problem": p, "action": "set refused"} for p in res.value_problems]
