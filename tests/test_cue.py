"""The sliding cue: position at time t, lanes, display geometry and finger samples."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from masking_lab.core.errors import ProtocolError
from masking_lab.core.stimulus import Stimulus
from masking_lab.core.trial import TrialPlan
from masking_lab.responders.cue import (
    CUE_SPEED_MM_S,
    CueLayout,
    DisplayGeometry,
    TrialTiming,
    finger_sample,
    should_record,
)

PAPER = TrialTiming(lead_in_s=1.2, stimulus_s=1.8, gap_s=0.6)
LAYOUT = CueLayout(PAPER)
# A 15.6" full-HD touch panel.
PANEL = DisplayGeometry(width_mm=344.2, width_px=1920, height_px=1080, source="rig.yaml")


def test_paper_speed_and_sweep():
    assert CUE_SPEED_MM_S == 51.0
    # 51 mm/s for 1.8 s
    assert LAYOUT.sweep_mm == pytest.approx(91.8)
    assert LAYOUT.start_x_mm == pytest.approx(-45.9)
    assert LAYOUT.end_x_mm == pytest.approx(45.9)


def test_timing_agrees_with_the_device_trial_plan():
    plan = TrialPlan(
        target=Stimulus("EV", 270.0),
        target_amplitude_v=1.0,
        target_interval=3,
        stimulus_s=1.8,
        gap_s=0.6,
        lead_in_s=1.2,
    )
    timing = TrialTiming.from_plan(plan)
    start_s = 100.0
    onsets = [start_s + timing.onset_s(k) for k in (1, 2, 3)]
    assert onsets == pytest.approx(plan.planned_onsets_s(start_s))
    assert timing.duration_s == pytest.approx(plan.duration_s)
    marks = CueLayout(timing).interval_marks()
    assert [m.onset_s for m in marks] == pytest.approx([1.2, 3.6, 6.0])
    assert [m.offset_s for m in marks] == pytest.approx([3.0, 5.4, 7.8])


def test_lanes_top_to_bottom_and_centred():
    ys = [LAYOUT.lane_y_mm(k) for k in (1, 2, 3)]
    assert ys == pytest.approx([30.0, 0.0, -30.0])
    two = CueLayout(TrialTiming(0.5, 1.0, 0.5, n_intervals=2), lane_spacing_mm=20.0)
    assert [two.lane_y_mm(k) for k in (1, 2)] == pytest.approx([10.0, -10.0])
    with pytest.raises(ValueError, match=r"interval must be 1\.\.3"):
        LAYOUT.lane_y_mm(4)


@given(st.floats(0.0, 1.8 - 1e-6), st.sampled_from([1, 2, 3]))
def test_cue_moves_at_51_mm_s_along_the_lane_of_the_playing_interval(dt, k):
    t = PAPER.onset_s(k) + dt
    state = LAYOUT.state_at(t)
    assert state.phase == "interval"
    assert state.interval == k
    assert state.moving
    assert state.x_mm == pytest.approx(-45.9 + 51.0 * dt, abs=1e-9)
    assert state.y_mm == pytest.approx(LAYOUT.lane_y_mm(k))
    # Speed from two nearby readings inside the interval.
    h = 1e-3
    if dt + h < 1.8:
        later = LAYOUT.state_at(t + h)
        assert (later.x_mm - state.x_mm) / h == pytest.approx(51.0, rel=1e-6)


@given(st.floats(-5.0, 1.2, exclude_max=True))
def test_cue_waits_at_the_start_of_lane_1_before_the_first_interval(t):
    state = LAYOUT.state_at(t)
    assert (state.phase, state.interval, state.moving) == ("lead_in", 1, False)
    assert (state.x_mm, state.y_mm) == pytest.approx((-45.9, 30.0))


@given(st.sampled_from([1, 2]), st.floats(0.0, 0.6 - 1e-9))
def test_cue_waits_at_the_start_of_the_next_lane_in_a_gap(k, dt):
    state = LAYOUT.state_at(PAPER.offset_s(k) + dt)
    assert (state.phase, state.interval, state.moving) == ("gap", k + 1, False)
    assert (state.x_mm, state.y_mm) == pytest.approx((-45.9, LAYOUT.lane_y_mm(k + 1)))


@given(st.floats(7.8, 1e6))
def test_cue_rests_at_the_end_of_the_last_lane_after_the_trial(t):
    state = LAYOUT.state_at(t)
    assert (state.phase, state.interval, state.moving) == ("response", 3, False)
    assert (state.x_mm, state.y_mm) == pytest.approx((45.9, -30.0))


def test_cue_reaches_the_end_of_each_lane():
    for k in (1, 2, 3):
        assert LAYOUT.state_at(PAPER.offset_s(k) - 1e-9).x_mm == pytest.approx(45.9, abs=1e-6)


def test_no_gap_and_no_lead_in():
    layout = CueLayout(TrialTiming(0.0, 1.0, 0.0))
    assert layout.state_at(0.0).phase == "interval"
    assert layout.state_at(1.0).interval == 2
    assert layout.state_at(1.0).x_mm == pytest.approx(layout.start_x_mm)


def test_other_speeds_and_spacings():
    layout = CueLayout(PAPER, speed_mm_s=30.0, lane_spacing_mm=40.0)
    assert layout.sweep_mm == pytest.approx(54.0)
    assert layout.state_at(PAPER.onset_s(2) + 1.0).x_mm == pytest.approx(-27.0 + 30.0)
    assert layout.lane_y_mm(3) == pytest.approx(-40.0)


def test_nan_time_is_refused():
    with pytest.raises(ValueError, match="NaN"):
        LAYOUT.state_at(math.nan)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"lead_in_s": -0.1, "stimulus_s": 1.8, "gap_s": 0.6}, "lead_in_s"),
        ({"lead_in_s": 1.0, "stimulus_s": 0.0, "gap_s": 0.6}, "stimulus_s"),
        ({"lead_in_s": 1.0, "stimulus_s": 1.8, "gap_s": math.inf}, "gap_s"),
        ({"lead_in_s": 1.0, "stimulus_s": 1.8, "gap_s": 0.6, "n_intervals": 0}, "n_intervals"),
    ],
)
def test_bad_timing_is_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        TrialTiming(**kwargs)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [({"speed_mm_s": 0.0}, "speed_mm_s"), ({"lane_spacing_mm": -1.0}, "lane_spacing_mm")],
)
def test_bad_layout_is_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        CueLayout(PAPER, **kwargs)


# -- display geometry ------------------------------------------------------------------------


def test_display_scale():
    assert PANEL.mm_per_px == pytest.approx(344.2 / 1920)
    assert PANEL.px_per_mm == pytest.approx(1920 / 344.2)
    assert PANEL.height_mm == pytest.approx(1080 * 344.2 / 1920)
    # The sweep on this panel: 91.8 mm ≈ 512 px.
    x0, _ = PANEL.mm_to_px(LAYOUT.start_x_mm, 0.0)
    x1, _ = PANEL.mm_to_px(LAYOUT.end_x_mm, 0.0)
    assert x1 - x0 == pytest.approx(91.8 * 1920 / 344.2)


@given(
    st.floats(10.0, 2000.0),
    st.integers(100, 8000),
    st.integers(100, 8000),
    st.floats(-1000.0, 1000.0),
    st.floats(-1000.0, 1000.0),
)
def test_mm_px_round_trip(width_mm, width_px, height_px, x, y):
    display = DisplayGeometry(width_mm, width_px, height_px)
    back = display.px_to_mm(*display.mm_to_px(x, y))
    assert back == pytest.approx((x, y), abs=1e-9)


def test_display_from_config_mapping():
    display = DisplayGeometry.from_mapping(
        {"width_mm": 344.2, "width_px": 1920, "height_px": 1080}, "protocols/devices/default.yaml"
    )
    assert display == DisplayGeometry(344.2, 1920, 1080, "protocols/devices/default.yaml")


@pytest.mark.parametrize(
    ("mapping", "key"),
    [
        ({"width_px": 1920, "height_px": 1080}, "display.width_mm"),
        ({"width_mm": 344.0, "height_px": 1080}, "display.width_px"),
        ({"width_mm": 0, "width_px": 1920, "height_px": 1080}, "display.width_mm"),
        ({"width_mm": "wide", "width_px": 1920, "height_px": 1080}, "display.width_mm"),
        ({"width_mm": math.nan, "width_px": 1920, "height_px": 1080}, "display.width_mm"),
        ({"width_mm": 344.0, "width_px": 1920.5, "height_px": 1080}, "display.width_px"),
        ({"width_mm": 344.0, "width_px": 1920, "height_px": 0}, "display.height_px"),
        ({"width_mm": 344.0, "width_px": True, "height_px": 1080}, "display.width_px"),
    ],
)
def test_bad_display_settings_name_file_and_key(mapping, key):
    with pytest.raises(ProtocolError) as info:
        DisplayGeometry.from_mapping(mapping, "rig.yaml")
    assert info.value.file == "rig.yaml"
    assert info.value.where == key


def test_display_section_must_be_a_mapping():
    with pytest.raises(ProtocolError, match=r"rig\.yaml: display: must be a mapping"):
        DisplayGeometry.from_mapping([344, 1920, 1080], "rig.yaml")


def test_lanes_fit_a_touch_panel():
    LAYOUT.check_fits(PANEL, label_room_mm=15.0, cue_radius_mm=4.0)


def test_too_narrow_screen_is_refused_with_the_numbers():
    phone = DisplayGeometry(width_mm=70.0, width_px=1080, height_px=2400, source="phone.yaml")
    with pytest.raises(ProtocolError, match=r"phone.yaml: display.width_mm: .*91.8 mm") as info:
        LAYOUT.check_fits(phone)
    assert "70 mm wide" in str(info.value)


def test_too_short_screen_is_refused():
    strip = DisplayGeometry(width_mm=400.0, width_px=4000, height_px=400, source="strip.yaml")
    with pytest.raises(ProtocolError, match=r"strip.yaml: display.height_px: .*60.0 mm"):
        LAYOUT.check_fits(strip)


# -- finger samples --------------------------------------------------------------------------


def test_finger_sample_converts_px_to_mm_and_rounds():
    display = DisplayGeometry(width_mm=400.0, width_px=800, height_px=600)  # 0.5 mm/px
    assert finger_sample(12.345678, 100.0, -33.0, display) == (12.3457, 50.0, -16.5)
    t, x, y = finger_sample(1.0, 1.0 / 3.0, 0.0, display)
    assert (t, x, y) == (1.0, 0.17, 0.0)
    assert all(isinstance(v, float) for v in (t, x, y))


def test_should_record():
    # A touch is always recorded, even when still or first.
    assert should_record(None, 0.0, 0.0, pressed=True)
    assert should_record((1.0, 1.0), 1.0, 1.0, pressed=True)
    # Without a touch only movement counts.
    assert not should_record(None, 5.0, 5.0, pressed=False)
    assert not should_record((1.0, 1.0), 1.0, 1.01, pressed=False)
    assert should_record((1.0, 1.0), 1.0, 1.2, pressed=False)
    assert should_record((1.0, 1.0), 1.04, 1.04, pressed=False)  # 0.057 mm diagonally
