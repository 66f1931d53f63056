"""The pure staircase: rules, bounds, replay, implied targets."""

from __future__ import annotations

import math
import re

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from masking_lab.core.errors import ProcedureError, StaircaseError
from masking_lab.procedures.staircase import (
    StaircaseSettings,
    implied_target_p,
    implied_target_p_for,
    replay,
    start,
)


def run(settings_: StaircaseSettings, responses: list[bool]):
    return replay(settings_, responses)


def test_three_correct_lower_one_wrong_raises():
    s = StaircaseSettings(start_level_db=10, step_sizes_db=(2,))
    track = run(s, [True, True, True, False, True, True])
    # down after the third correct, up after the wrong, no move on two correct
    assert track.levels_db == (10, 10, 10, 8, 10, 10)
    assert track.level_db == 10


def test_reversal_is_a_change_of_direction_at_the_trial_level():
    s = StaircaseSettings(start_level_db=10, step_sizes_db=(2,))
    track = run(s, [True, True, True, False])
    # first move (down) is not a reversal; down→up at trial 3 (level 8) is
    assert track.reversal_levels_db == (8,)
    assert track.reversal_trials == (3,)


def test_paper_rule_stops_after_11_reversals_and_averages_last_8():
    s = StaircaseSettings(start_level_db=0, step_sizes_db=(1,))
    # alternate: 3 correct (down) then 1 wrong (up) gives a reversal at every turn
    responses = ([True] * 3 + [False]) * 20
    track = start(s)
    for r in responses:
        if track.finished:
            break
        track = track.update(r)
    assert track.status == "completed"
    assert len(track.reversal_levels_db) == 11
    assert track.al_db == pytest.approx(sum(track.reversal_levels_db[-8:]) / 8)


def test_step_schedule_changes_after_reversals():
    s = StaircaseSettings(start_level_db=20, step_sizes_db=(4, 2))
    track = run(s, [True] * 3 + [False] + [False])
    # 20 → 16 (down, 4 dB) → wrong at 16: reversal #1, step becomes 2 → 18 → wrong → 20
    assert track.levels_db == (20, 20, 20, 16, 18)
    assert track.level_db == 20
    assert track.step_db == 2


def test_down_up_ratio_scales_only_the_down_step():
    s = StaircaseSettings(start_level_db=10, step_sizes_db=(2,), down_up_ratio=0.5)
    track = run(s, [True, True, True, False])
    assert track.levels_db == (10, 10, 10, 9)
    assert track.level_db == 11


def test_initial_one_down_one_up_phase():
    s = StaircaseSettings(start_level_db=10, step_sizes_db=(2,), initial_one_down_one_up=True)
    track = run(s, [True, True, False, True])
    # 1-down-1-up until the first reversal (at trial 2), whose step follows the same rule
    assert track.levels_db == (10, 8, 6, 8)
    assert track.reversal_levels_db == (6,)
    # after the first reversal the 3-down rule applies: one correct does not move the level
    assert track.level_db == 8


def test_clamp_counts_hits_and_ends_as_ceiling_without_al():
    s = StaircaseSettings(start_level_db=18, step_sizes_db=(4,), max_level_db=20, max_bound_hits=2)
    track = start(s)
    for _ in range(5):
        if track.finished:
            break
        track = track.update(False)
    # 18 → clamped to 20; at 20 asked up twice → ceiling
    assert track.levels_db == (18, 20, 20)
    assert track.status == "ceiling"
    assert track.al_db is None


def test_stop_policy_ends_at_first_step_past_a_bound():
    s = StaircaseSettings(start_level_db=2, step_sizes_db=(4,), min_level_db=0, bound_policy="stop")
    track = run(s, [True, True, True])
    assert track.status == "floor"
    assert track.al_db is None


def test_trial_cap_is_not_a_threshold():
    s = StaircaseSettings(start_level_db=0, max_trials=5)
    track = run(s, [True, False, True, False, True])
    assert track.status == "trial_cap"
    assert track.al_db is None


def test_finished_staircase_refuses_more_responses():
    s = StaircaseSettings(start_level_db=0, max_trials=1)
    track = run(s, [True])
    with pytest.raises(StaircaseError, match="finished"):
        track.update(True)
    with pytest.raises(ProcedureError, match="after the staircase finished"):
        replay(s, [True, True])


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"n_down": 0}, "n_down"),
        ({"n_up": 0}, "n_up"),
        ({"step_sizes_db": (2, -1)}, "step_sizes_db[1]"),
        ({"step_sizes_db": ()}, "step_sizes_db"),
        ({"n_reversals": 4, "n_reversals_averaged": 8}, "n_reversals_averaged"),
        ({"down_up_ratio": 0}, "down_up_ratio"),
        ({"min_level_db": 5, "max_level_db": 5}, "min_level_db"),
        ({"max_level_db": -1}, "start_level_db"),
        ({"bound_policy": "wrap"}, "bound_policy"),
        ({"max_trials": 0}, "max_trials"),
    ],
)
def test_invalid_settings_name_the_field(kwargs, field):
    with pytest.raises(StaircaseError, match=rf"staircase setting {re.escape(field)}"):
        StaircaseSettings(start_level_db=0, **kwargs)


def test_implied_targets_levitt_and_garcia_perez():
    assert implied_target_p(StaircaseSettings(0)) == pytest.approx(0.5 ** (1 / 3), abs=1e-9)
    assert implied_target_p_for(1, 2) == pytest.approx(math.sqrt(0.5), abs=1e-9)
    assert implied_target_p_for(1, 1) == pytest.approx(0.5, abs=1e-9)
    # García-Pérez (1998): down/up = 0.7393 makes 1-up 3-down converge on 83.15 %
    assert implied_target_p(StaircaseSettings(0, down_up_ratio=0.7393)) == pytest.approx(
        0.8315, abs=5e-5
    )
    # 2-up 1-down tracks the lower side: 1 − sqrt(0.5)
    assert implied_target_p_for(2, 1) == pytest.approx(1 - math.sqrt(0.5), abs=1e-9)


# ---------------------------------------------------------------- property tests

settings_strategy = st.builds(
    StaircaseSettings,
    start_level_db=st.floats(-20, 20, allow_nan=False),
    step_sizes_db=st.lists(st.sampled_from([0.5, 1.0, 2.0, 4.0]), min_size=1, max_size=4).map(
        tuple
    ),
    down_up_ratio=st.sampled_from([1.0, 0.7393, 0.5]),
    n_up=st.integers(1, 2),
    n_down=st.integers(1, 4),
    n_reversals=st.integers(4, 12),
    n_reversals_averaged=st.just(4),
    initial_one_down_one_up=st.booleans(),
    min_level_db=st.sampled_from([None, -30.0]),
    max_level_db=st.sampled_from([None, 30.0]),
    bound_policy=st.sampled_from(["clamp", "stop"]),
    max_bound_hits=st.integers(1, 4),
    max_trials=st.sampled_from([None, 60]),
)


def _drive(s: StaircaseSettings, responses: list[bool]):
    track = start(s)
    used = []
    for r in responses:
        if track.finished:
            break
        track = track.update(r)
        used.append(r)
    return track, used


@settings(max_examples=300, deadline=None)
@given(settings_strategy, st.lists(st.booleans(), max_size=150))
def test_replay_rebuilds_the_exact_state(s, responses):
    track, used = _drive(s, responses)
    assert replay(s, used) == track
    # and any prefix replays to the state seen at that point (the resume path)
    cut = len(used) // 2
    partial, _ = _drive(s, used[:cut])
    assert replay(s, used[:cut]) == partial


@settings(max_examples=300, deadline=None)
@given(settings_strategy, st.lists(st.booleans(), max_size=150))
def test_levels_never_leave_the_bounds(s, responses):
    track, _ = _drive(s, responses)
    for level in (*track.levels_db, track.level_db):
        if s.max_level_db is not None:
            assert level <= s.max_level_db
        if s.min_level_db is not None:
            assert level >= s.min_level_db


@settings(max_examples=300, deadline=None)
@given(settings_strategy, st.lists(st.booleans(), max_size=150))
def test_only_completed_tracks_have_an_al(s, responses):
    track, _ = _drive(s, responses)
    if track.status == "completed":
        assert len(track.reversal_levels_db) == s.n_reversals
        assert track.al_db is not None and math.isfinite(track.al_db)
    else:
        assert track.al_db is None
    if s.max_trials is not None:
        assert track.n_trials <= s.max_trials


@settings(max_examples=200, deadline=None)
@given(settings_strategy, st.lists(st.booleans(), max_size=150))
def test_each_step_has_the_scheduled_size_or_stops_at_a_bound(s, responses):
    track, _ = _drive(s, responses)
    levels = (*track.levels_db, track.level_db) if not track.finished else track.levels_db
    for i in range(1, len(levels)):
        delta = levels[i] - levels[i - 1]
        if delta == 0:
            continue
        n_rev = sum(1 for t in track.reversal_trials if t <= i - 1)
        up = s.up_step_db(n_rev)
        at_bound = levels[i] in (s.max_level_db, s.min_level_db)
        expected = up if delta > 0 else -up * s.down_up_ratio
        assert at_bound or delta == pytest.approx(expected)
