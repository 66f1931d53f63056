"""The participant window in a real PsychoPy window on a virtual X display (Xvfb).

The display is the session fixture ``x_display`` (tests/xdisplay.py): one Xvfb per test process
(``-displayfd`` picks a free display number) or, without Xvfb, an existing DISPLAY. With neither
it skips, unless MASKING_LAB_REQUIRE_DISPLAY=1 (CI), in which case it fails: CI must never
silently skip the window test (.ci/system-deps.sh installs Xvfb and xdotool).

Keys and pointer moves are injected with ``xdotool``: they go through the X server, pyglet and
PsychoPy's event module exactly like a participant's key press or finger, which PsychoPy's
private hooks (``event._onPygletKey``) would bypass.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import subprocess
import sys
import textwrap
import threading

import numpy as np
import pytest

from masking_lab.core.clock import RealClock
from masking_lab.core.errors import DeviceError, ProtocolError
from masking_lab.core.stimulus import Stimulus
from masking_lab.core.trial import PlayResult, TrialPlan
from masking_lab.responders.base import SetInfo, TrialPresentation
from masking_lab.responders.cue import CueLayout, DisplayGeometry, TrialTiming
from masking_lab.responders.participant_window import CUE_MOVING, CUE_WAITING, LANE, LANE_ACTIVE
from masking_lab.responders.psychopy_window import (
    NoiseSettings,
    PsychoPyWindowResponder,
    display_geometry,
)

# 800 × 600 px on a 400 mm wide screen: 0.5 mm per px, so positions are easy to check by hand.
DISPLAY = DisplayGeometry(width_mm=400.0, width_px=800, height_px=600, source="test display")
W, H = DISPLAY.width_px, DISPLAY.height_px
SET = SetInfo("MV120_10", 2, 15, Stimulus("EV", 270.0), Stimulus("MV", 120.0), 10.0)


def plan(stimulus_s=1.8, gap_s=0.6, lead_in_s=1.2, target_interval=2) -> TrialPlan:
    return TrialPlan(
        target=Stimulus("EV", 270.0),
        target_amplitude_v=0.8,
        target_interval=target_interval,
        masker=Stimulus("MV", 120.0),
        masker_amplitude_v=0.4,
        stimulus_s=stimulus_s,
        gap_s=gap_s,
        lead_in_s=lead_in_s,
    )


def presentation(trial_plan: TrialPlan, start_s: float, trial_index: int = 4) -> TrialPresentation:
    return TrialPresentation("MV120_10", trial_index, trial_plan, start_s, -3.0, 6.0, 10.0)


def to_image(x_mm: float, y_mm: float) -> tuple[float, float]:
    """Screen mm (centre origin, y up) → image (column, row) of the 800 × 600 screenshot."""
    x_px, y_px = x_mm * 2.0, y_mm * 2.0
    return W / 2 + x_px, H / 2 - y_px


def colour_mask(image: np.ndarray, rgb, tol: int = 12) -> np.ndarray:
    return np.all(np.abs(image.astype(int) - np.array(rgb)) <= tol, axis=-1)


# -- the virtual display -------------------------------------------------------------------------


def xdotool(display: str, *args: str) -> None:
    env = {**os.environ, "DISPLAY": display}
    subprocess.run(["xdotool", *args], env=env, check=True, timeout=10)


@pytest.fixture(scope="module")
def clock():
    return RealClock()


@pytest.fixture
def window(x_display, clock):
    responder = PsychoPyWindowResponder(DISPLAY, clock, fullscr=False, noise=None)
    yield responder
    responder.close()


def window_id(responder: PsychoPyWindowResponder) -> str:
    return str(responder.window.win.winHandle._window)  # the X window id of the pyglet window


# -- the trial screen, pixel by pixel -------------------------------------------------------------


def test_trial_screen_shows_lanes_marks_and_the_cue_where_cue_py_says(window, tmp_path):
    window.window.wait_for_start = False
    window.start_set(SET)
    trial_plan = plan()
    layout = CueLayout(TrialTiming.from_plan(trial_plan), lane_spacing_mm=30.0)
    t_s = layout.timing.onset_s(2) + 0.5  # half a second into interval 2
    state = layout.state_at(t_s)
    assert state.x_mm == pytest.approx(-45.9 + 25.5)
    path = window.window.save_screenshot(presentation(trial_plan, 0.0), t_s, tmp_path / "trial.png")
    from PIL import Image

    image = np.asarray(Image.open(path).convert("RGB"))
    assert image.shape == (H, W, 3)

    # The cue: a disc of radius 4 mm = 8 px, centred where cue.py puts it.
    cue = colour_mask(image, CUE_MOVING)
    rows, cols = np.nonzero(cue)
    col, row = to_image(state.x_mm, state.y_mm)
    assert cols.mean() == pytest.approx(col, abs=1.0)
    assert rows.mean() == pytest.approx(row, abs=1.0)
    assert cue.sum() == pytest.approx(np.pi * 8**2, rel=0.25)
    assert not colour_mask(image, CUE_WAITING).any()

    # Lanes at +30, 0, −30 mm; the one being swept (2) is bright, the others dim.
    for k, y_mm in ((1, 30.0), (2, 0.0), (3, -30.0)):
        col, row = to_image(30.0, y_mm)
        expected = LANE_ACTIVE if k == 2 else LANE
        assert colour_mask(image[int(row) - 1 : int(row) + 2, int(col)][None], expected).any()
        # Interval boundaries: marks 8 mm high at both ends of every lane, nothing just inside.
        for x_mm, inside in ((-45.9, 3.0), (45.9, -3.0)):
            col, row = to_image(x_mm, y_mm + 3.0)
            assert colour_mask(image[int(row), int(col) - 1 : int(col) + 2][None], LANE).any()
            col_in, _ = to_image(x_mm + inside, y_mm + 3.0)
            assert not image[int(row), int(col_in)].any()
        # The lane's number, 12 mm left of its start.
        col, row = to_image(-45.9 - 12.0, y_mm)
        box = image[int(row) - 8 : int(row) + 8, int(col) - 8 : int(col) + 8]
        assert box.max() > 100
    # The progress line near the top; nothing drawn far left or right of the lanes.
    assert image[:60].max() > 100
    assert image[:, :150].max() == 0
    assert image[:, 650:].max() == 0

    # During the lead-in the cue waits, dimmer, at the start of lane 1.
    path = window.window.save_screenshot(
        presentation(trial_plan, 0.0), 0.5, tmp_path / "lead_in.png"
    )
    image = np.asarray(Image.open(path).convert("RGB"))
    rows, cols = np.nonzero(colour_mask(image, CUE_WAITING))
    col, row = to_image(-45.9, 30.0)
    assert cols.mean() == pytest.approx(col, abs=1.0)
    assert rows.mean() == pytest.approx(row, abs=1.0)
    assert not colour_mask(image, CUE_MOVING).any()
    assert not colour_mask(image, LANE_ACTIVE).any()


# -- a whole trial with injected keys and pointer moves -------------------------------------------


class Script(threading.Thread):
    """Plays the participant: runs xdotool actions at session-clock times."""

    def __init__(self, display, clock, steps):
        super().__init__(daemon=True)
        self.display, self.clock, self.steps = display, clock, steps
        self.error: BaseException | None = None
        self.stop = threading.Event()

    def run(self):
        try:
            for at_s, args, repeat in self.steps:
                self.clock.sleep_until(at_s)
                xdotool(self.display, *args)
                # Keep pressing until the window has taken the key (it may not be listening yet).
                while repeat and not self.stop.wait(0.3):
                    xdotool(self.display, *args)
        except BaseException as exc:
            self.error = exc


def test_trial_completes_with_injected_keys_and_records_the_finger(x_display, clock, caplog):
    def failing_player(samples, sample_rate_hz):
        raise OSError("no sound card in this test")

    responder = PsychoPyWindowResponder(
        DISPLAY,
        clock,
        fullscr=False,
        noise=NoiseSettings(loop_s=0.5),
        noise_player=failing_player,
    )
    try:
        wid = window_id(responder)
        # The pointer in the window: X gives it keyboard focus (no window manager).
        xdotool(x_display, "mousemove", "--window", wid, "400", "300")
        starter = Script(x_display, clock, [(0.0, ("key", "space"), True)])
        starter.start()
        with caplog.at_level(logging.WARNING):
            responder.start_set(SET)
        starter.stop.set()
        starter.join(10)
        assert "pink masking noise is OFF" in caplog.text
        assert "OSError: no sound card" in caplog.text

        trial_plan = plan(stimulus_s=1.0, gap_s=0.3, lead_in_s=0.4, target_interval=3)
        timing = TrialTiming.from_plan(trial_plan)
        start_s = clock.now() + 0.3
        on = [start_s + timing.onset_s(k) for k in (1, 2, 3)]
        end_s = start_s + timing.duration_s
        # Pointer positions (window px, top-left origin) during intervals 1 and 2.
        moves = [(on[0] + 0.2, (300, 240)), (on[0] + 0.6, (420, 240)), (on[1] + 0.4, (350, 300))]
        steps = [
            (at, ("mousemove", "--window", wid, str(c), str(r)), False) for at, (c, r) in moves
        ]
        steps += [
            (on[2] + 0.5, ("key", "1"), False),  # too early: while interval 3 plays
            (end_s + 0.2, ("key", "x"), False),  # not an answer key
            (end_s + 0.3, ("key", "3"), True),
        ]
        participant = Script(x_display, clock, steps)
        calls = []
        played = PlayResult(
            trial_plan.planned_onsets_s(start_s), trial_plan.planned_onsets_s(start_s), 0.8, 0.4
        )

        def play():
            calls.append(threading.current_thread().name)
            clock.sleep_until(end_s)  # the device plays the three intervals
            return played

        participant.start()
        result, response = responder.trial(presentation(trial_plan, start_s), play)
        participant.stop.set()
        participant.join(10)
        assert participant.error is None, participant.error
    finally:
        responder.close()
        responder.close()  # idempotent

    assert result is played
    assert calls == ["masking-lab-play"]  # play() ran once, off the drawing thread
    assert response.interval == 3
    assert response.response_time_s > 0
    path = response.finger_path
    assert path, "no finger samples recorded"
    # Every sample lies inside an interval (the finger is logged while the cue sweeps).
    for t_s, _, _ in path:
        assert any(o - 1e-4 <= t_s <= o + timing.stimulus_s + 1e-4 for o in on), t_s
    # The pointer positions, converted to mm: (col − 400, 300 − row) px × 0.5 mm/px.
    # A sample carries its frame's time (the cue drawn for it); the pointer is read after that
    # frame's flip, so a move shows up to one frame before its own time. Each position must
    # appear after the move before it was made, never as a stale position from earlier.
    previous_at = start_s
    for at, (c, r) in moves:
        x_mm, y_mm = (c - W / 2) * 0.5, (H / 2 - r) * 0.5
        # One pixel (0.5 mm) of slack: pyglet counts rows from the bottom, 0-based.
        hits = [s for s in path if abs(s[1] - x_mm) <= 0.51 and abs(s[2] - y_mm) <= 0.51]
        assert hits, f"pointer at {(x_mm, y_mm)} mm not in the finger path {path}"
        assert min(s[0] for s in hits) > previous_at, (at, hits)
        previous_at = at


class FrozenClock:
    """A real-time-looking clock that stands still for ``frames`` readings, then jumps ahead."""

    virtual = False

    def __init__(self, frames: int) -> None:
        self.readings = 0
        self.frames = frames

    def now(self) -> float:
        self.readings += 1
        return 0.0 if self.readings <= self.frames else 1e6

    def sleep_until(self, t: float) -> None:
        pass


def test_device_failure_in_play_reaches_the_runner(x_display):
    # The clock stays in the lead-in for 200 frames: the fault must end the trial at once, not
    # when the cue would have finished.
    clock = FrozenClock(frames=200)
    responder = PsychoPyWindowResponder(DISPLAY, clock, fullscr=False, noise=None)

    def play():
        raise DeviceError("serial port /dev/ttyACM0 vanished")

    try:
        with pytest.raises(DeviceError, match="vanished"):
            responder.trial(presentation(plan(), 0.0), play)
    finally:
        responder.close()
    assert clock.readings < 200


def test_escape_stops_the_session(window, x_display, clock):
    trial_plan = plan(stimulus_s=0.2, gap_s=0.1, lead_in_s=0.1)
    start_s = clock.now()
    end_s = start_s + TrialTiming.from_plan(trial_plan).duration_s
    wid = window_id(window)
    xdotool(x_display, "mousemove", "--window", wid, "400", "300")
    escape = Script(x_display, clock, [(end_s + 0.1, ("key", "Escape"), True)])

    def play():
        clock.sleep_until(end_s)
        return PlayResult([start_s] * 3, [start_s] * 3, 0.8, 0.4)

    escape.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            window.trial(presentation(trial_plan, start_s), play)
    finally:
        escape.stop.set()
        escape.join(10)


def test_lanes_that_do_not_fit_are_refused_before_anything_plays(x_display, clock):
    narrow = DisplayGeometry(width_mm=80.0, width_px=800, height_px=600, source="rig.yaml")
    responder = PsychoPyWindowResponder(narrow, clock, fullscr=False, noise=None)
    calls = []
    try:
        with pytest.raises(ProtocolError, match=r"rig.yaml: display.width_mm: .*80 mm wide"):
            responder.trial(presentation(plan(), clock.now()), lambda: calls.append(1))
    finally:
        responder.close()
    assert calls == []


def test_full_screen_at_another_resolution_is_refused(x_display, clock):
    # Xvfb's screen is 1280 × 800; the settings claim 800 × 600.
    with pytest.raises(ProtocolError, match=r"display.width_px: the window opened at 1280×800"):
        PsychoPyWindowResponder(DISPLAY, clock, fullscr=True, noise=None)


def test_runner_factory_opens_full_screen_from_the_rig_config(x_display, clock, tmp_path):
    from masking_lab.formats.protocol import load_protocol
    from masking_lab.formats.resources import shipped
    from masking_lab.responders.psychopy_window import make_responder
    from masking_lab.session.runner import SessionContext

    reference = shipped("protocols", "devices/default.yaml").read_text(encoding="utf-8")
    head = reference.split("\ndisplay:")[0]
    # The rig's monitor as Xvfb has it: 1280 × 800 px, say 300 mm wide.
    rig = tmp_path / "rig.yaml"
    rig.write_text(head + "\ndisplay:\n  width_mm: 300.0\n  width_px: 1280\n  height_px: 800\n")
    context = SessionContext(
        participant="S01",
        seed=7,
        clock=clock,
        protocol=load_protocol(shipped("protocols", "baseline.yaml")),
        device_config=rig,
    )
    responder = make_responder(context)
    try:
        assert responder.window.display == DisplayGeometry(300.0, 1280, 800, str(rig))
        assert tuple(responder.window.win.size) == (1280, 800)
    finally:
        responder.close()


def test_real_audio_back_end_never_crashes_the_window(x_display, clock, caplog):
    # Whatever this machine's audio is (CI has none), the window runs: noise plays or is
    # reported off with a warning.
    responder = PsychoPyWindowResponder(
        DISPLAY, clock, fullscr=False, noise=NoiseSettings(loop_s=0.5), wait_for_start=False
    )
    try:
        with caplog.at_level(logging.WARNING):
            responder.start_set(SET)
        assert responder.window._noise is not None or "pink masking noise is OFF" in caplog.text
    finally:
        responder.close()


# -- without a display or without PsychoPy (subprocesses: pyglet keeps its display) ------------


def run_python(code: str, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, **env},
    )


OPEN_WINDOW = """
    import sys
    {prelude}
    from masking_lab.core.clock import RealClock
    from masking_lab.responders.cue import DisplayGeometry
    from masking_lab.core.errors import ResponderError
    from masking_lab.responders.psychopy_window import PsychoPyWindowResponder
    try:
        PsychoPyWindowResponder(DisplayGeometry(400.0, 800, 600), RealClock(), fullscr=False)
    except ResponderError as exc:
        print("RESPONDER_ERROR", exc)
        sys.exit(3)
    """


def test_no_display_is_a_clear_error():
    res = run_python(OPEN_WINDOW.format(prelude=""), {"DISPLAY": ":4242"})
    assert res.returncode == 3, res.stdout + res.stderr
    assert "cannot open the participant window" in res.stdout
    assert "--responder keys" in res.stdout


def test_missing_psychopy_is_a_clear_error():
    blocker = """
    class Block:
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] == "psychopy":
                raise ImportError(f"{name} is blocked for this test")
    sys.meta_path.insert(0, Block())
    """
    res = run_python(
        OPEN_WINDOW.format(prelude=textwrap.indent(textwrap.dedent(blocker), "    ")), {}
    )
    assert res.returncode == 3, res.stdout + res.stderr
    assert "pip install 'masking-lab[psychopy]'" in res.stdout


# -- monitor settings -------------------------------------------------------------------------


def test_display_from_the_reference_rig_config():
    from masking_lab.device.config import load_device_config

    config = load_device_config(None)
    display = display_geometry(config)
    assert (display.width_mm, display.width_px, display.height_px) == (
        config.display.width_mm,
        config.display.width_px,
        config.display.height_px,
    )


def test_explicit_monitor_settings_override_the_config():
    from masking_lab.device.config import load_device_config

    config = load_device_config(None)
    display = display_geometry(config, width_mm=300.0)
    assert display.width_mm == 300.0
    assert display.width_px == config.display.width_px
    assert "explicit" in display.source
    alone = display_geometry(None, width_mm=344.0, width_px=1920, height_px=1080)
    assert alone == DisplayGeometry(344.0, 1920, 1080, alone.source)


def test_missing_monitor_settings_say_where_to_add_them():
    from masking_lab.device.config import load_device_config

    config = dataclasses.replace(load_device_config(None), display=None)
    with pytest.raises(ProtocolError, match=r"display\.width_mm: .*add a display section") as info:
        display_geometry(config)
    assert info.value.file == config.path
    with pytest.raises(ProtocolError, match=r"display\.height_px"):
        display_geometry(None, width_mm=300.0, width_px=1024)
