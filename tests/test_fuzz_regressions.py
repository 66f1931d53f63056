"""Inputs a longer fuzz campaign (tests/fuzz/campaign.py, seed 21) found, each as a test."""

from __future__ import annotations

import json
import re
import subprocess
import sys

from masking_lab.formats.resources import shipped
from masking_lab.simulation.synthetic_logs import simulate_study

CLI = [sys.executable, "-m", "masking_lab.commands.cli"]


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=120)


def _masked_log(tmp_path):
    files = simulate_study(tmp_path / "data", n_participants=1, seed=2)
    return next(p for p in files if "baseline" not in p.name)


def test_a_set_id_that_is_not_text_is_a_reported_line_not_a_traceback(tmp_path):
    log = _masked_log(tmp_path)
    lines = log.read_text(encoding="utf-8").splitlines(keepends=True)
    trial = next(i for i, line in enumerate(lines) if '"record":"trial"' in line)
    rec = json.loads(lines[trial])
    rec["set_id"] = ["A", "B"]
    lines[trial] = json.dumps(rec) + "\n"
    log.write_text("".join(lines), encoding="utf-8")

    checked = _cli("validate", str(log))
    assert checked.returncode == 1 and "Traceback" not in checked.stderr + checked.stdout
    assert f"line {trial + 1}: set_id is not text" in checked.stdout + checked.stderr
    resumed = _cli("resume", str(log), "--no-progress")
    assert resumed.returncode == 2 and "Traceback" not in resumed.stderr
    # The trial tables stay (a second reader of the bad line); figures and the psychometric
    # bootstrap draw only from thresholds and fits, which the skipped line never reaches.
    out = ["--out", str(tmp_path / "out"), "--figures", "none", "--pf-boot", "0"]
    analysed = _cli("analyze", str(tmp_path / "data"), *out)
    assert "Traceback" not in analysed.stderr
    assert f"line {trial + 1}: set_id is not text" in (tmp_path / "out" / "problems.csv").read_text(
        encoding="utf-8"
    )


def test_a_log_whose_first_line_nests_too_deeply_is_refused_cleanly(tmp_path):
    log = tmp_path / "deep.jsonl"
    log.write_text("[" * 100_000 + "]" * 100_000 + "\n", encoding="utf-8")
    for command in (["resume", str(log), "--no-progress"], ["validate", str(log)]):
        res = _cli(*command)
        assert res.returncode in (1, 2), res
        assert "Traceback" not in res.stderr and "RecursionError" not in res.stderr


def test_a_scene_asking_for_a_billion_points_is_refused_at_once(tmp_path):
    """A mutated 919 made `render` allocate for a billion points until the campaign's limit."""
    text = shipped("protocols", "scenes/bump_rough.yaml").read_text(encoding="utf-8")
    scene = tmp_path / "huge.yaml"
    assert "n_points" in text
    scene.write_text(re.sub(r"n_points: *\d+", "n_points: 919999999", text), encoding="utf-8")
    res = _cli("render", str(scene), "--out", str(tmp_path / "out"))
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "path.n_points" in res.stderr and "maximum of 100000" in res.stderr


def test_a_data_folder_that_is_a_file_is_a_clean_error_and_nothing_is_played(tmp_path):
    """Found by hand after the campaign: `--data FILE` and `demo --out FILE` gave tracebacks."""
    not_a_folder = tmp_path / "afile"
    not_a_folder.write_text("", encoding="utf-8")
    baseline = str(shipped("protocols", "baseline.yaml"))
    res = _cli(
        "run", baseline, "--participant", "S01", "--device", "sim", "--responder", "sim",
        "--data", str(not_a_folder),
    )  # fmt: skip
    assert res.returncode == 2 and "Traceback" not in res.stderr
    # the first thing run creates under --data is its session lock (one runner at a time)
    assert "(Not a directory); choose a --data folder you can write to" in res.stderr
    assert "choose a --data folder" in res.stderr
    demo = _cli("demo", "--out", str(not_a_folder), "--participants", "2")
    assert demo.returncode == 2 and "Traceback" not in demo.stderr
    assert "a file, not a folder" in demo.stderr
    assert not_a_folder.read_text(encoding="utf-8") == ""
