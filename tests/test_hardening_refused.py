"""`run` exits non-zero when every set was refused (issue 21.9): a session that "completes" by
refusing each set before its first trial measured nothing, and says so with exit 2; one set
played beside a refused one is a completed session (exit 0)."""

from __future__ import annotations

import json

from runner_support import of_kind, records, write_calibration, write_protocol

from masking_lab.commands.cli import main

CAL = {"EV270": -14.0, "MV120": -26.0}


def _run(tmp_path, sets, capsys):
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    protocol = write_protocol(tmp_path, sets=sets, randomize=False)
    code = main(
        [
            *("run", str(protocol), "--participant", "S01", "--data", str(data)),
            *("--device", "sim", "--responder", "sim", "--seed", "3", "--no-progress"),
        ]
    )
    (log,) = (data / "S01").glob("*.jsonl")
    return code, capsys.readouterr(), records(log)


def test_every_set_refused_exits_2_with_nothing_played(tmp_path, capsys):
    # 30 dB SL over an EV270 AL of -14 dB re 1 V is 16 dB re 1 V, above the rig's 5 V limit.
    sets = [
        {"id": "A20", "masker": "MV120", "masker_level_db_sl": 20, "start_level_db": 30},
        {"id": "A25", "masker": "MV120", "masker_level_db_sl": 25, "start_level_db": 30},
    ]
    code, out, recs = _run(tmp_path, sets, capsys)
    assert code == 2, out.err
    assert "every set was refused, nothing was played (2 sets: A20, A25)" in out.err
    assert "Traceback" not in out.err
    assert of_kind(recs, "trial") == []
    assert {f["set_id"] for f in of_kind(recs, "fault")} == {"A20", "A25"}
    assert [e["status"] for e in of_kind(recs, "set_end")] == ["aborted", "aborted"]
    assert json.dumps(of_kind(recs, "session_end"))  # the log itself is complete


def test_one_set_played_beside_a_refused_one_completes(tmp_path, capsys):
    sets = [
        {"id": "A10", "masker": "MV120", "masker_level_db_sl": 10},
        {"id": "A20", "masker": "MV120", "masker_level_db_sl": 20, "start_level_db": 30},
    ]
    code, out, recs = _run(tmp_path, sets, capsys)
    assert code == 0, out.err
    assert "every set was refused" not in out.err
    assert of_kind(recs, "trial") and of_kind(recs, "fault")[0]["set_id"] == "A20"
