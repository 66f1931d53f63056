"""Progress bars of `render` and `demo` (issue 17, item 5): drawn on a terminal or with
--progress, absent otherwise.

`render` runs as a child process whose stderr is a real pseudo-terminal (what a lab sees) or a
pipe (a log file, a CI job); `demo` runs in-process with its stderr captured.
"""

from __future__ import annotations

import fcntl
import os
import pty
import select
import struct
import subprocess
import sys
import termios
from pathlib import Path

import pytest

from masking_lab.commands.cli import main

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "protocols" / "scenes" / "bump_rough.yaml"


@pytest.fixture(scope="module")
def params(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("fit")
    pools = ["--pool", "EV270|MV:120+180", "--pool", "MV|EV270:180+270"]
    assert main(["fit", str(ROOT / "data_schema" / "shifts.csv"), "--out", str(out), *pools]) == 0
    return out / "masking_params.json"


def render_argv(params: Path, out: Path, *extra: str) -> list[str]:
    argv = [sys.executable, "-m", "masking_lab.commands.cli", "render", str(SCENE)]
    return [*argv, "--params", str(params), "--out", str(out), "--no-figure", *extra]


def on_a_terminal(argv: list[str]) -> tuple[int, str, str]:
    """Run ``argv`` with stderr on a pseudo-terminal; (exit code, stdout, what the tty showed)."""
    master, slave = pty.openpty()
    # A terminal window 120 columns wide (a fresh pty is 0 × 0, where tqdm draws nothing).
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=slave, text=True)
    os.close(slave)
    shown = bytearray()
    while True:
        ready, _, _ = select.select([master], [], [], 1.0)
        if ready:
            try:
                chunk = os.read(master, 4096)
            except OSError:  # EIO: the child closed the terminal
                break
            if not chunk:
                break
            shown += chunk
        elif proc.poll() is not None:
            break
    out, _ = proc.communicate(timeout=120)
    os.close(master)
    return proc.returncode, out, shown.decode("utf-8", "replace")


def test_render_draws_its_bar_on_a_terminal(params, tmp_path):
    code, out, tty = on_a_terminal(render_argv(params, tmp_path / "r"))
    assert code == 0, tty
    assert "render: 100%" in tty and "5/5" in tty
    assert "writing points, summary and figures" in tty  # the step under way is named
    assert "wrote" in out and "render:" not in out  # the bar never mixes into stdout


def test_render_is_quiet_off_a_terminal_unless_asked(params, tmp_path):
    quiet = subprocess.run(render_argv(params, tmp_path / "q"), capture_output=True, text=True)
    assert quiet.returncode == 0, quiet.stderr
    assert "render:" not in quiet.stderr and "steps" not in quiet.stderr
    asked = subprocess.run(
        render_argv(params, tmp_path / "a", "--progress"), capture_output=True, text=True
    )
    assert asked.returncode == 0, asked.stderr
    assert "render: 100%" in asked.stderr and "5/5" in asked.stderr
    assert asked.stdout == quiet.stdout.replace(str(tmp_path / "q"), str(tmp_path / "a"))
    # --no-progress wins even on a terminal.
    code, _, tty = on_a_terminal(render_argv(params, tmp_path / "n", "--no-progress"))
    assert code == 0 and "render:" not in tty


def test_demo_draws_one_bar_over_sessions_analysis_and_rendering(tmp_path, capsys):
    argv = ["demo", "--out", str(tmp_path / "d"), "--participants", "2", "--device", "sim"]
    assert main([*argv, "--n-boot", "100", "--jobs", "1", "--progress"]) == 0
    captured = capsys.readouterr()
    err = captured.err
    # 2 participants × 3 sessions, analysis, rendering, done: 9 steps.
    assert "demo: 100%" in err and "9/9" in err
    for step in ("[ 6/6] S02 experiment2", "analysing the logs", "rendering the bump", "done"):
        assert step in err
    # The session lines live in the bar, not on lines of their own.
    assert not any(line.startswith("  [ 1/6]") for line in err.splitlines())
    assert captured.out.lstrip().startswith("masking-lab demo: done")  # the summary, unchanged


def test_an_error_after_a_bar_has_started_prints_on_a_line_of_its_own(params, tmp_path):
    # render's bar is drawn before the scene is read; a bad scene used to put the error message
    # on the bar's line, after its text.
    bad = tmp_path / "missing.yaml"
    argv = [sys.executable, "-m", "masking_lab.commands.cli", "render", str(bad)]
    argv += ["--params", str(params), "--out", str(tmp_path / "r"), "--no-figure"]
    code, _, tty = on_a_terminal(argv)
    assert code == 2, tty
    assert "render:" in tty  # the bar was drawn
    lines = tty.replace("\r\n", "\n").split("\n")
    error = [line for line in lines if "error:" in line]
    assert len(error) == 1 and error[0].startswith("masking-lab render: error:"), tty
    assert str(bad) in error[0]
