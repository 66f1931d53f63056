"""The compiled staircase ML fits (procedures/ml_loops.py) give the numpy route's numbers bit for
bit: the likelihood, its derivatives and whole fits of simulated staircases, on rows of any width
(numpy's pairwise sums change shape at 8 and 128 levels), at extreme scales and thresholds, and
with levels that make z NaN (those take the numpy route)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from masking_lab.procedures import ml_batch, ml_counts
from masking_lab.procedures.fused import compiled_loops
from masking_lab.procedures.ml_batch import ml_threshold_from_counts
from masking_lab.procedures.ml_counts import LevelCounts, index_levels, logistic_model
from masking_lab.procedures.staircase import StaircaseSettings
from masking_lab.procedures.staircase_batch import Observer, simulate

NUMPY = logistic_model(1 / 3, 0.02, 0.794)
COMPILED = dataclasses.replace(NUMPY, compiled=True)


def test_the_compiled_loops_run_in_the_test_environment():
    assert compiled_loops("ml_loops") is not None


def _case(
    rng: np.random.Generator, n_rows: int, width: int
) -> tuple[LevelCounts, np.ndarray, np.ndarray]:
    level = np.sort(rng.normal(-20.0, 6.0, (n_rows, width)), axis=1)
    n = rng.integers(0, 6, (n_rows, width)).astype(float)
    k = np.minimum(rng.integers(0, 6, (n_rows, width)), n).astype(float)
    t = rng.normal(-20.0, 8.0, n_rows)
    s = np.exp(rng.normal(0.5, 1.5, n_rows))
    return LevelCounts(level, n, k), t, s


def _same(a: object, b: object) -> None:
    """Equal arrays, NaN where NaN, and the same sign of every zero."""
    for x, y in zip(np.atleast_1d(a), np.atleast_1d(b), strict=True):
        np.testing.assert_array_equal(x, y)
        assert np.array_equal(np.signbit(x), np.signbit(y))


@pytest.mark.parametrize("seed", range(3))
def test_likelihood_and_derivatives_are_numpys_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    for width in [*range(1, 20), 31, 64, 127, 128, 129, 200, 300]:
        counts, t, s = _case(rng, int(rng.integers(1, 40)), width)
        for method in ("log_likelihood", "derivatives", "threshold_derivatives"):
            _same(getattr(COMPILED, method)(counts, t, s), getattr(NUMPY, method)(counts, t, s))


@pytest.mark.parametrize("method", ["log_likelihood", "derivatives", "threshold_derivatives"])
def test_extremes_are_numpys_bit_for_bit(method):
    rng = np.random.default_rng(5)
    counts, t, s = _case(rng, 6, 12)
    s[0], s[1] = 1e-300, 1e300  # (x − t)/s overflows to ±inf; underflows to ±0 (z = c)
    t[2], t[3] = 1e308, -1e308  # level − t overflows
    counts.n_correct[4] = 0.0  # no correct answer anywhere: ln p weighs nothing
    counts.n_trials[5] = counts.n_correct[5]  # no wrong answer anywhere
    counts = LevelCounts(counts.level_db, counts.n_trials, counts.n_correct)
    with np.errstate(all="ignore"):
        _same(getattr(COMPILED, method)(counts, t, s), getattr(NUMPY, method)(counts, t, s))


def test_a_nan_level_takes_the_numpy_route_with_its_numbers():
    rng = np.random.default_rng(9)
    counts, t, s = _case(rng, 5, 10)
    counts.level_db[2, 3] = np.nan  # weighs nothing where its counts are 0
    counts.n_trials[2, 3] = counts.n_correct[2, 3] = 0.0
    counts.level_db[4, 0] = np.nan  # weighed: the row's likelihood is NaN
    counts.n_trials[4, 0], counts.n_correct[4, 0] = 3.0, 1.0
    counts = LevelCounts(counts.level_db, counts.n_trials, counts.n_correct)
    ll = COMPILED.log_likelihood(counts, t, s)
    _same(ll, NUMPY.log_likelihood(counts, t, s))
    assert np.isfinite(ll[2]) and np.isnan(ll[4])


@pytest.mark.parametrize("fit_scale", [True, False])
def test_whole_fits_of_simulated_staircases_are_the_same(monkeypatch, fit_scale):
    settings = StaircaseSettings(start_level_db=-10.0, n_reversals=12)
    rng = np.random.default_rng(2)
    tracks = simulate(settings, rng.normal(-22.0, 3.0, 300), Observer(scale_db=1.5), rng)
    counts = index_levels(tracks.levels_db, tracks.correct).counts()
    used = []
    real = ml_counts.compiled_loops
    monkeypatch.setattr(ml_counts, "compiled_loops", lambda n: used.append(n) or real(n))
    compiled = ml_threshold_from_counts(counts, fit_scale=fit_scale)
    assert used and set(used) == {"ml_loops"}
    monkeypatch.setattr(ml_batch, "COMPILED_FROM", 10**9)  # the numpy route
    numpy_route = ml_threshold_from_counts(counts, fit_scale=fit_scale)
    assert np.isfinite(compiled.threshold_db).mean() > 0.9
    for field in dataclasses.fields(compiled):
        _same(getattr(compiled, field.name), getattr(numpy_route, field.name))


def test_few_tracks_load_no_numba(monkeypatch):
    monkeypatch.setattr(ml_counts, "compiled_loops", lambda name: pytest.fail(name))
    level = np.array([[-24.0, -22.0, -20.0, -18.0]] * 3)
    counts = LevelCounts(level, np.full((3, 4), 4.0), np.array([[1.0, 2.0, 3.0, 4.0]] * 3))
    fit = ml_threshold_from_counts(counts, min_trials=4)
    assert np.isfinite(fit.threshold_db).all()
