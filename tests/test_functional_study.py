"""A simulated functional-procedure study through the firmware emulator, analysed by `analyze`.

Ten simulated participants each sit the baseline (staircase; it calibrates them) and the
shipped ``experiment1_functional.yaml`` on ``--device emulator`` in virtual time; ``analyze``
recomputes every ramp posterior. The truth, in the session's terms: the participant's masked
AL relative to the calibration the rig measured, as a function of the *nominal* masker level
(the masker's calibration error moves its true level), is u + a + b·x above the knee, with u
the calibration error of the target's unmasked AL; the 95 % credible intervals of a and b must
hold it about as often as they promise (binomial bounds over 30 intervals each).
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
FUNCTIONAL = shipped("protocols", "experiment1_functional.yaml")


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    root = tmp_path_factory.mktemp("fstudy")
    data, out = root / "data", root / "out"
    for i in range(N_PARTICIPANTS):
        pid = f"P{i + 1:02d}"
        for protocol, seed in ((BASELINE, 300 + i), (FUNCTIONAL, 400 + i)):
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


def _true_ramps(data):
    """(participant, masker) → (intercept dB, slope) in nominal masker dB SL."""
    truth = load_ground_truth()
    out = {}
    for log in sorted(data.glob("P*/experiment1_functional-*.jsonl")):
        recs = [json.loads(line) for line in log.read_text(encoding="utf-8").splitlines()]
        header = recs[0]
        person = make_participant(truth, header["participant"], 0)
        cal = header["calibration"]
        for r in recs:
            if r["record"] != "set_start":
                continue
            target, masker = r["target"], r["masker"]
            d_m = cal[masker] - person.unmasked_al_db_v[masker]  # nominal → true masker SL

            def theta(x, target=target, masker=masker, d_m=d_m, person=person, cal=cal):
                return person.masked_al_db_v(target, masker, x + d_m) - cal[target]

            u = person.unmasked_al_db_v[target] - cal[target]
            b = (theta(25.0) - theta(20.0)) / 5.0
            out[(header["participant"], masker)] = (theta(25.0) - 25.0 * b - u, b)
    return out


def test_every_participant_gets_a_ramp_posterior_and_the_group_gets_both_estimates(study):
    _, out = study
    rows = _rows(out / "ramp_posteriors.csv")
    assert len(rows) == 3 * N_PARTICIPANTS
    assert all(r["status"] == "completed" and r["n_trials"] == "87" for r in rows)
    groups = _rows(out / "group_ramps.csv")
    assert {(g["masker"], g["estimate"]) for g in groups} == {
        (m, e) for m in ("MV120", "MV180", "MV270") for e in ("random_effects", "paper_route")
    }
    params = json.loads((out / "masking_params.json").read_text(encoding="utf-8"))
    assert {f["estimate"] for f in params["functions"]} == {"random_effects"}


def test_functional_sets_say_in_thresholds_csv_where_their_result_is(study):
    # A functional set names no single masker level; it used to be "invalid: set_start
    # unusable". Each is listed once, with its masker and the file that holds its ramp.
    _, out = study
    rows = [r for r in _rows(out / "thresholds.csv") if r["experiment"] == "experiment1_functional"]
    assert len(rows) == 3 * N_PARTICIPANTS
    for r in rows:
        assert r["status"] == "no_threshold", r
        assert "ramp_posteriors.csv" in r["note"] and r["masker"] in ("MV120", "MV180", "MV270")
        assert r["masker_level_db_sl"] == "" and r["al_db_v"] == ""


def test_the_intervals_hold_the_truth_about_as_often_as_they_promise(study):
    data, out = study
    truth = _true_ramps(data)
    rows = _rows(out / "ramp_posteriors.csv")
    hits_a = hits_b = 0
    for r in rows:
        a, b = truth[(r["participant"], r["masker"])]
        hits_a += float(r["intercept_ci_low_db"]) <= a <= float(r["intercept_ci_high_db"])
        hits_b += float(r["slope_ci_low"]) <= b <= float(r["slope_ci_high"])
    n = len(rows)
    low = binom.ppf(0.001, n, 0.95)
    assert hits_a >= low and hits_b >= low, (hits_a, hits_b, n)
