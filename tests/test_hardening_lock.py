"""The runner lock after a crash (issue 21.5): the lock is a `flock` on an open descriptor, not
a pid file, so a `run` killed with SIGKILL (no handler, no cleanup) leaves its lock file behind
but never a stale lock: the next `run` of the same participant and protocol starts at once, and
the killed session's log can be locked again (resumed). No override flag is needed; none exists."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from masking_lab.formats.log_lock import LogLock

BASELINE = str(Path(__file__).resolve().parents[1] / "protocols" / "baseline.yaml")
_MAIN = "import sys; from masking_lab.commands.cli import main; sys.exit(main(sys.argv[1:]))"


def _run(data: Path, *extra: str) -> list[str]:
    return [
        *(sys.executable, "-c", _MAIN, "run", BASELINE, "--participant", "P01", "--no-progress"),
        *("--device", "sim", "--responder", "sim", "--data", str(data), "--seed", "1", *extra),
    ]


def test_a_killed_run_leaves_no_stale_lock(tmp_path):
    data = tmp_path / "data"
    folder = data / "P01"
    first = subprocess.Popen(
        _run(data, "--real-time"), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        # Poll for the log's first trial (a bound on polling, not a timing assertion).
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            assert first.poll() is None, first.communicate()
            logs = list(folder.glob("*.jsonl")) if folder.is_dir() else []
            if logs and '"record":"trial"' in logs[0].read_text(encoding="utf-8"):
                break
            time.sleep(0.05)
        else:
            pytest.fail("the first run never logged a trial")
        # While it runs, a second run is refused (exit 2) ...
        held = subprocess.run(_run(data), capture_output=True, text=True, check=False)
        assert held.returncode == 2 and "is already running baseline" in held.stderr
        first.send_signal(signal.SIGKILL)  # ... then it dies without any cleanup
        assert first.wait(timeout=120) == -signal.SIGKILL
    finally:
        if first.poll() is None:
            first.kill()
        first.communicate()
    (killed,) = folder.glob("*.jsonl")
    assert (folder / ".P01.baseline.lock").exists()  # the file stays; its lock went
    again = subprocess.run(_run(data), capture_output=True, text=True, check=False)
    assert again.returncode == 0, again.stderr
    assert len(list(folder.glob("*.jsonl"))) == 2
    # The killed session's log is free too (its resume would continue in real time, as it
    # started: the lock, not the whole resume, is what this test is about).
    lock = LogLock.acquire(killed)
    lock.release()
