"""`analyze --no-trial-tables` reads each log once (issue 22): the study matrix and
participants.tsv come from the analysis' own typed read, with the same bytes as from the
general reader's second read that the trial tables still need."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from masking_lab.analysis import study_reading
from masking_lab.analysis.log_reading import fast_parse, read_one
from masking_lab.analysis.study_status import session_of
from masking_lab.analysis.thresholds import EstimatorSettings
from masking_lab.commands.cli import main
from masking_lab.formats.session_log import parse_log
from masking_lab.simulation.synthetic_logs import simulate_study

INFO_SPECS = [
    {"name": "age", "type": "integer", "unit": "years", "description": "Age"},
    {"name": "hand", "choices": ["left", "right"]},
    "not a spec",
]


def _with_info(path: Path, info: object, specs: object) -> None:
    """Give the log's header participant answers and the protocol's question specs."""
    head, rest = path.read_bytes().split(b"\n", 1)
    header = json.loads(head)
    header["info"] = info
    header["protocol"].setdefault("content", {})["info"] = specs
    path.write_bytes(json.dumps(header).encode() + b"\n" + rest)


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """Two simulated participants; one log with answers, one with a malformed ``info``."""
    root = tmp_path_factory.mktemp("study")
    simulate_study(root, n_participants=2, seed=7)
    logs = sorted(root.rglob("*.jsonl"))
    _with_info(logs[0], {"age": 31, "hand": "left"}, INFO_SPECS)
    _with_info(logs[-1], ["not", "a", "mapping"], {"not": "a list"})
    # a log that stops mid-session: its cell is not 'ended'
    lines = logs[1].read_bytes().splitlines(keepends=True)
    logs[1].write_bytes(b"".join(lines[: len(lines) // 2]))
    return root


def test_typed_header_gives_the_session_the_general_reader_gives(study):
    for path in sorted(study.rglob("*.jsonl")):
        raw = path.read_bytes()
        typed, general = fast_parse(raw, path), parse_log(raw, path)
        assert typed is not None  # the fast path is the one under test
        rel = path.relative_to(study).as_posix()
        assert session_of(typed.header, rel, typed.ended) == session_of(
            general.header, rel, general.ended
        )
    first = sorted(study.rglob("*.jsonl"))[0]
    session, info, specs = read_one(first, "x.jsonl", EstimatorSettings()).session
    assert info == {"age": 31, "hand": "left"}
    assert [s["name"] for s in specs] == ["age", "hand"]  # the malformed entry is left out
    assert session.ended and session.set_order  # the simulated log ran its planned sets


def test_no_trial_tables_reads_no_log_twice_and_keeps_the_bytes(study, tmp_path, monkeypatch):
    # Only the participant tables and the study matrix are compared: no figures.
    argv = ["analyze", str(study), "--quiet", "--figures", "none", "--pf-boot", "0"]
    full = tmp_path / "full"
    assert main([*argv, "--out", str(full)]) == 0

    def second_read(*args, **kwargs):
        raise AssertionError("a log was read a second time")

    monkeypatch.setattr(study_reading, "read_log", second_read)
    once = tmp_path / "once"
    assert main([*argv, "--out", str(once), "--no-trial-tables"]) == 0
    for name in ("participants.tsv", "participants.json", "study_status.csv"):
        assert (once / name).read_bytes() == (full / name).read_bytes(), name
    tsv = (once / "participants.tsv").read_text().splitlines()
    assert tsv[0].split("\t")[:4] == ["participant_id", "n_sessions", "age", "hand"]
    assert any(line.split("\t")[2:4] == ["31", "left"] for line in tsv[1:])
    status = (once / "study_status.csv").read_text()
    assert ",partial," in status  # the log that stops mid-session
    # with trial tables the general reader is still needed (intervals, response times)
    with pytest.raises(AssertionError, match="second time"):
        main(["analyze", str(study), "--out", str(tmp_path / "again"), "--quiet"])


@pytest.mark.parametrize(
    ("fields", "off"),
    [
        ({}, False),  # played as asked
        ({"played_target_v": 0.0105}, True),  # 0.42 dB off the request
        ({"played_target_v": 0.0}, True),  # silence
        ({"played_target_v": None}, False),  # nothing to compare
        ({"level_db_v": None, "played_target_v": 0.02}, False),
        ({"level_db_v": 1e5}, True),
        ({"level_db_v": -1e5, "played_target_v": 1e300}, True),
        ({"played_target_v": 1e-300}, True),
    ],
)
def test_played_level_check_answers_alike_for_typed_and_general_records(fields, off):
    """The typed view's trials take a shortcut in played_level_problems: same notes."""
    from masking_lab.analysis.played_levels import played_level_problems

    header = {"record": "header", "participant": "P1", "protocol": {"experiment": "e"}}
    ok = {"record": "trial", "set_id": "A", "level_db_v": -40.0, "played_target_v": 0.01}
    trials = [dict(ok, trial_index=0), dict(ok, trial_index=1, **fields)]
    recs = [header, {"record": "set_start", "set_id": "A", "target": "EV270"}, *trials]
    raw = b"".join(json.dumps(r).encode() + b"\n" for r in recs)
    typed, general = fast_parse(raw, "x.jsonl"), parse_log(raw, "x.jsonl")
    assert typed is not None and type(typed.records[1]).__name__ == "ATrial"
    notes = played_level_problems(typed.records, typed.lines)
    assert notes == played_level_problems(general.records, general.lines)
    assert bool(notes) == off
    if notes:
        assert notes[0].startswith("line 4: 1 trial(s) played more than 0.1 dB off")


def test_status_reads_each_log_once(study, monkeypatch, capsys):
    def second_read(*args, **kwargs):
        raise AssertionError("a log was read a second time")

    monkeypatch.setattr(study_reading, "read_log", second_read)
    assert main(["status", str(study)]) == 0
    out = capsys.readouterr().out
    assert "partial" in out and "complete" in out  # the cut log and the whole ones


def test_the_log_reading_workers_are_forked_without_the_statistics_modules():
    """analyze starts its read workers before it loads pandas and SciPy (it loads them while
    the workers read): importing the analysis shell and the reader must not pull them in."""
    import subprocess
    import sys

    probe = (
        "import sys, masking_lab.analysis.batch, masking_lab.analysis.log_reading\n"
        "print(sorted(m for m in ('pandas', 'scipy', 'matplotlib') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_a_whole_analysis_with_trial_tables_never_loads_scipy_optimize(study, tmp_path):
    """The staircases' target p for psychometric.csv is found by masking_lab.core.roots (the
    same bits as SciPy's brentq): loading scipy.optimize for it cost ~0.17 s of every run.
    Neither the analysing process nor the worker that computes the statistics beside it
    loads it (the worker loads scipy.special for the tests' p values)."""
    import subprocess
    import sys

    mark = tmp_path / "statistics_process.txt"
    probe = (
        "import sys\n"
        "import masking_lab.analysis.batch as batch\n"
        "from masking_lab.commands.cli import main\n"
        "inner = batch._statistics\n"
        "def statistics(*args):\n"
        "    result = inner(*args)\n"
        f"    with open({str(mark)!r}, 'w') as fh:\n"
        "        print('scipy.optimize' in sys.modules, 'scipy.special' in sys.modules, file=fh)\n"
        "    return result\n"
        "batch._statistics = statistics\n"
        f"code = main(['analyze', {str(study)!r}, '--out', {str(tmp_path / 'out')!r}, '--quiet'])\n"
        "print(code, 'scipy.optimize' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300)
    assert out.stdout.strip().splitlines()[-1] == "0 False", out.stderr[-2000:]
    assert mark.read_text().split() == ["False", "True"]
    assert (tmp_path / "out" / "psychometric.csv").is_file()


def test_reading_stopped_early_leaves_no_worker_behind(study, tmp_path):
    """read_logs hands every chunk to its workers at once; a caller that stops after the first
    result (an error in the analysis) cancels the chunks not yet read and ends the workers."""
    import multiprocessing

    from masking_lab.analysis.log_reading import read_logs
    from masking_lab.analysis.thresholds import EstimatorSettings

    paths = sorted(study.rglob("*.jsonl"))
    before = set(multiprocessing.active_children())  # e.g. earlier tests' figure workers
    reading = read_logs(paths, study, EstimatorSettings(), workers=2)
    assert set(multiprocessing.active_children()) > before  # reading started before asked
    first = next(reading)
    assert first.rel == paths[0].relative_to(study).as_posix()
    reading.close()
    assert set(multiprocessing.active_children()) <= before
    # and read to the end, the same results as one process
    alone = [r.rel for r in read_logs(paths, study, EstimatorSettings(), workers=1)]
    assert [r.rel for r in read_logs(paths, study, EstimatorSettings(), workers=2)] == alone
