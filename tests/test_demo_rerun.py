"""The README's first command can be run again: `demo` without --out writes a new folder next to
an earlier demo, `--force` overwrites the demo in --out, and an explicit --out holding a demo
without --force is refused (exit 2) with what to do."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

FAST = ["--participants", "2", "--device", "sim", "--jobs", "1", "--n-boot", "200"]


def _demo(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "masking_lab.commands.cli", "demo", *FAST, *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )


def _seed(log: Path) -> int:
    return json.loads(log.read_text(encoding="utf-8").split("\n", 1)[0])["seed"]


def _logs(folder: Path) -> list[Path]:
    return sorted((folder / "data").rglob("*.jsonl"))


@pytest.fixture(scope="module")
def first_demo(tmp_path_factory) -> Path:
    """One demo run without --out (so into ./demo_out): the earlier demo both tests start from.

    Each test works on a copy of it: a demo costs most of this file's time, and the two tests
    are about what a later run does next to, or over, a finished demo.
    """
    cwd = tmp_path_factory.mktemp("first")
    first = _demo(cwd)
    assert first.returncode == 0, first.stderr[-2000:]
    assert len(_logs(cwd / "demo_out")) == 6
    return cwd / "demo_out"


def test_demo_without_out_writes_a_new_folder_each_time(first_demo, tmp_path):
    shutil.copytree(first_demo, tmp_path / "demo_out")
    second = _demo(tmp_path)
    assert second.returncode == 0, second.stderr[-2000:]
    assert len(_logs(tmp_path / "demo_out")) == 6
    assert len(_logs(tmp_path / "demo_out-2")) == 6
    assert "demo_out-2/analysis" in second.stdout
    # Same seed, same numbers: the two demos' exports agree.
    a = (tmp_path / "demo_out" / "analysis" / "masking_params.json").read_text()
    b = (tmp_path / "demo_out-2" / "analysis" / "masking_params.json").read_text()
    assert a.split('"functions"')[1] == b.split('"functions"')[1]


def test_force_overwrites_the_demo_in_out_and_nothing_else(first_demo, tmp_path):
    out = tmp_path / "mine"
    shutil.copytree(first_demo, out)
    (out / "notes.txt").write_text("keep me\n")
    refused = _demo(tmp_path, "--out", str(out))
    assert refused.returncode == 2
    assert "--force" in refused.stderr and "Traceback" not in refused.stderr
    old = {_seed(p) for p in _logs(out)}
    forced = _demo(tmp_path, "--out", str(out), "--force", "--seed", "7")
    assert forced.returncode == 0, forced.stderr[-2000:]
    new = _logs(out)
    # Only the new demo's six sessions (master seed 7), none of the old ones.
    assert len(new) == 6 and not old & {_seed(p) for p in new}
    assert (out / "notes.txt").read_text() == "keep me\n"
    assert (out / "analysis" / "report.html").is_file()


def test_settings_the_analysis_refuses_stop_the_demo_before_anything_runs(first_demo, tmp_path):
    # Too few bootstrap replicates used to be refused only after every session had run, and
    # with --force after the earlier demo had been cleared.
    out = tmp_path / "kept"
    shutil.copytree(first_demo, out)
    before = {p: p.read_bytes() for p in _logs(out)}
    refused = _demo(tmp_path, "--out", str(out), "--force", "--n-boot", "20")
    assert refused.returncode == 2, refused.stderr[-2000:]
    assert "at least 100 bootstrap replicates" in refused.stderr
    assert "Traceback" not in refused.stderr and "session" not in refused.stderr.lower()
    assert {p: p.read_bytes() for p in _logs(out)} == before
    assert (out / "analysis" / "report.html").is_file()
