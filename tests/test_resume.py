"""Resume: a session cut at any record continues exactly as the uninterrupted run did."""

from __future__ import annotations

import io
import json

import pytest
from runner_support import (
    assert_valid_log,
    of_kind,
    records,
    timeless,
    trials,
    write_calibration,
    write_protocol,
)

from masking_lab.commands.cli import main
from masking_lab.core.errors import LogError
from masking_lab.session.frame import SessionOptions
from masking_lab.session.runner import RunOptions, resume_session, run_session

CAL = {"EV270": -14.0, "MV120": -26.0}


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted masked session (seed 7) and its log lines."""
    folder = tmp_path_factory.mktemp("ref")
    write_calibration(folder / "data", "S01", CAL)
    protocol = write_protocol(folder)
    result = run_session(
        RunOptions(protocol, "S01", data_dir=folder / "data", seed=7), stream=io.StringIO()
    )
    assert result.exit_code == 0
    text = result.log_path.read_text(encoding="utf-8")
    return protocol, text.splitlines(keepends=True), records(result.log_path)


def cut_log(tmp_path, lines, n, tail=""):
    """A copy of the first ``n`` lines (plus an incomplete ``tail``) in a fresh data folder."""
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    path = data / "S01" / "exp-S01-20240101T000000Z.jsonl"
    path.write_text("".join(lines[:n]) + tail, encoding="utf-8")
    return path


def cut_points(recs):
    kinds = [r["record"] for r in recs]
    first_end = kinds.index("set_end")
    trial_idx = [i for i, k in enumerate(kinds) if k == "trial"]
    second_set_trials = [i for i in trial_idx if i > first_end]
    return {
        "header only": 1,
        "after set_start": 2,
        "mid first set": trial_idx[len(trial_idx) // 4] + 1,
        "all trials of set 1, no set_end": first_end,
        "after set_end": first_end + 1,
        "mid second set": second_set_trials[len(second_set_trials) // 2] + 1,
        "no session_end": len(recs) - 1,
    }


@pytest.mark.parametrize(
    "where",
    [
        "header only",
        "after set_start",
        "mid first set",
        "all trials of set 1, no set_end",
        "after set_end",
        "mid second set",
        "no session_end",
    ],
)
def test_resume_from_any_cut_equals_the_uninterrupted_run(tmp_path, reference, where):
    _, lines, ref = reference
    n = cut_points(ref)[where]
    path = cut_log(tmp_path, lines, n)
    # A later baseline changed the calibration file: resume must use the logged copy.
    write_calibration(tmp_path / "data", "S01", {"EV270": -3.0, "MV120": -9.0})
    result = resume_session(path, stream=io.StringIO())
    assert result.exit_code == 0
    recs = assert_valid_log(path)
    assert timeless(recs) == timeless(ref)
    for set_id in ("A10", "A20"):
        idx = [t["trial_index"] for t in trials(recs, set_id)]
        assert idx == list(range(len(idx)))  # no trial lost or duplicated
    assert len(of_kind(recs, "set_end")) == 2 and recs[-1]["record"] == "session_end"
    assert [{k: e[k] for k in ("set_id", "status", "al_db")} for e in of_kind(recs, "set_end")] == [
        {k: e[k] for k in ("set_id", "status", "al_db")} for e in of_kind(ref, "set_end")
    ]
    # The log says what happened: an unexplained stop, then the resume.
    added = recs[n:]
    assert added[0]["record"] == "fault" and added[0]["kind"] == "unclean_stop"
    assert added[1]["record"] == "resume" and added[1]["dropped_partial_line"] is False
    # Nothing logged before the crash was rewritten.
    assert path.read_text(encoding="utf-8").startswith("".join(lines[:n]))
    # The virtual session clock goes on from where it was.
    times = [r["t_s"] for r in recs if "t_s" in r]
    assert times == sorted(times)
    assert {o.set_id for o in result.outcomes} == {"A10", "A20"}


def test_truncated_last_line_is_cut_reported_and_its_trial_rerun(tmp_path, reference):
    _, lines, ref = reference
    n = cut_points(ref)["mid first set"]
    partial = lines[n][: len(lines[n]) // 2]  # the crash hit while this trial was being written
    path = cut_log(tmp_path, lines, n, tail=partial)
    stream = io.StringIO()
    result = resume_session(path, stream=stream)
    assert result.exit_code == 0
    assert "cut an incomplete last line" in stream.getvalue()
    recs = assert_valid_log(path)
    assert timeless(recs) == timeless(ref)
    (resume,) = of_kind(recs, "resume")
    assert resume["dropped_partial_line"] is True
    fault = recs[n]
    assert fault["kind"] == "unclean_stop" and "incomplete last line" in fault["message"]
    assert fault["set_id"] == ref[n]["set_id"] and fault["trial_index"] == ref[n]["trial_index"]


def test_a_baseline_set_finished_just_before_the_crash_still_calibrates(tmp_path):
    protocol = write_protocol(tmp_path, kind="baseline", experiment="base")
    full = run_session(
        RunOptions(protocol, "S01", data_dir=tmp_path / "ref", seed=3), stream=io.StringIO()
    )
    ref = records(full.log_path)
    lines = full.log_path.read_text(encoding="utf-8").splitlines(keepends=True)
    first_end = [r["record"] for r in ref].index("set_end")
    path = tmp_path / "data" / "S01" / "base-S01-20240101T000000Z.jsonl"
    path.parent.mkdir(parents=True)
    path.write_text("".join(lines[:first_end]), encoding="utf-8")  # all trials, no set_end
    assert not (tmp_path / "data" / "S01" / "calibration.json").exists()
    assert resume_session(path, stream=io.StringIO()).exit_code == 0
    cal = json.loads((tmp_path / "data" / "S01" / "calibration.json").read_text())
    ref_cal = json.loads((tmp_path / "ref" / "S01" / "calibration.json").read_text())
    assert cal["unmasked_al_db_v"] == ref_cal["unmasked_al_db_v"]
    assert cal["sources"] == ["S01/base-S01-20240101T000000Z.jsonl"]


def test_a_finished_session_is_not_resumed(tmp_path, reference):
    _, lines, _ = reference
    path = cut_log(tmp_path, lines, len(lines))
    before = path.read_bytes()
    with pytest.raises(LogError, match="has finished"):
        resume_session(path, stream=io.StringIO())
    assert path.read_bytes() == before


def test_a_changed_protocol_file_stops_resume_unless_allowed(tmp_path, reference):
    protocol, lines, ref = reference
    path = cut_log(tmp_path, lines, cut_points(ref)["mid second set"])
    header = json.loads(lines[0])
    edited = tmp_path / "edited.yaml"
    edited.write_text(protocol.read_text() + "# edited after the session started\n")
    header["protocol"]["path"] = str(edited)
    lines = [json.dumps(header) + "\n", *path.read_text().splitlines(keepends=True)[1:]]
    path.write_text("".join(lines))
    before = path.read_bytes()
    with pytest.raises(LogError, match=r"edited\.yaml has changed .*--allow-changed-protocol"):
        resume_session(path, stream=io.StringIO())
    assert path.read_bytes() == before
    stream = io.StringIO()
    result = resume_session(path, SessionOptions(allow_changed_protocol=True), stream=stream)
    assert result.exit_code == 0 and "continuing with the protocol stored in the log" in (
        stream.getvalue()
    )
    assert timeless(records(path)) == timeless(ref)


def test_a_missing_protocol_file_does_not_matter(tmp_path, reference):
    _, lines, ref = reference
    path = cut_log(tmp_path, lines, cut_points(ref)["mid first set"])
    header = json.loads(lines[0])
    header["protocol"]["path"] = str(tmp_path / "gone.yaml")
    path.write_text(json.dumps(header) + "\n" + "".join(path.read_text().splitlines(True)[1:]))
    assert resume_session(path, stream=io.StringIO()).exit_code == 0
    assert timeless(records(path)) == timeless(ref)


def test_trials_that_do_not_replay_to_their_levels_are_refused(tmp_path, reference):
    _, lines, ref = reference
    n = cut_points(ref)["mid first set"]
    path = cut_log(tmp_path, lines, n)
    recs = records(path)
    recs[-1]["level_db_sl"] += 2.0  # edited by hand
    path.write_text("".join(json.dumps(r) + "\n" for r in recs))
    with pytest.raises(LogError, match=r"logged level .* replaying the logged responses gives"):
        resume_session(path, stream=io.StringIO())


def test_a_duplicated_trial_is_refused(tmp_path, reference):
    _, lines, ref = reference
    n = cut_points(ref)["mid first set"]
    path = cut_log(tmp_path, lines, n)
    path.write_text(path.read_text() + lines[n - 1])
    with pytest.raises(LogError, match=r"trial indices .* are not 0, 1, 2"):
        resume_session(path, stream=io.StringIO())


def test_a_header_that_breaks_the_schema_is_refused(tmp_path, reference):
    _, lines, _ = reference
    header = json.loads(lines[0])
    del header["seed"]
    path = tmp_path / "log.jsonl"
    path.write_text(json.dumps(header) + "\n" + "".join(lines[1:3]))
    with pytest.raises(LogError, match="header breaks the session-log schema"):
        resume_session(path, stream=io.StringIO())


def test_cli_resume(tmp_path, reference, capsys):
    _, lines, ref = reference
    path = cut_log(tmp_path, lines, cut_points(ref)["mid second set"])
    assert main(["resume", str(path)]) == 0
    out = capsys.readouterr().out
    assert f"log: {path}" in out and out.count("completed") == 2
    assert main(["resume", str(path)]) == 2
    assert "has finished" in capsys.readouterr().err
    assert main(["resume", str(tmp_path / "nope.jsonl")]) == 2
    err = capsys.readouterr().err
    assert "cannot read session log" in err and "Traceback" not in err
