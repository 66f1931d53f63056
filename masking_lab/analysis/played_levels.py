"""Trials whose played amplitude differs from the requested one (pure).

A board reports the amplitude it actually played after quantisation (``played_target_v``); the
trial record also keeps the requested level (``level_db_v``, and ``device_extra.
requested_target_v`` from protocol-2 devices). A trial played more than :data:`MAX_DIFF_DB` off
the request is reported by ``analyze`` (problems.csv and the report): its level is what was
asked for, not what the participant felt.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any, get_args

from msgspec import UNSET

from masking_lab.formats.log_records import AnalysisRecord, ATrial

MAX_DIFF_DB = 0.1
_TYPED_OTHERS = frozenset(get_args(AnalysisRecord)) - {ATrial}


def _get(record: Any, key: str) -> Any:
    if isinstance(record, Mapping):
        return record.get(key)
    value = getattr(record, key, None)
    return None if type(value).__name__ == "UnsetType" else value


def _kind(record: Any) -> Any:
    if isinstance(record, Mapping):
        return record.get("record")
    # a typed (msgspec) record carries its kind as the struct's tag
    return getattr(getattr(type(record), "__struct_config__", None), "tag", None)


def played_level_problems(records: Iterable[Any], lines: Iterable[int] | None = None) -> list[str]:
    """One note per log if any trial's target played more than 0.1 dB off its request.

    Parameters
    ----------
    records : iterable of trial records (dicts or typed log records)
        A log's records; records that are not trials are skipped.
    lines : iterable of int, optional
        The records' line numbers in the log (for the message).

    Returns
    -------
    list of str
        Empty, or one ``"line N: ..."`` note naming how many trials and the worst one.

    Examples
    --------
    >>> trial = {"record": "trial", "set_id": "A", "trial_index": 0, "level_db_v": -40.0,
    ...          "played_target_v": 0.0105}
    >>> played_level_problems([trial], [2])[0][:60]
    'line 2: 1 trial(s) played more than 0.1 dB off the requested'
    >>> played_level_problems([{**trial, "played_target_v": 0.01}], [2])
    []
    """
    numbers = list(lines) if lines is not None else None
    off: list[tuple[float, int, Any]] = []
    for i, rec in enumerate(records):
        cls = type(rec)
        if cls is ATrial:
            # The typed view's trial (most records of most logs): its fields are float, None or
            # UNSET, and it decodes no device_extra, so the request is the logged level. The
            # same answers as the general path below, without its per-field type tests.
            level, played = rec.level_db_v, rec.played_target_v
            if level is None or level is UNSET or not math.isfinite(level):
                continue
            if played is None or played is UNSET or not math.isfinite(played):
                continue
            requested_db = float(level)
        elif cls in _TYPED_OTHERS:  # typed records of other kinds: no trial
            continue
        else:
            if _kind(rec) != "trial":
                continue
            played, level = _get(rec, "played_target_v"), _get(rec, "level_db_v")
            extra = _get(rec, "device_extra") or {}
            requested = extra.get("requested_target_v") if isinstance(extra, Mapping) else None
            # Compared in dB: a hostile level (1e5 dB) overflows 10 ** (level / 20) as a ratio.
            if isinstance(requested, (int, float)) and math.isfinite(requested) and requested > 0:
                requested_db = 20.0 * math.log10(requested)
            elif requested is None and isinstance(level, (int, float)) and math.isfinite(level):
                requested_db = float(level)
            else:
                continue
            if not (isinstance(played, (int, float)) and math.isfinite(played)):
                continue
        diff = math.inf if played <= 0 else abs(20.0 * math.log10(played) - requested_db)
        if diff > MAX_DIFF_DB:
            line = numbers[i] if numbers is not None and i < len(numbers) else i + 1
            off.append((diff, line, rec))
    if not off:
        return []
    diff, line, rec = max(off, key=lambda item: (item[0], -item[1]))
    worst = "as silence" if math.isinf(diff) else f"{diff:.2f} dB off"
    return [
        f"line {off[0][1]}: {len(off)} trial(s) played more than {MAX_DIFF_DB:g} dB off the "
        f"requested level (worst: line {line}, set {_get(rec, 'set_id')} trial "
        f"{_get(rec, 'trial_index')}, {worst}); the device could not render these levels: "
        "check the rig's converter and attenuator steps (docs/devices.md)"
    ]
