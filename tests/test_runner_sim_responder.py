"""The simulated responder: reproducible per trial, answers by the psychometric function."""

from __future__ import annotations

import pytest

from masking_lab.core.errors import ProtocolError
from masking_lab.core.stimulus import parse_stimulus
from masking_lab.core.trial import PlayResult, TrialPlan
from masking_lab.responders.base import SetInfo, TrialPresentation
from masking_lab.responders.sim import SimResponder
from masking_lab.simulation.observer import load_ground_truth, make_participant

EV = parse_stimulus("EV270")
MV = parse_stimulus("MV120")


def presentation(level_db_v, trial_index=0, interval=2, masker_v=0.0, set_id="s"):
    plan = TrialPlan(
        target=EV,
        target_amplitude_v=10 ** (level_db_v / 20),
        target_interval=interval,
        masker=MV if masker_v > 0 else None,
        masker_amplitude_v=masker_v,
    )
    return TrialPresentation(set_id, trial_index, plan, 0.0, level_db_v, None, None)


@pytest.fixture(scope="module")
def responder():
    return SimResponder.from_ground_truth(None, "S01", seed=11)


def test_answers_are_reproducible_per_session_seed_set_and_trial(responder):
    again = SimResponder.from_ground_truth(None, "S01", seed=11)
    other = SimResponder.from_ground_truth(None, "S01", seed=12)
    al = responder.participant.unmasked_al_db_v["EV270"]
    ps = [presentation(al, i, interval=1 + i % 3) for i in range(200)]
    mine = [responder.answer(p) for p in ps]
    assert mine == [again.answer(p) for p in ps]
    assert mine != [other.answer(p) for p in ps]
    assert all(r.response_time_s >= 0.4 for r in mine)


def test_far_above_threshold_nearly_always_right_far_below_chance(responder):
    al = responder.participant.unmasked_al_db_v["EV270"]
    high = [responder.answer(presentation(al + 30, i, interval=3)) for i in range(600)]
    low = [responder.answer(presentation(al - 40, i, interval=3)) for i in range(1500)]
    lapse, guess = responder.participant.truth.lapse, responder.participant.truth.guess
    p_high = sum(r.interval == 3 for r in high) / len(high)
    assert p_high == pytest.approx(1 - lapse + lapse * guess, abs=0.02)
    p_low = sum(r.interval == 3 for r in low) / len(low)
    assert p_low == pytest.approx(1 / 3, abs=0.04)
    wrong = [r.interval for r in low if r.interval != 3]
    assert set(wrong) == {1, 2}
    assert abs(wrong.count(1) - wrong.count(2)) < 0.15 * len(wrong)


def test_a_strong_masker_lowers_the_hit_rate(responder):
    part = responder.participant
    al = part.unmasked_al_db_v["EV270"]
    # MV120 at 25 dB SL of this participant's true AL shifts EV270's AL by ~10 dB (Table 2).
    masker_v = 10 ** ((part.unmasked_al_db_v["MV120"] + 25) / 20)
    level = al + 4
    clear = [responder.answer(presentation(level, i)) for i in range(800)]
    masked = [responder.answer(presentation(level, i, masker_v=masker_v)) for i in range(800)]
    hit = lambda rs: sum(r.interval == 2 for r in rs) / len(rs)  # noqa: E731
    assert hit(clear) > 0.85
    assert hit(masked) < 0.5


def test_trial_plays_once_then_answers(responder):
    calls = []

    def play():
        calls.append(1)
        return PlayResult([1.0, 2.0, 3.0], [1.0, 2.0, 3.0], 0.1, 0.0)

    p = presentation(0.0)
    result, response = responder.trial(p, play)
    assert calls == [1] and result.actual_onsets_s == [1.0, 2.0, 3.0]
    assert response == responder.answer(p)


def test_the_same_participant_sits_every_session():
    a = SimResponder.from_ground_truth(None, "S07", seed=1)
    b = SimResponder.from_ground_truth(None, "S07", seed=2)
    # The participant's true ALs do not depend on the session seed.
    assert a.participant.unmasked_al_db_v == b.participant.unmasked_al_db_v
    truth = load_ground_truth(None)
    assert a.participant == make_participant(truth, "S07", 0)


def test_unknown_stimulus_is_refused_before_the_set(responder):
    info = SetInfo("x", 1, 1, parse_stimulus("EV500"), None, None)
    with pytest.raises(ProtocolError, match="no unmasked AL for EV500"):
        responder.start_set(info)
    responder.start_set(SetInfo("y", 1, 1, EV, MV, 10.0))  # known: fine


def test_bad_ground_truth_files(tmp_path):
    with pytest.raises(ProtocolError, match="cannot read the ground truth"):
        SimResponder.from_ground_truth(tmp_path / "missing.yaml", "S01", 1)
    bad = tmp_path / "bad.yaml"
    bad.write_text("unmasked_al_db_v: [1, 2\n", encoding="utf-8")
    with pytest.raises(ProtocolError, match="malformed"):
        SimResponder.from_ground_truth(bad, "S01", 1)
    incomplete = tmp_path / "incomplete.yaml"
    incomplete.write_text("unmasked_al_db_v: {EV270: -14}\n", encoding="utf-8")
    with pytest.raises(ProtocolError, match="not a valid ground-truth"):
        SimResponder.from_ground_truth(incomplete, "S01", 1)
