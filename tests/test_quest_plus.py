"""QUEST+ / psi-marginal: oracle tests against the `questplus` package and property tests.

questplus (GPL-3) is used here only, as an independent implementation of Watson's (2017)
algorithm: same grids, same prior, and — because it has no logistic — our forced-choice
logistic injected as its likelihood table, built from masking_lab.core.psychometric (not from
the table code under test). It has no psi-marginal placement; that is checked against a
brute-force marginal-entropy computation written out below.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from masking_lab.core.errors import ProcedureError
from masking_lab.core.psychometric import Psychometric
from masking_lab.procedures.base import Procedure, replay
from masking_lab.procedures.quest_plus import (
    QuestPlus,
    QuestPlusSettings,
    expected_entropy,
    tables,
)

qp_module = pytest.importorskip("questplus")
xr = pytest.importorskip("xarray")


def _reference_likelihood(s: QuestPlusSettings) -> np.ndarray:
    """p(correct), shape (S, T, K, L), straight from Psychometric.p_correct."""
    t = tables(s)
    out = np.empty((t.levels_db.size, t.thresholds_db.size, len(s.scales_db), len(s.lapses)))
    for j, thr in enumerate(t.thresholds_db):
        for k, sc in enumerate(s.scales_db):
            for m, lam in enumerate(s.lapses):
                psy = Psychometric(float(thr), sc, s.guess, lam, s.p_at_threshold)
                out[:, j, k, m] = psy.p_correct(t.levels_db)
    return out


def _oracle(s: QuestPlusSettings):
    """A questplus.QuestPlus on the same grids and prior with our model as its likelihood."""
    t = tables(s)
    prior = None
    if s.prior == "normal":
        prior = {
            "threshold": np.exp(-0.5 * ((t.thresholds_db - s.prior_mean_db) / s.prior_sd_db) ** 2)
        }
    q = qp_module.QuestPlus(
        stim_domain={"intensity": t.levels_db},
        param_domain={
            "threshold": t.thresholds_db,
            "slope": np.asarray(s.scales_db),
            "lower_asymptote": np.array([s.guess]),
            "lapse_rate": np.asarray(s.lapses),
        },
        outcome_domain={"response": ["Correct", "Incorrect"]},
        prior=prior,
        func="weibull",  # replaced below: questplus has no logistic
        stim_scale="dB",
        stim_selection_method="min_entropy",
        param_estimation_method="mean",
    )
    pc = _reference_likelihood(s)[:, :, :, None, :]  # lower_asymptote axis
    coords = {
        "response": ["Correct", "Incorrect"],
        "intensity": t.levels_db,
        "threshold": t.thresholds_db,
        "slope": np.asarray(s.scales_db),
        "lower_asymptote": np.array([s.guess]),
        "lapse_rate": np.asarray(s.lapses),
    }
    like = xr.DataArray(np.stack([pc, 1.0 - pc]), dims=list(coords), coords=coords)
    q.likelihoods = like.transpose(*q.likelihoods.dims)
    return q


def _observer_answers(rng, true_db: float, level: float) -> bool:
    return bool(rng.random() < Psychometric(true_db, 1.5, 1 / 3, 0.02).p_correct(level))


ORACLE_CASES = [
    # known slope and lapse (stated: the defaults marginalise them), flat prior over the level
    # range (the paper's default observer)
    QuestPlusSettings(-20.0, 45.0, scales_db=1.5, lapses=0.02, max_trials=40),
    # normal prior, coarser threshold grid wider than the stimulus range
    QuestPlusSettings(
        -10.0, 30.0, threshold_min_db=-15.0, threshold_max_db=35.0, threshold_step_db=1.0,
        prior="normal", prior_mean_db=10.0, prior_sd_db=8.0, scales_db=1.5, lapses=0.02,
        max_trials=30,
    ),
    # unknown slope and lapse, joint entropy: Watson's QUEST+ exactly
    QuestPlusSettings(
        -10.0, 30.0, level_step_db=1.0, scales_db=(0.75, 1.5, 3.0), lapses=(0.0, 0.04),
        entropy_over="all", max_trials=30,
    ),
]  # fmt: skip


@pytest.mark.parametrize("case", range(len(ORACLE_CASES)))
@pytest.mark.parametrize("seed", [1, 2])
def test_same_levels_and_posteriors_as_questplus(case, seed):
    s = ORACLE_CASES[case]
    rng = np.random.default_rng(seed)
    true_db = float(rng.uniform(*s.threshold_range_db))
    q = _oracle(s)
    track = s.start()
    shape = (track.posterior.shape[0], len(s.scales_db), len(s.lapses))
    while not track.finished:
        theirs = q.next_stim["intensity"]
        assert track.next_level() == pytest.approx(theirs, abs=1e-9), track.n_trials
        correct = _observer_answers(rng, true_db, track.next_level())
        q.update(
            stim={"intensity": theirs}, outcome={"response": "Correct" if correct else "Incorrect"}
        )
        track = track.update(correct)
        post = q.posterior.values.reshape(shape)
        np.testing.assert_allclose(track.posterior.reshape(shape), post, rtol=1e-9, atol=1e-15)
    assert track.n_trials == s.max_trials
    assert track.posterior_mean_db == pytest.approx(q.param_estimate["threshold"], abs=1e-9)


def _brute_marginal_entropy(t, post: np.ndarray) -> np.ndarray:
    """Expected entropy of the threshold marginal, one level at a time (Prins 2013, eq. 7)."""
    out = []
    for i in range(t.levels_db.size):
        eh = 0.0
        for like in (t.p_correct[i], t.p_wrong[i]):
            joint = post * like
            pk = joint.sum()
            marg = joint.sum(axis=1) / pk
            eh += pk * -sum(m * math.log(m) for m in marg if m > 0)
        out.append(eh)
    return np.array(out)


def test_psi_marginal_places_by_the_threshold_marginal_entropy():
    s = QuestPlusSettings(
        -10.0, 20.0, level_step_db=1.0, scales_db=(0.5, 1.5, 4.0), lapses=(0.0, 0.05),
        max_trials=25,
    )  # fmt: skip
    t = tables(s)
    rng = np.random.default_rng(3)
    track = s.start()
    joint_levels = []
    while not track.finished:
        brute = _brute_marginal_entropy(t, track.posterior)
        ours = expected_entropy(t, track.posterior[None], "threshold")[0]
        np.testing.assert_allclose(ours, brute, rtol=1e-10)
        assert track.next_level() == t.levels_db[int(np.argmin(brute))]
        joint = expected_entropy(t, track.posterior[None], "all")[0]
        joint_levels.append(float(t.levels_db[int(np.argmin(joint))]))
        track = track.update(_observer_answers(rng, 4.0, track.next_level()))
    # The two placements genuinely differ (else this test would not check psi-marginal).
    assert joint_levels != list(track.levels_db)


# ---------------------------------------------------------------- properties

SMALL = QuestPlusSettings(
    -10.0, 20.0, level_step_db=1.0, scales_db=(1.0, 2.0), target_sd_db=1.0, min_trials=5,
    max_trials=25,
)  # fmt: skip


@settings(max_examples=40, deadline=None, derandomize=True)
@given(st.lists(st.booleans(), min_size=0, max_size=25))
def test_replay_equals_step_by_step_and_invariants_hold(answers):
    track = SMALL.start()
    grid = tables(SMALL).levels_db
    used = 0
    for a in answers:
        if track.finished:
            break
        track = track.update(a)
        used += 1
        assert math.isclose(float(track.posterior.sum()), 1.0, rel_tol=1e-12)
        assert np.all(track.posterior >= 0)
        assert track.next_level() in grid
        summary = track.trial_summary()
        assert all(math.isfinite(v) for v in summary.values())
    assert replay(SMALL, answers[:used]) == track
    assert isinstance(track, Procedure)
    if track.finished:
        with pytest.raises(ProcedureError, match="no more responses"):
            track.update(True)
        with pytest.raises(ProcedureError, match="after the quest_plus finished"):
            replay(SMALL, [*answers[:used], True])


def test_stop_rules_and_estimate():
    rng = np.random.default_rng(7)
    s = QuestPlusSettings(-20.0, 45.0, target_sd_db=1.08, min_trials=10, max_trials=200)
    track = s.start()
    while not track.finished:
        track = track.update(_observer_answers(rng, 12.0, track.next_level()))
    est = track.estimate()
    assert track.status == "completed" and est.method == "posterior_mean"
    assert est.sd_db <= 1.08 and track.n_trials >= 10
    assert est.level_db == pytest.approx(12.0, abs=4 * 1.08)
    # The precision rule did not hold one trial earlier.
    earlier = replay(s, track.responses[:-1])
    assert earlier.posterior_sd_db > 1.08 or earlier.n_trials < 10

    capped = replay(QuestPlusSettings(-20.0, 45.0, target_sd_db=0.1, max_trials=15), [True] * 15)
    assert capped.status == "trial_cap" and capped.estimate().level_db is None
    counted = replay(QuestPlusSettings(-20.0, 45.0, max_trials=15), track.responses[:15])
    assert counted.status == "completed" and counted.estimate().sd_db > 0


def test_a_threshold_above_the_grid_ends_as_a_ceiling_not_a_number():
    s = QuestPlusSettings(-20.0, 45.0, target_sd_db=1.08, max_trials=100)
    rng = np.random.default_rng(0)
    track = s.start()
    while not track.finished:
        track = track.update(_observer_answers(rng, 60.0, track.next_level()))
    assert track.status == "ceiling"
    assert track.estimate().level_db is None


def test_settings_validation_and_from_mapping():
    s = QuestPlusSettings.from_mapping(
        {"kind": "quest_plus", "min_level_db": -20, "max_level_db": 45, "scales_db": 1.5,
         "lapses": [0.0, 0.02], "target_sd_db": 1.08}
    )  # fmt: skip
    assert s.kind == "quest_plus" and s.scales_db == (1.5,) and s.lapses == (0.0, 0.02)
    assert s.guess == pytest.approx(1 / 3)
    assert tables(s) is tables(QuestPlusSettings.from_mapping({**s.__dict__}))  # cached
    with pytest.raises(ProcedureError, match=r"unknown key.*step_db.*valid keys"):
        QuestPlusSettings.from_mapping({"min_level_db": 0, "max_level_db": 1, "step_db": 1})
    with pytest.raises(ProcedureError, match="max_level_db is required"):
        QuestPlusSettings.from_mapping({"min_level_db": 0})
    bad = [
        ({"max_trials": None}, "needs a stop rule"),
        ({"level_step_db": 0}, "level_step_db: must be a positive"),
        ({"lapses": (0.7,)}, "lapse rate must lie in"),
        ({"prior": "normal"}, "prior_mean_db"),
        ({"min_trials": 99}, "exceeds max_trials"),
        ({"n_intervals": 1}, "n_intervals"),
        ({"entropy_over": "slope"}, "entropy_over"),
        ({"p_at_threshold": 0.2}, "p_at_threshold"),
    ]
    for kwargs, match in bad:
        with pytest.raises(ProcedureError, match=match):
            QuestPlusSettings(-20.0, 45.0, **kwargs)
    assert isinstance(s.start(), QuestPlus)


def test_xlogx_is_the_masked_log_with_and_without_underflowed_cells():
    """The plain-log path (no cell at 0) and the masked one give the masked log's values."""
    from masking_lab.procedures.quest_plus_model import xlogx

    def masked(a):
        out = np.zeros_like(a)
        np.log(a, out=out, where=a > 0)
        return out * a

    rng = np.random.default_rng(7)
    a = rng.random((4, 9, 13)) * 1e-3 + np.finfo(float).tiny
    assert np.array_equal(xlogx(a), masked(a))  # bit for bit
    a[1, 2, 3] = a[3, 0, 0] = 0.0  # underflowed cells add 0, not NaN
    got = xlogx(a)
    assert np.array_equal(got, masked(a)) and got[1, 2, 3] == 0.0 and np.isfinite(got).all()
    assert xlogx(np.zeros((0, 3))).shape == (0, 3)
