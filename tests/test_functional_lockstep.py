"""Functional tracks advanced together equal the scalar tracks bit for bit: the same stimuli,
answers and final posteriors, the same moments at the checkpoints, also when a precision rule
stops some tracks early (the placement shared by the tracks never mixes them up)."""

from __future__ import annotations

import numpy as np

from masking_lab.core.masking import ramp
from masking_lab.core.psychometric import Psychometric
from masking_lab.procedures.functional import FunctionalRampSettings, expected_entropy
from masking_lab.procedures.functional_lockstep import (
    expected_entropy_batch,
    run_lockstep,
    stop_status,
)

SMALL = FunctionalRampSettings(
    intercept_min_db=-12.0, intercept_max_db=0.0, slope_step=0.1, max_trials=25
)


def _answers(n_tracks: int, width: int, seed: int):
    rng = np.random.default_rng(seed)
    draws = rng.random((width, n_tracks))
    offsets = rng.normal(0.0, 1.0, n_tracks)
    psy = Psychometric(0.0, 1.5, 1 / 3, 0.02)

    def answer(i: int, k: int, masker_db_sl: float, target_db: float) -> bool:
        theta = offsets[i] + float(ramp(masker_db_sl, -7.4, 0.71))
        return bool(draws[k, i] < psy.p_correct(target_db - theta))

    return answer


def _scalar(settings: FunctionalRampSettings, answer, i: int):
    state = settings.start()
    moments = {}
    while not state.finished:
        x, y = state.next_masker_level_db_sl(), state.next_level()
        state = state.update(answer(i, state.n_trials, x, y))
        moments[state.n_trials] = state.moments()
    return state, moments


def test_the_batched_placement_equals_the_scalar_one_bit_for_bit():
    t_settings = SMALL
    state = t_settings.start()
    posteriors = []
    answer = _answers(1, 12, seed=2)
    for k in range(5):  # five distinct posteriors, and an odd count against the pass size
        state = state.update(answer(0, k, state.next_masker_level_db_sl(), state.next_level()))
        posteriors.append(state.posterior)
    from masking_lab.procedures.functional import ramp_tables

    t = ramp_tables(t_settings)
    batch = expected_entropy_batch(t, np.stack(posteriors))
    for k, post in enumerate(posteriors):
        assert np.array_equal(batch[k], expected_entropy(t, post))


def test_tracks_run_together_equal_the_scalar_tracks():
    answer = _answers(5, SMALL.max_trials, seed=7)
    run = run_lockstep(SMALL, answer, 5, checkpoints=(10, 25))
    for i in range(5):
        state, moments = _scalar(SMALL, answer, i)
        assert run.n_trials[i] == state.n_trials == 25
        assert tuple(run.levels_db[i]) == state.levels_db
        assert tuple(run.maskers_db_sl[i]) == state.maskers_db_sl
        assert tuple(run.correct[i]) == state.responses
        assert np.array_equal(run.posterior[i], state.posterior)
        assert run.status[i] == state.status
        assert run.at_trials[10][i] == moments[10] and run.at_trials[25][i] == moments[25]


def test_a_precision_rule_stops_tracks_at_different_trials_as_the_scalar_track():
    settings = FunctionalRampSettings(
        intercept_min_db=-12.0,
        intercept_max_db=0.0,
        slope_step=0.1,
        max_trials=40,
        target_sd_intercept_db=2.9,
        min_trials=8,
    )
    answer = _answers(6, settings.max_trials, seed=11)
    run = run_lockstep(settings, answer, 6)
    lengths = set()
    for i in range(6):
        state, _ = _scalar(settings, answer, i)
        lengths.add(state.n_trials)
        assert run.n_trials[i] == state.n_trials
        assert run.status[i] == state.status
        assert np.array_equal(run.posterior[i], state.posterior)
        k = state.n_trials
        assert (
            np.isnan(run.levels_db[i, k:]).all() and tuple(run.levels_db[i, :k]) == state.levels_db
        )
    assert len(lengths) > 1, "the seed should stop tracks at different trials"


def test_the_stop_rule_is_the_scalar_tracks():
    s = FunctionalRampSettings(max_trials=10, target_sd_slope=0.1, min_trials=3)
    assert stop_status(s, 2, {"intercept_sd_db": 0.0, "slope_sd": 0.01}) == "running"
    assert stop_status(s, 3, {"intercept_sd_db": 9.0, "slope_sd": 0.01}) == "completed"
    assert stop_status(s, 10, {"intercept_sd_db": 9.0, "slope_sd": 0.5}) == "trial_cap"
