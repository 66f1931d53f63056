"""`analyze`, `fit` and `usertest-report` write into a fresh folder and swap it in only when the
run completes: a run that fails midway leaves the previous results byte for byte, says so on
stderr and exits 2; folders that are not previous outputs are never replaced."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from test_usertest_analysis import header, trial_records, write_log

from masking_lab.commands.cli import main
from masking_lab.core.errors import AnalysisError, OutputFolderError
from masking_lab.formats.output_dir import staged_output
from masking_lab.simulation.synthetic_logs import simulate_study


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {
        p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()
    }


def _no_leftovers(parent: Path) -> None:
    hidden = [p.name for p in parent.iterdir() if p.name.startswith(".")]
    assert hidden == [], hidden


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    root = tmp_path_factory.mktemp("swap")
    simulate_study(root / "data", n_participants=3, seed=5, baseline_start_above_db=10.0)
    return root / "data"


def _analyze(data: Path, out: Path, *extra: str) -> int:
    return main(["analyze", str(data), "--out", str(out), "--n-boot", "200", "--quiet", *extra])


def test_a_failed_analyze_leaves_the_previous_results_untouched(study, tmp_path, capsys):
    data = tmp_path / "data"
    data.mkdir()
    for p in study.rglob("*.jsonl"):
        (data / p.name).write_bytes(p.read_bytes())
    out = tmp_path / "results"
    assert _analyze(data, out) == 0
    before = _snapshot(out)
    assert "report.html" in before and "thresholds.csv" in before
    # A bad log: experiment II's masking measured under experiment I's id (both directions
    # under one experiment), so the analysis fails after thresholds.csv is written.
    src = next(p for p in sorted(data.glob("*.jsonl")) if "experiment2" in p.name)
    lines = src.read_text(encoding="utf-8").splitlines()
    head = json.loads(lines[0])
    head["protocol"]["experiment"] = "experiment1"
    (data / "zz_mislabelled.jsonl").write_text(
        "\n".join([json.dumps(head), *lines[1:]]) + "\n", encoding="utf-8"
    )
    capsys.readouterr()
    assert _analyze(data, out) == 2
    err = capsys.readouterr().err
    assert "belongs to several pairs" in err and "Traceback" not in err
    assert f"previous results in {out} are left untouched" in err
    assert _snapshot(out) == before
    failed = tmp_path / "results.failed"
    assert f"partial outputs of this run are in {failed}" in err
    assert (failed / "thresholds.csv").read_bytes() != before["thresholds.csv"]
    _no_leftovers(tmp_path)


def test_a_complete_rerun_replaces_the_folder_as_a_whole(study, tmp_path, capsys):
    out = tmp_path / "results"
    # Track figures without the psychometric ones (--no-trial-tables): a folder of figures to
    # go stale is all this needs, and the psychometric figures took most of the run.
    assert _analyze(study, out, "--figures", "all", "--no-trial-tables") == 0
    assert list((out / "figures" / "tracks").glob("*.png"))
    assert not (out / "psychometric.csv").exists()
    assert _analyze(study, out, "--figures", "summary") == 0
    assert (out / "psychometric.csv").is_file()
    # No stale track figures from the earlier run: the folder is this run's alone.
    assert not (out / "figures" / "tracks").exists()
    assert (out / "report.txt").is_file()
    _no_leftovers(tmp_path)


def test_a_failed_first_run_keeps_its_explanation(study, tmp_path, capsys):
    data = tmp_path / "data"
    data.mkdir()
    for p in study.rglob("*baseline*.jsonl"):
        (data / p.name).write_bytes(p.read_bytes())
    out = tmp_path / "results"
    assert _analyze(data, out) == 2
    err = capsys.readouterr().err
    assert "no completed masked set" in err and f"partial outputs of this run are in {out}" in err
    assert (out / "thresholds.csv").is_file()
    assert "sets by status: completed" in (out / "report.txt").read_text(encoding="utf-8")
    _no_leftovers(tmp_path)


def test_folders_that_are_not_outputs_are_refused(study, tmp_path, capsys):
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("precious\n")
    assert _analyze(study, foreign) == 2
    err = capsys.readouterr().err
    assert "not masking-lab outputs" in err and "Traceback" not in err
    assert [p.name for p in foreign.iterdir()] == ["thesis.tex"]
    # An output folder holding the data would be swapped away with it.
    assert main(["analyze", str(study), "--out", str(study.parent), "--quiet"]) == 2
    assert "holds the input" in capsys.readouterr().err
    assert list(study.rglob("*.jsonl"))


def test_a_failed_fit_leaves_the_previous_results_untouched(tmp_path, capsys):
    table = tmp_path / "shifts.csv"
    rows = ["participant,target,masker,masker_level_db_sl,shift_db"]
    for i, p in enumerate(("A", "B", "C")):
        for m in ("MV120", "MV180"):
            for x in (5, 10, 15, 20, 25):
                rows.append(f"{p},EV270,{m},{x},{max(0.0, 0.6 * x - 6 + 0.1 * i):.3f}")
    table.write_text("\n".join(rows) + "\n")
    out = tmp_path / "fitted"
    argv = ["fit", str(table), "--out", str(out), "--n-boot", "200"]
    assert main(argv) == 0
    before = _snapshot(out)
    table.write_text("\n".join([*rows, "C,EV270,MV120,30,nan"]) + "\n")
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"previous results in {out} are left untouched" in err
    assert _snapshot(out) == before
    _no_leftovers(tmp_path)


def test_a_failed_usertest_report_leaves_the_previous_report_untouched(tmp_path, capsys):
    data = tmp_path / "data"
    for p in ("A", "B"):
        write_log(data / p / f"usertest-{p}.jsonl", [header(p), *trial_records(p)])
    out = tmp_path / "report"
    assert main(["usertest-report", str(data), "--out", str(out)]) == 0
    before = _snapshot(out)
    assert {"report.html", "report.txt", "figure8a.png"} <= set(before)
    # A log of another design: the analysis refuses to mix them.
    other = header("C", geometries=["bump", "hole", "flat"])
    write_log(data / "C" / "usertest-C.jsonl", [other, *trial_records("C")])
    capsys.readouterr()
    assert main(["usertest-report", str(data), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "separate folders" in err and f"previous results in {out} are left untouched" in err
    assert _snapshot(out) == before
    _no_leftovers(tmp_path)


def test_an_interrupted_run_removes_its_staging_folder(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "report.txt").write_text("old\n")
    with pytest.raises(KeyboardInterrupt), staged_output(out) as staging:
        (staging / "report.txt").write_text("new\n")
        raise KeyboardInterrupt
    assert (out / "report.txt").read_text() == "old\n"
    _no_leftovers(tmp_path)
    with pytest.raises(AnalysisError, match="left untouched"), staged_output(out):
        raise AnalysisError("boom")
    assert (out / "report.txt").read_text() == "old\n"
    with pytest.raises(OutputFolderError, match="is a file"), staged_output(out / "report.txt"):
        pass
