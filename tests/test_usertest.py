"""The user test's pure parts: protocol, trial order, levels along the path, observer, analysis."""

from __future__ import annotations

import math
import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from masking_lab.commands.cli import main
from masking_lab.core.errors import AnalysisError, ProtocolError, SolverError
from masking_lab.rendering.solver import MissingMaskingError, MutualMasking
from masking_lab.simulation.observer import load_ground_truth
from masking_lab.usertest.design import UserTestTiming, load_usertest, trial_list, trial_record
from masking_lab.usertest.observer import IdentificationObserver, simulate_usertest
from masking_lab.usertest.playback import (
    levels_at,
    path_position_mm,
    path_x_from_screen_mm,
    render_objects,
    trial_levels_db_v,
)
from masking_lab.usertest.stats import analyze_usertest

ROOT = Path(__file__).resolve().parents[1]
USERTEST = ROOT / "protocols" / "usertest.yaml"
INF = math.inf


@pytest.fixture(scope="module")
def design():
    return load_usertest(USERTEST)


@pytest.fixture(scope="module")
def truth(design):
    gt = load_ground_truth()
    return {
        (mv, ev): MutualMasking.from_functions(
            gt.masking_function(mv, ev), gt.masking_function(ev, mv)
        )
        for mv, ev in design.stimulus_pairs()
    }


@pytest.fixture(scope="module")
def objects(design, truth):
    return render_objects(design, truth)


def test_the_paper_design(design):
    assert design.geometries == ("bump", "hole", "ascending", "descending")
    assert design.textures == ("smooth", "rough", "coarse")
    assert design.conditions == ("compensated", "uncompensated") and design.repeats == 5
    assert design.n_trials == 120
    assert design.timing.trial_s == pytest.approx(7.8)
    assert design.sweep_mm == pytest.approx(91.8) and design.tracking == "cue"
    assert len(design.scenes) == 12
    assert design.stimulus_pairs() == [
        ("MV120am40", "EV270"),
        ("MV180", "EV270"),
        ("MV270", "EV270"),
    ]
    assert main(["validate", str(USERTEST)]) == 0


def test_trial_list_is_balanced_seeded_and_shuffled(design):
    trials = trial_list(design, seed=11)
    assert len(trials) == 120 and [t.index for t in trials] == list(range(120))
    counts = Counter((t.geometry, t.texture, t.condition) for t in trials)
    assert len(counts) == 24 and set(counts.values()) == {5}
    for t in trials:
        assert design.geometries[t.geometry_key - 1] == t.geometry
        assert design.textures[t.texture_key - 1] == t.texture
        assert t.compensated == (t.condition == "compensated")
    assert trial_list(design, seed=11) == trials
    other = trial_list(design, seed=12)
    assert [t.object for t in other] != [t.object for t in trials]
    ordered = trial_list(_replace(design, randomize=False), seed=11)
    assert [t.object for t in ordered[:3]] == [
        ("bump", "smooth"),
        ("bump", "rough"),
        ("bump", "coarse"),
    ]
    assert [t.repeat for t in ordered] == sorted(t.repeat for t in ordered)


def _replace(design, **changes):
    from dataclasses import replace

    return replace(design, **changes)


@pytest.mark.parametrize(
    "t_s, expected",
    [
        (0.0, None),  # lead-in
        (1.19, None),
        (1.2, (1, 0.0)),
        (2.1, (1, 0.9)),
        (3.0, None),  # first gap starts as the first presentation ends
        (3.5, None),
        (3.6, (2, 0.0)),
        (6.0, (3, 0.0)),
        (7.79, (3, 1.79)),
        (7.8, None),  # trial over
        (-1.0, None),
        (math.nan, None),
    ],
)
def test_presentations_in_a_trial(t_s, expected):
    got = UserTestTiming().presentation_at(t_s)
    if expected is None:
        assert got is None
    else:
        assert got[0] == expected[0] and got[1] == pytest.approx(expected[1], abs=1e-9)


def test_cue_position_along_the_path(design):
    assert path_position_mm(design, 1.2 + 0.9) == pytest.approx(45.9)  # mid-path at 51 mm/s
    assert path_position_mm(design, 3.6 + 1.8 - 1e-6) == pytest.approx(91.8, abs=1e-3)
    assert path_position_mm(design, 3.3) is None
    assert path_x_from_screen_mm(design, -45.9) == pytest.approx(0.0)
    assert path_x_from_screen_mm(design, 45.9) == pytest.approx(91.8)


def test_levels_follow_the_rendering(objects):
    r = objects[("bump", "rough")]
    i = 300
    x = r.x_mm[i]
    assert levels_at(r, x, compensated=True) == (r.ev_input_db_sl[i], r.mv_input_db_sl[i])
    assert levels_at(r, x, compensated=False) == (r.ev_target_db_sl[i], r.mv_target_db_sl[i])
    mid = 0.5 * (r.x_mm[i] + r.x_mm[i + 1])
    ev, mv = levels_at(r, mid, compensated=True)
    assert ev == pytest.approx(0.5 * (r.ev_input_db_sl[i] + r.ev_input_db_sl[i + 1]))
    assert mv == pytest.approx(0.5 * (r.mv_input_db_sl[i] + r.mv_input_db_sl[i + 1]))
    for off in (-0.1, 92.0, math.nan):
        assert levels_at(r, off, compensated=True) == (-INF, -INF)


CAL = {"EV270": -14.0, "MV120am40": -24.0, "MV180": -30.0, "MV270": -32.0}


def test_trial_levels_with_cue_tracking(design, objects):
    trial = next(t for t in trial_list(design, 3) if t.object == ("hole", "smooth"))
    r = objects[trial.object]
    t_s = design.timing.onset_s(2) + 0.5
    x = design.cue_speed_mm_s * 0.5
    ev_sl, mv_sl = levels_at(r, x, compensated=trial.compensated)
    ev_v, mv_v = trial_levels_db_v(design, objects, trial, CAL, t_s=t_s)
    assert ev_v == pytest.approx(ev_sl - 14.0) and mv_v == pytest.approx(mv_sl - 32.0)
    # A finger position is ignored when the cue sets the pace.
    assert trial_levels_db_v(design, objects, trial, CAL, t_s=t_s, finger_x_mm=80.0) == (
        ev_v,
        mv_v,
    )
    assert trial_levels_db_v(design, objects, trial, CAL, t_s=0.5) == (-INF, -INF)
    assert trial_levels_db_v(design, objects, trial, CAL, t_s=3.2) == (-INF, -INF)
    with pytest.raises(SolverError, match="no unmasked AL for MV270"):
        trial_levels_db_v(design, objects, trial, {"EV270": -14.0}, t_s=t_s)


def test_trial_levels_with_finger_tracking(design, objects):
    finger = _replace(design, tracking="finger")
    trial = next(t for t in trial_list(finger, 3) if t.object == ("bump", "coarse"))
    r = objects[trial.object]
    t_s = finger.timing.onset_s(1) + 0.2
    ev_sl, mv_sl = levels_at(r, 60.0, compensated=trial.compensated)
    got = trial_levels_db_v(finger, objects, trial, CAL, t_s=t_s, finger_x_mm=60.0)
    assert got == pytest.approx((ev_sl - 14.0, mv_sl - 24.0))
    off_path = trial_levels_db_v(finger, objects, trial, CAL, t_s=t_s, finger_x_mm=120.0)
    assert off_path == (-INF, -INF)
    with pytest.raises(SolverError, match="finger tracking needs"):
        trial_levels_db_v(finger, objects, trial, CAL, t_s=t_s)


def test_render_objects_lists_missing_pairs(design, truth):
    partial = {k: v for k, v in truth.items() if k[0] != "MV120am40"}
    with pytest.raises(MissingMaskingError) as info:
        render_objects(design, partial)
    assert "MV120am40 with EV270" in str(info.value)
    assert {(p.target, p.masker) for p in info.value.problems} == {
        ("MV120am40", "EV270"),
        ("EV270", "MV120am40"),
    }


def test_render_objects_refuses_pairs_it_cannot_compensate(design, truth):
    folded = dict(truth)
    folded[("MV180", "EV270")] = MutualMasking(1.0, 2.0, -1.0, 1.0, mv="MV180", ev="EV270")
    with pytest.raises(SolverError, match="cannot be compensated"):
        render_objects(design, folded)


def test_observer_feels_the_targets_when_compensated(design, objects, truth):
    observer = IdentificationObserver(truth)
    for r in objects.values():
        mv_felt, ev_felt = observer.felt(r, compensated=True)
        np.testing.assert_allclose(mv_felt, np.maximum(r.mv_target_db_sl, 0), atol=1e-9)
        np.testing.assert_allclose(ev_felt, np.maximum(r.ev_target_db_sl, 0), atol=1e-9)
        # Uncompensated, each channel loses the other's masking (and nothing goes below 0).
        mm = truth[(r.scene.texture.stimulus, "EV270")]
        mv_u, ev_u = observer.felt(r, compensated=False)
        f = np.maximum(0, mm.a_db + mm.b * r.ev_target_db_sl)
        g = np.maximum(0, mm.c_db + mm.d * r.mv_target_db_sl)
        np.testing.assert_allclose(mv_u, np.maximum(0, r.mv_target_db_sl - f), atol=1e-9)
        np.testing.assert_allclose(ev_u, np.maximum(0, r.ev_target_db_sl - g), atol=1e-9)


def test_noise_free_observer_identifies_every_compensated_object(design, objects, truth):
    observer = IdentificationObserver(truth, noise_db=1e-6, quality_noise_db=1e-6)
    rng = np.random.default_rng(0)
    for t in trial_list(design, 5):
        if t.compensated:
            assert observer.respond(design, objects, t, rng) == (t.geometry_key, t.texture_key)


def test_observer_without_true_masking_is_refused(design, objects):
    observer = IdentificationObserver({})
    with pytest.raises(SolverError, match="no true masking"):
        observer.felt(objects[("bump", "rough")], compensated=True)


def test_simulated_study_shows_the_effect_of_compensation(design, objects, truth):
    observers = {f"S{i:02d}": IdentificationObserver(truth) for i in range(1, 11)}
    records = simulate_usertest(design, objects, observers, seed=2020)
    assert len(records) == 10 * 120
    assert records == simulate_usertest(design, objects, observers, seed=2020)
    result = analyze_usertest(records, design.geometries, design.textures)
    tests = {t.measure: t for t in result.tests}
    # Paper §3.4: compensation raises "both" and "geometry" correct rates (p < 0.01).
    for measure in ("both", "geometry"):
        t = tests[measure]
        assert t.n == 10 and t.mean_compensated > t.mean_uncompensated and t.p < 0.01
    assert len(result.rates) == 20 and set(result.rates["n_trials"]) == {60}
    for cond in ("compensated", "uncompensated"):
        assert result.confusion[cond]["geometry"].to_numpy().sum() == 600


def _rec(participant, condition, geometry, texture, g_answer, t_answer):
    return {
        "participant": participant,
        "condition": condition,
        "geometry": geometry,
        "texture": texture,
        "geometry_answer": g_answer,
        "texture_answer": t_answer,
    }


G = ("bump", "hole", "ascending", "descending")
T = ("smooth", "rough", "coarse")


def _hand_records():
    # Per participant and condition, four trials; correct rates worked out by hand below.
    recs = []
    # P1 compensated: 4 trials, both right in 3, geometry 4/4, texture 3/4.
    recs += [_rec("P1", "compensated", "bump", "rough", 1, 2)] * 3
    recs += [_rec("P1", "compensated", "hole", "smooth", 2, 3)]
    # P1 uncompensated: geometry 2/4, texture 3/4 (one not answered), both 1/4.
    recs += [
        _rec("P1", "uncompensated", "bump", "rough", 1, 2),
        _rec("P1", "uncompensated", "bump", "rough", 4, 2),
        _rec("P1", "uncompensated", "hole", "coarse", 4, 3),
        _rec("P1", "uncompensated", "hole", "coarse", 2, None),
    ]
    # P2 compensated: both right 4/4.
    recs += [_rec("P2", "compensated", "ascending", "coarse", 3, 3)] * 4
    # P2 uncompensated: geometry 1/4, texture 4/4, both 1/4.
    recs += [_rec("P2", "uncompensated", "ascending", "coarse", 3, 3)]
    recs += [_rec("P2", "uncompensated", "ascending", "coarse", 4, 3)] * 3
    return recs


def test_analysis_rates_tests_and_confusion_from_hand_counted_records():
    result = analyze_usertest(_hand_records(), G, T)
    rates = result.rates.set_index(["participant", "condition"])
    assert tuple(rates.loc[("P1", "compensated"), ["both", "geometry", "texture"]]) == (
        0.75,
        1.0,
        0.75,
    )
    assert tuple(rates.loc[("P1", "uncompensated"), ["both", "geometry", "texture"]]) == (
        0.25,
        0.5,
        0.75,
    )
    assert rates.loc[("P1", "uncompensated"), "n_no_answer"] == 1
    assert tuple(rates.loc[("P2", "uncompensated"), ["both", "geometry", "texture"]]) == (
        0.25,
        0.25,
        1.0,
    )
    tests = {t.measure: t for t in result.tests}
    ref = stats.ttest_rel([0.75, 1.0], [0.25, 0.25])
    assert tests["both"].t == pytest.approx(ref.statistic) and tests["both"].p == pytest.approx(
        ref.pvalue
    )
    assert tests["both"].mean_difference == pytest.approx(0.625)
    assert tests["both"].dz == pytest.approx(0.625 / np.std([0.5, 0.75], ddof=1))
    summary = result.summary.set_index(["condition", "measure"])
    assert summary.loc[("compensated", "geometry"), "mean"] == 1.0
    assert summary.loc[("uncompensated", "texture"), "sd"] == pytest.approx(
        np.std([0.75, 1.0], ddof=1)
    )
    geo = result.confusion["uncompensated"]["geometry"]
    assert geo.loc["bump", "bump"] == 1 and geo.loc["bump", "descending"] == 1
    assert geo.loc["ascending", "descending"] == 3 and geo.to_numpy().sum() == 8
    tex = result.confusion["uncompensated"]["texture"]
    assert tex.loc["coarse", "no answer"] == 1 and tex.loc["coarse", "coarse"] == 5


def test_analysis_notes_when_a_paired_test_is_impossible():
    one = [r for r in _hand_records() if r["participant"] == "P1"]
    tests = {t.measure: t for t in analyze_usertest(one, G, T).tests}
    assert tests["both"].p is None and "≥ 2 participants" in tests["both"].note
    # P3 answers exactly as P1: every participant's difference is the same.
    equal = one + [{**r, "participant": "P3"} for r in one]
    tests = {t.measure: t for t in analyze_usertest(equal, G, T).tests}
    assert tests["geometry"].p is None and "the same" in tests["geometry"].note
    only_comp = [r for r in _hand_records() if r["condition"] == "compensated"]
    tests = {t.measure: t for t in analyze_usertest(only_comp, G, T).tests}
    assert tests["texture"].t is None and "needs both conditions" in tests["texture"].note
    assert tests["texture"].mean_compensated is None  # never NaN


@pytest.mark.parametrize(
    "change, message",
    [
        ({"geometry": "ridge"}, "geometry 'ridge' is not one of"),
        ({"texture": "silky"}, "texture 'silky' is not one of"),
        ({"condition": "maybe"}, "condition 'maybe' is not one of"),
        ({"geometry_answer": 5}, "geometry_answer is 5"),
        ({"texture_answer": 0}, "texture_answer is 0"),
        ({"texture_answer": "2"}, "texture_answer is '2'"),
        ({"geometry_answer": True}, "geometry_answer is True"),
    ],
)
def test_bad_records_are_named(change, message):
    recs = _hand_records()
    recs[2] = {**recs[2], **change}
    with pytest.raises(AnalysisError, match="record 2: " + message):
        analyze_usertest(recs, G, T)


def test_missing_fields_and_no_records():
    rec = _rec("P1", "compensated", "bump", "rough", 1, 2)
    del rec["texture_answer"]
    with pytest.raises(AnalysisError, match="record 0: no 'texture_answer'"):
        analyze_usertest([rec], G, T)
    with pytest.raises(AnalysisError, match="no user-test trial records"):
        analyze_usertest([], G, T)


def test_trial_record_is_what_the_analysis_reads(design):
    trial = trial_list(design, 1)[0]
    rec = trial_record(trial, "S01", trial.geometry_key, None, response_time_s=1.5)
    assert rec["record"] == "usertest_trial" and rec["response_time_s"] == 1.5
    result = analyze_usertest([rec], design.geometries, design.textures)
    row = result.rates.iloc[0]
    assert (row["geometry"], row["texture"], row["n_no_answer"]) == (1.0, 0.0, 1)


def _copy_protocol(tmp_path, text=None):
    shutil.copytree(ROOT / "protocols" / "scenes", tmp_path / "scenes")
    p = tmp_path / "usertest.yaml"
    p.write_text(text if text is not None else USERTEST.read_text(encoding="utf-8"))
    return p


def test_protocol_faults(tmp_path):
    good = USERTEST.read_text(encoding="utf-8")
    p = _copy_protocol(tmp_path)
    assert load_usertest(p).n_trials == 120
    p.write_text(good.replace("repeats: 5", "repeats: 0"))
    with pytest.raises(ProtocolError) as info:
        load_usertest(p)
    assert info.value.where == "repeats (line 14)" and "must be ≥ 1, got 0" in info.value.message
    p.write_text(good.replace("kind: usertest", "kind: masked"))
    with pytest.raises(ProtocolError, match=r"kind \(line 5\): must be 'usertest', got 'masked'"):
        load_usertest(p)
    p.write_text(good.replace("[smooth, rough, coarse]", "[smooth, rough, silky]"))
    with pytest.raises(ProtocolError, match="no scene for geometry 'bump' with texture 'silky'"):
        load_usertest(p)
    p.write_text(good)
    (tmp_path / "scenes" / "hole_rough.yaml").write_text(
        (tmp_path / "scenes" / "bump_rough.yaml").read_text()
    )
    with pytest.raises(ProtocolError, match="expects a 'hole' here"):
        load_usertest(p)
    p.write_text("kind: [usertest\n")
    with pytest.raises(ProtocolError, match="malformed YAML"):
        load_usertest(p)
    p.write_text("- a list\n")
    with pytest.raises(ProtocolError, match="is a YAML mapping"):
        load_usertest(p)
    with pytest.raises(ProtocolError, match="cannot read"):
        load_usertest(tmp_path / "nope.yaml")


def test_validate_reports_a_bad_usertest_protocol(tmp_path, capsys):
    p = _copy_protocol(tmp_path, USERTEST.read_text().replace("tracking: cue", "tracking: eyes"))
    assert main(["validate", str(p)]) == 1
    assert "INVALID" in capsys.readouterr().err
