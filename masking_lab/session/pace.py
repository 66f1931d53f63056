"""Trials left in a set and in the session, for any procedure (pure: no I/O, no clock).

The staircase's pace is counted in reversals (:func:`masking_lab.session.trials.
estimate_time_left_s`). A QUEST+ track stops on its posterior SD or its trial count, so its
trials left come from the stop rule: each trial adds to the posterior's precision 1/SD² about
``efficiency`` × I*, the Fisher information of the most informative trial
(:func:`masking_lab.procedures.fisher.max_information`; QUEST+ runs at ~60 % of it,
docs/procedures.md), so a track at SD σ needs about (1/target² − 1/σ²)/(efficiency·I*) more.

Units: SDs and levels in dB, information in dB⁻², times in s.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np

from masking_lab.procedures.fisher import max_information
from masking_lab.procedures.quest_plus import QuestPlus, QuestPlusSettings
from masking_lab.procedures.staircase import Staircase
from masking_lab.session.trials import estimate_time_left_s

#: QUEST+'s measured efficiency against the Cramér-Rao bound (docs/procedures.md: 59 %).
QUEST_EFFICIENCY = 0.6


@functools.lru_cache(maxsize=32)
def _information(settings: QuestPlusSettings) -> float:
    """I* of the settings' model (first scale and lapse of its grids), dB⁻²."""
    info, _, _ = max_information(
        scale_db=settings.scales_db[0], guess=settings.guess, lapse=settings.lapses[0]
    )
    return info


def quest_trials_left(
    settings: QuestPlusSettings, n_trials: int, sd_db: float | None = None
) -> float:
    """Expected trials before a QUEST+ track stops.

    Parameters
    ----------
    settings : QuestPlusSettings
        The track's rules.
    n_trials : int
        Trials answered so far.
    sd_db : float or None
        The posterior SD now, dB (None before the track starts: the prior counts as no
        information).

    Returns
    -------
    float
        Trials, ≥ 0: ``max_trials − n_trials`` without a precision rule; otherwise the
        information still missing for ``target_sd_db`` over what a trial brings, at least
        ``min_trials − n_trials``, at most the trials left to ``max_trials``.

    Examples
    --------
    >>> s = QuestPlusSettings(-20.0, 45.0, target_sd_db=1.08, max_trials=80)
    >>> round(quest_trials_left(s, 0))
    27
    >>> quest_trials_left(s, 20, 1.0)
    0.0
    """
    s = settings
    cap = math.inf if s.max_trials is None else max(0.0, float(s.max_trials - n_trials))
    if s.target_sd_db is None:
        return cap
    have = 0.0 if sd_db is None or not sd_db > 0 else 1.0 / sd_db**2
    missing = max(0.0, 1.0 / s.target_sd_db**2 - have)
    left = missing / (QUEST_EFFICIENCY * _information(s))
    left = max(left, float(s.min_trials - n_trials))
    return float(min(left, cap))


def track_trials_left(
    state: Staircase | QuestPlus, finished_set_trials: Sequence[int] = ()
) -> float:
    """Expected trials before one running track stops (any procedure).

    Examples
    --------
    >>> s = QuestPlusSettings(-20.0, 45.0, max_trials=40)
    >>> track_trials_left(s.start().update(True))
    39.0
    """
    return session_time_left_s(
        state, seconds_per_trial=1.0, sets_after_current=0, finished_set_trials=finished_set_trials
    )


def session_time_left_s(
    state: Staircase | QuestPlus,
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
    >>> s = QuestPlusSettings(-20.0, 45.0, max_trials=40)
    >>> session_time_left_s(s.start(), seconds_per_trial=10.0, sets_after_current=1)
    800.0
    """
    if isinstance(state, Staircase):
        sc = state.settings
        return estimate_time_left_s(
            seconds_per_trial=seconds_per_trial,
            trials_done_in_set=state.n_trials,
            reversals_in_set=len(state.reversal_levels_db),
            n_reversals=sc.n_reversals,
            max_trials=sc.max_trials,
            sets_after_current=sets_after_current,
            finished_set_trials=finished_set_trials,
            rest_between_sets_s=rest_between_sets_s,
        )
    sd = state.posterior_sd_db if state.n_trials else None
    current = quest_trials_left(state.settings, state.n_trials, sd)
    if finished_set_trials:
        per_set = float(np.mean(finished_set_trials))
    else:
        per_set = quest_trials_left(state.settings, 0)
    trials = current + sets_after_current * per_set
    return max(0.0, trials * seconds_per_trial + sets_after_current * rest_between_sets_s)
