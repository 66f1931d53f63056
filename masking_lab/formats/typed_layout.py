"""Where each set of an intact typed log lies, found in one pass (pure).

A log the writer wrote without mishap is a run of sets, each a ``set_start``, its trials
counting 0, 1, 2, … and its ``set_end``, then ``session_end``. For such a log, one loop over
the records finds everything the reading of ``analyze`` asks of their order: the records of
each set (:meth:`~masking_lab.formats.session_log.SessionLog.sets`, then slices of the record
list), that no structural continuity problem is there
(:meth:`~masking_lab.formats.session_log.SessionLog.continuity_problems`) and whether any trial
reports the amplitude it played (:mod:`masking_lab.analysis.played_levels`); before, each was
its own loop over every record.

:func:`intact_layout` answers only for that common shape; anything else (a fault or resume
record, a user-test trial, a record out of place) answers None, and the caller takes the
record-by-record routes, which say what is wrong and where.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from msgspec import UNSET

from masking_lab.formats.log_records import ASessionEnd, ASetEnd, ASetStart, ATrial

__all__ = ["Layout", "intact_layout"]


@dataclass(frozen=True)
class Layout:
    """The sets of an intact typed log.

    Attributes
    ----------
    spans : list of (int, int)
        Per set, in order: ``(start, stop)`` positions in the record list. ``records[start]``
        is its ``set_start``, ``records[start + 1 : stop]`` are all its trials, and
        ``records[stop]`` is its ``set_end`` unless the set is the last and did not end.
    ended : list of bool
        Per set, whether it has its ``set_end``.
    played : bool
        Some trial carries ``played_target_v`` (not absent, not null).
    """

    spans: list[tuple[int, int]]
    ended: list[bool]
    played: bool


def intact_layout(records: list[Any]) -> Layout | None:
    """The :class:`Layout` of a typed log's records, or None if they are not of its shape.

    Not None only when the log holds nothing but sets, their trials and at most one
    ``session_end`` (its last record); no set starts twice or while another is open; each
    set's trials lie between its ``set_start`` and ``set_end``, carry its id and count 0, 1,
    2, …; and each ``set_end`` names its set and, if it counts trials, counts them right.
    These are exactly the logs of this shape in which the full continuity check
    (:func:`~masking_lab.formats.log_integrity.problems_of_keys`) finds no structural
    problem. Set ids absent and null are one id when records are grouped, so a log holding
    both answers None too.

    Examples
    --------
    >>> from masking_lab.formats.log_records import ANALYSIS_DECODER
    >>> recs = ANALYSIS_DECODER.decode_lines(
    ...     b'{"record":"set_start","set_id":"A"}\\n'
    ...     b'{"record":"trial","set_id":"A","trial_index":0}\\n'
    ...     b'{"record":"set_end","set_id":"A","n_trials":1}\\n')
    >>> intact_layout(recs)
    Layout(spans=[(0, 2)], ended=[True], played=False)
    >>> intact_layout(recs[1:]) is None  # a trial before its set_start
    True
    """
    unset = UNSET
    spans: list[tuple[int, int]] = []
    ids: list[Any] = []
    open_at = -1
    sid: Any = None
    n_trials = 0
    played = ended = False
    for i, rec in enumerate(records):
        if ended:
            return None
        cls = type(rec)
        if cls is ATrial:
            if open_at < 0 or rec.set_id != sid or rec.trial_index != n_trials:
                return None
            n_trials += 1
            if not played:
                value = rec.played_target_v
                played = value is not unset and value is not None
        elif cls is ASetStart:
            if open_at >= 0:
                return None
            open_at, sid, n_trials = i, rec.set_id, 0
            ids.append(sid)
        elif cls is ASetEnd:
            if open_at < 0 or rec.set_id != sid:
                return None
            if rec.n_trials is not unset and rec.n_trials != n_trials:
                return None
            spans.append((open_at, i))
            open_at = -1
        elif cls is ASessionEnd:
            ended = True
        else:
            return None
    closed = [True] * len(spans)
    if open_at >= 0:  # the session stopped mid-set: its trials follow its set_start
        spans.append((open_at, open_at + 1 + n_trials))
        closed.append(False)
    if len(set(ids)) != len(ids) or (unset in ids and None in ids):
        return None
    return Layout(spans, closed, played)
