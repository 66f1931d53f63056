"""`analyze` estimates QUEST+ sets from their logged trials: posterior mean, SD and interval."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binom

from masking_lab.analysis.procedure_estimates import posterior_summary, procedure_estimate
from masking_lab.core.psychometric import Psychometric
from masking_lab.procedures.log_fields import settings_record
from masking_lab.procedures.quest_plus import QuestPlusSettings

SETTINGS = QuestPlusSettings(-20.0, 45.0, target_sd_db=1.5, min_trials=10, max_trials=60)


def _track(true_db: float, seed: int):
    rng = np.random.default_rng(seed)
    psy = Psychometric(0.0, 1.5, lapse=0.02)
    track = SETTINGS.start()
    while not track.finished:
        track = track.update(bool(rng.random() < psy.p_correct(track.next_level() - true_db)))
    return track


@pytest.mark.parametrize("seed", range(4))
def test_the_posterior_from_the_log_is_the_tracks_own(seed):
    track = _track(7.0, seed)
    mean, sd, lo, hi = posterior_summary(SETTINGS, track.levels_db, track.responses)
    assert mean == pytest.approx(track.posterior_mean_db, abs=1e-9)
    assert sd == pytest.approx(track.posterior_sd_db, abs=1e-9)
    cdf = np.cumsum(track.threshold_posterior)
    grid = np.linspace(-20.0, 45.0, 131)
    assert np.interp(lo, grid, cdf) == pytest.approx(0.025, abs=1e-9)
    assert np.interp(hi, grid, cdf) == pytest.approx(0.975, abs=1e-9)
    est = procedure_estimate(settings_record(SETTINGS), track.levels_db, track.responses)
    assert (est.al_db, est.sd_db, est.method) == (mean, sd, "posterior_mean")


def test_ml_over_the_trials_and_bad_records():
    track = _track(3.0, 9)
    rec = settings_record(SETTINGS)
    ml = procedure_estimate(rec, track.levels_db, track.responses, estimator="ml")
    assert ml.method == "ml" and ml.status == "completed" and abs(ml.al_db - 3.0) < 4.0
    assert ml.sd_db == pytest.approx(track.posterior_sd_db, abs=1e-9)
    bad = procedure_estimate({**rec, "max_trials": 0}, track.levels_db, track.responses)
    assert bad.status == "invalid" and "max_trials" in bad.note
    other = procedure_estimate({"kind": "psi"}, [1.0], [True])
    assert other.status == "invalid" and "psi" in other.note


def test_interval_covers_the_truth_about_95_percent_of_the_time():
    hits = 0
    n = 120
    for seed in range(n):
        track = _track(5.0, 100 + seed)
        _, _, lo, hi = posterior_summary(SETTINGS, track.levels_db, track.responses)
        hits += lo <= 5.0 <= hi
    assert binom.ppf(0.001, n, 0.95) <= hits <= binom.ppf(0.999, n, 0.95)


def test_synthetic_quest_plus_logs_are_real_logs_and_analyse(tmp_path):
    from runner_support import assert_valid_log

    from masking_lab.commands.cli import main
    from masking_lab.simulation.synthetic_logs import simulate_study

    paths = simulate_study(
        tmp_path / "logs", n_participants=2, seed=1, protocols=("baseline", "experiment1_questplus")
    )
    quest = [p for p in paths if "questplus" in p.name]
    assert len(quest) == 2
    for path in quest:
        recs = assert_valid_log(path)
        trials = [r for r in recs if r["record"] == "trial"]
        assert all(set(r["posterior"]) == {"mean_db", "sd_db"} for r in trials)
        ends = [r for r in recs if r["record"] == "set_end"]
        assert len(ends) == 15 and all(e["method"] == "posterior_mean" for e in ends)
    out = tmp_path / "out"
    assert main(["analyze", str(tmp_path / "logs"), "--out", str(out), "--quiet"]) == 0
    rows = (out / "thresholds.csv").read_text(encoding="utf-8").splitlines()
    assert sum(",posterior_mean," in r for r in rows) == 30
