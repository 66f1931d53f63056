"""Participant metadata (issue 17): a protocol's info section, `run --info`, the session header,
and analyze's participants.tsv with its JSON sidecar."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from masking_lab.commands.cli import main
from masking_lab.core.errors import ProtocolError
from masking_lab.formats.protocol import load_protocol

ROOT = Path(__file__).resolve().parents[1]
INFO = """info:
  - {name: age, type: integer, required: true, unit: years}
  - {name: handedness, type: choice, choices: [left, right, ambidextrous], required: true}
  - {name: finger, type: choice, choices: [index, middle], description: finger on the plate}
  - {name: skin_temperature, type: number, unit: degC}
  - {name: notes, type: text, description: experimenter's notes}
"""


def _protocol(tmp_path: Path, info: str = INFO) -> Path:
    text = (ROOT / "protocols" / "baseline.yaml").read_text()
    path = tmp_path / "baseline_info.yaml"
    path.write_text(text.replace("kind: baseline\n", "kind: baseline\n" + info, 1))
    return path


def _run(protocol: Path, data: Path, *info: str) -> int:
    argv = ["run", str(protocol), "--participant", "S1", "--device", "sim", "--responder", "sim"]
    return main([*argv, "--data", str(data), *[a for kv in info for a in ("--info", kv)]])


def test_run_writes_the_metadata_into_the_header_and_analyze_into_participants_tsv(tmp_path):
    protocol = _protocol(tmp_path)
    data = tmp_path / "data"
    code = _run(protocol, data, "age=31", "handedness=right", "notes=cold room, 19 °C")
    assert code == 0
    (log,) = (data / "S1").glob("*.jsonl")
    header = json.loads(log.read_text().splitlines()[0])
    assert header["info"] == {"age": 31, "handedness": "right", "notes": "cold room, 19 °C"}
    out = tmp_path / "out"
    main(["analyze", str(data), "--out", str(out), "--quiet", "--figures", "none"])
    rows = [line.split("\t") for line in (out / "participants.tsv").read_text().splitlines()]
    assert rows[0] == [
        "participant_id", "n_sessions", "age", "handedness", "finger", "skin_temperature", "notes",
    ]  # fmt: skip
    assert rows[1] == ["S1", "1", "31", "right", "n/a", "n/a", "cold room, 19 °C"]
    sidecar = json.loads((out / "participants.json").read_text())
    assert set(sidecar) == set(rows[0])
    assert sidecar["age"]["Units"] == "years"
    assert sidecar["handedness"]["Levels"] == {v: v for v in ("left", "right", "ambidextrous")}
    assert sidecar["finger"]["Description"] == "finger on the plate"


def test_every_problem_with_the_metadata_is_named_at_once_before_anything_plays(tmp_path, capsys):
    protocol = _protocol(tmp_path)
    data = tmp_path / "data"
    assert _run(protocol, data, "agee=31", "handedness=up", "skin_temperature=warm") == 2
    err = capsys.readouterr().err
    assert "unknown field agee" in err
    assert "handedness: 'up' is not one of left, right, ambidextrous" in err
    assert "skin_temperature: 'warm' is not a number" in err
    assert "missing required age: give --info age=..." in err
    assert not data.exists() or not list(data.rglob("*.jsonl"))  # nothing was started


def test_info_given_to_a_protocol_without_an_info_section_is_refused(tmp_path, capsys):
    assert _run(ROOT / "protocols" / "baseline.yaml", tmp_path / "d", "age=3") == 2
    assert "has no info section" in capsys.readouterr().err


def test_the_protocol_schema_checks_the_info_section(tmp_path):
    bad = _protocol(tmp_path, "info:\n  - {name: age, type: date}\n")
    with pytest.raises(ProtocolError, match="info"):
        load_protocol(bad)
    assert load_protocol(_protocol(tmp_path)).content["info"][0]["name"] == "age"
