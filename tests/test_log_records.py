"""Typed log records: one writer, one reader, a fast typed view with the same results.

The analysis reads logs through a typed view (msgspec) and falls back to the general reader
for anything unusual; both must give the same thresholds. The participant bootstrap by weight
matrix must agree with the materialised resampling it replaced.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import msgspec
import numpy as np
import pytest
from fit_memo import once_per_input
from hypothesis import given
from hypothesis import strategies as st
from runner_support import write_calibration, write_protocol

from masking_lab.analysis import log_reading, thresholds
from masking_lab.analysis.batch import run_analyze
from masking_lab.analysis.log_reading import fast_parse, read_logs
from masking_lab.analysis.ramp_fit import (
    participant_bootstrap,
    ramp_least_squares,
    ramp_least_squares_batch,
)
from masking_lab.analysis.settings import AnalysisSettings
from masking_lab.analysis.thresholds import EstimatorSettings, session_rows
from masking_lab.formats.log_records import (
    ANALYSIS_DECODER,
    Header,
    SetEnd,
    SetStart,
    Trial,
    check_record,
    decode_record,
    record_kind,
)
from masking_lab.formats.records import encode_record
from masking_lab.formats.session_log import parse_log
from masking_lab.session.runner import RunOptions, run_session
from masking_lab.simulation.synthetic_logs import simulate_study

OUTPUTS = (
    "thresholds.csv",
    "anova.csv",
    "sphericity.csv",
    "posthoc.csv",
    "one_sample.csv",
    "ramp_fits.csv",
    "masking_params.json",
    "problems.csv",
)


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    folder = tmp_path_factory.mktemp("study")
    simulate_study(folder / "logs", n_participants=8, seed=5)
    return folder / "logs"


def test_every_line_of_a_real_session_decodes_to_its_typed_record(tmp_path):
    write_calibration(tmp_path / "data", "S01", {"EV270": -14.0, "MV120": -26.0})
    protocol = write_protocol(tmp_path)
    result = run_session(
        RunOptions(protocol, "S01", data_dir=tmp_path / "data", seed=1), stream=io.StringIO()
    )
    lines = result.log_path.read_bytes().splitlines()
    typed = [decode_record(line) for line in lines]
    assert [record_kind(r) for r in typed] == [json.loads(line)["record"] for line in lines]
    assert isinstance(typed[0], Header) and typed[0].participant == "S01"
    trials = [r for r in typed if isinstance(r, Trial)]
    assert trials and all(isinstance(t.level_db_sl, float) for t in trials)
    assert [r.seq for r in typed] == list(range(1, len(lines) + 1))
    assert {type(r) for r in typed} >= {Header, SetStart, Trial, SetEnd}


@pytest.mark.parametrize(
    ("record", "message"),
    [
        ({"record": "trial", "trial_index": "3"}, "Expected `int"),
        ({"record": "set_end", "reversal_levels_db": [1.0, "x"]}, "Expected `float"),
        ({"record": "trial", "correct": 1}, "Expected `bool"),
        ({"record": "nonsense"}, "Invalid value 'nonsense'"),
    ],
)
def test_the_writer_refuses_records_of_the_wrong_shape(record, message):
    with pytest.raises(ValueError, match=message):
        check_record(record)


def test_synthetic_logs_are_the_writer_s_encoding_plus_the_counter(study):
    for path in sorted(study.rglob("*.jsonl"))[:6]:
        for n, line in enumerate(path.read_bytes().decode("utf-8").splitlines(), start=1):
            rec = json.loads(line)
            assert rec.pop("seq") == n
            assert line == encode_record(rec)[:-1] + f',"seq":{n}}}'


def test_the_typed_view_gives_the_general_reader_s_rows_and_checks(study, monkeypatch):
    # Both views handing the ML estimator the same arrays share one fit; arrays that differ
    # between them get a fit each, and the rows then differ.
    monkeypatch.setattr(thresholds, "ml_threshold", once_per_input(thresholds.ml_threshold))
    monkeypatch.setattr(thresholds, "fit_pf", once_per_input(thresholds.fit_pf))
    paths = sorted(study.rglob("*.jsonl"))
    # The ML rows over the first two participants' sessions (all three protocols): the other
    # participants' logs have the same records and fields, and their fits are most of the cost.
    with_ml = set(paths[:6])
    assert {json.loads(p.read_bytes().split(b"\n", 1)[0])["protocol"]["experiment"]
            for p in with_ml} == {"baseline", "experiment1", "experiment2"}  # fmt: skip
    for path in paths:
        raw = path.read_bytes()
        fast, slow = fast_parse(raw, path), parse_log(raw, path)
        assert fast is not None
        for key in ("record", "participant", "session_id", "created_utc", "calibration"):
            assert fast.header[key] == slow.header[key]
        assert fast.header["protocol"]["experiment"] == slow.header["protocol"]["experiment"]
        for estimator in ("reversals", "ml") if path in with_ml else ("reversals",):
            settings = EstimatorSettings(estimator=estimator)
            assert session_rows(fast, "x", settings) == session_rows(slow, "x", settings)
        assert fast.continuity_problems() == slow.continuity_problems() == []
        assert fast.lines == slow.lines


@pytest.mark.parametrize(
    "damage",
    [
        lambda b: b[:-5],  # torn last line
        lambda b: b.replace(b"\n", b"\n\n", 1),  # blank line
        lambda b: b.replace(b"\n", b"\n \t\n", 1),  # a line of white space only
        lambda b: b.replace(b'"correct":true', b'"correct":"yes"', 1),  # wrong type
        lambda b: b + b'{"record":"future_kind"}\n',  # unknown record kind
    ],
    ids=["torn", "blank", "white", "type", "kind"],
)
def test_unusual_logs_go_to_the_general_reader(study, damage):
    path = sorted(study.rglob("*experiment1.jsonl"))[0]
    raw = damage(path.read_bytes())
    assert fast_parse(raw, path) is None
    assert parse_log(raw, path).problems or parse_log(raw, path).records


@given(st.binary(max_size=4096))
def test_the_line_count_that_guards_the_typed_read_is_bytes_count(raw):
    assert log_reading._newlines(raw) == raw.count(b"\n")


def test_the_view_refuses_a_field_it_does_not_decode():
    (trial,) = ANALYSIS_DECODER.decode_lines(b'{"record":"trial","set_id":"A","x":1}\n')
    assert trial["set_id"] == "A" and trial.get("level_db_v") is None
    with pytest.raises(KeyError):
        trial["level_db_v"]
    with pytest.raises(AttributeError, match="does not decode 'x'"):
        trial.get("x")


def _outputs(folder: Path) -> dict[str, bytes]:
    return {name: (folder / name).read_bytes() for name in OUTPUTS}


def test_analyze_outputs_are_the_same_typed_or_general_in_process_or_parallel(
    study, tmp_path, monkeypatch
):
    # OUTPUTS hold no trial table: the psychometric fits and trials.csv are not compared.
    settings = AnalysisSettings(figures="none", n_boot=300, pf_boot=0, trial_tables=False)
    run_analyze(study, tmp_path / "typed", settings)
    monkeypatch.setattr(log_reading, "PARALLEL_FROM", 1)
    run_analyze(study, tmp_path / "parallel", settings)
    monkeypatch.setattr(log_reading, "PARALLEL_FROM", 10**9)
    monkeypatch.setattr(log_reading, "fast_parse", lambda raw, path: None)
    run_analyze(study, tmp_path / "general", settings)
    typed = _outputs(tmp_path / "typed")
    assert _outputs(tmp_path / "parallel") == typed
    assert _outputs(tmp_path / "general") == typed


def test_read_logs_keeps_the_order_and_hashes_the_bytes_parsed(study):
    paths = sorted(study.rglob("*.jsonl"))
    settings = EstimatorSettings()
    serial = list(read_logs(paths, study, settings, workers=1))
    parallel = list(read_logs(paths, study, settings, workers=2))
    assert [r.rel for r in parallel] == [p.relative_to(study).as_posix() for p in paths]
    assert [(r.sha256, r.rows) for r in parallel] == [(r.sha256, r.rows) for r in serial]


def test_analyze_reports_broken_continuity_by_file_and_line(study, tmp_path):
    data = tmp_path / "data"
    for path in sorted(study.rglob("*.jsonl")):
        dest = data / path.relative_to(study)
        dest.parent.mkdir(parents=True, exist_ok=True)
        dest.write_bytes(path.read_bytes())
    victim = sorted(data.rglob("*experiment1.jsonl"))[0]
    lines = victim.read_bytes().splitlines(keepends=True)
    victim.write_bytes(b"".join([*lines[:9], *lines[10:]]))  # line 10 deleted
    settings = AnalysisSettings(figures="none", n_boot=200, pf_boot=0, trial_tables=False)
    summary = run_analyze(data, tmp_path / "out", settings)
    with open(tmp_path / "out" / "problems.csv", encoding="utf-8", newline="") as fh:
        problems = list(csv.DictReader(fh))
    rel = victim.relative_to(data).as_posix()
    mine = [p for p in problems if p["log"] == rel]
    assert any(
        p["problem"].startswith("line 10: record counter jumps from 9 to 11")
        and p["action"] == "records kept; check the log"
        for p in mine
    )
    assert any("line 10: record counter jumps" in w and rel in w for w in summary.warnings)
    report = (tmp_path / "out" / "report.txt").read_text(encoding="utf-8")
    assert "record counter jumps" in report


def _bootstrap_by_copies(x, data, n_boot, rng):
    """The materialised resampling the weight matrix replaced (the oracle)."""
    n_part = data.shape[0]
    draws = rng.integers(0, n_part, size=(n_boot, n_part))
    present = np.isfinite(data)
    filled = np.where(present, data, 0.0)
    counts = present[draws].sum(axis=1)
    sums = filled[draws].sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = sums / counts
    complete = (counts > 0).all(axis=1)
    a, b = ramp_least_squares_batch(x, means[complete])
    a_out, b_out, failed = [a], [b], 0
    for row in np.flatnonzero(~complete):
        keep = counts[row] > 0
        if np.unique(x[keep]).size < 2:
            failed += 1
            continue
        a1, b1 = ramp_least_squares(x[keep], means[row, keep])
        a_out.append(np.array([a1]))
        b_out.append(np.array([b1]))
    return np.concatenate(a_out), np.concatenate(b_out), failed


@pytest.mark.parametrize("n_part", [2, 7, 400])
def test_bootstrap_by_weights_agrees_with_materialised_copies(n_part):
    gen = np.random.default_rng(n_part)
    x = np.array([5.0, 10.0, 15.0, 20.0, 25.0, 30.0])
    data = gen.normal(0.0, 3.0, (n_part, x.size)) + np.maximum(0, -8 + 0.9 * x)
    data[gen.random(data.shape) < 0.25] = np.nan
    a0, b0, f0 = _bootstrap_by_copies(x, data, 1500, np.random.default_rng(3))
    a1, b1, f1 = participant_bootstrap(x, data, n_boot=1500, rng=np.random.default_rng(3))
    assert f1 == f0 and a1.shape == a0.shape
    np.testing.assert_allclose(a1, a0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(b1, b0, rtol=0, atol=1e-12)


def test_msgspec_decoding_is_what_the_view_uses():
    # The view relies on msgspec's tagged unions; a record without a kind is not a record.
    with pytest.raises(msgspec.ValidationError):
        ANALYSIS_DECODER.decode_lines(b'{"set_id":"A"}\n')
