"""Least-squares ramp fits: exactness, the paper's Table 2 fits, uncertainty, degenerate data."""

from __future__ import annotations

import numpy as np
import pytest
import statsmodels.api as sm
from hypothesis import given, settings
from hypothesis import strategies as st

from masking_lab.analysis.ramp_fit import (
    fit_ramp,
    participant_bootstrap,
    ramp_least_squares,
    ramp_least_squares_batch,
    with_bootstrap,
)
from masking_lab.core.errors import AnalysisError

LEVELS = np.array([5.0, 10.0, 15.0, 20.0, 25.0])
# Paper Table 2 (mean AL shifts, dB) at 5..25 dB SL.
EXP1 = {
    120: [0.433, 0.322, 2.992, 7.265, 10.107],
    180: [0.771, 0.808, 3.611, 7.427, 10.502],
    270: [1.171, 3.608, 6.411, 9.428, 13.301],
}
EXP2 = {
    120: [4.017, 9.506, 13.376, 18.727, 22.891],
    180: [6.118, 12.158, 18.015, 22.278, 27.612],
    270: [6.546, 13.235, 18.306, 23.580, 29.195],
}


def _pooled(table, freqs):
    x = np.concatenate([LEVELS] * len(freqs))
    y = np.concatenate([table[f] for f in freqs])
    return x, y


def _ramp_loss(x, y, a, b):
    return float(((np.maximum(0.0, a + b * x) - y) ** 2).sum())


def _brute_force(x, y):
    """Independent optimum by scanning the knee κ on a fine grid.

    For a fixed knee the ramp is ``b·max(0, x − κ)`` and the best ``b ≥ 0`` has a closed form;
    a constant ``max(0, c)`` covers the flat (b = 0) ramps.
    """
    lo, hi = x.min(), x.max()
    kappa = np.concatenate(
        [
            np.linspace(lo - 1000, lo - 40, 2001),
            np.linspace(lo - 40, lo, 40001),
            np.linspace(lo, hi, 30001),
        ]
    )
    d = np.maximum(0.0, x[None, :] - kappa[:, None])
    dd = (d * d).sum(axis=1)
    b = np.where(dd > 0, np.maximum(0.0, d @ y) / np.where(dd > 0, dd, 1.0), 0.0)
    losses = ((b[:, None] * d - y) ** 2).sum(axis=1)
    c = max(0.0, float(y.mean()))
    return min(float(losses.min()), float(((c - y) ** 2).sum()))


@pytest.mark.parametrize(
    ("table", "freqs", "a_ref", "b_ref", "a_paper", "b_paper"),
    [
        # Paper §2.4 / §3.3: EV pooled 120+180 Hz "≈ −6.22, 0.66"; MV pooled 180+270 "≈ 1.39, 1.09".
        (EXP1, (120, 180), -6.2628, 0.66526, -6.22, 0.66),
        (EXP2, (180, 270), 1.39165, 1.08751, 1.39, 1.09),
    ],
)
def test_table2_pooled_fits_reproduce_the_paper(table, freqs, a_ref, b_ref, a_paper, b_paper):
    x, y = _pooled(table, freqs)
    fit = fit_ramp(x, y)
    assert fit.status == "fitted"
    # The least-squares values, recomputed independently (brute force below and by hand).
    assert fit.intercept_db == pytest.approx(a_ref, abs=1e-4)
    assert fit.slope == pytest.approx(b_ref, abs=1e-5)
    # The paper's rounded numbers.
    assert fit.intercept_db == pytest.approx(a_paper, abs=0.05)
    assert fit.slope == pytest.approx(b_paper, abs=0.01)
    assert _ramp_loss(x, y, fit.intercept_db, fit.slope) == pytest.approx(
        _brute_force(x, y), abs=1e-6
    )


def test_table2_slopes_are_in_the_papers_ranges():
    ev = [fit_ramp(*_pooled(EXP1, f)).slope for f in ((120, 180), (270,))]
    mv = [fit_ramp(*_pooled(EXP2, f)).slope for f in ((120,), (180, 270))]
    assert all(0.6 <= b <= 0.7 for b in ev)  # "approximately 0.6–0.7" for EV
    assert all(0.9 <= b <= 1.1 for b in mv)  # "0.9–1.1" for MV


def test_ev_pooled_fit_has_a_flat_region_and_high_adjusted_r2():
    fit = fit_ramp(*_pooled(EXP1, (120, 180)))
    assert fit.knee_db_sl == pytest.approx(6.2628 / 0.66526, rel=1e-4)
    assert 5.0 < fit.knee_db_sl < 10.0  # 5 dB SL is in the flat region
    assert fit.n_active_levels == 4
    # Over all 10 points the ramp's adjusted R² is 0.986; over the points above the knee
    # it is 0.990 — the paper reports "> 0.99".
    assert fit.adj_r2 == pytest.approx(0.98649, abs=1e-4)
    assert fit.adj_r2_active > 0.989


finite = st.floats(-40, 40, allow_nan=False, allow_infinity=False)


@settings(max_examples=40, deadline=None)
@given(
    x=st.lists(st.sampled_from([0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0]), min_size=3, max_size=9),
    a=st.floats(-20, 10),
    b=st.floats(0, 2),
    noise=st.lists(st.floats(-3, 3), min_size=9, max_size=9),
)
def test_exact_fit_is_never_beaten_by_brute_force(x, a, b, noise):
    xv = np.array(x)
    if np.unique(xv).size < 2:
        return
    y = np.maximum(0.0, a + b * xv) + np.array(noise[: xv.size])
    a_hat, b_hat = ramp_least_squares(xv, y)
    assert b_hat >= 0
    assert _ramp_loss(xv, y, a_hat, b_hat) <= _brute_force(xv, y) + 1e-7


@settings(max_examples=40, deadline=None)
@given(a=st.floats(-15, 5), b=st.floats(0.2, 2.0))
def test_noise_free_ramps_are_recovered_exactly(a, b):
    y = np.maximum(0.0, a + b * LEVELS)
    if np.count_nonzero(y > 1e-6) < 2:  # fewer than two points carry the slope
        return
    a_hat, b_hat = ramp_least_squares(LEVELS, y)
    assert b_hat == pytest.approx(b, abs=1e-7)
    assert np.allclose(np.maximum(0, a_hat + b_hat * LEVELS), y, atol=1e-7)


def test_batch_equals_single_fits():
    rng = np.random.default_rng(4)
    x = np.repeat(LEVELS, 2)
    Y = np.maximum(0, -6 + 0.7 * x) + rng.normal(0, 1, size=(50, x.size))
    a, b = ramp_least_squares_batch(x, Y)
    for i in range(Y.shape[0]):
        assert (a[i], b[i]) == pytest.approx(ramp_least_squares(x, Y[i]))


def test_asymptotic_se_matches_ols_when_every_point_is_above_the_knee():
    x, y = _pooled(EXP2, (180, 270))
    fit = fit_ramp(x, y)
    ols = sm.OLS(y, sm.add_constant(x)).fit()
    assert fit.intercept_db == pytest.approx(ols.params[0])
    assert fit.slope == pytest.approx(ols.params[1])
    assert fit.intercept_se_db == pytest.approx(ols.bse[0])
    assert fit.slope_se == pytest.approx(ols.bse[1])
    lo, hi = ols.conf_int(alpha=0.05)[1]
    assert fit.slope_ci == pytest.approx((lo, hi))
    assert fit.adj_r2 == pytest.approx(ols.rsquared_adj)
    assert fit.uncertainty == "asymptotic"


def test_decreasing_shifts_give_a_flat_ramp_not_a_negative_slope():
    y = np.array([5.0, 4.0, 3.0, 2.0, 1.0])
    fit = fit_ramp(LEVELS, y)
    assert fit.slope == 0.0
    assert fit.intercept_db == pytest.approx(3.0)
    assert fit.knee_db_sl is None
    assert "does not change with masker level" in fit.message


def test_every_point_in_the_flat_region_is_no_masking():
    fit = fit_ramp(LEVELS, [-0.4, 0.0, -0.2, -0.1, -0.3])
    assert fit.status == "no_masking"
    assert (fit.intercept_db, fit.slope) == (0.0, 0.0)
    assert "flat region" in fit.message
    assert fit.intercept_se_db is None and fit.knee_db_sl is None


def test_one_masker_level_is_insufficient_data():
    fit = fit_ramp([15.0, 15.0, 15.0], [3.0, 3.5, 2.5])
    assert fit.status == "insufficient_data"
    assert fit.intercept_db is None and fit.slope is None
    assert "two or more masker levels" in fit.message and "15" in fit.message


def test_zero_variance_shifts_have_no_r2_but_no_nan():
    fit = fit_ramp(LEVELS, [2.0] * 5)
    assert fit.status == "fitted"
    assert fit.slope == 0.0 and fit.intercept_db == pytest.approx(2.0)
    assert fit.adj_r2 is None
    values = [v for v in vars(fit).values() if isinstance(v, float)]
    assert all(np.isfinite(values))


def test_two_points_fit_exactly_without_uncertainty():
    fit = fit_ramp([10.0, 20.0], [2.0, 8.0])
    assert fit.slope == pytest.approx(0.6)
    assert fit.intercept_se_db is None
    assert "no degrees of freedom" in fit.message


def test_single_level_above_the_knee_is_flagged():
    fit = fit_ramp(LEVELS, [0.0, 0.0, 0.0, 0.0, 6.0])
    assert fit.status == "fitted"
    assert fit.n_active_levels == 1
    assert "only one masker level" in fit.message
    assert fit.slope_se is None


@pytest.mark.parametrize(
    ("x", "y", "match"),
    [([5.0, np.nan], [1.0, 2.0], "masker level"), ([5.0, 10.0], [1.0, np.inf], "shift")],
)
def test_non_finite_input_is_refused(x, y, match):
    with pytest.raises(AnalysisError, match=match):
        fit_ramp(x, y)


def test_participant_bootstrap_is_seeded_and_covers_the_estimate():
    rng = np.random.default_rng(0)
    x = np.tile(LEVELS, 2)
    truth = np.maximum(0, -6.0 + 0.7 * x)
    data = truth + rng.normal(0, 1.0, size=(12, 1)) + rng.normal(0, 0.7, size=(12, x.size))
    fit = fit_ramp(x, data.mean(axis=0))
    a1, b1, f1 = participant_bootstrap(x, data, n_boot=400, rng=np.random.default_rng(7))
    a2, b2, f2 = participant_bootstrap(x, data, n_boot=400, rng=np.random.default_rng(7))
    assert np.array_equal(a1, a2) and np.array_equal(b1, b2) and f1 == f2 == 0
    boot = with_bootstrap(fit, a1, b1)
    assert boot.uncertainty == "bootstrap"
    assert boot.slope_ci[0] < fit.slope < boot.slope_ci[1]
    assert boot.intercept_ci_db[0] < fit.intercept_db < boot.intercept_ci_db[1]
    assert boot.slope_se == pytest.approx(np.std(b1, ddof=1))


def test_bootstrap_with_missing_cells_counts_unfittable_replicates():
    x = np.array([5.0, 10.0])
    # Participant 0 has only the 5 dB SL cell, participant 1 only the 10 dB SL cell.
    data = np.array([[1.0, np.nan], [np.nan, 4.0]])
    a, b, failed = participant_bootstrap(x, data, n_boot=200, rng=np.random.default_rng(1))
    # A replicate drawing the same participant twice has one level left and cannot be fitted.
    assert failed > 0
    assert a.size + failed == 200
    assert np.all(b >= 0)


def _bootstrap_flat_count(x, data, n_boot, rng):
    """participant_bootstrap as it counted before (int64 draws, one flat bincount per block)."""
    import masking_lab.analysis.ramp_fit as rf

    n_part = data.shape[0]
    present = np.isfinite(data)
    filled = np.where(present, data, 0.0)
    present_f = present.astype(float)
    counts = np.empty((n_boot, data.shape[1]))
    sums = np.empty_like(counts)
    block = max(1, 2_000_000 // max(1, n_part))
    for lo in range(0, n_boot, block):
        rows = min(block, n_boot - lo)
        draws = rng.integers(0, n_part, size=(rows, n_part))
        draws += (np.arange(rows) * n_part)[:, None]
        weights = np.bincount(draws.ravel(), minlength=rows * n_part).reshape(rows, n_part)
        weights = weights.astype(float)
        counts[lo : lo + rows] = weights @ present_f
        sums[lo : lo + rows] = weights @ filled
    means = sums / counts
    return rf.ramp_least_squares_batch(np.asarray(x, float), means)


@pytest.mark.parametrize("n_part", [3, 40, 1001, 3334])
def test_participant_bootstrap_draws_and_counts_as_before(n_part):
    """The draws are counted a replicate at a time from int32 draws (less memory): the
    replicates are bit for bit the flat int64 count's, blocks of several replicates included."""
    rng = np.random.default_rng(n_part)
    x = np.array([5.0, 10.0, 15.0])
    data = rng.normal(2.0, 3.0, size=(n_part, 3)) * np.array([0.1, 1.0, 2.3])
    a, b, failed = participant_bootstrap(x, data, n_boot=1500, rng=np.random.default_rng(3))
    a0, b0 = _bootstrap_flat_count(x, data, 1500, np.random.default_rng(3))
    assert failed == 0
    assert a.tobytes() == a0.tobytes() and b.tobytes() == b0.tobytes()
