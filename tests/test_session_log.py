"""Session logs: fsynced appends, truncated tails, reopening."""

from __future__ import annotations

import json

import pytest

from masking_lab.core.errors import LogError
from masking_lab.formats.session_log import SessionLogWriter, read_log

HEADER = {"session_id": "s1", "participant": "S01"}


def _trial(i: int) -> dict:
    return {"record": "trial", "set_id": "a", "trial_index": i, "correct": True}


def test_round_trip_and_grouping(tmp_path):
    path = tmp_path / "S01" / "log.jsonl"
    with SessionLogWriter.create(path, HEADER) as w:
        w.append({"record": "set_start", "set_id": "a"})
        for i in range(3):
            w.append(_trial(i))
        w.append({"record": "set_end", "set_id": "a", "status": "completed"})
    log = read_log(path)
    assert log.header["record"] == "header" and log.header["participant"] == "S01"
    sets = log.sets()
    assert [t["trial_index"] for t in sets["a"].trials] == [0, 1, 2]
    assert sets["a"].end["status"] == "completed"
    assert log.truncated_tail is None and log.problems == []


def test_existing_log_is_never_overwritten(tmp_path):
    path = tmp_path / "log.jsonl"
    SessionLogWriter.create(path, HEADER).close()
    with pytest.raises(LogError, match="resume"):
        SessionLogWriter.create(path, HEADER)


def test_truncated_last_line_is_reported_not_fatal_and_cut_on_reopen(tmp_path):
    path = tmp_path / "log.jsonl"
    with SessionLogWriter.create(path, HEADER) as w:
        w.append(_trial(0))
    with open(path, "a", encoding="utf-8") as fh:
        fh.write('{"record": "trial", "set_id": "a", "tri')  # crash mid-write
    log = read_log(path)
    assert [r["trial_index"] for r in log.records] == [0]
    assert log.truncated_tail is not None
    assert any("truncated last line" in p for p in log.problems)

    writer, before = SessionLogWriter.reopen(path)
    assert before.truncated_tail is not None
    writer.append(_trial(1))
    writer.close()
    log = read_log(path)
    assert [r["trial_index"] for r in log.records] == [0, 1]
    assert log.truncated_tail is None and log.problems == []


def test_garbage_in_the_middle_is_skipped_and_reported(tmp_path):
    path = tmp_path / "log.jsonl"
    lines = [json.dumps({"record": "header"}), "not json at all", json.dumps(_trial(0))]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    log = read_log(path)
    assert len(log.records) == 1
    assert log.problems == ["line 2: not valid JSON (Expecting value); line skipped"]


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("", "no session header"),
        (json.dumps(_trial(0)) + "\n", "first record must be the session header"),
    ],
)
def test_not_a_log(tmp_path, content, message):
    path = tmp_path / "log.jsonl"
    path.write_text(content, encoding="utf-8")
    with pytest.raises(LogError, match=message):
        read_log(path)


def test_missing_file(tmp_path):
    with pytest.raises(LogError, match="cannot read"):
        read_log(tmp_path / "nope.jsonl")


def test_nan_is_never_written(tmp_path):
    with SessionLogWriter.create(tmp_path / "log.jsonl", HEADER) as w, pytest.raises(ValueError):
        w.append({"record": "trial", "level_db_v": float("nan")})
