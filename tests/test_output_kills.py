"""Output folders survive a kill at any instant (issue 21.6): real `masking-lab` processes are
SIGKILLed at each named step of their output swap (the test hook MASKING_LAB_TEST_KILL_AT,
masking_lab.formats.fileio.kill_point), with the atomic exchange and with the two-rename
fallback; afterwards the output path holds the previous or the new complete results, and the
next run restores or clears what the killed one left. A full disk (ENOSPC injected into the
one atomic-write function, fileio._write_data) is a clean error with the previous results intact.
"""

from __future__ import annotations

import errno
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from test_render import write_params
from test_usertest_analysis import header, trial_records, write_log

from masking_lab.commands.cli import main
from masking_lab.core.errors import OutputFolderError
from masking_lab.formats import fileio
from masking_lab.formats.output_dir import recover_leftovers, staged_output
from masking_lab.simulation.synthetic_logs import simulate_study

PROTOCOLS = Path(__file__).resolve().parents[1] / "protocols"


def _snapshot(folder: Path) -> dict[str, bytes] | None:
    if not folder.is_dir():
        return None
    return {
        p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()
    }


def _hidden(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if p.name.startswith("."))


def _cli(argv: list[str], kill_at: str, fallback: bool = False) -> int:
    """Run ``masking-lab argv`` in a process of its own that SIGKILLs itself at ``kill_at``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("MASKING_LAB_TEST_")}
    env["MASKING_LAB_TEST_KILL_AT"] = kill_at
    if fallback:
        env["MASKING_LAB_TEST_NO_EXCHANGE"] = "1"
    code = "import sys; from masking_lab.commands.cli import main; sys.exit(main(sys.argv[1:]))"
    done = subprocess.run(
        [sys.executable, "-c", code, *argv], env=env, capture_output=True, text=True, check=False
    )
    assert "Traceback" not in done.stderr, done.stderr
    return done.returncode


def _run(argv: list[str]) -> int:
    """A complete run, in this process: only the kills need a process of their own (and a
    subprocess would pay the imports of numpy, pandas and matplotlib again each time)."""
    assert not any(k.startswith("MASKING_LAB_TEST_") for k in os.environ)
    return main(argv)


@pytest.fixture(scope="module")
def studies(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("kills")
    simulate_study(root / "new", n_participants=3, seed=5, baseline_start_above_db=10.0)
    shutil.copytree(root / "new", root / "old")
    shutil.rmtree(root / "old" / "P03")
    return root / "old", root / "new"


def _shifts(path: Path, extra: int) -> Path:
    rows = ["participant,target,masker,masker_level_db_sl,shift_db"]
    for i, p in enumerate(("A", "B", "C")):
        for m in ("MV120", "MV180"):
            for x in (5, 10, 15, 20, 25):
                rows.append(f"{p},EV270,{m},{x},{max(0.0, 0.6 * x - 6 + 0.1 * i + extra):.3f}")
    path.write_text("\n".join(rows) + "\n")
    return path


def _commands(kind: str, studies, tmp_path: Path) -> tuple[list[str], list[str], Path]:
    out = tmp_path / "results"
    if kind == "analyze":
        old, new = studies
        # Few bootstrap sets, no figures or trial tables: they cost most of a run and are no
        # concern of the swap (a folder with a subfolder, figures/, is swapped by `fit`).
        common = ["--out", str(out), "--n-boot", "100", "--pf-boot", "0", "--figures", "none"]
        common += ["--no-trial-tables", "--quiet"]
        return ["analyze", str(old), *common], ["analyze", str(new), *common], out
    if kind == "fit":
        a, b = _shifts(tmp_path / "a.csv", 0), _shifts(tmp_path / "b.csv", 1)
        common = ["--out", str(out), "--n-boot", "100"]
        return ["fit", str(a), *common], ["fit", str(b), *common], out
    if kind == "plan":
        exp1 = str(PROTOCOLS / "experiment1.yaml")
        # --force: each run replaces the plan already in --out (else plan refuses it); one step
        # schedule, no ML fits or QUEST+ comparison: the costly parts, no concern of the swap
        common = ["--out", str(out), "--ml-replicates", "0", "--quest-replicates", "0", "--force"]
        common += ["--schedules", "4"]
        return (
            ["plan", exp1, "--replicates", "5", *common],
            ["plan", exp1, "--replicates", "6", *common],
            out,
        )
    if kind == "render":
        params = write_params(tmp_path / "masking_params.json")
        scenes = [str(PROTOCOLS / "scenes" / f"{s}_smooth.yaml") for s in ("bump", "hole")]
        common = ["--params", params, "--out", str(out), "--no-figure"]
        return ["render", scenes[0], *common], ["render", scenes[1], *common], out
    data_a, data_b = tmp_path / "ua", tmp_path / "ub"
    for data, people in ((data_a, "AB"), (data_b, "ABC")):
        for p in people:
            write_log(data / p / f"usertest-{p}.jsonl", [header(p), *trial_records(p)])
    return (
        ["usertest-report", str(data_a), "--out", str(out)],
        ["usertest-report", str(data_b), "--out", str(out)],
        out,
    )


ALL_STEPS = ["staged", "file:1", "file:3", "written", "swapped"]
CASES = [  # every step for analyze; the steps that differ by command for the others
    ("analyze", False, ALL_STEPS),
    ("analyze", True, ["moved_aside", "swapped"]),
    ("fit", False, ["file:2", "written", "swapped"]),
    ("fit", True, ["moved_aside"]),
    ("usertest-report", False, ["file:2", "swapped"]),
    ("usertest-report", True, ["moved_aside"]),
    ("plan", False, ["file:2", "swapped"]),
    ("render", False, ["file:1", "written", "swapped"]),
    ("render", True, ["moved_aside"]),
]


@pytest.mark.parametrize(("kind", "fallback", "steps"), CASES)
def test_a_kill_at_any_step_leaves_old_or_new_results_and_the_next_run_tidies(
    kind, fallback, steps, studies, tmp_path
):
    runs = _commands(kind, studies, tmp_path)
    out = runs[2]
    assert _run(runs[0]) == 0
    snaps = [_snapshot(out)]
    assert _run(runs[1]) == 0
    snaps.append(_snapshot(out))
    assert snaps[0] and snaps[1] and snaps[0] != snaps[1]
    now = 1  # which run's results the folder holds; each kill runs the other one
    for step in steps:
        other = 1 - now
        assert _cli(runs[other], kill_at=step, fallback=fallback) == -signal.SIGKILL, step
        mid = _snapshot(out)
        if step == "moved_aside":
            assert mid is None  # the one window of the fallback: restored by the next run
            old, staging = _hidden(tmp_path)
            assert ".old-" in old and ".partial-" in staging
            assert recover_leftovers(out) == [
                f"restored the previous results of a killed run from {old}",
                f"deleted {staging}, left by a killed run",
            ]
            mid = _snapshot(out)
        assert mid == snaps[other if step == "swapped" else now], step
        assert _run(runs[other]) == 0, step
        assert _snapshot(out) == snaps[other], step
        assert _hidden(tmp_path) == [], step
        now = other


def test_leftovers_of_a_running_process_are_left_alone(tmp_path):
    out = tmp_path / "out"
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        mine = tmp_path / f".out.partial-{sleeper.pid}"
        mine.mkdir()
        dead = tmp_path / ".out.partial-999999999"
        dead.mkdir()
        other = tmp_path / ".other.old-999999999"
        other.mkdir()
        assert recover_leftovers(out) == ["deleted .out.partial-999999999, left by a killed run"]
        assert _hidden(tmp_path) == [".other.old-999999999", mine.name]
    finally:
        sleeper.kill()
        sleeper.wait()


def _full_disk_after(monkeypatch, n_files: int) -> None:
    """fileio._write_data accepts ``n_files`` writes, then fails like a full disk."""
    calls = {"n": 0}
    real = fileio._write_data

    def write(fh, data):
        calls["n"] += 1
        if calls["n"] > n_files:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(fh, data)

    monkeypatch.setattr(fileio, "_write_data", write)


@pytest.mark.parametrize("kind", ["analyze", "fit", "usertest-report", "plan", "render"])
@pytest.mark.parametrize("n_files", [0, 1])
def test_a_full_disk_is_a_clean_error_with_the_previous_results_intact(
    kind, n_files, studies, tmp_path, monkeypatch, capsys
):
    first, second, out = _commands(kind, studies, tmp_path)
    assert main(first) == 0
    before = _snapshot(out)
    capsys.readouterr()
    with monkeypatch.context() as m:
        _full_disk_after(m, n_files)
        assert main(second) == 2
    err = capsys.readouterr().err
    assert "No space left on device" in err and "Traceback" not in err
    assert f"previous results in {out} are left untouched" in err
    assert _snapshot(out) == before
    assert _hidden(tmp_path) == []
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("results")) == ["results"]


def test_a_full_disk_on_a_first_run_leaves_nothing_behind(tmp_path, monkeypatch):
    with monkeypatch.context() as m:
        _full_disk_after(m, 0)
        with (
            pytest.raises(OutputFolderError, match="nothing was written to"),
            staged_output(tmp_path / "out") as staging,
        ):
            fileio.write_text_atomic(staging / "report.txt", "x\n")
    assert list(tmp_path.iterdir()) == []
