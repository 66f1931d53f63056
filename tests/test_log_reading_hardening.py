"""Logs are counted once and read safely (issue 21.4): hostile integers, oversized files, future
schema versions, CRLF and a byte-order mark, copies of a session, a protocol completed twice, and
non-finite levels — each a line in problems.csv and the report, never a traceback."""

from __future__ import annotations

import csv
import json
import math
import re
import shutil
from pathlib import Path

import pytest
from fit_memo import once_per_input

from masking_lab.analysis import thresholds
from masking_lab.analysis.batch import run_analyze
from masking_lab.analysis.settings import AnalysisSettings
from masking_lab.commands.cli import main
from masking_lab.core.errors import LogError
from masking_lab.formats import log_bytes
from masking_lab.formats.session_log import SessionLogWriter, read_log
from masking_lab.simulation.synthetic_logs import simulate_study


@pytest.fixture(scope="module")
def study(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("hostile")
    simulate_study(root / "data", n_participants=3, seed=5, baseline_start_above_db=10.0)
    return root / "data"


@pytest.fixture(scope="module")
def ml_fits() -> dict:
    """The ML fits of the study's sets, shared by the non-finite cases: each case refuses the
    same set before any estimator sees it, and hands the fit the other sets' unchanged trials."""
    return {}


@pytest.fixture(scope="module")
def reference(study, tmp_path_factory) -> dict[str, str]:
    out = tmp_path_factory.mktemp("ref") / "out"
    # Only thresholds.csv is compared: no figures, psychometric bootstrap or trial tables.
    run_analyze(
        study, out, AnalysisSettings(n_boot=200, figures="none", pf_boot=0, trial_tables=False)
    )
    return {"thresholds": (out / "thresholds.csv").read_text(), "out": str(out)}


def _copy(study: Path, tmp_path: Path) -> Path:
    data = tmp_path / "data"
    shutil.copytree(study, data)
    return data


# The figures and the psychometric bootstrap draw only from the thresholds and the fits, which
# no test here reads; the trial tables stay on, as their second read of every log is one more
# reader the hostile bytes must not break. One non-finite case keeps all of them.
SLIM = ("--figures", "none", "--pf-boot", "0")


def _analyze(data: Path, out: Path, *extra: str, slim: bool = True) -> int:
    argv = ["analyze", str(data), "--out", str(out), "--n-boot", "200", "--quiet", *extra]
    return main(argv + list(SLIM if slim else ()))


def _problems(out: Path) -> list[dict[str, str]]:
    with open(out / "problems.csv", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def _edit_line(path: Path, index: int, edit) -> None:
    lines = path.read_text(encoding="utf-8").split("\n")
    lines[index] = edit(lines[index])
    path.write_text("\n".join(lines), encoding="utf-8")


def _non_finite_cells(path: Path) -> list[str]:
    with open(path, encoding="utf-8") as fh:
        cells = [c for row in csv.reader(fh) for c in row]
    out = []
    for c in cells:
        try:
            x = float(c)
        except ValueError:
            continue
        if not math.isfinite(x):
            out.append(c)
    return out


def _trial_line(path: Path, k: int = 3) -> int:
    lines = path.read_text(encoding="utf-8").split("\n")
    return [i for i, line in enumerate(lines) if '"record":"trial"' in line][k]


def test_a_5000_digit_integer_is_a_reported_line_in_validate_analyze_and_resume(
    study, tmp_path, capsys
):
    data = _copy(study, tmp_path)
    log = data / "P01" / "P01_experiment1.jsonl"
    i = _trial_line(log)
    _edit_line(log, i, lambda s: s.replace('"trial_index":', '"trial_index":' + "9" * 5000, 1))
    parsed = read_log(log)
    assert any("an integer of 5" in p and f"line {i + 1}" in p for p in parsed.problems)
    capsys.readouterr()
    assert main(["validate", str(log)]) != 0
    assert "Traceback" not in capsys.readouterr().err
    assert _analyze(data, tmp_path / "out") == 0
    assert any("an integer of 5" in p["problem"] for p in _problems(tmp_path / "out"))
    # In the header, the log cannot be read at all: skipped, the cause named.
    _edit_line(log, 0, lambda s: s.replace('"seed":', '"seed":' + "7" * 5000 + ',"x":', 1))
    with pytest.raises(LogError, match=r"an integer of 50\d\d digits"):
        read_log(log)
    assert main(["resume", str(log)]) != 0
    err = capsys.readouterr().err
    assert re.search(r"an integer of 50\d\d digits", err) and "Traceback" not in err
    assert _analyze(data, tmp_path / "out") == 0
    skipped = [p for p in _problems(tmp_path / "out") if p["action"] == "file skipped"]
    assert [p["log"] for p in skipped] == ["P01/P01_experiment1.jsonl"]


def test_an_oversized_log_is_refused_from_its_size_before_reading(study, tmp_path):
    data = _copy(study, tmp_path)
    huge = data / "P02" / "sparse.jsonl"
    with open(huge, "wb") as fh:  # sparse: no disk used, and never read
        fh.truncate(log_bytes.MAX_LOG_BYTES + 1)
    with pytest.raises(LogError, match="more than the 134,217,728 bytes"):
        read_log(huge)
    assert _analyze(data, tmp_path / "out") == 0
    (row,) = [p for p in _problems(tmp_path / "out") if p["log"] == "P02/sparse.jsonl"]
    assert row["action"] == "file skipped" and "134,217,728" in row["problem"]


def test_the_size_limit_also_holds_for_a_file_that_grows_while_read(tmp_path):
    p = tmp_path / "log.jsonl"
    p.write_bytes(b'{"record":"header"}\n' * 10)
    assert len(log_bytes.read_log_bytes(p, max_bytes=200)) == 200
    with pytest.raises(LogError, match="more than the 199 bytes"):
        log_bytes.read_log_bytes(p, max_bytes=199)
    with pytest.raises(LogError, match="not a regular file"):
        log_bytes.read_log_bytes(tmp_path)


def test_a_log_of_a_future_schema_version_is_refused_everywhere(study, tmp_path, capsys):
    data = _copy(study, tmp_path)
    log = data / "P01" / "P01_baseline.jsonl"
    _edit_line(log, 0, lambda s: s.replace('"schema_version":1', '"schema_version":2', 1))
    with pytest.raises(LogError, match="schema version 2, but this masking-lab reads version 1"):
        read_log(log)
    with pytest.raises(LogError, match="schema version 2"):
        SessionLogWriter.reopen(log)
    assert _analyze(data, tmp_path / "out") == 0
    (row,) = [p for p in _problems(tmp_path / "out") if p["log"] == "P01/P01_baseline.jsonl"]
    assert row["action"] == "file skipped" and "newer masking-lab" in row["problem"]
    _edit_line(log, 0, lambda s: s.replace('"schema_version":2', '"schema_version":"1"', 1))
    with pytest.raises(LogError, match='schema_version "1" is not a version'):
        read_log(log)


def test_crlf_line_ends_and_a_byte_order_mark_read_like_the_original(study, tmp_path, reference):
    data = _copy(study, tmp_path)
    for log in data.rglob("*.jsonl"):
        log.write_bytes(b"\xef\xbb\xbf" + log.read_bytes().replace(b"\n", b"\r\n"))
    assert _analyze(data, tmp_path / "out") == 0
    assert (tmp_path / "out" / "thresholds.csv").read_text() == reference["thresholds"]
    assert _problems(tmp_path / "out") == []
    log = read_log(data / "P01" / "P01_baseline.jsonl")
    assert log.problems == [] and log.continuity_problems() == []


def test_copies_of_a_session_are_reported_and_analysed_once(study, tmp_path, reference):
    data = _copy(study, tmp_path)
    deep = data / "backup" / "old" / "deeper"
    deep.mkdir(parents=True)
    shutil.copy(data / "P01" / "P01_experiment1.jsonl", deep / "copy.jsonl")
    shutil.copy(data / "P02" / "P02_experiment2.jsonl", data / "P02" / "P02_experiment2 (1).jsonl")
    # A copy taken mid-session (the session went on afterwards): a prefix of the log.
    lines = (data / "P03" / "P03_baseline.jsonl").read_bytes().split(b"\n")
    (data / "P03" / "early.jsonl").write_bytes(b"\n".join(lines[:40]) + b"\n")
    assert _analyze(data, tmp_path / "out") == 0
    assert (tmp_path / "out" / "thresholds.csv").read_text() == reference["thresholds"]
    rows = {p["log"]: p for p in _problems(tmp_path / "out")}
    assert rows["backup/old/deeper/copy.jsonl"]["problem"].startswith(
        "a byte copy of P01/P01_experiment1.jsonl"
    )
    # The shorter name is taken for the original, though it sorts after its copy.
    assert rows["P02/P02_experiment2 (1).jsonl"]["problem"].startswith(
        "a byte copy of P02/P02_experiment2.jsonl"
    )
    assert "longer (a copy taken before" in rows["P03/early.jsonl"]["problem"]
    assert {r["action"] for r in rows.values()} == {"file skipped"}
    report = (tmp_path / "out" / "report.txt").read_text()
    assert "SKIPPED backup/old/deeper/copy.jsonl: a byte copy" in report


def test_two_complete_sessions_of_one_protocol_are_reported_and_the_latest_counts(study, tmp_path):
    data = _copy(study, tmp_path)
    src = data / "P02" / "P02_experiment1.jsonl"
    lines = src.read_text(encoding="utf-8").splitlines()
    head = json.loads(lines[0])
    head["session_id"] += "-again"
    head["created_utc"] = "2030-01-01T00:00:00Z"
    again = data / "P02" / "again.jsonl"
    again.write_text("\n".join([json.dumps(head), *lines[1:]]) + "\n", encoding="utf-8")
    assert _analyze(data, tmp_path / "out") == 0
    (row,) = [p for p in _problems(tmp_path / "out") if "complete sessions" in p["problem"]]
    assert row["log"] == "P02/P02_experiment1.jsonl"
    assert "the latest, P02/again.jsonl, counts" in row["problem"]
    assert row["problem"] in (tmp_path / "out" / "report.txt").read_text()
    with open(tmp_path / "out" / "thresholds.csv", encoding="utf-8") as fh:
        table = [r for r in csv.DictReader(fh) if r["participant"] == "P02"]
    first = {r["status"] for r in table if r["log"] == "P02/P02_experiment1.jsonl"}
    later = {r["status"] for r in table if r["log"] == "P02/again.jsonl"}
    assert first == {"superseded"} and later == {"completed"}


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-1e999"])
def test_a_non_finite_level_refuses_its_set_alike_for_every_estimator(
    study, tmp_path, literal, ml_fits, monkeypatch
):
    monkeypatch.setattr(
        thresholds, "ml_threshold", once_per_input(thresholds.ml_threshold, ml_fits)
    )
    monkeypatch.setattr(thresholds, "fit_pf", once_per_input(thresholds.fit_pf, ml_fits))
    data = _copy(study, tmp_path)
    log = data / "P01" / "P01_experiment1.jsonl"
    i = _trial_line(log)
    _edit_line(log, i, lambda s: re.sub(r'"level_db_sl":[-0-9.e]+', f'"level_db_sl":{literal}', s))
    assert any(f"non-finite number ({literal})" in p for p in read_log(log).value_problems)
    assert main(["validate", str(log)]) == 1
    statuses = {}
    full = literal == "NaN"  # figures, psychometric bootstrap and trial tables see it once
    for estimator in ("reversals", "ml"):
        out = tmp_path / estimator
        # The trial tables do not depend on the estimator: the reversals run wrote them.
        extra = () if full or estimator == "reversals" else ("--no-trial-tables",)
        assert _analyze(data, out, "--estimator", estimator, *extra, slim=not full) == 0
        with open(out / "thresholds.csv", encoding="utf-8") as fh:
            bad = [r for r in csv.DictReader(fh) if r["status"] == "invalid"]
        assert len(bad) == 1 and "non-finite level" in bad[0]["note"]
        statuses[estimator] = (bad[0]["set_id"], bad[0]["al_db_v"], bad[0]["shift_db"])
        (row,) = [p for p in _problems(out) if p["action"] == "set refused"]
        assert row["log"] == "P01/P01_experiment1.jsonl" and f"line {i + 1}" in row["problem"]
        for name in ("thresholds.csv", "ramp_fits.csv", "one_sample.csv", "anova.csv"):
            assert _non_finite_cells(out / name) == []
    assert statuses["reversals"] == statuses["ml"]
    assert statuses["ml"][1:] == ("", "")


def test_resume_refuses_a_log_holding_a_non_finite_number(study, tmp_path, capsys):
    data = _copy(study, tmp_path)
    log = data / "P01" / "P01_baseline.jsonl"
    i = _trial_line(log, 1)
    _edit_line(log, i, lambda s: re.sub(r'"trial_index":\d+', '"trial_index":-Infinity', s))
    capsys.readouterr()
    assert main(["resume", str(log), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "non-finite number (-Infinity)" in err and "cannot be resumed" in err
    assert "Traceback" not in err


def test_a_bad_utf8_byte_inside_a_record_value_is_a_reported_line(study, tmp_path):
    # msgspec raises UnicodeDecodeError (not a DecodeError) for it: found by the campaign.
    data = _copy(study, tmp_path)
    log = data / "P01" / "P01_baseline.jsonl"
    raw = log.read_bytes().split(b"\n")
    raw[2] = raw[2].replace(b'"record":"trial"', b'"record":"tri\xa6al"', 1)
    log.write_bytes(b"\n".join(raw))
    assert _analyze(data, tmp_path / "out") == 0
    rows = [p for p in _problems(tmp_path / "out") if p["log"] == "P01/P01_baseline.jsonl"]
    assert rows[0]["problem"] == "line 3: not valid UTF-8; line skipped"
