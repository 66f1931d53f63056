"""One responder suite: the same checks over every responder, threshold (3IFC) and user test.

In the style of scikit-learn's ``parametrize_with_checks``: plain check functions, each run over
every responder — the simulated observers, the keypad on a real pseudo-terminal and the
participant window on the real Xvfb display (the session fixture ``x_display``, tests/xdisplay.py).

Keys are injected without wall-clock waits: the keypad reads its clock through a stepping clock
that types the scripted keys into the pty's master side on its first reading after the stimuli
(when keys typed earlier have been discarded); the window's key source wraps PsychoPy's
``event`` module and hands out the scripted keys once the window asks for an answer. A timeout
is the stepping clock jumping past the deadline. Nothing here waits on the wall clock.
"""

from __future__ import annotations

import contextlib
import os
import termios
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from masking_lab.core.levels import db_v_to_volts
from masking_lab.core.stimulus import parse_stimulus
from masking_lab.core.trial import PlayResult, TrialPlan
from masking_lab.responders.base import TrialPresentation
from masking_lab.responders.keys import KeyReader, KeysResponder
from masking_lab.responders.sim import SimResponder
from masking_lab.usertest.design import UserTestTiming, UserTrial
from masking_lab.usertest.keys_responder import UserTestKeysResponder
from masking_lab.usertest.responder_base import StreamResult, UserTestInfo, UserTrialPresentation

GEOMETRIES = ("bump", "hole", "ascending", "descending")
TEXTURES = ("smooth", "fine", "rough")
TIMING = UserTestTiming(lead_in_s=0.05, stimulus_s=0.1, gap_s=0.05, n_presentations=3)
PLAYED_3IFC = PlayResult([0.6, 3.0, 5.4], [0.6, 3.0, 5.4], 0.5, 0.0)
X = np.zeros(1)
PLAYED_USERTEST = StreamResult(
    [0.05], [0.05], X, X, {"EV": X, "MV": X}, {"EV": "EV270", "MV": "MV180"}, 0
)


class SteppingClock:
    """A virtual session clock: each reading is ``step_s`` later; ``on_read`` hears each."""

    virtual = True

    def __init__(self, step_s: float = 0.25) -> None:
        self.t = 0.0
        self.step_s = step_s
        self.on_read: Callable[[], None] = lambda: None

    def now(self) -> float:
        self.on_read()
        t, self.t = self.t, self.t + self.step_s
        return t

    def sleep_until(self, t: float) -> None:
        self.t = max(self.t, t)


# -- how each responder is driven ------------------------------------------------------------


@dataclass
class Case:
    """One responder and how the suite feeds it a participant's keys.

    ``answer(keys, timeout_s)`` runs one trial whose participant presses ``keys`` (names as the
    3IFC answer: "1".."4", or "abort") and returns (what play returned, the answer, plays).
    """

    name: str
    kind: str  # "threshold" or "usertest"
    human: bool
    make: Callable[[], Any]
    feed: Callable[[Any, list[str], float], None] = lambda responder, keys, step: None
    responder: Any = None
    cleanup: list[Callable[[], None]] = field(default_factory=list)

    def answer(self, keys: list[str], timeout_s: float | None = None, step_s: float = 0.25):
        self.feed(self.responder, keys, step_s)
        plays: list[object] = []
        if self.kind == "threshold":
            result, response = self.responder.trial(threshold_trial(), _play(plays, PLAYED_3IFC))
        else:
            pres = usertest_trial(timeout_s)
            result, response = self.responder.trial(pres, _play(plays, PLAYED_USERTEST))
        return result, response, plays


def _play(plays: list[object], result: Any) -> Callable[..., Any]:
    def play(*finger: object) -> Any:
        plays.append(finger)
        return result

    return play


def threshold_trial(level_db_v: float = -14.0, index: int = 0) -> TrialPresentation:
    plan = TrialPlan(parse_stimulus("EV270"), db_v_to_volts(level_db_v), 2)
    return TrialPresentation("A", index, plan, 0.0, level_db_v, None, None)


def usertest_trial(timeout_s: float | None = None) -> UserTrialPresentation:
    import dataclasses

    timing = dataclasses.replace(TIMING, response_timeout_s=timeout_s)
    trial = UserTrial(0, "bump", "rough", "uncompensated", 0, 1, 3)
    return UserTrialPresentation(trial, 4, 0.0, timing, "cue", 51.0, 91.8)


def keypad_case(kind: str) -> Case:
    master, slave = os.openpty()
    mode = termios.tcgetattr(slave)
    mode[3] &= ~termios.ISIG  # Ctrl-C arrives as a byte (a pty that is no controlling terminal)
    termios.tcsetattr(slave, termios.TCSANOW, mode)
    clock = SteppingClock()
    reader = KeyReader(slave, slave, now=clock.now)
    cls = KeysResponder if kind == "threshold" else UserTestKeysResponder
    case = Case(f"{kind}-keys", kind, True, lambda: cls(reader, wait_for_start=False))

    def feed(responder: Any, keys: list[str], step_s: float) -> None:
        typed = b"".join(b"\x03" if k == "abort" else k.encode() for k in keys)
        clock.step_s = step_s

        def type_once() -> None:  # the first reading after the stimuli: typed now
            clock.on_read = lambda: None
            os.write(master, typed)
            _drain(master)

        clock.on_read = type_once

    case.feed = feed
    case.cleanup += [lambda: _close(master), lambda: _close(slave)]
    return case


def window_case(kind: str, request: pytest.FixtureRequest) -> Case:
    request.getfixturevalue("x_display")  # the real Xvfb display
    from test_psychopy_window import DISPLAY

    from masking_lab.responders.psychopy_window import PsychoPyWindowResponder
    from masking_lab.usertest.window_responder import UserTestWindowResponder

    clock = SteppingClock(step_s=0.02)
    events = ScriptedKeys()
    cls = PsychoPyWindowResponder if kind == "threshold" else UserTestWindowResponder
    options = {"fullscr": False, "noise": None, "wait_for_start": False, "events": events}
    case = Case(f"{kind}-window", kind, True, lambda: cls(DISPLAY, clock, **options))

    def feed(responder: Any, keys: list[str], step_s: float) -> None:
        clock.step_s = step_s
        events.script = ["escape" if k == "abort" else k for k in keys]

    case.feed = feed
    return case


class ScriptedKeys:
    """PsychoPy's ``event`` module with scripted key presses handed out by ``getKeys``.

    An answer key comes only once the window asks for an answer (after it cleared the keys
    typed during the stimuli); Escape comes at the first look for it.
    """

    def __init__(self) -> None:
        from psychopy import event

        self.event = event
        self.script: list[str] = []
        self.asking = False

    def clearEvents(self, kind: str | None = None) -> None:
        self.event.clearEvents(kind) if kind else self.event.clearEvents()
        self.asking = kind == "keyboard"

    def getKeys(self, keyList: list[str] | None = None) -> list[str]:
        self.event.getKeys(keyList=keyList)  # the real queue is read and dropped
        while self.script and (self.asking or self.script[0] == "escape"):
            key = self.script.pop(0)
            if keyList is None or key in keyList:
                return [key]  # a key the window does not take is pressed and ignored
        return []


def sim_case(kind: str) -> Case:
    if kind == "threshold":
        return Case(
            "threshold-sim", kind, False, lambda: SimResponder.from_ground_truth(None, "P01", 7)
        )
    return Case("usertest-sim", kind, False, usertest_sim)


def usertest_sim() -> Any:
    import tempfile
    from pathlib import Path

    from usertest_support import RAMPS, write_usertest

    from masking_lab.rendering.solver import MutualMasking
    from masking_lab.simulation.observer import load_ground_truth
    from masking_lab.usertest.design import load_usertest
    from masking_lab.usertest.playback import render_objects
    from masking_lab.usertest.sim_responder import UserTestSimResponder

    folder = Path(tempfile.mkdtemp(prefix="suite-"))
    design = load_usertest(write_usertest(folder, repeats=1))
    pairs = {
        (mv, "EV270"): MutualMasking(a, b, c, d, mv=mv, ev="EV270")
        for mv, ((a, b), (c, d)) in RAMPS.items()
    }
    objects = render_objects(design, pairs)
    return UserTestSimResponder.from_ground_truth(design, objects, load_ground_truth(), "S01", 3)


def _drain(master: int) -> None:
    """Read what the responder printed so far, so its writes never block."""
    import select

    while select.select([master], [], [], 0)[0]:
        try:
            if not os.read(master, 4096):
                return
        except OSError:
            return


def _close(fd: int) -> None:
    with contextlib.suppress(OSError):
        os.close(fd)


CASES = {
    "threshold-sim": lambda request: sim_case("threshold"),
    "usertest-sim": lambda request: sim_case("usertest"),
    "threshold-keys": lambda request: keypad_case("threshold"),
    "usertest-keys": lambda request: keypad_case("usertest"),
    "threshold-window": lambda request: window_case("threshold", request),
    "usertest-window": lambda request: window_case("usertest", request),
}


# -- the checks --------------------------------------------------------------------------------


def check_plays_once_and_returns_what_was_played(case: Case) -> None:
    keys = ["2"] if case.kind == "threshold" else ["3", "2"]
    result, _, plays = case.answer(keys)
    assert len(plays) == 1
    assert result is (PLAYED_3IFC if case.kind == "threshold" else PLAYED_USERTEST)
    if case.kind == "usertest" and case.human:
        assert plays == [(None,)]  # cue tracking: no finger reader handed to the stream


def check_key_mapping(case: Case) -> None:
    if case.kind == "threshold":
        for key in ("3", "1"):
            _, response, _ = case.answer(["9", "x", key])  # others are ignored
            assert response.interval == int(key)
            assert response.response_time_s >= 0
        return
    _, answer, _ = case.answer(["9", "4", "3"])  # 9 is no key; geometry 4, texture 3
    assert (answer.geometry, answer.texture) == (4, 3)
    assert 0 <= answer.geometry_time_s <= answer.texture_time_s


def check_timeout(case: Case) -> None:
    _, answer, _ = case.answer([], timeout_s=0.3, step_s=10.0)  # the clock jumps past it
    assert (answer.geometry, answer.texture) == (None, None)
    assert answer.response_time_s == 0.0


def check_abort(case: Case) -> None:
    with pytest.raises(KeyboardInterrupt):
        case.answer(["abort"])


def check_sim_answers(case: Case) -> None:
    if case.kind == "threshold":
        loud = [case.answer([])[1].interval for _ in range(3)]
        assert len(set(loud)) == 1  # one seed, set and trial: one answer
        sim = case.responder
        al = sim.participant.unmasked_al_db_v["EV270"]
        far_above = [sim.answer(threshold_trial(al + 30.0, i)).interval for i in range(60)]
        assert sum(i == 2 for i in far_above) >= 54  # right except for lapses
        return
    first, second = case.answer([])[1], case.answer([])[1]
    assert first == second  # seeded per trial
    assert first.geometry in range(1, 5) and first.texture in range(1, 4)
    assert 0 < first.geometry_time_s < first.texture_time_s


def check_close_is_idempotent(case: Case) -> None:
    case.responder.close()
    case.responder.close()


CHECKS = [
    check_plays_once_and_returns_what_was_played,
    check_key_mapping,
    check_timeout,
    check_abort,
    check_sim_answers,
    check_close_is_idempotent,
]


# Which checks apply to which responder, by its kind ("threshold" or "usertest") and whether a
# person answers (keys) or a simulated observer does. The suite runs every applicable pair and
# no other: a check that cannot apply is not generated (rather than skipped), and
# test_every_check_and_responder_is_covered keeps the table honest.
TRAITS = {
    "threshold-sim": ("threshold", False),
    "usertest-sim": ("usertest", False),
    "threshold-keys": ("threshold", True),
    "usertest-keys": ("usertest", True),
    "threshold-window": ("threshold", True),
    "usertest-window": ("usertest", True),
}
APPLIES: dict[Callable[[Case], None], Callable[[str, bool], bool]] = {
    check_plays_once_and_returns_what_was_played: lambda kind, human: True,
    check_key_mapping: lambda kind, human: human,  # a simulated observer presses no keys
    check_timeout: lambda kind, human: kind == "usertest" and human,  # 3IFC waits for an answer
    check_abort: lambda kind, human: human,  # nobody presses Escape for a simulated observer
    check_sim_answers: lambda kind, human: not human,  # a participant's answers are the keys
    check_close_is_idempotent: lambda kind, human: True,
}
PAIRS = [
    pytest.param(name, check, id=f"{name}-{check.__name__}")
    for name in CASES
    for check in CHECKS
    if APPLIES[check](*TRAITS[name])
]


def test_every_check_and_responder_is_covered():
    assert set(TRAITS) == set(CASES) and set(APPLIES) == set(CHECKS)
    for check in CHECKS:
        assert any(name for name, c in (p.values for p in PAIRS) if c is check), check.__name__
    for name in CASES:
        assert sum(1 for n, _ in (p.values for p in PAIRS) if n == name) >= 3, name


@pytest.mark.parametrize(("name", "check"), PAIRS)
def test_responder(name: str, check: Callable[[Case], None], request: pytest.FixtureRequest):
    case = CASES[name](request)
    assert (case.kind, case.human) == TRAITS[name]  # the table says what the case is
    case.responder = case.make()
    if case.kind == "usertest":
        case.responder.start_session(UserTestInfo(GEOMETRIES, TEXTURES, 4, 0, "cue"))
    try:
        check(case)
    finally:
        case.responder.close()
        for cleanup in case.cleanup:
            cleanup()
