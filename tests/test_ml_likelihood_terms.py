"""The batch ML likelihood skips logarithms whose weight is 0 (levels answered all right or all
wrong, padding): it must give the plain binomial sum k·ln p + (n − k)·ln q bit for bit."""

from __future__ import annotations

import numpy as np

from masking_lab.procedures import ml_counts
from masking_lab.procedures.ml_counts import level_counts, logistic_model
from masking_lab.procedures.staircase import StaircaseSettings
from masking_lab.procedures.staircase_batch import Observer, simulate


def _plain(model, counts, t, s):
    """The log-likelihood with every logarithm taken (the formula before the shortcut)."""
    y = (counts.level_db - t[:, None]) / s[:, None]
    f = 1.0 / (1.0 + np.exp(-(y + model.c)))
    p = model.guess + model.rise * f
    q = model.lapse + model.rise * (1.0 - f)
    return (counts.n_correct * np.log(p) + (counts.n_trials - counts.n_correct) * np.log(q)).sum(1)


def test_skipped_logarithms_leave_the_likelihood_unchanged():
    s = StaircaseSettings(start_level_db=12.0, step_sizes_db=(4.0, 4.0, 4.0, 2.0), max_trials=60)
    thr = np.random.default_rng(5).uniform(0, 8, 300)
    tracks = simulate(s, thr, Observer(scale_db=1.5), np.random.default_rng(6))
    counts = level_counts(tracks.levels_db, tracks.correct)
    weightless = (counts.n_correct == 0) | (counts.n_correct == counts.n_trials)
    assert weightless.mean() > 0.3  # the shortcut is exercised, padding included
    assert (counts.n_trials == 0).any()
    model = logistic_model(1 / 3, 0.02, 0.794)
    rng = np.random.default_rng(7)
    for _ in range(5):
        t = rng.uniform(-5.0, 15.0, thr.size)
        sc = rng.uniform(0.2, 5.0, thr.size)
        ours = model.log_likelihood(counts, t, sc)
        # Same parts as the model computes them (one exp, no cancellation): bit for bit.
        _, f, g = ml_counts._logistic_parts(counts, t, sc, model.c)
        tiny = np.finfo(float).tiny
        p = np.maximum(model.guess + model.rise * f, tiny)
        q = np.maximum(model.lapse + model.rise * g, tiny)
        every_log = (counts.n_correct * np.log(p) + counts.n_wrong * np.log(q)).sum(axis=1)
        np.testing.assert_array_equal(ours, every_log)
        # and the textbook formula to rounding
        np.testing.assert_allclose(ours, _plain(model, counts, t, sc), rtol=1e-12, atol=1e-9)


def test_the_in_place_likelihood_is_the_parts_formula_for_odd_rows_too():
    # Rows without trials, all-right and all-wrong rows, and a threshold that is not finite:
    # the in-place arithmetic still gives the numbers of the parts formula (0 for an empty row).
    level = np.array([[0.0, 2.0, 4.0], [0.0, 0.0, 0.0], [1.0, 3.0, 3.0], [-2.0, 0.0, 2.0]])
    n = np.array([[3.0, 2.0, 1.0], [0.0, 0.0, 0.0], [2.0, 2.0, 0.0], [1.0, 1.0, 1.0]])
    k = np.array([[1.0, 2.0, 1.0], [0.0, 0.0, 0.0], [2.0, 2.0, 0.0], [0.0, 0.0, 0.0]])
    counts = ml_counts.LevelCounts(level, n, k)
    model = logistic_model(1 / 3, 0.02, 0.794)
    t = np.array([1.0, np.nan, 2.0, 0.5])
    s = np.array([1.5, 1.5, 0.01, 40.0])
    ours = model.log_likelihood(counts, t, s)
    _, f, g = ml_counts._logistic_parts(counts, t, s, model.c)
    tiny = np.finfo(float).tiny
    ln_p = np.log(np.maximum(model.guess + model.rise * f, tiny), out=np.zeros_like(f), where=k > 0)
    ln_q = np.log(np.maximum(model.lapse + model.rise * g, tiny), out=np.zeros_like(g),
                  where=n - k > 0)  # fmt: skip
    np.testing.assert_array_equal(ours, (k * ln_p + (n - k) * ln_q).sum(axis=1))
    assert ours[1] == 0.0 and np.all(np.isfinite(ours))


def test_the_maxima_select_the_terms_the_masks_select():
    # The likelihood picks F(z), 1 − F(z) and the weightless terms by maxima instead of masked
    # loops; the masked form (kept for a z holding NaN) must give the same bits wherever z is
    # a number, at both guess rates, without lapses (p reaches 1) and at extreme z.
    rng = np.random.default_rng(11)
    for guess, lapse in ((1 / 3, 0.02), (0.5, 0.0), (0.25, 0.05)):
        level = np.sort(np.round(rng.uniform(-30.0, 30.0, (200, 17))), axis=1)
        n = rng.integers(0, 5, level.shape).astype(float)
        k = np.minimum(n, rng.integers(0, 5, level.shape)).astype(float)
        counts = ml_counts.LevelCounts(level, n, k)
        model = logistic_model(guess, lapse, (1 + guess) / 2)
        t = np.round(rng.uniform(-40.0, 40.0, 200))  # some z exactly 0
        s = np.exp(rng.uniform(np.log(1e-3), np.log(50.0), 200))
        fast = model.log_likelihood(counts, t, s)
        z = (level - t[:, None]) / s[:, None] + model.c
        masked = model._log_likelihood_masked(counts, z)
        assert fast.tobytes() == masked.tobytes()


def test_a_nan_threshold_leaves_weightless_terms_zero():
    level = np.array([[0.0, 2.0], [0.0, 2.0]])
    counts = ml_counts.LevelCounts(level, np.zeros((2, 2)), np.zeros((2, 2)))
    model = logistic_model(1 / 3, 0.02, 0.794)
    ll = model.log_likelihood(counts, np.array([np.nan, 1.0]), np.array([1.5, 1.5]))
    np.testing.assert_array_equal(ll, [0.0, 0.0])


def test_the_threshold_derivatives_are_those_of_the_full_derivatives():
    rng = np.random.default_rng(12)
    level = np.sort(rng.uniform(-20.0, 20.0, (150, 12)), axis=1)
    n = rng.integers(0, 5, level.shape).astype(float)
    k = np.minimum(n, rng.integers(0, 5, level.shape)).astype(float)
    counts = ml_counts.LevelCounts(level, n, k)
    model = logistic_model(1 / 3, 0.02, 0.794)
    t, s = rng.uniform(-25.0, 25.0, 150), np.exp(rng.uniform(-3.0, 3.0, 150))
    g_t, _, h_tt, *_ = model.derivatives(counts, t, s)
    score, curvature = model.threshold_derivatives(counts, t, s)
    assert score.tobytes() == g_t.tobytes() and curvature.tobytes() == h_tt.tobytes()
