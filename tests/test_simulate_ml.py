"""Batch maximum-likelihood thresholds: sufficient statistics, agreement with the analysis's
scalar estimator (masking_lab.procedures.estimators) and with scipy, recovery of known
thresholds."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy.optimize import minimize_scalar

from masking_lab.core.errors import AnalysisError
from masking_lab.core.psychometric import Psychometric
from masking_lab.procedures.ml_batch import (
    LevelCounts,
    index_levels,
    level_counts,
    log_likelihood,
    ml_threshold_from_counts,
)
from masking_lab.procedures.staircase import StaircaseSettings
from masking_lab.procedures.staircase_batch import Observer, simulate

estimators = pytest.importorskip("masking_lab.procedures.estimators")


def ml_threshold_db(levels_db, correct, **options):
    """ML fit of every track of a (tracks × trials) level and answer matrix."""
    return ml_threshold_from_counts(level_counts(levels_db, correct), **options)


def staircase_tracks(n: int, seed: int, scale_db: float = 1.5):
    s = StaircaseSettings(start_level_db=12.0, step_sizes_db=(4.0, 4.0, 4.0, 2.0), max_trials=150)
    thr = np.random.default_rng(seed).uniform(0, 8, n)
    return simulate(s, thr, Observer(scale_db=scale_db), np.random.default_rng(seed + 1))


def row(tracks, i):
    n = int(tracks.n_trials[i])
    return tracks.levels_db[i, :n], tracks.correct[i, :n]


# ---------------------------------------------------------------- counts


levels_strategy = hnp.arrays(
    np.float64,
    st.tuples(st.integers(1, 5), st.integers(0, 30)),
    elements=st.sampled_from([np.nan, -2.0, 0.0, 0.5, 2.0, 7.25]),
)


@settings(max_examples=150, deadline=None)
@given(levels_strategy, st.data())
def test_level_counts_are_the_trials_and_correct_answers_per_distinct_level(levels, data):
    correct = data.draw(hnp.arrays(np.bool_, levels.shape))
    counts = level_counts(levels, correct)
    for i in range(levels.shape[0]):
        want_n, want_k = Counter(), Counter()
        for x, c in zip(levels[i], correct[i], strict=True):
            if not np.isnan(x):
                want_n[float(x)] += 1
                want_k[float(x)] += int(c)
        got_n, got_k = Counter(), Counter()
        for x, n, k in zip(
            counts.level_db[i], counts.n_trials[i], counts.n_correct[i], strict=True
        ):
            if n:
                got_n[float(x)] += int(n)
                got_k[float(x)] += int(k)
        assert got_n == want_n
        assert got_k == want_k


@settings(max_examples=80, deadline=None)
@given(levels_strategy, st.data())
def test_prefix_counts_equal_counts_of_the_cut_tracks(levels, data):
    correct = data.draw(hnp.arrays(np.bool_, levels.shape))
    cut = data.draw(hnp.arrays(np.int64, levels.shape[0], elements=st.integers(0, levels.shape[1])))
    cols = np.arange(levels.shape[1])[None, :]
    cut_levels = np.where(cols < cut[:, None], levels, np.nan)
    direct = level_counts(cut_levels, correct & (cols < cut[:, None]))
    via_index = index_levels(levels, correct).counts(cut)
    for i in range(levels.shape[0]):
        a = {
            x: (n, k)
            for x, n, k in zip(
                *(v[i] for v in (direct.level_db, direct.n_trials, direct.n_correct)), strict=True
            )
            if n
        }
        b = {
            x: (n, k)
            for x, n, k in zip(
                *(v[i] for v in (via_index.level_db, via_index.n_trials, via_index.n_correct)),
                strict=True,
            )
            if n
        }
        assert a == b


# ---------------------------------------------------------------- agreement


def test_agrees_with_the_analysis_estimator_on_staircase_tracks():
    tracks = staircase_tracks(40, seed=11)
    fit = ml_threshold_db(tracks.levels_db, tracks.correct, lapse=0.02)
    counts = level_counts(tracks.levels_db, tracks.correct)
    well_defined = 0
    for i in range(40):
        x, c = row(tracks, i)
        ref = estimators.ml_threshold(x, c, lapse=0.02)
        assert ref.ok == (not math.isnan(fit.threshold_db[i])), (i, ref.message)
        if not ref.ok:
            continue
        one = LevelCounts(
            counts.level_db[i : i + 1], counts.n_trials[i : i + 1], counts.n_correct[i : i + 1]
        )
        theirs = log_likelihood(one, [ref.threshold_db], ref.scale_db, lapse=0.02)[0]
        # Ours is never a worse maximum than theirs ...
        assert fit.log_likelihood[i] >= theirs - 1e-6
        # ... and wherever the likelihood has a well-defined peak (not a near-step function,
        # whose likelihood is a plateau between two levels) it is the same point.
        if ref.scale_db >= 0.3:
            well_defined += 1
            assert fit.threshold_db[i] == pytest.approx(ref.threshold_db, abs=0.01)
            assert fit.scale_db[i] == pytest.approx(ref.scale_db, rel=0.02)
    assert well_defined >= 25


def test_fixed_scale_fit_matches_scipy():
    tracks = staircase_tracks(6, seed=5)
    fit = ml_threshold_db(
        tracks.levels_db, tracks.correct, scale_db=1.5, lapse=0.02, fit_scale=False
    )
    for i in range(6):
        x, c = row(tracks, i)

        def nll(t, x=x, c=c):
            p = Psychometric(t, 1.5, lapse=0.02).p_correct(x)
            return -float(np.sum(np.where(c, np.log(p), np.log1p(-p))))

        best = minimize_scalar(
            nll, bounds=(x.min() - 5, x.max() + 5), method="bounded", options={"xatol": 1e-10}
        )
        assert fit.threshold_db[i] == pytest.approx(best.x, abs=1e-5)
        assert fit.log_likelihood[i] == pytest.approx(-best.fun, abs=1e-8)


def test_recovers_a_known_function_from_plentiful_constant_stimuli():
    truth = Psychometric(threshold_db=3.0, scale_db=2.0, lapse=0.02)
    levels = np.repeat(np.arange(-6.0, 13.0, 1.0), 400)
    rng = np.random.default_rng(4)
    correct = rng.random(levels.size) < truth.p_correct(levels)
    fit = ml_threshold_db(levels[None, :], correct[None, :], lapse=0.02)
    assert fit.threshold_db[0] == pytest.approx(3.0, abs=0.2)
    assert fit.scale_db[0] == pytest.approx(2.0, rel=0.15)


# ---------------------------------------------------------------- failures


def test_tracks_without_an_interior_maximum_fail_as_nan():
    levels = np.array(
        [
            [0.0, 2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0, 16.0, 18.0, 20.0, 22.0],  # all correct
            [0.0, 2.0, 4.0, np.nan, np.nan, np.nan, np.nan, np.nan, np.nan, np.nan, np.nan, np.nan],
            [np.nan] * 12,
        ]
    )
    correct = np.array([[True] * 12, [True, False, True] + [False] * 9, [False] * 12])
    fit = ml_threshold_db(levels, correct, lapse=0.02)
    assert np.all(np.isnan(fit.threshold_db))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"lapse": 0.7}, "lapse"),
        ({"guess": 1.2}, "guess"),
        ({"p_target": 0.2}, "p_target"),
        ({"scale_db": 50.0}, "scale_db"),
        ({"scale_bounds_db": (2.0, 1.0)}, "scale_bounds_db"),
    ],
)
def test_impossible_models_are_refused(kwargs, match):
    with pytest.raises(AnalysisError, match=match):
        ml_threshold_db(np.zeros((1, 12)), np.ones((1, 12), dtype=bool), **kwargs)


def test_mismatched_arrays_are_refused():
    with pytest.raises(AnalysisError, match="matching 2-D"):
        level_counts(np.zeros((2, 3)), np.zeros((2, 4), dtype=bool))
