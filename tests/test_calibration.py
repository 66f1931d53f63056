"""Participant calibration files: read, merge per stimulus, atomic writes, refusals."""

from __future__ import annotations

import json
import math

import pytest

from masking_lab.core.errors import CalibrationError
from masking_lab.formats.calibration import (
    Calibration,
    calibration_path,
    load_calibration,
    read_calibration,
    record_al,
    require,
    with_al,
    write_calibration,
)
from masking_lab.formats.schemas import schema_errors


def test_recording_als_merges_per_stimulus_and_validates(tmp_path):
    cal, previous = record_al(
        tmp_path, "S01", "EV270", -14.5, "S01/a.jsonl", "2024-01-01T00:00:00Z"
    )
    assert previous is None
    cal, previous = record_al(
        tmp_path, "S01", "MV120", -26.0, "S01/b.jsonl", "2024-01-02T00:00:00Z"
    )
    assert previous is None
    cal, previous = record_al(
        tmp_path, "S01", "EV270", -13.0, "S01/b.jsonl", "2024-01-03T00:00:00Z"
    )
    assert previous == -14.5
    path = calibration_path(tmp_path, "S01")
    assert path == tmp_path / "S01" / "calibration.json"
    data = json.loads(path.read_text(encoding="utf-8"))
    assert schema_errors(data, "calibration") == []
    assert data["unmasked_al_db_v"] == {"EV270": -13.0, "MV120": -26.0}
    assert data["sources"] == ["S01/a.jsonl", "S01/b.jsonl"]
    assert data["updated_utc"] == "2024-01-03T00:00:00Z"
    assert read_calibration(path) == cal
    # Atomic replace leaves no temporary files behind.
    assert sorted(p.name for p in path.parent.iterdir()) == ["calibration.json"]


def test_missing_file_is_an_empty_calibration(tmp_path):
    cal = load_calibration(tmp_path, "S02")
    assert cal == Calibration(participant="S02")
    assert cal.missing(["EV270", "MV120"]) == ["EV270", "MV120"]


def test_require_names_missing_stimuli_and_the_baseline_command(tmp_path):
    cal = Calibration("S01", {"EV270": -14.0})
    require(cal, ["EV270"], tmp_path)  # complete: no error
    with pytest.raises(CalibrationError) as info:
        require(cal, ["EV270", "MV180", "MV120"], tmp_path)
    message = str(info.value)
    assert "no unmasked AL for MV120, MV180" in message
    assert "calibrated: EV270" in message
    assert "masking-lab run protocols/baseline.yaml --participant S01" in message


def test_invalid_json_names_the_line(tmp_path):
    path = calibration_path(tmp_path, "S01")
    path.parent.mkdir()
    path.write_text('{\n  "participant": "S01",\n  oops\n}\n', encoding="utf-8")
    with pytest.raises(CalibrationError, match=r"calibration\.json: line 3: not valid JSON"):
        load_calibration(tmp_path, "S01")


def test_schema_violation_names_the_key(tmp_path):
    path = calibration_path(tmp_path, "S01")
    path.parent.mkdir()
    bad = {"participant": "S01", "unmasked_al_db_v": {"EV270": "loud"}, "sources": []}
    path.write_text(json.dumps(bad), encoding="utf-8")
    with pytest.raises(CalibrationError, match=r"unmasked_al_db_v\.EV270"):
        load_calibration(tmp_path, "S01")


def test_calibration_of_another_participant_is_refused(tmp_path):
    write_calibration(tmp_path, Calibration("S01", {"EV270": -14.0}, ("x",)))
    (tmp_path / "S02").mkdir()
    calibration_path(tmp_path, "S01").rename(calibration_path(tmp_path, "S02"))
    with pytest.raises(CalibrationError, match="participant is 'S01' but the folder is 'S02'"):
        load_calibration(tmp_path, "S02")


def test_unreadable_file_is_a_calibration_error(tmp_path):
    with pytest.raises(CalibrationError, match="cannot read"):
        read_calibration(tmp_path / "nope.json")


@pytest.mark.parametrize(
    ("stimulus", "al", "message"),
    [
        ("EV270", math.inf, "finite"),
        ("EV270", math.nan, "finite"),
        ("XY12", -3.0, "not a stimulus"),
    ],
)
def test_bad_entries_are_refused(stimulus, al, message):
    with pytest.raises(CalibrationError, match=message):
        with_al(Calibration("S01"), stimulus, al, "log", "t")


def test_write_refuses_a_record_that_breaks_the_schema(tmp_path):
    with pytest.raises(CalibrationError, match="refusing to write"):
        write_calibration(tmp_path, Calibration("S01", {"not a stimulus": 1.0}))
    assert not calibration_path(tmp_path, "S01").exists()
