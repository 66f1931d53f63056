"""The functional (ramp) procedure against independent computations: its likelihood against
the project's psychometric function and the paper's ramp, its posterior against a brute-force
grid computation on recorded answers, its placement against a float64 brute-force expected
entropy, and its stop rules and settings checks."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from masking_lab.core.errors import ProcedureError
from masking_lab.core.masking import ramp
from masking_lab.core.psychometric import Psychometric
from masking_lab.procedures.base import replay
from masking_lab.procedures.functional import (
    FunctionalRampSettings,
    expected_entropy,
    ramp_tables,
)

SMALL = FunctionalRampSettings(
    masker_min_db_sl=5.0,
    masker_max_db_sl=25.0,
    masker_step_db=10.0,
    min_level_db=-4.0,
    max_level_db=24.0,
    level_step_db=2.0,
    intercept_min_db=-12.0,
    intercept_max_db=4.0,
    intercept_step_db=2.0,
    slope_min=0.3,
    slope_max=1.2,
    slope_step=0.15,
    unmasked_offsets_db=(-1.0, 0.0, 1.0),
    scales_db=(1.0, 2.5),
    lapses=(0.0, 0.05),
    max_trials=40,
)


def _answers(settings, a, b, seed, n=None):
    rng = np.random.default_rng(seed)
    state = settings.start()
    out = []
    while not state.finished and (n is None or len(out) < n):
        theta = float(ramp(state.next_masker_level_db_sl(), a, b))
        p = Psychometric(theta, 1.5, 1 / 3, 0.02).p_correct(state.next_level())
        r = bool(rng.random() < p)
        out.append(r)
        state = state.update(r)
    return state, out


def test_the_likelihood_is_the_psychometric_function_around_the_papers_ramp():
    t = ramp_tables(SMALL)
    rng = np.random.default_rng(0)
    for _ in range(50):
        i, s, n = (int(rng.integers(k)) for k in (t.intercepts_db.size, t.targets_db.size, 12))
        u, scale, lapse = t.nuisance[n]
        theta = u + float(ramp(t.maskers_db_sl[s], t.intercepts_db[i], t.slopes[i]))
        want = Psychometric(theta, scale, 1 / 3, lapse).p_correct(t.targets_db[s])
        assert t.p_correct[n, i, s] == pytest.approx(want, rel=1e-6)


def test_the_posterior_equals_a_brute_force_grid_computation_on_recorded_answers():
    state, answers = _answers(SMALL, -6.0, 0.8, seed=3)
    # Independent: loop over every grid point with the core psychometric function.
    a_grid = np.arange(-12.0, 4.0 + 1e-9, 2.0)
    b_grid = np.round(np.arange(0.3, 1.2 + 1e-9, 0.15), 9)
    log_post = {}
    for a, b, u, scale, lapse in itertools.product(
        a_grid, b_grid, (-1.0, 0.0, 1.0), (1.0, 2.5), (0.0, 0.05)
    ):
        total = 0.0
        for x, y, r in zip(state.maskers_db_sl, state.levels_db, answers, strict=True):
            theta = u + max(0.0, a + b * x)
            p = Psychometric(theta, scale, 1 / 3, lapse).p_correct(y)
            total += math.log(p if r else 1 - p)
        log_post.setdefault((a, b), []).append(total)
    top = max(max(v) for v in log_post.values())
    weights = {k: sum(math.exp(v - top) for v in vs) for k, vs in log_post.items()}
    norm = sum(weights.values())
    mean_a = sum(k[0] * w for k, w in weights.items()) / norm
    mean_b = sum(k[1] * w for k, w in weights.items()) / norm
    sd_a = math.sqrt(sum((k[0] - mean_a) ** 2 * w for k, w in weights.items()) / norm)
    m = state.moments()
    assert m["intercept_db"] == pytest.approx(mean_a, rel=1e-9, abs=1e-9)
    assert m["slope"] == pytest.approx(mean_b, rel=1e-9, abs=1e-9)
    assert m["intercept_sd_db"] == pytest.approx(sd_a, rel=1e-9)


def test_placement_picks_the_least_expected_entropy_of_the_ramps_marginal():
    state, _ = _answers(SMALL, -4.0, 0.7, seed=5, n=12)
    t = ramp_tables(SMALL)
    post = state.posterior
    # float64 brute force: for every stimulus, the (a, b) marginal after each answer.
    like = np.stack(
        [
            np.array(
                [
                    [
                        Psychometric(
                            u + float(ramp(t.maskers_db_sl[s], a, b)), sc, 1 / 3, lam
                        ).p_correct(t.targets_db[s])
                        for (u, sc, lam) in t.nuisance
                    ]
                    for a, b in zip(t.intercepts_db, t.slopes, strict=True)
                ]
            )
            for s in range(t.targets_db.size)
        ]
    )  # (S, A, N)
    brute = []
    for s in range(t.targets_db.size):
        total = 0.0
        for lk in (like[s], 1 - like[s]):
            m = (post * lk).sum(axis=1)
            pk = m.sum()
            q = m / pk
            total += pk * -(q[q > 0] * np.log(q[q > 0])).sum()
        brute.append(total)
    brute = np.array(brute)
    ours = expected_entropy(t, post)
    np.testing.assert_allclose(ours, brute, rtol=1e-4, atol=1e-5)
    assert brute[state.stimulus] <= brute.min() + 1e-4


def test_the_track_recovers_a_ramp_within_its_interval_and_uses_several_masker_levels():
    state, _ = _answers(FunctionalRampSettings(max_trials=87), -7.442, 0.711, seed=11)
    m = state.moments()
    assert abs(m["intercept_db"] + 7.442) < 2.5 * m["intercept_sd_db"]
    assert abs(m["slope"] - 0.711) < 2.5 * m["slope_sd"]
    assert len(set(state.maskers_db_sl)) >= 3
    assert state.status == "completed" and state.n_trials == 87


def test_precision_targets_stop_early_and_the_cap_is_a_trial_cap():
    loose = FunctionalRampSettings(
        max_trials=60, target_sd_intercept_db=6.0, target_sd_slope=0.4, min_trials=5
    )
    state, _ = _answers(loose, -5.0, 0.8, seed=2)
    assert state.status == "completed" and 5 <= state.n_trials < 60
    strict = FunctionalRampSettings(max_trials=8, target_sd_intercept_db=0.01)
    state, _ = _answers(strict, -5.0, 0.8, seed=2)
    assert state.status == "trial_cap" and state.n_trials == 8
    assert replay(strict, [True] * 8).status == "trial_cap"
    with pytest.raises(ProcedureError, match="finished"):
        state.update(True)


@pytest.mark.parametrize(
    ("change", "key"),
    [
        ({"masker_step_db": 0.0}, "masker_step_db"),
        ({"slope_min": 1.0, "slope_max": 0.5}, "slope_min"),
        ({"lapses": (0.9,)}, "lapses"),
        ({"max_trials": 0}, "max_trials"),
        ({"level_step_db": 1e-4}, "level_step_db"),
        ({"scales_db": ()}, "scales_db"),
        ({"intercept_min_db": math.nan}, "intercept_min_db"),
    ],
)
def test_bad_settings_name_their_key(change, key):
    with pytest.raises(ProcedureError, match=key):
        FunctionalRampSettings(**change)


def test_an_unknown_key_lists_the_valid_ones():
    with pytest.raises(ProcedureError, match="valid keys are masker_min_db_sl"):
        FunctionalRampSettings.from_mapping({"kind": "functional_ramp", "slopes": [1]})
