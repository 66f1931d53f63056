"""What a track puts in the session log, for every procedure kind (pure: JSON-ready data).

The ``set_start`` record holds the settings in force under the kind's log key (``staircase``
for the staircase, as before; ``procedure`` with its ``kind`` for any other), so resume and
analysis rebuild the exact track from the log alone; each ``trial`` record holds the
procedure's view of that trial (reversal and step for the staircase, the posterior's summary
for Bayesian kinds); ``set_end`` holds the estimate and how it was formed. Every kind's part
comes from :mod:`masking_lab.procedures.registry`. Levels are dB in the set's ``level_unit``.
Used by the session runner and by :mod:`masking_lab.simulation.synthetic_logs`.
"""

from __future__ import annotations

from typing import Any

from masking_lab.procedures.base import Procedure
from masking_lab.procedures.registry import kind_of
from masking_lab.procedures.registry import settings_record as settings_record

#: The settings of any procedure a set may run (every registered kind's settings class).
SetProcedure = Any

__all__ = ["SetProcedure", "end_fields", "settings_record", "start_fields", "trial_fields"]


def start_fields(settings: SetProcedure) -> dict[str, Any]:
    """The ``set_start`` keys naming the procedure: its kind's log key and its settings.

    Examples
    --------
    >>> from masking_lab.procedures.staircase import StaircaseSettings
    >>> sorted(start_fields(StaircaseSettings(start_level_db=0.0)))
    ['staircase']
    """
    return {kind_of(settings).log_key: settings_record(settings)}


def trial_fields(before: Procedure, after: Procedure) -> dict[str, Any]:
    """The procedure's keys of a ``trial`` record (None values are dropped by the writer).

    Examples
    --------
    >>> from masking_lab.procedures.quest_plus import QuestPlusSettings
    >>> track = QuestPlusSettings(-20.0, 45.0, max_trials=5).start()
    >>> sorted(trial_fields(track, track.update(True)))
    ['at_bound', 'next_level_db', 'posterior', 'reversal', 'step_db']
    """
    fields: dict[str, Any] = {
        "reversal": False,
        "step_db": None,
        "next_level_db": None if after.finished else after.next_level(),
        "at_bound": None,
    }
    fields.update(kind_of(after).trial_fields(before, after))
    return fields


def end_fields(state: Procedure) -> dict[str, Any]:
    """The procedure's keys of a ``set_end`` record: the AL in level_unit and how it was formed.

    Examples
    --------
    >>> from masking_lab.procedures.quest_plus import QuestPlusSettings
    >>> track = QuestPlusSettings(-20.0, 45.0, max_trials=1).start().update(True)
    >>> sorted(end_fields(track))
    ['al_db', 'method', 'reversal_levels_db', 'sd_db']
    """
    estimate = state.estimate()
    out: dict[str, Any] = {
        "al_db": estimate.level_db,
        "reversal_levels_db": [],
        "method": estimate.method,
    }
    out.update(kind_of(state).end_fields(state))
    if estimate.sd_db is not None:
        out["sd_db"] = estimate.sd_db
    return out
