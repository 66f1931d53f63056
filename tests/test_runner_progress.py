"""The experimenter's progress line: format, and when it is shown."""

from __future__ import annotations

import io
import os
import select
import time

import pytest

from masking_lab.session.progress import ProgressLine, format_duration, format_progress


def test_progress_line_reads_as_the_issue_shows_it():
    line = format_progress(
        set_number=3,
        n_sets=15,
        set_id="MV120_10",
        trial_index=16,
        reversals=4,
        n_reversals=11,
        level_db=12.0,
        level_unit="db_sl",
        time_left_s=6 * 60 + 10,
    )
    assert line == "set 3/15 MV120_10 | trial 17 | reversals 4/11 | level 12.0 dB SL | ~6 min left"


def test_baseline_levels_are_labelled_as_drive_levels():
    line = format_progress(
        set_number=1,
        n_sets=4,
        set_id="EV270",
        trial_index=0,
        reversals=0,
        n_reversals=11,
        level_db=-3.5,
        level_unit="db_v",
        time_left_s=30,
    )
    assert "| level -3.5 dB re 1 V |" in line
    assert line.endswith("~30 s left")


@pytest.mark.parametrize(
    ("seconds", "text"),
    [
        (0, "~0 s"),
        (-3, "~0 s"),
        (float("nan"), "~0 s"),
        (2, "~5 s"),
        (44, "~45 s"),
        (89, "~1 min"),
        (59 * 60, "~59 min"),
        (65 * 60, "~1 h 05 min"),
        (float("inf"), "?"),
    ],
)
def test_durations(seconds, text):
    assert format_duration(seconds) == text


def test_quiet_when_not_a_terminal_unless_forced():
    quiet = io.StringIO()
    ProgressLine(quiet).update("set 1/1 a | trial 1")
    assert quiet.getvalue() == ""
    forced = io.StringIO()
    p = ProgressLine(forced, force=True)
    p.update("one")
    p.update("two")
    p.message("done")
    assert forced.getvalue() == "one\ntwo\ndone\n"


def test_messages_are_printed_even_when_progress_is_quiet():
    stream = io.StringIO()
    ProgressLine(stream).message("session log: x.jsonl")
    assert stream.getvalue() == "session log: x.jsonl\n"


def _read_until(fd: int, text: str, timeout_s: float = 5.0) -> str:
    # One read() of a pty returns what has arrived so far, which under load can be a part.
    out = b""
    deadline = time.monotonic() + timeout_s
    while text.encode() not in out and time.monotonic() < deadline:
        ready, _, _ = select.select([fd], [], [], 0.1)
        if ready:
            out += os.read(fd, 4096)
    return out.decode()


def test_on_a_terminal_the_line_is_redrawn_in_place():
    master, slave = os.openpty()
    try:
        with open(slave, "w", encoding="utf-8", closefd=False) as tty:
            p = ProgressLine(tty)
            assert p.enabled and p.tty
            p.update("trial 1")
            p.update("trial 2")
            p.message("set done")
        out = _read_until(master, "set done")
    finally:
        os.close(master)
        os.close(slave)
    assert out.startswith("\r\x1b[Ktrial 1\r\x1b[Ktrial 2\r\x1b[Kset done")
    assert "\n" not in out.split("set done")[0]
    never = ProgressLine(open(os.devnull, "w"), force=False)  # noqa: SIM115
    assert not never.enabled
    never.stream.close()
