"""AL estimators: reversal mean and the maximum-likelihood psychometric fit."""

from __future__ import annotations

import numpy as np
import pytest

from masking_lab.core.errors import AnalysisError
from masking_lab.core.psychometric import LEVITT_1U3D, Psychometric
from masking_lab.procedures.estimators import ml_threshold, reversal_mean_al
from masking_lab.procedures.staircase import StaircaseSettings, implied_target_p, start


def _track(psy, rng, start_db=20.0):
    sc = start(StaircaseSettings(start_db, max_trials=150))
    while not sc.finished:
        sc = sc.update(bool(rng.random() < psy.p_correct(sc.level_db)))
    return sc


def test_reversal_mean_averages_the_last_k():
    assert reversal_mean_al([10, 2, 4, 6, 8], 2) == pytest.approx(7.0)
    assert reversal_mean_al([10, 2, 4, 6, 8], 5) == pytest.approx(6.0)
    with pytest.raises(AnalysisError, match="only 3 reversals logged"):
        reversal_mean_al([1, 2, 3], 8)
    with pytest.raises(AnalysisError, match="≥ 1"):
        reversal_mean_al([1, 2, 3], 0)


def test_ml_threshold_is_read_at_the_staircases_target_p():
    assert implied_target_p(StaircaseSettings(0.0)) == pytest.approx(LEVITT_1U3D, abs=1e-9)
    # Noise-free data from a known function: many trials at fixed levels, answers in the exact
    # expected proportions, so the MLE is the generating function.
    psy = Psychometric(threshold_db=3.0, scale_db=1.5, lapse=0.02)
    levels, correct = [], []
    for x in np.arange(-6.0, 12.0, 1.0):
        k = round(400 * float(psy.p_correct(x)))
        levels += [x] * 400
        correct += [True] * k + [False] * (400 - k)
    fit = ml_threshold(levels, correct, lapse=0.02)
    assert fit.ok
    assert fit.threshold_db == pytest.approx(3.0, abs=0.05)
    assert fit.scale_db == pytest.approx(1.5, abs=0.05)
    fitted = Psychometric(fit.threshold_db, fit.scale_db, lapse=0.02)
    assert float(fitted.p_correct(fit.threshold_db)) == pytest.approx(LEVITT_1U3D)


def test_both_estimators_estimate_the_same_threshold_on_staircase_tracks():
    rng = np.random.default_rng(11)
    psy = Psychometric(threshold_db=5.0, scale_db=1.5, lapse=0.02)
    ml, rev = [], []
    for _ in range(40):
        sc = _track(psy, rng)
        fit = ml_threshold(sc.levels_db, sc.responses)
        assert fit.ok, fit.message
        ml.append(fit.threshold_db)
        rev.append(sc.al_db)
    # 40 tracks: SE of each mean ≈ 0.15 dB.
    assert np.mean(ml) == pytest.approx(5.0, abs=0.6)
    assert np.mean(rev) == pytest.approx(5.0, abs=0.6)
    assert abs(np.mean(ml) - np.mean(rev)) < 0.6


def test_fitted_lapse_stays_in_bounds():
    rng = np.random.default_rng(5)
    sc = _track(Psychometric(0.0, 1.5, lapse=0.05), rng)
    fit = ml_threshold(sc.levels_db, sc.responses, lapse=None, max_lapse=0.1)
    assert fit.ok and 0.0 <= fit.lapse <= 0.1


@pytest.mark.parametrize(
    ("levels", "correct", "match"),
    [
        ([1.0] * 5, [True, False] * 2 + [True], "only 5 trials"),
        (list(range(20)), [True] * 20, "every answer was correct"),
        (list(range(20)), [False] * 20, "every answer was wrong"),
    ],
)
def test_ml_failures_are_reported_not_raised(levels, correct, match):
    fit = ml_threshold(levels, correct)
    assert not fit.ok and fit.threshold_db is None
    assert match in fit.message


def test_ml_flat_data_fails_with_a_reason():
    # Answers independent of level: the likelihood runs to a flat function or the range edge.
    rng = np.random.default_rng(2)
    levels = rng.uniform(0, 20, 200)
    correct = rng.random(200) < 0.6
    fit = ml_threshold(levels, correct)
    assert not fit.ok
    assert "flat" in fit.message or "edge of the search range" in fit.message


def test_ml_rejects_bad_arguments():
    with pytest.raises(AnalysisError, match="one per trial"):
        ml_threshold([1.0, 2.0], [True])
    with pytest.raises(AnalysisError, match="finite"):
        ml_threshold([1.0, np.nan] * 6, [True, False] * 6)
    with pytest.raises(AnalysisError, match="p_target"):
        ml_threshold([1.0, 2.0] * 6, [True, False] * 6, p_target=0.2)


def test_ml_gradient_matches_finite_differences():
    from scipy.optimize import check_grad

    from masking_lab.procedures.estimators import _nll_and_grad

    rng = np.random.default_rng(0)
    x = rng.uniform(0, 10, 60)
    r = rng.random(60) < 0.7
    args = (x, r, 1 / 3, 0.02, LEVITT_1U3D)
    for p0 in ([3.0, 0.2], [6.0, 1.0], [1.0, -0.5]):
        err = check_grad(
            lambda p: _nll_and_grad(p, *args)[0], lambda p: _nll_and_grad(p, *args)[1], p0
        )
        assert err < 1e-4
