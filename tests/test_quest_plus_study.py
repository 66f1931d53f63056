"""A simulated QUEST+ study through the firmware emulator, analysed like a staircase study.

Ten simulated participants each sit the baseline (staircase; it calibrates them) and the
shipped QUEST+ protocol on ``--device emulator`` in virtual time; ``analyze`` then estimates
every QUEST+ set by its posterior mean with a 95 % credible interval. The intervals must hold
the simulated truth at least as often as they promise (slope and lapse are marginalised, so
they may be conservative): the truth is the participant's AL (the 0.794
point) in the session's dB SL, i.e. relative to the calibration the rig measured, at the
masker's true sensation level; the hit counts must lie within binomial bounds.
"""

from __future__ import annotations

import csv
import json

import pytest
from scipy.stats import binom

from masking_lab.commands.cli import main
from masking_lab.formats.resources import shipped
from masking_lab.simulation.observer import load_ground_truth, make_participant

N_PARTICIPANTS = 10
BASELINE = shipped("protocols", "baseline.yaml")
QUEST = shipped("protocols", "experiment1_questplus.yaml")


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    root = tmp_path_factory.mktemp("study")
    data, out = root / "data", root / "out"
    for i in range(N_PARTICIPANTS):
        pid = f"P{i + 1:02d}"
        for protocol, seed in ((BASELINE, 100 + i), (QUEST, 200 + i)):
            args = ["run", str(protocol), "--participant", pid, "--device", "emulator"]
            args += ["--responder", "sim", "--data", str(data), "--seed", str(seed)]
            assert main([*args, "--no-progress"]) == 0
    # The tests read the tables and masking_params.json: no figures, trial tables or
    # psychometric bootstraps, and the ramp bootstrap's intervals are not looked at.
    quick = ["--figures", "none", "--no-trial-tables", "--pf-boot", "0", "--n-boot", "200"]
    assert main(["analyze", str(data), "--out", str(out), "--quiet", *quick]) == 0
    return data, out


def _rows(path):
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def _truth_db_sl(data):
    """(participant, set_id) → true AL in the session's dB SL, from the logs and ground truth."""
    truth = load_ground_truth()
    out = {}
    for log in sorted(data.glob("P*/experiment1_questplus-*.jsonl")):
        recs = [json.loads(line) for line in log.read_text(encoding="utf-8").splitlines()]
        header = recs[0]
        person = make_participant(truth, header["participant"], 0)
        for r in recs:
            if r["record"] != "set_start":
                continue
            masker_true_sl = r["masker_level_db_v"] - person.unmasked_al_db_v[r["masker"]]
            al_v = person.masked_al_db_v(r["target"], r["masker"], masker_true_sl)
            out[(header["participant"], r["set_id"])] = al_v - r["unmasked_al_db_v"]
    return out


def test_the_study_is_analysed_and_exported_like_a_staircase_study(study):
    _, out = study
    rows = [r for r in _rows(out / "thresholds.csv") if r["experiment"] == "experiment1_questplus"]
    assert len(rows) == 15 * N_PARTICIPANTS
    assert all(r["status"] == "completed" for r in rows)
    assert all(float(r["al_sd_db"]) <= 1.6 for r in rows)  # the protocol's stop rule
    fits = [r for r in _rows(out / "ramp_fits.csv") if r["experiment"] == "experiment1_questplus"]
    assert fits and all(r["status"] == "fitted" for r in fits)
    anova = [r for r in _rows(out / "anova.csv") if r["experiment"] == "experiment1_questplus"]
    assert anova  # ten participants with every cell: the RM ANOVA runs
    params = json.loads((out / "masking_params.json").read_text(encoding="utf-8"))
    assert "experiment1_questplus" in json.dumps(params)
    assert "experiment1_questplus" in (out / "report.txt").read_text(encoding="utf-8")


def test_the_intervals_hold_the_truth_as_often_as_they_promise(study):
    data, out = study
    truth = _truth_db_sl(data)
    rows = [r for r in _rows(out / "thresholds.csv") if r["experiment"] == "experiment1_questplus"]
    n = len(rows)
    in_95 = in_1sd = 0
    for r in rows:
        true = truth[(r["participant"], r["set_id"])]
        lo, hi = float(r["al_ci95_low_db"]), float(r["al_ci95_high_db"])
        assert lo < float(r["al_db_sl"]) < hi
        in_95 += lo <= true <= hi
        in_1sd += abs(float(r["al_db_sl"]) - true) <= float(r["al_sd_db"])
    # The shipped protocol marginalises slope and lapse: for these observers (near the middle
    # of its grids) the posterior also carries slopes the data cannot rule out, so its
    # intervals may be wider than promised, never narrower (docs/procedures.md, "Intervals when
    # the observer is not the model").
    for hits, p in ((in_95, 0.95), (in_1sd, 0.6827)):
        assert binom.ppf(0.001, n, p) <= hits, (hits, n, p)
