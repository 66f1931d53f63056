"""Session planning: level units, effective bounds, refusals, target intervals, time left."""

from __future__ import annotations

import hashlib
import itertools
import math
from collections import Counter

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from masking_lab.core.errors import CalibrationError, LevelError
from masking_lab.core.seeding import (
    STREAM_RESPONDER,
    STREAM_TARGET_INTERVAL,
    draw_target_interval,
    trial_rng,
)
from masking_lab.core.stimulus import parse_stimulus
from masking_lab.formats.protocol import SetSpec, Timing
from masking_lab.procedures.staircase import StaircaseSettings
from masking_lab.session.trials import (
    estimate_time_left_s,
    nominal_seconds_per_trial,
    plan_set,
    plan_trial,
)

CAL = {"EV270": -14.0, "MV120": -26.0}
LIMITS = {"EV": 100.0, "MV": 10.0}  # 40 dB re 1 V and 20 dB re 1 V


def masked_set(
    start: float = 20.0, hi: float | None = 45.0, lo: float | None = -20.0, masker_sl: float = 10.0
) -> SetSpec:
    return SetSpec(
        id="MV120_10",
        target=parse_stimulus("EV270"),
        masker=parse_stimulus("MV120"),
        masker_level_db_sl=masker_sl,
        staircase=StaircaseSettings(start_level_db=start, min_level_db=lo, max_level_db=hi),
    )


def baseline_set(start: float = 0.0, hi: float | None = None) -> SetSpec:
    return SetSpec(
        id="EV270",
        target=parse_stimulus("EV270"),
        masker=None,
        masker_level_db_sl=None,
        staircase=StaircaseSettings(start_level_db=start, min_level_db=-60.0, max_level_db=hi),
    )


def test_masked_set_converts_through_the_calibration():
    plan = plan_set(masked_set(), "db_sl", CAL, LIMITS)
    assert plan.unmasked_al_db_v == -14.0
    assert plan.level_db_v(12.0) == pytest.approx(-2.0)  # 12 dB SL above an AL of -14 dB re 1 V
    assert plan.level_db_sl(12.0) == 12.0
    assert plan.to_level_unit_db(-2.0) == pytest.approx(12.0)
    # Masker: its own AL (-26) + 10 dB SL = -16 dB re 1 V = 10**(-16/20) V.
    assert plan.masker_level_db_v == pytest.approx(-16.0)
    assert plan.masker_amplitude_v == pytest.approx(10 ** (-16 / 20))
    # Device: 100 V = 40 dB re 1 V = 54 dB SL for this participant; the protocol's 45 is lower.
    assert plan.staircase.max_level_db == 45.0
    assert plan.staircase.min_level_db == -20.0


def test_device_limit_lowers_the_upper_bound_in_the_staircase_unit():
    limits = {"EV": 1.0, "MV": 10.0}  # EV: 0 dB re 1 V = 14 dB SL for an AL of -14
    plan = plan_set(masked_set(start=10.0), "db_sl", CAL, limits)
    assert plan.staircase.max_level_db == pytest.approx(14.0)
    trial = plan_trial(plan, plan.staircase.max_level_db, 2, Timing())
    assert trial.target_amplitude_v <= 1.0
    assert trial.target_amplitude_v == pytest.approx(1.0)


def test_baseline_set_runs_in_drive_levels_bounded_by_the_device():
    plan = plan_set(baseline_set(), "db_v", {}, LIMITS)
    assert plan.unmasked_al_db_v is None and plan.masker is None
    assert plan.level_db_v(-7.5) == -7.5
    assert plan.level_db_sl(-7.5) is None
    assert plan.masker_amplitude_v == 0.0 and plan.masker_level_db_v is None
    assert plan.staircase.max_level_db == pytest.approx(40.0)  # 20·log10(100 V)


def test_start_level_the_device_cannot_drive_is_refused():
    with pytest.raises(LevelError, match=r"set MV120_10: start level 30 dB SL .* above"):
        plan_set(masked_set(start=30.0), "db_sl", CAL, {"EV": 1.0, "MV": 10.0})


def test_masker_the_device_cannot_drive_is_refused():
    # MV limit 0.1 V = -20 dB re 1 V; the masker wants -26 + 25 = -1 dB re 1 V.
    with pytest.raises(LevelError, match=r"masker MV120 at 25 dB SL.*exceeds the device limit"):
        plan_set(masked_set(masker_sl=25.0), "db_sl", CAL, {"EV": 100.0, "MV": 0.1})


def test_device_limit_below_the_lower_bound_is_refused():
    with pytest.raises(LevelError, match="no room to move"):
        # EV limit -44 dB re 1 V = -30 dB SL: exactly the lower bound and the start level.
        plan_set(masked_set(start=-30.0, lo=-30.0), "db_sl", CAL, {"EV": 10**-2.2, "MV": 10.0})


@pytest.mark.parametrize("missing", ["EV270", "MV120"])
def test_missing_calibration_names_the_stimulus(missing):
    cal = {k: v for k, v in CAL.items() if k != missing}
    with pytest.raises(CalibrationError, match=f"no unmasked AL for {missing}.*baseline"):
        plan_set(masked_set(), "db_sl", cal, LIMITS)


def test_non_finite_calibration_is_refused():
    with pytest.raises(CalibrationError, match="not a finite"):
        plan_set(masked_set(), "db_sl", {**CAL, "EV270": math.nan}, LIMITS)


@pytest.mark.parametrize("limits", [{"MV": 10.0}, {"EV": 0.0, "MV": 10.0}])
def test_channel_without_a_usable_limit_is_refused(limits):
    with pytest.raises(LevelError, match=r"channels\.EV\.max_drive_v"):
        plan_set(masked_set(), "db_sl", CAL, limits)


def test_trial_plan_carries_stimuli_timing_and_interval():
    timing = Timing(stimulus_s=0.5, gap_s=0.25, lead_in_s=0.1)
    plan = plan_set(masked_set(), "db_sl", CAL, LIMITS)
    trial = plan_trial(plan, 6.0, 3, timing)
    assert trial.target_interval == 3
    assert trial.target_amplitude_v == pytest.approx(10 ** ((6.0 - 14.0) / 20))
    assert trial.masker is not None and trial.masker.name == "MV120"
    assert (trial.stimulus_s, trial.gap_s, trial.lead_in_s) == (0.5, 0.25, 0.1)
    assert trial.planned_onsets_s(10.0) == pytest.approx([10.1, 10.85, 11.6])


@pytest.mark.parametrize("interval", [0, 4])
def test_trial_plan_refuses_an_impossible_interval(interval):
    plan = plan_set(masked_set(), "db_sl", CAL, LIMITS)
    with pytest.raises(LevelError, match="1, 2 or 3"):
        plan_trial(plan, 6.0, interval, Timing())


def test_trial_plan_refuses_a_level_above_the_limit():
    plan = plan_set(masked_set(start=10.0), "db_sl", CAL, {"EV": 1.0, "MV": 10.0})
    with pytest.raises(LevelError, match="exceeds the device limit"):
        plan_trial(plan, 20.0, 1, Timing())  # 20 dB SL = 6 dB re 1 V > 0 dB re 1 V


@settings(max_examples=200, deadline=None)
@given(
    al=st.floats(-60, 10),
    limit_v=st.floats(0.01, 400),
    protocol_max=st.one_of(st.none(), st.floats(-10, 80)),
    start=st.floats(-10, 60),
    frac=st.floats(0, 1),
)
def test_every_playable_level_stays_within_the_device_limit(al, limit_v, protocol_max, start, frac):
    spec = SetSpec(
        id="s",
        target=parse_stimulus("EV270"),
        masker=None,
        masker_level_db_sl=None,
        staircase=StaircaseSettings(start_level_db=start, min_level_db=-20.0, max_level_db=None),
    )
    if protocol_max is not None and protocol_max > start:
        spec = SetSpec(
            spec.id,
            spec.target,
            None,
            None,
            StaircaseSettings(start_level_db=start, min_level_db=-20.0, max_level_db=protocol_max),
        )
    try:
        plan = plan_set(spec, "db_sl", {"EV270": al}, {"EV": limit_v, "MV": 1.0})
    except LevelError:
        # Refused only when the start level really is beyond the device.
        assert start + al > 20 * math.log10(limit_v) - 1e-9 or -20.0 + al >= 20 * math.log10(
            limit_v
        )
        return
    hi = plan.staircase.max_level_db
    assert hi is not None
    assert hi <= 20 * math.log10(limit_v) - al + 1e-9
    if spec.staircase.max_level_db is not None:
        assert hi <= spec.staircase.max_level_db
    level = -20.0 + frac * (hi + 20.0)
    trial = plan_trial(plan, level, 1, Timing())
    assert 0 < trial.target_amplitude_v <= limit_v
    assert plan.to_level_unit_db(plan.level_db_v(level)) == pytest.approx(level)


def test_target_intervals_are_reproducible_and_uniform():
    draws = [draw_target_interval(7, "MV120_10", i) for i in range(3000)]
    assert draws == [draw_target_interval(7, "MV120_10", i) for i in range(3000)]
    counts = Counter(draws)
    assert set(counts) == {1, 2, 3}
    assert all(900 < c < 1100 for c in counts.values()), counts
    # Another set or seed gives another sequence.
    assert draws[:50] != [draw_target_interval(7, "MV120_15", i) for i in range(50)]
    assert draws[:50] != [draw_target_interval(8, "MV120_10", i) for i in range(50)]


def test_random_streams_are_independent():
    a = trial_rng(1, "s", 0, STREAM_TARGET_INTERVAL).random(4)
    b = trial_rng(1, "s", 0, STREAM_RESPONDER).random(4)
    assert list(a) != list(b)
    with pytest.raises(ValueError):
        trial_rng(-1, "s", 0, STREAM_RESPONDER)


def test_trial_streams_are_numpys_seed_sequence_of_the_documented_key():
    # The logged sessions' draws are fixed by this definition: a generator seeded with
    # SeedSequence([seed, key(set_id), trial_index, key(stream)]), key = the first 8 bytes of
    # sha256, little-endian. Seeds and indices of one and of several 32-bit words.
    def key(text: str) -> int:
        return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "little")

    for seed, set_id, index in [
        (0, "MV120_05", 0),
        (2020, "EV270", 17),
        (2**32 - 1, "", 2**32),
        (2**63 + 5, "ü", 123456),
        (4052283373, "MV270_EV270_25", 149),
    ]:
        for stream in (STREAM_TARGET_INTERVAL, STREAM_RESPONDER):
            entropy = [seed, key(set_id), index, key(stream)]
            want = np.random.default_rng(np.random.SeedSequence(entropy))
            got = trial_rng(seed, set_id, index, stream)
            assert list(got.integers(0, 2**62, 3)) == list(want.integers(0, 2**62, 3))
            assert got.random() == want.random()


def test_time_left_from_the_pace_of_this_set_and_finished_sets():
    # This set: 12 trials for 3 reversals = 4 per reversal, 8 reversals to go = 32 trials.
    # Two later sets at the mean of the finished ones (60, 40 → 50): 100 trials; rests 2 × 300 s.
    left = estimate_time_left_s(
        seconds_per_trial=10.0,
        trials_done_in_set=12,
        reversals_in_set=3,
        n_reversals=11,
        max_trials=150,
        sets_after_current=2,
        finished_set_trials=[60, 40],
        rest_between_sets_s=300.0,
    )
    assert left == pytest.approx((32 + 100) * 10.0 + 600.0)


def test_time_left_before_any_pace_is_known_uses_the_prior():
    left = estimate_time_left_s(
        seconds_per_trial=9.0,
        trials_done_in_set=0,
        reversals_in_set=0,
        n_reversals=11,
        max_trials=None,
        sets_after_current=0,
        prior_trials_per_reversal=6.0,
    )
    assert left == pytest.approx(11 * 6 * 9.0)


def test_time_left_respects_the_trial_cap_and_shrinks_with_reversals():
    common = {"seconds_per_trial": 1.0, "n_reversals": 11, "sets_after_current": 1}
    capped = estimate_time_left_s(
        trials_done_in_set=95, reversals_in_set=1, max_trials=100, **common
    )
    assert capped == pytest.approx(5 + 66)  # 5 left in this set, the next capped at 66 < 100
    values = [
        estimate_time_left_s(
            trials_done_in_set=4 * r, reversals_in_set=r, max_trials=None, **common
        )
        for r in range(2, 12)
    ]
    assert all(a > b for a, b in itertools.pairwise(values))
    done = estimate_time_left_s(
        seconds_per_trial=5.0,
        trials_done_in_set=40,
        reversals_in_set=11,
        n_reversals=11,
        max_trials=None,
        sets_after_current=0,
    )
    assert done == 0.0


def test_nominal_seconds_per_trial_adds_answer_and_pause():
    timing = Timing(stimulus_s=1.8, gap_s=0.6, lead_in_s=1.2, inter_trial_s=0.5)
    assert nominal_seconds_per_trial(timing, response_time_s=1.0) == pytest.approx(
        1.2 + 3 * 1.8 + 2 * 0.6 + 1.0 + 0.5
    )


def test_a_masker_on_the_targets_channel_leaves_only_the_rest_of_the_limit():
    spec = SetSpec(
        id="tex",
        target=parse_stimulus("MV120am40"),
        masker=parse_stimulus("MV180"),
        masker_level_db_sl=10.0,
        staircase=StaircaseSettings(start_level_db=0.0, min_level_db=-20.0, max_level_db=40.0),
    )
    cal = {"MV120am40": -24.0, "MV180": -10.0}  # masker drive: 0 dB re 1 V = 1 V
    plan = plan_set(spec, "db_sl", cal, {"EV": 5.0, "MV": 3.0})
    assert plan.target_max_v == pytest.approx(2.0)  # 3 V limit − 1 V masker
    assert plan.staircase.max_level_db == pytest.approx(20 * math.log10(2.0) + 24.0)
    with pytest.raises(LevelError, match="nothing is left for the target"):
        plan_set(spec, "db_sl", cal, {"EV": 5.0, "MV": 1.0})
