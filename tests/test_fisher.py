"""Fisher information, the Cramér-Rao bound, efficiencies, and the down/up ratio."""

from __future__ import annotations

import numpy as np
import pytest

from masking_lab.core.errors import StaircaseError
from masking_lab.core.psychometric import Psychometric
from masking_lab.procedures.downup_ratio import (
    GARCIA_PEREZ_2AFC_RATIO,
    downup_ratio_for,
    simulated_target_p,
)
from masking_lab.procedures.efficiency import PAPER_STAIRCASE, experiment1_thresholds_db
from masking_lab.procedures.fisher import (
    cramer_rao_sd,
    cramer_rao_trials,
    efficiency,
    fisher_information,
    max_information,
)
from masking_lab.procedures.staircase import implied_target_p_for
from masking_lab.procedures.staircase_batch import Observer, simulate


def test_information_peaks_where_issue_13_says():
    info, p, offset = max_information(scale_db=1.5, guess=1 / 3, lapse=0.02)
    assert info == pytest.approx(0.0534, abs=5e-5)
    assert p == pytest.approx(0.708, abs=5e-4)
    assert float(Psychometric(0.0).p_correct(offset)) == pytest.approx(p)
    assert cramer_rao_trials(1.08) == pytest.approx(16.0, abs=0.2)
    assert cramer_rao_sd(cramer_rao_trials(0.5)) == pytest.approx(0.5)


def test_information_equals_a_numerical_derivative_of_the_likelihood():
    # I(x) = E[(d log L / dθ)²], with dp/dθ by central differences on Psychometric itself.
    x = np.linspace(-6.0, 6.0, 25)
    h = 1e-5
    dp = (Psychometric(h).p_correct(x) - Psychometric(-h).p_correct(x)) / (2 * h)
    p = Psychometric(0.0).p_correct(x)
    np.testing.assert_allclose(fisher_information(x), dp**2 / (p * (1 - p)), rtol=1e-6)
    # Steeper functions carry more information; information scales as 1/scale².
    assert max_information(scale_db=0.75)[0] == pytest.approx(4 * max_information()[0])


def test_the_papers_staircase_is_about_31_percent_efficient():
    thr = np.repeat(experiment1_thresholds_db(), 200)
    tracks = simulate(
        PAPER_STAIRCASE, thr, Observer(), np.random.default_rng(0), store_levels=False
    )
    err = (tracks.al_db - thr).reshape(15, 200)
    sd = float(np.sqrt(np.mean(np.var(err, axis=1))))
    eff = float(efficiency(sd, tracks.n_trials.mean()))
    assert tracks.n_trials.mean() == pytest.approx(52, abs=2)
    assert 0.9 < sd < 1.25  # 1.08 dB with 2000 tracks per set
    assert 0.24 < eff < 0.38


def test_downup_ratio_inverts_the_zero_drift_point():
    assert downup_ratio_for(0.8315, 3) == pytest.approx(GARCIA_PEREZ_2AFC_RATIO, abs=5e-4)
    assert downup_ratio_for(0.5 ** (1 / 3), 3) == pytest.approx(1.0)
    for n_up, n_down, p in [(1, 3, 0.85), (1, 2, 0.75), (2, 3, 0.7), (2, 1, 0.4), (1, 4, 0.9)]:
        r = downup_ratio_for(p, n_down, n_up, guess_rate=0.0)
        assert implied_target_p_for(n_up, n_down, r) == pytest.approx(p, abs=1e-9)
    with pytest.raises(StaircaseError, match="between the guess rate"):
        downup_ratio_for(0.3, 3)  # below 3IFC chance
    with pytest.raises(StaircaseError, match="integers"):
        downup_ratio_for(0.8, 0)


def test_small_steps_settle_where_the_formula_says_and_large_ones_do_not():
    rng = np.random.default_rng(1)
    r = downup_ratio_for(0.85, 3)
    assert simulated_target_p(r, 0.375, rng, n_tracks=400) == pytest.approx(0.85, abs=0.006)
    # 3IFC, 2-scale steps: García-Pérez's ratio overshoots its 83.15 % target (his is 2AFC).
    p = simulated_target_p(GARCIA_PEREZ_2AFC_RATIO, 3.0, rng, n_tracks=400)
    assert p > 0.84
