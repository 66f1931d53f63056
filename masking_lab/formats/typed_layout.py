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
record-by-record routes, which say what is wrong and where. :func:`typed_structure_intact` is
the wider structural shortcut for those (faults, resumes and user-test trials allowed).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from msgspec import UNSET

from masking_lab.formats.log_records import (
    AFault,
    AResume,
    ASessionEnd,
    ASetEnd,
    ASetStart,
    ATrial,
    AUsertestTrial,
)

__all__ = ["Layout", "intact_layout", "typed_structure_intact"]


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


_NO_SET = object()  # no set open (distinct from a set whose id is missing)


def typed_structure_intact(records: list[Any]) -> bool:
    """True only if :func:`~masking_lab.formats.log_integrity.problems_of_keys` would find no
    structural problem in these typed view records of a non-interleaved log.

    The common case, answered in one tight pass (about a sixth of the cost of building the
    keys); anything unusual (a set started twice, a set open while another starts, a second
    header, a set_end whose count is not an int) answers False, and the caller runs the full
    check, which says what is wrong and where.
    """
    unset = UNSET
    open_set: Any = _NO_SET
    seen: set[Any] = set()
    n_trials = usertest_trials = 0
    ended = False
    for rec in records:
        if ended:
            return False
        cls = type(rec)
        if cls is ATrial:
            if rec.set_id != open_set or rec.trial_index != n_trials:
                return False
            n_trials += 1
        elif cls is ASetStart:
            if open_set is not _NO_SET or rec.set_id in seen:
                return False
            open_set = rec.set_id
            seen.add(open_set)
            n_trials = 0
        elif cls is ASetEnd:
            if rec.set_id != open_set or (rec.n_trials is not unset and rec.n_trials != n_trials):
                return False
            open_set = _NO_SET
        elif cls is AUsertestTrial:
            if rec.trial != usertest_trials:
                return False
            usertest_trials += 1
        elif cls is ASessionEnd:
            ended = True
        elif cls is not AFault and cls is not AResume:
            return False
    return True
