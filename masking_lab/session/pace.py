"""Trials left in a set and in the session, for any procedure (pure: no I/O, no clock).

Each procedure kind states its own trials-left rule in :mod:`masking_lab.procedures.registry`
(reversals for the staircase, the precision stop rule for QUEST+, ...); this module adds the
session's later sets and rests.

Units: times in s.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from masking_lab.procedures.base import Procedure
from masking_lab.procedures.registry import kind_of

__all__ = ["session_time_left_s", "track_trials_left"]


def track_trials_left(state: Procedure, finished_set_trials: Sequence[int] = ()) -> float:
    """Expected trials before one running track stops (any procedure), at most its cap.

    Examples
    --------
    >>> from masking_lab.procedures.quest_plus import QuestPlusSettings
    >>> s = QuestPlusSettings(-20.0, 45.0, max_trials=40)
    >>> track_trials_left(s.start().update(True))
    39.0
    """
    return float(kind_of(state).trials_left(state, finished_set_trials))


def session_time_left_s(
    state: Procedure,
    *,
    seconds_per_trial: float,
    sets_after_current: int,
    finished_set_trials: Sequence[int] = (),
    rest_between_sets_s: float = 0.0,
) -> float:
    """Expected session time left, s, with the current set's track in ``state``.

    Later sets take the mean trial count of the finished ones, else what a fresh track of the
    current set's procedure is expected to need.

    Examples
    --------
    >>> from masking_lab.procedures.quest_plus import QuestPlusSettings
    >>> s = QuestPlusSettings(-20.0, 45.0, max_trials=40)
    >>> session_time_left_s(s.start(), seconds_per_trial=10.0, sets_after_current=1)
    800.0
    """
    current = track_trials_left(state, finished_set_trials)
    if finished_set_trials:
        per_set = float(np.mean(finished_set_trials))
    else:
        # every procedure kind carries its settings; the Procedure protocol does not declare them
        per_set = track_trials_left(state.settings.start())  # type: ignore[attr-defined]
    trials = current + sets_after_current * per_set
    return max(0.0, trials * seconds_per_trial + sets_after_current * rest_between_sets_s)
