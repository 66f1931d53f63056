"""Logs → thresholds table: re-estimation, unmasked-AL sources, statuses that never average."""

from __future__ import annotations

import json

import pytest

from masking_lab.analysis.thresholds import (
    EstimatorSettings,
    session_rows,
    shifts_long,
    thresholds_table,
)
from masking_lab.core.errors import AnalysisError
from masking_lab.core.psychometric import LEVITT_1U3D
from masking_lab.formats.session_log import SessionLogWriter, read_log
from masking_lab.procedures.estimators import ml_threshold

REVERSALS = [12.0, 4.0, 8.0, 2.0, 6.0, 4.0, 6.0, 2.0, 4.0, 2.0, 6.0]  # last 8 average 4.0


def _set(
    set_id, target, masker, level, unit, *, reversals=REVERSALS, status="completed", offset=0.0
):
    """Records of one set whose trials sit exactly on the given reversal levels (+ offset)."""
    start = {
        "record": "set_start",
        "set_id": set_id,
        "target": target,
        "masker": masker,
        "masker_level_db_sl": level,
        "level_unit": unit,
        "staircase": {"n_reversals_averaged": 8, "n_up": 1, "n_down": 3, "down_up_ratio": 1.0},
    }
    trials = []
    for i, lv in enumerate(reversals):
        lv = lv + offset
        trials.append(
            {
                "record": "trial",
                "set_id": set_id,
                "trial_index": i,
                "level_db_sl": lv if unit == "db_sl" else None,
                "level_db_v": lv if unit == "db_v" else lv - 20.0,
                "correct": i % 2 == 0,
                "reversal": True,
            }
        )
    end = {
        "record": "set_end",
        "set_id": set_id,
        "status": status,
        "al_db": None,
        "n_trials": len(trials),
        "reversal_levels_db": [v + offset for v in reversals],
    }
    return [start, *trials, end]


def _write(
    path,
    participant,
    experiment,
    records,
    calibration=None,
    created="2024-01-01T10:00:00Z",
    session_id=None,
):
    header = {
        "schema_version": 1,
        "session_id": session_id or f"{participant}-{experiment}",
        "created_utc": created,
        "protocol": {"experiment": experiment},
        "participant": participant,
        "calibration": calibration or {},
    }
    with SessionLogWriter.create(path, header) as w:
        for r in records:
            w.append(r)
    return read_log(path)


def _rows(logs, settings=None):
    rows = []
    for log in logs:
        rows += session_rows(log, log.path.name, settings or EstimatorSettings())
    return rows


def test_masked_al_shift_from_the_baseline_log(tmp_path):
    base = _write(
        tmp_path / "b.jsonl",
        "S1",
        "baseline",
        _set("EV270", "EV270", None, None, "db_v", offset=-20.0),  # AL −16 dB re 1 V
    )
    masked = _write(
        tmp_path / "m.jsonl",
        "S1",
        "experiment1",
        _set("MV120_10", "EV270", "MV120", 10.0, "db_sl", offset=1.0),  # AL 5 dB SL
        calibration={"EV270": -15.0, "MV120": -26.0},
        created="2024-01-02T10:00:00Z",
    )
    table = thresholds_table(_rows([base, masked]))
    row = table[table["experiment"] == "experiment1"].iloc[0]
    assert row["al_db_sl"] == pytest.approx(5.0)
    assert row["al_db_v"] == pytest.approx(-10.0)  # 5 dB SL on a −15 dB re 1 V calibration
    assert row["unmasked_al_db_v"] == pytest.approx(-16.0)  # from the baseline log
    assert row["shift_db"] == pytest.approx(6.0)
    assert row["unmasked_source"] == "baseline"
    assert (row["masker_frequency_hz"], row["mv_stimulus"], row["mv_frequency_hz"]) == (
        120.0,
        "MV120",
        120.0,
    )
    base_row = table[table["experiment"] == "baseline"].iloc[0]
    assert base_row["al_db_v"] == pytest.approx(-16.0) and base_row["masker"] is None

    cal = thresholds_table(_rows([base, masked]), unmasked_al="calibration")
    row = cal[cal["experiment"] == "experiment1"].iloc[0]
    assert row["shift_db"] == pytest.approx(5.0) and row["unmasked_source"] == "calibration"


def test_experiment2_frequency_factor_is_the_target(tmp_path):
    log = _write(
        tmp_path / "m.jsonl",
        "S1",
        "experiment2",
        _set("MV180_EV270_05", "MV180", "EV270", 5.0, "db_sl"),
        calibration={"MV180": -30.0, "EV270": -14.0},
    )
    row = thresholds_table(_rows([log])).iloc[0]
    assert row["masker_frequency_hz"] == 270.0
    assert (row["mv_stimulus"], row["mv_frequency_hz"]) == ("MV180", 180.0)
    assert row["unmasked_source"] == "calibration"  # auto: no baseline log → header


def test_participant_without_baseline(tmp_path):
    log = _write(
        tmp_path / "m.jsonl",
        "S2",
        "experiment1",
        _set("MV120_10", "EV270", "MV120", 10.0, "db_sl"),
        calibration={"EV270": -15.0},
    )
    strict = thresholds_table(_rows([log]), unmasked_al="baseline").iloc[0]
    assert strict["status"] == "no_baseline"
    assert "S2 has no completed baseline AL for EV270" in strict["note"]
    assert "--unmasked-al calibration" in strict["note"]
    assert shifts_long(thresholds_table(_rows([log]), unmasked_al="baseline")).empty
    # Without any calibration for the target, even the header cannot help.
    bare = _write(
        tmp_path / "bare.jsonl",
        "S3",
        "experiment1",
        _set("MV120_10", "EV270", "MV120", 10.0, "db_sl"),
    )
    row = thresholds_table(_rows([bare])).iloc[0]
    assert row["status"] == "no_baseline" and "no calibration for EV270" in row["note"]


@pytest.mark.parametrize("status", ["ceiling", "floor", "aborted", "trial_cap"])
def test_unfinished_staircases_are_listed_never_averaged(tmp_path, status):
    log = _write(
        tmp_path / "m.jsonl",
        "S1",
        "experiment1",
        _set("MV270_25", "EV270", "MV270", 25.0, "db_sl", status=status),
        calibration={"EV270": -15.0},
    )
    table = thresholds_table(_rows([log]))
    row = table.iloc[0]
    assert row["status"] == status
    assert row["shift_db"] is None and row["al_db_v"] is None
    assert "not a threshold" in row["note"]
    assert shifts_long(table).empty


def test_set_without_end_is_incomplete(tmp_path):
    records = _set("MV120_05", "EV270", "MV120", 5.0, "db_sl")[:-1]
    log = _write(tmp_path / "m.jsonl", "S1", "experiment1", records, calibration={"EV270": -15.0})
    row = thresholds_table(_rows([log])).iloc[0]
    assert row["status"] == "incomplete" and "stopped mid-set" in row["note"]


def test_later_completed_attempt_supersedes_the_earlier(tmp_path):
    cal = {"EV270": -15.0}
    first = _write(
        tmp_path / "a.jsonl",
        "S1",
        "experiment1",
        _set("MV120_05", "EV270", "MV120", 5.0, "db_sl"),
        calibration=cal,
        created="2024-01-01T10:00:00Z",
        session_id="first",
    )
    second = _write(
        tmp_path / "b.jsonl",
        "S1",
        "experiment1",
        _set("MV120_05", "EV270", "MV120", 5.0, "db_sl", offset=2.0),
        calibration=cal,
        created="2024-01-03T10:00:00Z",
        session_id="second",
    )
    table = thresholds_table(_rows([second, first]))  # input order must not matter
    by_session = dict(zip(table["session_id"], table["status"], strict=True))
    assert by_session == {"first": "superseded", "second": "completed"}
    assert shifts_long(table)["shift_db"].tolist() == [pytest.approx(6.0)]


def test_reversal_count_setting_and_ml_estimator(tmp_path):
    log = _write(
        tmp_path / "m.jsonl",
        "S1",
        "experiment1",
        _set("MV120_05", "EV270", "MV120", 5.0, "db_sl"),
        calibration={"EV270": -15.0},
    )
    last4 = thresholds_table(_rows([log], EstimatorSettings(n_reversals_averaged=4))).iloc[0]
    assert last4["al_db_sl"] == pytest.approx((2 + 4 + 2 + 6) / 4)
    too_many = thresholds_table(_rows([log], EstimatorSettings(n_reversals_averaged=12))).iloc[0]
    assert too_many["status"] == "estimator_failed" and "only 11 reversals" in too_many["note"]
    ml = thresholds_table(_rows([log], EstimatorSettings(estimator="ml"))).iloc[0]
    assert ml["estimator"] == "ml" and ml["status"] == "completed"
    # The ML estimator sees the trials in the set's unit (dB SL) and the staircase's target p.
    trials = log.sets()["MV120_05"].trials
    direct = ml_threshold(
        [t["level_db_sl"] for t in trials], [t["correct"] for t in trials], p_target=LEVITT_1U3D
    )
    assert ml["al_db_sl"] == pytest.approx(direct.threshold_db)
    records = _set("MV120_10", "EV270", "MV120", 10.0, "db_sl")
    for r in records[1:-1]:
        r["correct"] = True
    all_right = _write(
        tmp_path / "r.jsonl", "S1", "experiment1", records, calibration={"EV270": -15.0}
    )
    failed = thresholds_table(_rows([all_right], EstimatorSettings(estimator="ml"))).iloc[0]
    assert failed["status"] == "estimator_failed" and "every answer was correct" in failed["note"]
    with pytest.raises(AnalysisError, match="unknown estimator"):
        EstimatorSettings(estimator="median")


def test_bad_trial_records_make_the_set_invalid(tmp_path):
    records = _set("MV120_05", "EV270", "MV120", 5.0, "db_sl")
    del records[3]["level_db_sl"]
    log = _write(tmp_path / "m.jsonl", "S1", "experiment1", records, calibration={"EV270": -15.0})
    row = thresholds_table(_rows([log])).iloc[0]
    assert row["status"] == "invalid" and "level_db_sl" in row["note"]


def test_disagreeing_reversal_flags_use_the_set_end_list(tmp_path):
    records = _set("MV120_05", "EV270", "MV120", 5.0, "db_sl")
    records[5]["reversal"] = False  # e.g. a line lost and rewritten
    log = _write(tmp_path / "m.jsonl", "S1", "experiment1", records, calibration={"EV270": -15.0})
    row = thresholds_table(_rows([log])).iloc[0]
    assert row["al_db_sl"] == pytest.approx(4.0)
    assert "used set_end's reversals" in row["note"]


def test_unusable_set_start_is_invalid(tmp_path):
    records = _set("X", "EV270", "MV120", 5.0, "db_sl")
    records[0]["target"] = "banana"
    log = _write(tmp_path / "m.jsonl", "S1", "experiment1", records, calibration={"EV270": -15.0})
    row = thresholds_table(_rows([log])).iloc[0]
    assert row["status"] == "invalid" and "set_start unusable" in row["note"]


def test_unknown_unmasked_source_is_refused():
    with pytest.raises(AnalysisError, match="unmasked-AL source"):
        thresholds_table([], unmasked_al="guess")


def test_rows_are_sorted_deterministically(tmp_path):
    logs = []
    for i, level in enumerate([25.0, 5.0, 15.0]):
        logs.append(
            _write(
                tmp_path / f"{i}.jsonl",
                "S1",
                "experiment1",
                _set(f"MV120_{level:g}", "EV270", "MV120", level, "db_sl"),
                calibration={"EV270": -15.0},
                session_id=f"s{i}",
            )
        )
    table = thresholds_table(_rows(logs))
    assert table["masker_level_db_sl"].tolist() == [5.0, 15.0, 25.0]
    assert json.dumps(table.to_dict("records"), default=str) == json.dumps(
        thresholds_table(_rows(logs[::-1])).to_dict("records"), default=str
    )


def test_each_pair_gets_its_own_frequency_columns_however_the_rows_interleave():
    # The pairs' columns are worked out once per (target, masker): rows of experiment I (the
    # masker is the MV stimulus) and II (the target is) interleaved must each get their own.
    pairs = [("EV270", "MV120"), ("MV180", "EV270"), ("EV270", "MV120"), ("MV270", "EV270")]
    rows = [
        {"participant": f"P{k}", "experiment": "e", "set_id": f"S{k}", "target": t, "masker": m,
         "masker_level_db_sl": 10.0, "status": "completed", "al_db_v": -20.0, "log": f"{k}.jsonl"}
        for k, (t, m) in enumerate(pairs)
    ]  # fmt: skip
    table = thresholds_table(rows, unmasked_al="calibration")
    got = table[["target", "masker_frequency_hz", "mv_stimulus", "mv_frequency_hz"]]
    assert got.values.tolist() == [
        ["EV270", 120.0, "MV120", 120.0],
        ["MV180", 270.0, "MV180", 180.0],
        ["EV270", 120.0, "MV120", 120.0],
        ["MV270", 270.0, "MV270", 270.0],
    ]
    with pytest.raises(Exception, match="stimulus"):  # a malformed name fails as before
        thresholds_table([{**rows[0], "masker": "XX9"}])
