"""The vectorized staircase equals masking_lab.procedures.staircase track for track; observers
answer as ψ."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from masking_lab.core.errors import StaircaseError
from masking_lab.core.psychometric import Psychometric
from masking_lab.procedures.staircase import StaircaseSettings, start
from masking_lab.procedures.staircase_batch import (
    STATUSES,
    Observer,
    outcome_under,
    replay_many,
    run_staircases,
    simulate,
    truncate,
)

settings_strategy = st.builds(
    StaircaseSettings,
    start_level_db=st.floats(-20, 20, allow_nan=False),
    step_sizes_db=st.lists(st.sampled_from([0.5, 1.0, 2.0, 4.0]), min_size=1, max_size=4).map(
        tuple
    ),
    down_up_ratio=st.sampled_from([1.0, 0.7393, 0.5]),
    n_up=st.integers(1, 2),
    n_down=st.integers(1, 4),
    n_reversals=st.integers(1, 12),
    n_reversals_averaged=st.just(1),
    initial_one_down_one_up=st.booleans(),
    min_level_db=st.sampled_from([None, -30.0, -22.0]),
    max_level_db=st.sampled_from([None, 30.0, 22.0]),
    bound_policy=st.sampled_from(["clamp", "stop"]),
    max_bound_hits=st.integers(1, 4),
    max_trials=st.sampled_from([None, 5, 60]),
).flatmap(lambda s: st.integers(1, s.n_reversals).map(lambda k: replace(s, n_reversals_averaged=k)))

responses_strategy = hnp.arrays(
    np.bool_, st.tuples(st.integers(1, 6), st.integers(0, 120)), elements=st.booleans()
)


def reference(s: StaircaseSettings, answers) -> object:
    """masking_lab.procedures.staircase fed the answers until it finishes or they run out."""
    track = start(s)
    for r in answers:
        if track.finished:
            break
        track = track.update(bool(r))
    return track


def assert_row_equals(sim, i: int, track) -> None:
    n = int(sim.n_trials[i])
    assert n == track.n_trials
    assert tuple(sim.levels_db[i, :n].tolist()) == track.levels_db
    assert tuple(sim.correct[i, :n].tolist()) == track.responses
    assert np.all(np.isnan(sim.levels_db[i, n:]))
    k = int(sim.reversal_count[i])
    assert tuple(sim.reversal_levels_db[i, :k].tolist()) == track.reversal_levels_db
    assert tuple(sim.reversal_trials[i, :k].tolist()) == track.reversal_trials
    assert sim.status[i] == track.status
    if track.al_db is None:
        assert math.isnan(sim.al_db[i])
    else:
        assert sim.al_db[i] == track.al_db  # exact: same fsum over the same floats


@settings(max_examples=250, deadline=None)
@given(settings_strategy, responses_strategy)
def test_same_responses_give_the_same_tracks_as_the_scalar_staircase(s, answers):
    sim = replay_many(s, answers)
    for i in range(answers.shape[0]):
        assert_row_equals(sim, i, reference(s, answers[i]))


@settings(max_examples=60, deadline=None)
@given(settings_strategy, responses_strategy, st.data())
def test_per_row_start_levels_match_the_scalar_staircase(s, answers, data):
    lo = s.min_level_db if s.min_level_db is not None else -25.0
    hi = s.max_level_db if s.max_level_db is not None else 25.0
    starts = data.draw(
        hnp.arrays(np.float64, answers.shape[0], elements=st.floats(lo, hi, allow_nan=False))
    )
    sim = replay_many(s, answers, start_level_db=starts)
    for i in range(answers.shape[0]):
        assert_row_equals(
            sim, i, reference(replace(s, start_level_db=float(starts[i])), answers[i])
        )


def test_a_track_that_runs_out_of_answers_is_still_running():
    s = StaircaseSettings(start_level_db=0.0, max_trials=None)
    sim = replay_many(s, np.ones((2, 4), dtype=bool))
    assert list(sim.status) == ["running", "running"]
    assert np.all(np.isnan(sim.al_db))
    assert sim.fraction("running") == 1.0


def test_storing_no_levels_keeps_reversals_counts_and_statuses():
    s = StaircaseSettings(
        start_level_db=10.0, step_sizes_db=(2.0,), n_reversals=5, n_reversals_averaged=4
    )
    thr = np.linspace(-3, 3, 50)
    full = simulate(s, thr, Observer(), np.random.default_rng(3))
    lean = simulate(s, thr, Observer(), np.random.default_rng(3), store_levels=False)
    assert lean.levels_db.shape == (50, 0)
    np.testing.assert_array_equal(lean.n_trials, full.n_trials)
    np.testing.assert_array_equal(lean.status_code, full.status_code)
    np.testing.assert_array_equal(lean.al_db, full.al_db)


# ---------------------------------------------------------------- deriving shorter rules


@settings(max_examples=40, deadline=None)
@given(
    st.integers(2, 12),
    st.data(),
    st.sampled_from([None, 20, 45]),
    st.sampled_from([(4.0, 2.0), (2.0,), (3.0, 1.0)]),
    st.sampled_from([1.0, 0.7393]),
    st.integers(0, 2**31),
)
def test_outcome_under_a_shorter_rule_or_cap_equals_resimulating(
    long_n, data, cap, steps, ratio, seed
):
    n = data.draw(st.integers(1, long_n))
    k = data.draw(st.integers(1, n))
    base = StaircaseSettings(
        start_level_db=8.0,
        step_sizes_db=steps,
        down_up_ratio=ratio,
        n_reversals=long_n,
        n_reversals_averaged=1,
        min_level_db=-10.0,
        max_level_db=12.0,
        max_bound_hits=2,
        max_trials=None,
    )
    thr = np.random.default_rng(seed).uniform(-8, 14, 40)  # some hit the ceiling or the floor
    obs = Observer(scale_db=1.0, lapse=0.05)
    long_run = simulate(base, thr, obs, np.random.default_rng(seed))
    direct = simulate(
        replace(base, n_reversals=n, n_reversals_averaged=k, max_trials=cap),
        thr,
        obs,
        np.random.default_rng(seed),
    )
    derived = truncate(long_run, n, k, cap)
    np.testing.assert_array_equal(derived.n_trials, direct.n_trials)
    np.testing.assert_array_equal(derived.status_code, direct.status_code)
    np.testing.assert_array_equal(derived.al_db, direct.al_db)
    np.testing.assert_array_equal(
        derived.levels_db, direct.levels_db[:, : derived.levels_db.shape[1]]
    )
    np.testing.assert_array_equal(derived.reversal_count, direct.reversal_count)
    np.testing.assert_array_equal(derived.reversal_levels_db, direct.reversal_levels_db)
    fast = outcome_under(long_run, n, k, cap, exact=False)
    np.testing.assert_allclose(fast.al_db, direct.al_db, rtol=0, atol=1e-12)


def test_truncate_refuses_what_cannot_be_derived():
    s = StaircaseSettings(start_level_db=0.0, n_reversals=5, n_reversals_averaged=4, max_trials=30)
    run = simulate(s, np.zeros(5), Observer(), np.random.default_rng(0))
    with pytest.raises(StaircaseError, match="simulate with the longest stop rule"):
        truncate(run, 6, 4)
    with pytest.raises(StaircaseError, match="capped at 30"):
        outcome_under(run, 5, 4, max_trials=40)
    with pytest.raises(StaircaseError, match="max_trials must be"):
        outcome_under(run, 5, 4, max_trials=0)
    with pytest.raises(StaircaseError, match="n_reversals_averaged"):
        outcome_under(run, 3, 4)


# ---------------------------------------------------------------- simulated observers


def test_observers_answer_with_the_psychometric_probability():
    # Pool every trial by its level offset from the observer's threshold: the fraction
    # correct must match ψ within binomial noise.
    s = StaircaseSettings(
        start_level_db=6.0, step_sizes_db=(1.0,), n_reversals=30, n_reversals_averaged=20
    )
    obs = Observer(scale_db=2.0, lapse=0.04)
    thr = np.random.default_rng(1).uniform(-2, 2, 3000).round()  # whole dB keeps offsets on 1 dB
    run = simulate(s, thr, obs, np.random.default_rng(2))
    offset = (run.levels_db - thr[:, None]).round(9)
    psy = Psychometric(0.0, 2.0, lapse=0.04)
    checked = 0
    for x in np.unique(offset[~np.isnan(offset)]):
        at = offset == x
        n = int(at.sum())
        if n < 500:
            continue
        p = float(psy.p_correct(x))
        observed = run.correct[at].mean()
        assert abs(observed - p) < 4.5 * math.sqrt(p * (1 - p) / n), (x, observed, p)
        checked += 1
    assert checked >= 5


def test_same_seed_same_sessions_and_different_seed_different_ones():
    s = StaircaseSettings(start_level_db=10.0)
    thr = np.zeros(20)
    a = simulate(s, thr, Observer(), np.random.default_rng(7))
    b = simulate(s, thr, Observer(), np.random.default_rng(7))
    c = simulate(s, thr, Observer(), np.random.default_rng(8))
    np.testing.assert_array_equal(a.levels_db, b.levels_db)
    assert not np.array_equal(a.n_trials, c.n_trials)


def test_ceiling_when_the_observer_cannot_feel_anything_below_the_bound():
    s = StaircaseSettings(start_level_db=10.0, max_level_db=20.0, max_bound_hits=3)
    run = simulate(s, np.full(30, 200.0), Observer(lapse=0.0), np.random.default_rng(0))
    # p(correct) is the guess rate: the track climbs and sits at the bound (a few guesses in a
    # row may briefly delay it, never turn it into a threshold)
    assert run.fraction("ceiling") + run.fraction("trial_cap") == 1.0
    assert run.fraction("ceiling") > 0.9
    assert np.all(np.isnan(run.al_db))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"start_level_db": np.array([0.0, 99.0])}, "above max_level_db"),
        ({"start_level_db": np.array([0.0, -99.0])}, "below min_level_db"),
        ({"start_level_db": np.array([0.0, np.nan])}, "finite"),
    ],
)
def test_bad_start_levels_are_refused(kwargs, match):
    s = StaircaseSettings(start_level_db=0.0, min_level_db=-10.0, max_level_db=10.0)
    with pytest.raises(StaircaseError, match=match):
        replay_many(s, np.ones((2, 3), dtype=bool), **kwargs)


def test_other_faults_are_refused_with_a_clear_message():
    s = StaircaseSettings(start_level_db=0.0)
    with pytest.raises(StaircaseError, match="2-D"):
        replay_many(s, np.ones(3, dtype=bool))
    with pytest.raises(StaircaseError, match="finite"):
        simulate(s, np.array([0.0, np.inf]), Observer(), np.random.default_rng(0))
    with pytest.raises(StaircaseError, match="n_replicates"):
        run_staircases(s, lambda t, rows, lv: np.ones(rows.size, bool), 0)
    with pytest.raises(StaircaseError, match="answers for 2 running tracks"):
        run_staircases(s, lambda t, rows, lv: np.ones(1, bool), 2)


def test_status_names_are_the_scalar_staircase_ones():
    assert set(STATUSES) == {"running", "completed", "ceiling", "floor", "trial_cap"}


def test_completion_wins_over_a_step_that_would_cross_a_bound():
    # The reversal that completes the track would, with the next (larger) scheduled step, leave
    # the bounds; the scalar staircase stops as completed before stepping, and so must we.
    s = StaircaseSettings(
        start_level_db=4.0,
        step_sizes_db=(1.0, 8.0),
        n_reversals=1,
        n_reversals_averaged=1,
        max_level_db=5.0,
        bound_policy="stop",
    )
    answers = np.array([[True, True, True, False]])
    sim = replay_many(s, answers)
    assert_row_equals(sim, 0, reference(s, answers[0]))
    assert sim.status[0] == "completed"
    assert sim.al_db[0] == 3.0
