"""What a track puts in the session log, for every procedure kind (pure: JSON-ready data).

The ``set_start`` record holds the settings in force (``staircase`` for the staircase, as
before; ``procedure`` with its ``kind`` for any other), so resume and analysis rebuild the
exact track from the log alone; each ``trial`` record holds the procedure's view of that trial
(reversal and step for the staircase, the posterior's mean and SD for QUEST+); ``set_end``
holds the estimate and how it was formed. Levels are dB in the set's ``level_unit``. Used by
the session runner and by :mod:`masking_lab.simulation.synthetic_logs`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from masking_lab.procedures.base import Procedure
from masking_lab.procedures.quest_plus import QuestPlus, QuestPlusSettings
from masking_lab.procedures.staircase import Staircase, StaircaseSettings

#: The settings of any procedure a set may run.
SetProcedure = StaircaseSettings | QuestPlusSettings

__all__ = ["SetProcedure", "end_fields", "settings_record", "start_fields", "trial_fields"]


def settings_record(settings: SetProcedure) -> dict[str, Any]:
    """The settings as JSON-ready data (tuples as lists; ``kind`` for non-staircase ones).

    Examples
    --------
    >>> settings_record(QuestPlusSettings(-20.0, 45.0))["kind"]
    'quest_plus'
    """
    record = dataclasses.asdict(settings)
    for key, value in record.items():
        if isinstance(value, tuple):
            record[key] = list(value)
    if not isinstance(settings, StaircaseSettings):
        record = {"kind": settings.kind, **record}
    return record


def start_fields(settings: SetProcedure) -> dict[str, Any]:
    """The ``set_start`` keys naming the procedure: ``staircase`` or ``procedure``.

    Examples
    --------
    >>> sorted(start_fields(StaircaseSettings(start_level_db=0.0)))
    ['staircase']
    """
    key = "staircase" if isinstance(settings, StaircaseSettings) else "procedure"
    return {key: settings_record(settings)}


def trial_fields(before: Procedure, after: Procedure) -> dict[str, Any]:
    """The procedure's keys of a ``trial`` record (None values are dropped by the writer).

    Examples
    --------
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
    if isinstance(before, Staircase) and isinstance(after, Staircase):
        fields["reversal"] = len(after.reversal_levels_db) > len(before.reversal_levels_db)
        fields["step_db"] = before.step_db
        fields["at_bound"] = after.at_bound
    if isinstance(after, QuestPlus):
        fields["posterior"] = {"mean_db": after.posterior_mean_db, "sd_db": after.posterior_sd_db}
    return fields


def end_fields(state: Procedure) -> dict[str, Any]:
    """The procedure's keys of a ``set_end`` record: the AL in level_unit and how it was formed.

    Examples
    --------
    >>> track = QuestPlusSettings(-20.0, 45.0, max_trials=1).start().update(True)
    >>> sorted(end_fields(track))
    ['al_db', 'method', 'reversal_levels_db', 'sd_db']
    """
    estimate = state.estimate()
    reversals = list(state.reversal_levels_db) if isinstance(state, Staircase) else []
    out: dict[str, Any] = {
        "al_db": estimate.level_db,
        "reversal_levels_db": reversals,
        "method": estimate.method,
    }
    if estimate.sd_db is not None:
        out["sd_db"] = estimate.sd_db
    return out
