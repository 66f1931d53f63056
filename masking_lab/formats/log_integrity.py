"""Session-log integrity, pure: where a torn last line ends, and record continuity.

Two questions about a log's bytes and records, answered without I/O:

- :func:`split_tail` — is the last line complete? A crash mid-write leaves a last line without
  its newline. The answer is found on *bytes* (never on decoded-and-re-encoded text, which
  would miscount a multi-byte UTF-8 character cut in half): the complete part ends at the last
  ``\\n``; the rest is either a whole record that only lacks its newline (kept) or a torn one
  (cut).
- :func:`continuity_problems` — were records deleted, duplicated or reordered? Every record the
  writer writes carries ``seq``, its 1-based line number, so a gap, a repeat or a step back is
  visible; trial indices must count 0, 1, 2, … within each set, trials belong between their
  set's ``set_start`` and ``set_end``, a set ends once with the number of trials it holds, and
  nothing follows ``session_end``. Each problem names its line.

Logs written before ``seq`` existed have no counter; their structure is still checked.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

__all__ = [
    "Tail",
    "continuity_problems",
    "interleaved",
    "problems_of_keys",
    "record_key",
    "split_tail",
]


@dataclass(frozen=True)
class Tail:
    """How a log's bytes end.

    Attributes
    ----------
    complete_end : int
        Byte offset just after the last ``\\n`` (0 if there is none): the complete lines.
    tail : bytes
        The bytes after it (empty when the file ends with a newline).
    whole_record : bool
        The tail is a complete JSON object with a ``record`` key that lacks only its newline
        (a crash between the record and its ``\\n``): keep it, and add the newline.
    """

    complete_end: int
    tail: bytes
    whole_record: bool


def split_tail(raw: bytes) -> Tail:
    """Where the complete lines of a log's bytes end, and what follows them.

    A proper prefix of a JSON object is never a complete JSON object (its closing brace is
    its last byte), so a tail that parses as an object is the whole record.

    Examples
    --------
    >>> split_tail(b'{"record":"header"}\\n{"record":"tri')
    Tail(complete_end=20, tail=b'{"record":"tri', whole_record=False)
    >>> split_tail(b'{"record":"header"}\\n{"record":"trial"}').whole_record
    True
    """
    end = raw.rfind(b"\n") + 1
    tail = raw[end:]
    whole = False
    if tail.strip():
        try:
            value = json.loads(tail.decode("utf-8"))
        except (UnicodeDecodeError, ValueError, RecursionError):
            value = None
        whole = isinstance(value, dict) and "record" in value
    return Tail(end, tail, whole)


@dataclass
class _SetState:
    start_line: int
    n_trials: int = 0
    end_line: int | None = None


def continuity_problems(entries: Sequence[tuple[int, Mapping[str, Any]]]) -> list[str]:
    """Every continuity problem of a log's records, as ``"line N: ..."`` notes.

    Parameters
    ----------
    entries : sequence of (line, record)
        Each parsed record (header included) with its 1-based line number, in file order.
        Records are mappings or anything with ``get`` (the typed analysis view).

    Returns
    -------
    list[str]
        Empty for an intact log.

    Examples
    --------
    >>> recs = [{"record": "header", "seq": 1}, {"record": "set_start", "set_id": "A", "seq": 2},
    ...         {"record": "trial", "set_id": "A", "trial_index": 0, "seq": 4}]
    >>> continuity_problems(list(enumerate(recs, start=1)))
    ['line 3: record counter jumps from 2 to 4: 1 record(s) missing before this line']
    """
    keys = [(line, *record_key(rec)) for line, rec in entries]
    return problems_of_keys(keys, interleaved=_interleaved(entries))


def problems_of_keys(
    keys: Sequence[Key], *, interleaved: bool = False, counter_intact: bool = False
) -> list[str]:
    """:func:`continuity_problems` from ``(line, kind, seq, set_id, index)`` tuples.

    ``counter_intact``: the caller has checked that every ``seq`` equals its line (the
    common case, checked in bulk), so only the structure is checked here.

    Examples
    --------
    >>> problems_of_keys([(1, "header", 1, None, None), (2, "trial", 2, "A", 0)])
    ['line 2: trial of set A before any set_start of it']
    """
    problems: list[str] = []
    if not counter_intact:
        problems += _counter_problems(keys)
    problems += _structure_problems(keys, interleaved=interleaved)
    problems.sort(key=lambda p: int(p.split(":", 1)[0].removeprefix("line ")))
    return problems


_INDEX_FIELD = {"trial": "trial_index", "set_end": "n_trials", "usertest_trial": "trial"}
Key = tuple[int, Any, Any, Any, Any]  # line, kind, seq, set_id, index (see record_key)


def record_key(rec: Any) -> tuple[Any, Any, Any, Any]:
    """What continuity looks at in a record: (kind, seq, set_id, index).

    ``index`` is ``trial_index`` of a trial, ``n_trials`` of a set_end, ``trial`` of a user-test
    trial, else None.

    Examples
    --------
    >>> record_key({"record": "trial", "seq": 5, "set_id": "A", "trial_index": 2})
    ('trial', 5, 'A', 2)
    """
    kind = rec.get("record")
    field = _INDEX_FIELD.get(kind) if isinstance(kind, str) else None
    return kind, rec.get("seq"), rec.get("set_id"), rec.get(field) if field else None


def _counter_problems(keys: Sequence[Key]) -> list[str]:
    out: list[str] = []
    seen: dict[int, int] = {}
    prev: int | None = None
    offset = 0  # line - seq expected for the next record: 0 in an intact log
    for line, kind, seq, _, _ in keys:
        if seq is None:
            if prev is not None:
                out.append(
                    f"line {line}: {kind} record without a record counter (seq) "
                    "after records with one: written by other software or edited"
                )
            continue
        if not isinstance(seq, int) or isinstance(seq, bool):
            out.append(f"line {line}: record counter seq={seq!r} is not an integer")
            continue
        if seq in seen:
            out.append(
                f"line {line}: repeats record {seq} (first on line {seen[seq]}): "
                "a duplicated record"
            )
        elif prev is not None and seq < prev:
            out.append(f"line {line}: record {seq} comes after record {prev}: records out of order")
        elif prev is not None and seq > prev + 1:
            out.append(
                f"line {line}: record counter jumps from {prev} to {seq}: "
                f"{seq - prev - 1} record(s) missing before this line"
            )
        elif line - seq != offset:
            # Report a shifted counter once, where the shift starts, not on every later line.
            out.append(
                f"line {line}: record {seq} is on line {line}: lines were added or removed "
                "before it"
            )
        seen.setdefault(seq, line)
        prev = seq if prev is None else max(prev, seq)
        offset = line - prev
    return out


def interleaved(header: Any) -> bool:
    """Whether the header's protocol interleaves its sets (``order.interleave``).

    Examples
    --------
    >>> interleaved({"protocol": {"content": {"order": {"interleave": True}}}})
    True
    """
    return _interleaved([(1, header)])


def _interleaved(entries: Sequence[tuple[int, Mapping[str, Any]]]) -> bool:
    """Whether the header's protocol interleaves its sets (``order.interleave``): then every
    set starts before the first trial and several are open at once, by design."""
    if not entries:
        return False
    header = entries[0][1]
    protocol = header.get("protocol") if hasattr(header, "get") else None
    content = protocol.get("content") if isinstance(protocol, Mapping) else None
    order = content.get("order") if isinstance(content, Mapping) else None
    return bool(order.get("interleave", False)) if isinstance(order, Mapping) else False


def _structure_problems(keys: Sequence[Key], *, interleaved: bool = False) -> list[str]:
    out: list[str] = []
    sets: dict[Any, _SetState] = {}
    open_set: Any = None
    ended_at: int | None = None
    usertest_trials = 0
    for k, (line, kind, _, sid, index) in enumerate(keys):
        if ended_at is not None:
            out.append(f"line {line}: {kind} record after session_end (line {ended_at})")
        if kind == "header":
            if k > 0:
                out.append(f"line {line}: a second header record")
            continue
        state = sets.get(sid)
        if kind == "set_start":
            if state is not None and state.end_line is not None:
                out.append(
                    f"line {line}: set_start of set {sid} after its set_end (line {state.end_line})"
                )
            elif open_set is not None and open_set != sid and not interleaved:
                out.append(
                    f"line {line}: set {sid} starts while set {open_set} "
                    f"(line {sets[open_set].start_line}) has no set_end"
                )
            if state is None:
                sets[sid] = _SetState(line)
            open_set = sid
        elif kind == "trial":
            if state is None:
                out.append(f"line {line}: trial of set {sid} before any set_start of it")
                continue
            if state.end_line is not None:
                out.append(
                    f"line {line}: trial of set {sid} after its set_end (line {state.end_line})"
                )
            if index != state.n_trials:
                out.append(
                    f"line {line}: trial index {index} in set {sid}, expected {state.n_trials} "
                    "(a trial record is missing, repeated or out of order)"
                )
            state.n_trials += 1
        elif kind == "set_end":
            if state is None:
                out.append(f"line {line}: set_end of set {sid} before any set_start of it")
                continue
            if state.end_line is not None:
                out.append(
                    f"line {line}: a second set_end of set {sid} (first on line {state.end_line})"
                )
            if isinstance(index, int) and index != state.n_trials:
                out.append(
                    f"line {line}: set_end of set {sid} counts {index} trials, the log holds "
                    f"{state.n_trials}"
                )
            state.end_line = line
            if open_set == sid:
                open_set = None
        elif kind == "usertest_trial":
            if index != usertest_trials:
                out.append(
                    f"line {line}: user-test trial {index}, expected {usertest_trials} "
                    "(a trial record is missing, repeated or out of order)"
                )
            usertest_trials += 1
        elif kind == "session_end":
            ended_at = line
    return out
