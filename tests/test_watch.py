"""`masking-lab watch LOG` (issue 17): a live view of a running session that always ends."""

from __future__ import annotations

import io
import time
from pathlib import Path

import pytest

from masking_lab.commands.cli import main
from masking_lab.commands.watch import follow
from masking_lab.simulation.synthetic_logs import simulate_study


@pytest.fixture(scope="module")
def finished_log(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("w")
    simulate_study(root, n_participants=1, seed=2, baseline_start_above_db=10.0)
    return root / "P01" / "P01_experiment1.jsonl"


def test_once_shows_the_finished_session_and_exits(finished_log, capsys):
    assert main(["watch", str(finished_log), "--once"]) == 0
    out = capsys.readouterr().out
    assert "participant P01 | experiment1" in out
    assert "sets 15/15 done" in out and "session ended: completed" in out


def test_follow_redraws_as_the_log_grows_and_ends_with_the_session(finished_log, tmp_path):
    lines = finished_log.read_bytes().splitlines(keepends=True)
    live = tmp_path / "live.jsonl"
    live.write_bytes(b"".join(lines[:30]))
    rest = iter(range(30, len(lines), 97))
    waits = []

    def grow() -> None:  # instead of sleeping: the session writes more (a torn line, too)
        start = next(rest)
        chunk = b"".join(lines[start : start + 97])
        with live.open("ab") as fh:
            fh.write(chunk[:-7])
            fh.flush()
            fh.write(chunk[-7:])
        waits.append(start)

    out = io.StringIO()
    assert follow(live, wait=grow, stream=out) == 0
    shown = out.getvalue()
    assert len(waits) == len(range(30, len(lines), 97))  # ended exactly when session_end came
    views = shown.split("\nparticipant ")
    assert len(views) >= 3  # redrawn as it grew
    assert "set MV" in views[0] and "●" in views[0]  # the current set's track
    assert shown.rstrip().endswith("session ended: completed")


def test_a_stopped_session_says_it_waits_for_resume_and_ctrl_c_leaves(
    finished_log, tmp_path, monkeypatch, capsys
):
    lines = finished_log.read_text().splitlines(keepends=True)
    log = tmp_path / "stopped.jsonl"
    fault = (
        '{"record":"fault","kind":"interrupted","message":"interrupted by SIGINT; outputs '
        'zeroed","set_id":"X","trial_index":4}\n'
    )
    log.write_text("".join(lines[:40]) + fault)

    def interrupt(_s: float) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(time, "sleep", interrupt)
    assert main(["watch", str(log)]) == 0
    captured = capsys.readouterr()
    assert "interrupted in set X, trial 5" in captured.out
    assert "waiting for `masking-lab resume`" in captured.out
    assert "stopped (the session goes on)" in captured.err


def test_a_missing_log_is_an_error_not_a_traceback(tmp_path, capsys):
    assert main(["watch", str(tmp_path / "nope.jsonl"), "--once"]) == 2
    assert "cannot read the session log" in capsys.readouterr().err
