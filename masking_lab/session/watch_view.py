"""What ``masking-lab watch LOG`` shows of a running session (pure: works on a parsed log).

:func:`watch_view` turns the records so far into a few lines: who and what, sets and trials
done and left, the current set's track as a small text chart (● correct, ○ wrong, levels in
the set's unit) or its QUEST+ posterior, and every fault. The command re-reads the log as it
grows and redraws (``masking_lab/commands/watch.py``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from masking_lab.formats.session_log import SessionLog

__all__ = ["track_chart", "watch_view"]

_UNIT = {"db_sl": "dB SL", "db_v": "dB re 1 V"}


def track_chart(
    levels: Sequence[float], correct: Sequence[bool], *, width: int = 60, height: int = 8
) -> list[str]:
    """The last ``width`` trials as a text chart: one column per trial, ● correct, ○ wrong.

    Examples
    --------
    >>> print("\\n".join(track_chart([8.0, 4.0, 4.0, 0.0, 4.0], [True, True, True, False, True],
    ...                              height=3)))
         8 ●
         4  ●● ●
         0    ○
    """
    lv = list(levels)[-width:]
    ok = list(correct)[-width:]
    if not lv:
        return []
    top, bottom = max(lv), min(lv)
    span = top - bottom
    rows = max(1, min(height, round(span) + 1)) if span > 0 else 1
    grid = [[" "] * len(lv) for _ in range(rows)]
    for i, (v, c) in enumerate(zip(lv, ok, strict=True)):
        r = 0 if span == 0 else round((top - v) / span * (rows - 1))
        grid[r][i] = "●" if c else "○"
    labels = [top - (span * r / (rows - 1) if rows > 1 else 0) for r in range(rows)]
    return [f"{lab:>6g} " + "".join(g).rstrip() for lab, g in zip(labels, grid, strict=True)]


def _num(v: Any) -> float | None:
    return float(v) if isinstance(v, int | float) and not isinstance(v, bool) else None


def watch_view(log: SessionLog, *, width: int = 60) -> list[str]:
    """The lines ``watch`` shows for the log's records so far.

    Parameters
    ----------
    log : SessionLog
        The log as read so far (a torn last line is simply not there yet).
    width : int
        Trials shown in the track chart.

    Returns
    -------
    list of str
        Header line, progress (sets and trials done, trials left estimated from the finished
        sets), the current set's track or posterior, faults, and the end when there is one.

    Examples
    --------
    >>> from masking_lab.formats.session_log import parse_log
    >>> raw = (b'{"record":"header","participant":"P1","protocol":{"experiment":"e1"},'
    ...        b'"set_order":["A","B"]}\\n'
    ...        b'{"record":"set_start","set_id":"A","level_unit":"db_sl","staircase":'
    ...        b'{"n_reversals":11}}\\n'
    ...        b'{"record":"trial","set_id":"A","trial_index":0,"level_db_sl":8,"correct":true,'
    ...        b'"reversal":false}\\n')
    >>> watch_view(parse_log(raw, "x"))[1]
    'sets 0/2 done; 1 trial done; trials left: unknown until a set ends'
    """
    h = log.header if isinstance(log.header, Mapping) else {}
    raw_protocol = h.get("protocol")
    protocol = raw_protocol if isinstance(raw_protocol, Mapping) else {}
    order = [str(s) for s in h.get("set_order") or []]
    sets = log.sets()
    done = {sid: r for sid, r in sets.items() if r.end is not None}
    n_trials = sum(len(r.trials) for r in sets.values())
    lines = [
        f"participant {h.get('participant', '?')} | {protocol.get('experiment', '?')} | "
        f"session {h.get('session_id', '?')} | {log.path.name}"
    ]
    finished = [
        len(r.trials)
        for r in sets.values()
        if r.end is not None and r.end.get("status") != "aborted"
    ]
    current = next((sid for sid, r in sets.items() if r.end is None), None)
    left_text = "unknown until a set ends"
    if finished:
        per_set = sum(finished) / len(finished)
        cur_done = len(sets[current].trials) if current else 0
        n_left_sets = len([s for s in order if s not in done])
        left = max(0.0, n_left_sets * per_set - cur_done)
        left_text = f"~{math.ceil(left)} (about {per_set:.0f} per set)"
    lines.append(
        f"sets {len(done)}/{len(order) or len(sets)} done; {n_trials} trial"
        f"{'' if n_trials == 1 else 's'} done; trials left: {left_text}"
    )
    if current is not None:
        lines += _current_set(current, sets[current], width)
    faults = [r for r in log.records if r.get("record") == "fault"]
    if faults:
        lines.append(f"faults ({len(faults)}):")
        lines += [
            f"  {f.get('kind', '?')}"
            + (f" in set {f['set_id']}" if f.get("set_id") else "")
            + (f", trial {f['trial_index'] + 1}" if isinstance(f.get("trial_index"), int) else "")
            + f": {f.get('message', '')}"
            for f in faults[-5:]
        ]
    else:
        lines.append("faults: none")
    if log.ended:
        end = next(r for r in reversed(log.records) if r.get("record") == "session_end")
        lines.append(f"session ended: {end.get('status', 'completed')}")
    elif log.records and log.records[-1].get("record") == "fault":
        lines.append("stopped at this fault; waiting for `masking-lab resume` (Ctrl-C to leave)")
    return lines


def _current_set(sid: str, rec: Any, width: int) -> list[str]:
    start = rec.start
    unit_key = "level_db_sl" if start.get("level_unit") == "db_sl" else "level_db_v"
    unit = _UNIT.get(str(start.get("level_unit")), "dB")
    levels, correct = [], []
    for t in rec.trials:
        v = _num(t.get(unit_key))
        if v is not None and isinstance(t.get("correct"), bool):
            levels.append(v)
            correct.append(t["correct"])
    head = f"set {sid}: {len(rec.trials)} trials"
    last = rec.trials[-1] if rec.trials else None
    post = last.get("posterior") if last is not None else None
    if isinstance(post, Mapping) and _num(post.get("mean_db")) is not None:
        head += f", posterior {post['mean_db']:.1f} ± {post.get('sd_db', float('nan')):.1f} {unit}"
    else:
        n_rev = sum(1 for t in rec.trials if t.get("reversal") is True)
        goal = (start.get("staircase") or {}).get("n_reversals", "?")
        head += f", reversals {n_rev}/{goal}"
    if levels:
        head += f", last level {levels[-1]:g} {unit}"
    return [head, *track_chart(levels, correct, width=width)]
