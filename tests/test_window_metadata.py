"""Participant metadata asked in the participant's PsychoPy window (issue 17, item 4).

The form's rules are tested as pure state (``responders.info_form``); the window itself is tested
for real: ``masking-lab run --responder psychopy`` runs in a child process on a virtual X display
(Xvfb, the session fixture ``x_display``, tests/xdisplay.py) and ``xdotool`` types the answers
through the X server, as an experimenter at the rig's keyboard would.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from test_psychopy_window import xdotool

from masking_lab.core.errors import ProtocolError
from masking_lab.formats.resources import shipped
from masking_lab.responders.info_form import backspace, start_form, submit, type_text
from masking_lab.session.participant_info import InfoField, resolve_info

ROOT = Path(__file__).resolve().parents[1]
FIELDS = [
    InfoField("age", "integer", required=True, unit="years"),
    InfoField("handedness", "choice", ("left", "right", "ambidextrous"), required=True),
    InfoField("finger", "choice", ("index", "middle")),
    InfoField("skin_temperature", "number", unit="degC"),
    InfoField("notes", description="experimenter's notes"),
]
INFO = """info:
  - {name: age, type: integer, required: true, unit: years}
  - {name: handedness, type: choice, choices: [left, right, ambidextrous], required: true}
  - {name: finger, type: choice, choices: [index, middle], description: finger on the plate}
  - {name: skin_temperature, type: number, unit: degC}
  - {name: notes, type: text, description: experimenter's notes}
"""


def typed(state, *entries: str):
    """Type each entry and press Enter after it; ``\\b`` is Backspace."""
    for entry in entries:
        for ch in entry:
            state = backspace(state) if ch == "\b" else type_text(state, ch)
        state = submit(state)
    return state


# -- the form's rules (pure) ---------------------------------------------------------------------


def test_required_fields_are_refused_when_empty_and_optional_ones_skipped():
    s = typed(start_form(FIELDS, {}), "")
    assert (s.field.name, s.error) == ("age", "age is required: type it, then Enter")
    s = typed(s, "   ")
    assert s.field.name == "age" and "required" in s.error
    s = typed(s, "24", "right", "", "", "")
    assert s.done
    assert dict(s.answers) == {
        "age": "24", "handedness": "right", "finger": "", "skin_temperature": "", "notes": "",
    }  # fmt: skip
    assert resolve_info(FIELDS, s.answers) == {"age": 24, "handedness": "right"}


def test_typed_values_are_checked_and_a_refused_answer_stays_to_be_corrected():
    s = typed(start_form(FIELDS, {}), "2x")
    assert (s.field.name, s.text, s.error) == ("age", "2x", "age: '2x' is not a whole number")
    s = typed(s, "\b\b31")  # corrected in the box: the error goes with the accepted answer
    assert (s.field.name, s.error) == ("handedness", "")
    s = typed(s, "right", "", "warm")
    assert (s.field.name, s.error) == (
        "skin_temperature",
        "skin_temperature: 'warm' is not a number",
    )
    s = typed(s, "\b" * 4 + "inf")
    assert s.error == "skin_temperature: 'inf' is not a finite number"
    s = typed(s, "\b\b\b31.5", "cold room, 19 °C")
    assert s.done
    assert resolve_info(FIELDS, s.answers) == {
        "age": 31, "handedness": "right", "skin_temperature": 31.5, "notes": "cold room, 19 °C",
    }  # fmt: skip


def test_choices_are_enforced_and_may_be_picked_by_number():
    s = typed(start_form(FIELDS, {"age": "30"}), "up")
    assert s.error == "handedness: 'up' is not one of left, right, ambidextrous"
    s = typed(s, "\b\b4")
    assert s.error == "handedness: choose 1 to 3 (or type the choice)"
    s = typed(s, "\b3")
    assert s.answers["handedness"] == "ambidextrous" and s.field.name == "finger"
    assert s.choices_line() == "1 = index    2 = middle"
    # Choices that are numbers themselves are typed as they are, never picked by position.
    sizes = [InfoField("glove", "choice", ("7", "8", "9"), required=True)]
    s = typed(start_form(sizes, {}), "1")
    assert s.error == "glove: '1' is not one of 7, 8, 9"
    assert typed(s, "\b8").answers == {"glove": "8"}


def test_given_values_are_not_asked_again_and_the_question_says_what_is_asked():
    s = start_form(FIELDS, {"age": "24", "handedness": "left", "notes": " "})
    assert s.field.name == "finger" and s.position() == "field 3 of 5"
    assert s.question() == "finger, optional: Enter skips"
    s = typed(s, "", "")
    assert s.question() == "experimenter's notes, optional: Enter skips"
    assert typed(s, "").done


def test_a_window_run_refuses_a_bad_info_value_before_the_window_opens(tmp_path):
    # The given values are checked when the session is planned, whoever answers.
    from masking_lab.commands.cli import main

    protocol = _protocol(tmp_path)
    argv = ["run", str(protocol), "--participant", "S1", "--device", "sim"]
    argv += ["--responder", "psychopy", "--data", str(tmp_path / "data"), "--info", "age=old"]
    with pytest.raises(ProtocolError, match="age: 'old' is not a whole number"):
        from masking_lab.session.runner import RunOptions, run_session

        run_session(
            RunOptions(protocol, "S1", responder="psychopy", info={"age": "old"}),
            make_responder=lambda *_: pytest.fail("the window opened"),
        )
    assert main(argv) == 2
    assert not (tmp_path / "data").exists() or not list((tmp_path / "data").rglob("*.jsonl"))


# -- the real window under Xvfb ------------------------------------------------------------------


def _protocol(tmp_path: Path) -> Path:
    text = (ROOT / "protocols" / "baseline.yaml").read_text()
    path = tmp_path / "baseline_info.yaml"
    path.write_text(text.replace("kind: baseline\n", "kind: baseline\n" + INFO, 1))
    return path


def _rig(tmp_path: Path) -> Path:
    reference = shipped("protocols", "devices/default.yaml").read_text(encoding="utf-8")
    rig = tmp_path / "rig.yaml"  # the monitor as Xvfb has it: 1280 × 800 px
    head = reference.split("\ndisplay:")[0]
    rig.write_text(head + "\ndisplay:\n  width_mm: 300.0\n  width_px: 1280\n  height_px: 800\n")
    return rig


class Run:
    """``masking-lab run --responder psychopy`` in a child process; its stderr read by lines."""

    def __init__(self, display: str, tmp_path: Path, *extra: str) -> None:
        self.display = display
        self.data = tmp_path / "data"
        argv = [sys.executable, "-m", "masking_lab.commands.cli", "run", str(_protocol(tmp_path))]
        argv += ["--participant", "S1", "--device", "sim", "--responder", "psychopy"]
        argv += ["--data", str(self.data), "--device-config", str(_rig(tmp_path)), *extra]
        self.proc = subprocess.Popen(
            argv,
            env={**os.environ, "DISPLAY": display},
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            cwd=tmp_path,
        )
        self.lines: queue.Queue[str] = queue.Queue()
        self.err: list[str] = []
        # The one reader of stderr (communicate() would race it for lines).
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.err.append(line)
            self.lines.put(line)

    def wait_for(self, text: str) -> None:
        """Block until stderr says ``text`` (a guard against a hang, not a timing check)."""
        while True:
            try:
                line = self.lines.get(timeout=120)
            except queue.Empty:
                self.proc.kill()
                pytest.fail(f"no {text!r} on stderr; got {''.join(self.err)}")
            if text in line:
                return

    def keys(self, *keys: str) -> None:
        xdotool(self.display, "key", "--delay", "40", *keys)

    def type(self, text: str) -> None:
        xdotool(self.display, "type", "--delay", "40", text)

    def finish(self) -> tuple[int, str]:
        """Exit code and all of stderr, once the process has ended."""
        self.proc.wait(timeout=120)
        self.reader.join(timeout=120)
        return self.proc.returncode, "".join(self.err)


def test_the_window_asks_checks_and_logs_the_participant_fields(x_display, tmp_path):
    run = Run(x_display, tmp_path, "--info", "finger=index")
    try:
        # The form's handlers are in place before its first frame, which follows this line:
        # keys typed from here on reach it, in order.
        run.wait_for("asked in the participant window")
        xdotool(x_display, "mousemove", "640", "400")  # the pointer in the window: focus
        run.keys("Return")  # age empty: refused (required)
        run.type("2x")
        run.keys("Return")  # refused: not a whole number
        run.keys("BackSpace", "BackSpace")
        run.type("31")
        run.keys("Return")
        run.type("up")
        run.keys("Return")  # refused: not a choice
        run.keys("BackSpace", "BackSpace", "2", "Return")  # 2 = right
        run.type("warm")  # finger came from --info: this is the skin temperature
        run.keys("Return")  # refused: not a number
        run.keys(*["BackSpace"] * 4)
        run.type("31.5")
        run.keys("Return")
        run.type("Cold room, 19 C")
        run.keys("Return")
        # The log is written once the form is done; the first set then waits for the space
        # bar, where Esc stops the session.
        run.wait_for("session log:")
        while run.proc.poll() is None:
            run.keys("Escape")
            with contextlib.suppress(subprocess.TimeoutExpired):
                run.proc.wait(timeout=0.5)
    finally:
        if run.proc.poll() is None:
            run.proc.kill()
    code, err = run.finish()
    assert code == 130, err
    (log,) = (run.data / "S1").glob("*.jsonl")
    header = json.loads(log.read_text().splitlines()[0])
    assert header["info"] == {
        "age": 31, "handedness": "right", "finger": "index", "skin_temperature": 31.5,
        "notes": "Cold room, 19 C",
    }  # fmt: skip


def test_escape_in_the_form_stops_before_anything_is_logged(x_display, tmp_path):
    run = Run(x_display, tmp_path)
    try:
        run.wait_for("asked in the participant window")
        xdotool(x_display, "mousemove", "640", "400")
        run.type("45")
        run.keys("Return", "Escape")
        code, err = run.finish()
    finally:
        if run.proc.poll() is None:
            run.proc.kill()
    assert code == 130, err
    assert "stopped in the participant form: nothing was played or logged" in err
    assert "Traceback" not in err
    assert not list(run.data.rglob("*.jsonl"))  # no log, not even a header
    # The runner lock is released: the same command may start again at once.
    assert _lock_free(run.data)


def _lock_free(data: Path) -> bool:
    from masking_lab.formats.log_lock import RunnerLock

    lock = RunnerLock.acquire(data / "S1", "S1", "baseline")
    lock.release()
    return True


class NoFormWindow:
    """A stand-in participant window without a form (e.g. a lab's own responder factory)."""

    closed = False

    def close(self) -> None:
        self.closed = True


def test_a_window_without_a_form_refuses_missing_fields_and_closes_it(tmp_path):
    from masking_lab.session.runner import RunOptions, run_session

    window = NoFormWindow()
    data = tmp_path / "data"
    options = RunOptions(_protocol(tmp_path), "S1", responder="psychopy", data_dir=data)
    with pytest.raises(ProtocolError, match=r"missing required age, handedness: give --info"):
        run_session(options, make_responder=lambda *_: window)
    assert window.closed
    assert not list(data.rglob("*.jsonl"))
