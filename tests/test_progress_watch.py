"""`masking-lab watch LOG` beside a real running session (issue 17, item 5).

`masking-lab run` runs in a child process with the keypad responder on a pseudo-terminal: the
test is the participant and answers each trial only after `masking-lab watch` (a second child
process, following the growing log) has shown the trials done so far. So every view checked
here was drawn from the log of a live session, in step with it, with no sleeps and no timing
assumptions; the session's device is the in-process simulation on the real clock.
"""

from __future__ import annotations

import os
import pty
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GUARD_S = 120.0  # against a hang only; nothing here measures time


def short_protocol(tmp_path: Path, max_trials: int) -> Path:
    """The baseline with 50 ms intervals and a trial cap, so a set ends after a few answers."""
    text = (ROOT / "protocols" / "baseline.yaml").read_text()
    for old, new in (
        ("max_trials: 150", f"max_trials: {max_trials}"),
        ("stimulus_s: 1.8 ", "stimulus_s: 0.05"),
        ("gap_s: 0.6", "gap_s: 0.0"),
        ("lead_in_s: 1.2", "lead_in_s: 0.0"),
        ("inter_trial_s: 0.5", "inter_trial_s: 0.0"),
    ):
        assert old in text, old
        text = text.replace(old, new, 1)
    path = tmp_path / "baseline_short.yaml"
    path.write_text(text)
    return path


class Keypad:
    """The participant's side of the pty: reads the prompts, types the keys."""

    def __init__(self) -> None:
        self.master, self.slave = pty.openpty()
        self.seen = bytearray()

    def expect(self, text: bytes) -> None:
        deadline = time.monotonic() + GUARD_S
        while text not in self.seen:
            left = deadline - time.monotonic()
            assert left > 0, f"never saw {text!r}: {bytes(self.seen)[-500:]!r}"
            ready, _, _ = select.select([self.master], [], [], left)
            if ready:
                self.seen += os.read(self.master, 4096)

    def type(self, keys: bytes) -> None:
        os.write(self.master, keys)

    def close(self) -> None:
        for fd in (self.master, self.slave):
            os.close(fd)


class Watch:
    """``masking-lab watch LOG`` in a child process; what it has printed so far."""

    def __init__(self, log: Path) -> None:
        argv = [sys.executable, "-m", "masking_lab.commands.cli", "watch", str(log)]
        self.proc = subprocess.Popen(
            [*argv, "--interval", "0.05"], stdout=subprocess.PIPE, stderr=subprocess.PIPE
        )
        self.out = ""
        self.changed = threading.Condition()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in iter(self.proc.stdout.readline, b""):
            with self.changed:
                self.out += line.decode()
                self.changed.notify_all()

    def expect(self, text: str) -> str:
        """Block until watch has printed ``text``; the view (blank-line separated) holding it."""
        with self.changed:
            if not self.changed.wait_for(lambda: text in self.out, timeout=GUARD_S):
                pytest.fail(f"watch never showed {text!r}; it showed:\n{self.out[-2000:]}")
            return next(v for v in reversed(self.out.split("\n\n")) if text in v)


def start(tmp_path: Path, pad: Keypad, max_trials: int) -> tuple[subprocess.Popen, Path]:
    data = tmp_path / "data"
    argv = [sys.executable, "-m", "masking_lab.commands.cli", "run"]
    argv += [str(short_protocol(tmp_path, max_trials)), "--participant", "S1", "--sets", "EV270"]
    argv += ["--device", "sim", "--responder", "keys", "--data", str(data)]
    argv += ["--participant-tty", os.ttyname(pad.slave)]
    run = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    pad.expect(b"space bar")  # the log and its header exist before the first set starts
    (log,) = (data / "S1").glob("*.jsonl")
    return run, log


def answer(pad: Keypad, watch: Watch, trial: int) -> str:
    """Wait for trial ``trial``'s question, check watch shows the trials before it, answer."""
    pad.expect(f"Trial {trial}: feel".encode())
    pad.expect(b"Which interval was different?")
    done = trial - 1
    view = watch.expect(f"; {done} trial{'' if done == 1 else 's'} done;")
    pad.seen.clear()
    pad.type(b"1")
    return view


def test_watch_follows_a_live_session_trial_by_trial_to_its_end(tmp_path):
    pad = Keypad()
    run = watch = None
    try:
        run, log = start(tmp_path, pad, max_trials=5)
        watch = Watch(log)
        first = watch.expect("sets 0/1 done; 0 trials done")
        assert "participant S1 | baseline" in first and "faults: none" in first
        pad.type(b" ")
        views = [answer(pad, watch, k) for k in range(1, 6)]
        # The fifth answer hits the cap: the set and the session end, and so does watch.
        assert watch.proc.wait(timeout=GUARD_S) == 0
        assert run.wait(timeout=GUARD_S) == 0, run.stderr.read()
    finally:
        for proc in (run, watch and watch.proc):
            if proc is not None and proc.poll() is None:
                proc.kill()
        pad.close()
    # Before trial k the current set's track shows the k − 1 answered trials as a chart.
    for k, view in enumerate(views[1:], start=2):
        assert f"set EV270: {k - 1} trial" in view
        assert sum(view.count(c) for c in "●○") == k - 1
        assert "trials left: unknown until a set ends" in view  # no set has finished yet
    final = watch.out.split("\n\n")[-1]
    assert "sets 1/1 done; 5 trials done; trials left: ~0" in final
    assert final.rstrip().endswith("session ended: completed")


def test_watch_shows_a_live_sessions_fault_and_waits_for_resume(tmp_path):
    pad = Keypad()
    run = watch = None
    try:
        run, log = start(tmp_path, pad, max_trials=20)
        watch = Watch(log)
        watch.expect("0 trials done")
        pad.type(b" ")
        for k in (1, 2, 3):
            answer(pad, watch, k)
        pad.expect(b"Which interval was different?")  # trial 4 played, not yet answered
        watch.expect("; 3 trials done;")
        run.send_signal(signal.SIGINT)  # the experimenter's Ctrl-C
        assert run.wait(timeout=GUARD_S) == 130
        view = watch.expect("waiting for `masking-lab resume`")
        assert watch.proc.poll() is None  # the session is not over: watch goes on
        watch.proc.send_signal(signal.SIGINT)
        assert watch.proc.wait(timeout=GUARD_S) == 0
    finally:
        for proc in (run, watch and watch.proc):
            if proc is not None and proc.poll() is None:
                proc.kill()
        pad.close()
    assert "faults (1):" in view and "interrupted in set EV270, trial 4" in view
    assert "stopped (the session goes on)" in watch.proc.stderr.read().decode()
