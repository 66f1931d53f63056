"""One runner per participant and protocol at a time (issue 21.5), with real processes: while a
`masking-lab run` of a participant's protocol is under way, a second `run` of the same
participant and protocol, or a `resume` of another of its logs, is refused before anything is
played; another participant, or the same one once the first run has ended, runs."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from masking_lab.core.errors import LogLockedError
from masking_lab.formats.log_lock import RunnerLock

BASELINE = str(Path(__file__).resolve().parents[1] / "protocols" / "baseline.yaml")
_MAIN = "import sys; from masking_lab.commands.cli import main; sys.exit(main(sys.argv[1:]))"


def _argv(data: Path, participant: str, *extra: str) -> list[str]:
    return [
        *(sys.executable, "-c", _MAIN, "run", BASELINE, "--participant", participant),
        *("--device", "sim", "--responder", "sim", "--data", str(data), "--seed", "1", *extra),
    ]


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", _MAIN, *args], capture_output=True, text=True, check=False
    )


def _wait_for_log(folder: Path, proc: subprocess.Popen[str], known: set[Path]) -> Path:
    """The new log of the running ``proc`` once its header is on disk (a generous bound on
    polling, not a timing assertion: a busy machine may take long to start Python)."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        new = [p for p in folder.glob("*.jsonl") if p not in known and p.stat().st_size > 0]
        if new:
            return new[0]
        time.sleep(0.05)
    pytest.fail("the first run never wrote its log")


@pytest.fixture
def running(tmp_path):
    """A real-time `run` of P01's baseline in a child process (stopped at the end)."""
    procs: list[subprocess.Popen[str]] = []

    def start(participant: str = "P01") -> tuple[subprocess.Popen[str], Path]:
        folder = tmp_path / "data" / participant
        known = set(folder.glob("*.jsonl")) if folder.is_dir() else set()
        proc = subprocess.Popen(
            _argv(tmp_path / "data", participant, "--real-time"),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        procs.append(proc)
        folder.mkdir(parents=True, exist_ok=True)
        return proc, _wait_for_log(folder, proc, known)

    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
        proc.communicate()


def _interrupt(proc: subprocess.Popen[str]) -> int:
    proc.send_signal(signal.SIGINT)
    proc.communicate(timeout=120)
    return proc.returncode


def test_a_second_run_of_the_same_participant_and_protocol_is_refused(running, tmp_path):
    first, log = running()
    second = subprocess.run(
        _argv(tmp_path / "data", "P01"), capture_output=True, text=True, check=False
    )
    assert second.returncode == 2, second.stderr
    assert "participant P01 is already running baseline" in second.stderr
    assert "Traceback" not in second.stderr
    assert sorted((tmp_path / "data" / "P01").glob("*.jsonl")) == [log]  # no second log
    assert first.poll() is None  # the first run goes on, untouched
    # Another participant is not held up.
    other = RunnerLock.acquire(tmp_path / "data" / "P02", "P02", "baseline")
    other.release()
    with pytest.raises(LogLockedError, match="already running baseline"):
        RunnerLock.acquire(tmp_path / "data" / "P01", "P01", "baseline")
    assert _interrupt(first) == 130
    # Once the first has ended, the same command runs to the end (virtual time: seconds).
    again = subprocess.run(
        _argv(tmp_path / "data", "P01"), capture_output=True, text=True, check=False
    )
    assert again.returncode == 0, again.stderr
    assert len(list((tmp_path / "data" / "P01").glob("*.jsonl"))) == 2


def test_resuming_another_log_while_the_protocol_runs_is_refused(running, tmp_path):
    first, interrupted = running()
    assert _interrupt(first) == 130
    second, _ = running()
    done = _cli("resume", str(interrupted))
    assert done.returncode == 2, done.stderr
    assert "participant P01 is already running baseline" in done.stderr
    assert "Traceback" not in done.stderr
    assert _interrupt(second) == 130
    # Free again once the second run has ended (the lock went with its process).
    RunnerLock.acquire(interrupted.parent, "P01", "baseline").release()
