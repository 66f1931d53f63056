"""The user test in the participant's PsychoPy window on a virtual X display (Xvfb).

Keys and a touching finger (pointer moved with the button held) are injected with ``xdotool``,
through the X server, as in tests/test_psychopy_window.py, whose participant script is reused, on
the session's display (``x_display``, tests/xdisplay.py). Both scenarios' windows open in one
child process, which prints their results as JSON for the tests below.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from test_psychopy_window import DISPLAY, Script, window_id, xdotool

from masking_lab.core.clock import RealClock, VirtualClock
from masking_lab.core.errors import ProtocolError
from masking_lab.usertest.design import UserTestTiming, UserTrial, load_usertest
from masking_lab.usertest.responder_base import (
    StreamResult,
    UserTestInfo,
    UserTrialPresentation,
)
from masking_lab.usertest.window_responder import answer_keys, make_responder

TESTS = Path(__file__).resolve().parent
GEOMETRIES = ("bump", "hole", "ascending", "descending")
TEXTURES = ("smooth", "rough", "coarse")
TRIAL = UserTrial(7, "hole", "rough", "compensated", 2, 2, 2)


def played() -> StreamResult:
    x = np.zeros(1)
    return StreamResult([0.0], [0.0], x, x, {"EV": x, "MV": x}, {"EV": "EV270", "MV": "MV180"}, 0)


# -- what the child process does (no assertions: it reports, the tests below check) ------------


def answers_and_finger(display: str) -> dict:
    """Start, one finger-tracked trial with injected touches and keys; what was seen."""
    from masking_lab.usertest.window_responder import UserTestWindowResponder

    clock = RealClock()
    window = UserTestWindowResponder(DISPLAY, clock, fullscr=False, noise=None)
    try:
        wid = window_id(window)
        xdotool(display, "mousemove", "--window", wid, "400", "300")
        starter = Script(display, clock, [(0.0, ("key", "space"), True)])
        starter.start()
        window.start_session(UserTestInfo(GEOMETRIES, TEXTURES, 120, 0, "finger"))
        starter.stop.set()
        starter.join(10)

        timing = UserTestTiming(lead_in_s=0.3, stimulus_s=0.6, gap_s=0.2, n_presentations=3)
        start_s = clock.now() + 0.3
        pres = UserTrialPresentation(TRIAL, 120, start_s, timing, "finger", 51.0, 51.0 * 0.6)
        on = [start_s + timing.onset_s(k) for k in (1, 2, 3)]
        end_s = pres.end_s
        # The lanes are centred: window column 410 is +5 mm on screen, 5 + 15.3 mm on the path.
        steps = [
            (on[0] + 0.05, ("mousemove", "--window", wid, "410", "240"), False),
            (on[0] + 0.06, ("mousedown", "1"), False),
            (on[0] + 0.3, ("mousemove", "--window", wid, "420", "240"), False),
            (on[0] + 0.55, ("mouseup", "1"), False),
            (on[2] + 0.2, ("key", "2"), False),  # while the object plays: discarded
            (end_s + 0.3, ("key", "9"), False),  # no geometry key
            (end_s + 0.5, ("key", "3"), False),
            (end_s + 0.9, ("key", "1"), False),
        ]
        participant = Script(display, clock, steps)
        seen: dict = {}
        threads = []

        def play(finger):
            threads.append(threading.current_thread().name)
            for name, at in (("early", on[0] + 0.2), ("late", on[0] + 0.5), ("gap", on[0] + 0.7)):
                clock.sleep_until(at)
                seen[name] = finger(clock.now())
            clock.sleep_until(end_s)
            return played()

        participant.start()
        _, answer = window.trial(pres, play)
        participant.stop.set()
        participant.join(10)
    finally:
        window.close()
    return {
        "script_error": None if participant.error is None else repr(participant.error),
        "threads": threads,
        "answer": [answer.geometry, answer.texture],
        "times": [answer.geometry_time_s, answer.texture_time_s],
        "seen": seen,
        "first_onset": on[0],
        "finger_path": [list(p) for p in answer.finger_path],
    }


def timeout_without_answer() -> dict:
    """A cue-tracked trial nobody answers, with a response timeout."""
    from masking_lab.usertest.window_responder import UserTestWindowResponder

    clock = RealClock()
    window = UserTestWindowResponder(DISPLAY, clock, fullscr=False, noise=None)
    try:
        window.window.wait_for_start = False
        window.start_session(UserTestInfo(GEOMETRIES, TEXTURES, 120, 5, "cue"))
        timing = UserTestTiming(
            lead_in_s=0.05, stimulus_s=0.2, gap_s=0.05, n_presentations=3, response_timeout_s=0.3
        )
        pres = UserTrialPresentation(TRIAL, 120, clock.now(), timing, "cue", 51.0, 10.2)
        fingers = []

        def play(finger):
            fingers.append(finger)
            clock.sleep_until(pres.end_s)
            return played()

        _, answer = window.trial(pres, play)
    finally:
        window.close()
    return {"fingers": [f is None for f in fingers], "answer": [answer.geometry, answer.texture]}


def _child_main(display: str) -> None:
    results = {"answers": answers_and_finger(display), "timeout": timeout_without_answer()}
    print("RESULT " + json.dumps(results))


@pytest.fixture(scope="module")
def window_results(x_display):
    code = (
        f"import sys; sys.path.insert(0, {str(TESTS)!r}); "
        f"import test_usertest_runner_window as m; m._child_main({x_display!r})"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code],
        env={**os.environ, "DISPLAY": x_display},
        capture_output=True,
        text=True,
        timeout=120,
        cwd=TESTS.parent,
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, proc.stdout[-2000:] + proc.stderr[-3000:]
    return json.loads(lines[-1][len("RESULT ") :])


# -- tests -------------------------------------------------------------------------------------


def test_answer_keys_cover_the_number_row_and_the_keypad():
    assert answer_keys(3) == {"1": 1, "num_1": 1, "2": 2, "num_2": 2, "3": 3, "num_3": 3}


def test_two_answers_and_the_finger_positioning_the_stream(window_results):
    r = window_results["answers"]
    assert r["script_error"] is None
    assert r["threads"] == ["masking-lab-play"]  # play() ran once, off the drawing thread
    assert r["answer"] == [3, 1]
    g_s, t_s = r["times"]
    assert 0.0 < g_s < t_s
    # 0.5 mm per px: column 410 → +5 mm → 20.3 mm along the path; column 420 → 25.3 mm.
    assert r["seen"]["early"] == pytest.approx(20.3, abs=0.6)
    assert r["seen"]["late"] == pytest.approx(25.3, abs=0.6)
    assert r["seen"]["gap"] is None  # the cue stopped, the finger lifted: no position
    on = r["first_onset"]
    assert r["finger_path"] and all(on <= t <= on + 0.6 for t, _, _ in r["finger_path"])


def test_no_answer_after_the_timeout(window_results):
    r = window_results["timeout"]
    assert r["fingers"] == [True]  # cue tracking: no finger reader
    assert r["answer"] == [None, None]


def test_the_factory_refuses_a_cue_speed_the_window_does_not_draw():
    from masking_lab.usertest.runner import UserTestContext

    design = load_usertest(TESTS.parent / "protocols" / "usertest.yaml")
    slow = dataclasses.replace(design, cue_speed_mm_s=40.0)
    context = UserTestContext("S01", 1, VirtualClock(), slow, {})
    with pytest.raises(ProtocolError, match="cue_speed_mm_s: 51"):
        make_responder(context)
