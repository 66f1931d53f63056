"""The session runner on the in-process `sim` device: logs, calibration, levels, refusals, CLI."""

from __future__ import annotations

import io
import itertools
import json
import math
import os
import re
import signal

import pytest
import yaml
from runner_support import (
    REPO,
    assert_valid_log,
    of_kind,
    only_log,
    records,
    timeless,
    trials,
    write_calibration,
    write_device_config,
    write_protocol,
)

from masking_lab.commands.cli import main
from masking_lab.core.errors import CalibrationError, MaskingLabError, ProtocolError
from masking_lab.formats.protocol import load_protocol
from masking_lab.session.runner import RunOptions, SessionInterrupted, SessionSignals, run_session

CAL = {"EV270": -14.0, "MV120": -26.0, "MV180": -30.0, "MV270": -32.0}


def run(tmp_path, protocol, **kw):
    opts = {
        "participant": "S01",
        "device": "sim",
        "responder": "sim",
        "data_dir": tmp_path / "data",
    }
    opts.update(kw)
    return run_session(RunOptions(protocol=protocol, **opts), stream=io.StringIO())


def test_baseline_session_logs_every_trial_and_writes_the_calibration(tmp_path):
    protocol = write_protocol(tmp_path, kind="baseline", experiment="base")
    result = run(tmp_path, protocol, seed=5)
    assert result.exit_code == 0
    log = only_log(tmp_path / "data", experiment="base")
    assert result.log_path == log
    assert re.fullmatch(r"base-S01-\d{8}T\d{6}Z\.jsonl", log.name)
    recs = assert_valid_log(log)
    header = recs[0]
    assert header["seed"] == 5 and header["participant"] == "S01"
    assert header["set_order"] == load_protocol(protocol).set_order(5)
    assert header["device"]["backend"] == "sim" and header["clock"] == "virtual"
    assert header["calibration"] == {}
    assert header["protocol"]["content"]["experiment"] == "base"
    assert [r["record"] for r in recs[1:]][-1] == "session_end"

    cal = json.loads((tmp_path / "data" / "S01" / "calibration.json").read_text())
    for set_id, stimulus in (("EV", "EV270"), ("MV", "MV120")):
        ts = trials(recs, set_id)
        assert [t["trial_index"] for t in ts] == list(range(len(ts)))
        assert all(t["level_db_sl"] is None for t in ts)
        assert all(t["correct"] == (t["target_interval"] == t["response_interval"]) for t in ts)
        # The AL is the mean of the last 4 reversal levels, recomputed from the trial records.
        reversal_levels = [t["level_db_v"] for t in ts if t["reversal"]]
        (end,) = [r for r in of_kind(recs, "set_end") if r["set_id"] == set_id]
        assert end["status"] == "completed" and end["n_trials"] == len(ts)
        assert end["reversal_levels_db"] == reversal_levels
        assert end["al_db"] == pytest.approx(sum(reversal_levels[-4:]) / 4)
        assert end["al_db_v"] == end["al_db"] and end["al_db_sl"] is None
        assert cal["unmasked_al_db_v"][stimulus] == pytest.approx(end["al_db"])
        # Each trial's level follows from the previous one by the staircase's step.
        for a, b in itertools.pairwise(ts):
            assert b["level_db_v"] == pytest.approx(a["next_level_db"])
    assert cal["sources"] == [f"S01/{log.name}"]
    assert [o.status for o in result.outcomes] == ["completed", "completed"]


def test_masked_session_places_levels_with_the_calibration(tmp_path):
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    protocol = write_protocol(tmp_path)
    result = run(tmp_path, protocol, seed=3)
    assert result.exit_code == 0
    recs = assert_valid_log(result.log_path)
    assert recs[0]["calibration"] == {"EV270": -14.0, "MV120": -26.0}
    for start in of_kind(recs, "set_start"):
        assert start["level_unit"] == "db_sl" and start["unmasked_al_db_v"] == -14.0
        assert start["masker_level_db_v"] == pytest.approx(-26.0 + start["masker_level_db_sl"])
        # Reference rig: EV limit 5 V = 13.98 dB re 1 V = 27.98 dB SL, below the protocol's 40.
        assert start["max_level_db"] == pytest.approx(20 * math.log10(5.0) + 14.0)
        ts = trials(recs, start["set_id"])
        assert ts
        for t in ts:
            assert t["level_db_v"] == pytest.approx(t["level_db_sl"] - 14.0)
            # requested as calibrated; played as the 12-bit, 10 V converter renders it at the
            # logged attenuator step (within one LSB there)
            extra = t["device_extra"]
            assert extra["requested_target_v"] == pytest.approx(10 ** (t["level_db_v"] / 20))
            lsb = 20 / 4096 / 10 ** (extra["target_att_db"] / 20)
            assert abs(t["played_target_v"] - extra["requested_target_v"]) <= lsb / 2 + 1e-6
            masker_v = 10 ** (start["masker_level_db_v"] / 20)
            assert extra["requested_masker_v"] == pytest.approx(masker_v)
            m_lsb = 20 / 4096 / 10 ** (extra["masker_att_db"] / 20)
            assert abs(t["played_masker_v"] - masker_v) <= m_lsb / 2 + 1e-6
    ends = of_kind(recs, "set_end")
    assert all(e["al_db_v"] == pytest.approx(e["al_db_sl"] - 14.0) for e in ends)


def test_masked_session_without_calibration_refuses_to_start(tmp_path):
    data = tmp_path / "data"
    write_calibration(data, "S01", {"EV270": -14.0})
    protocol = write_protocol(tmp_path)
    with pytest.raises(CalibrationError) as info:
        run(tmp_path, protocol)
    assert "no unmasked AL for MV120" in str(info.value)
    assert "masking-lab run protocols/baseline.yaml --participant S01" in str(info.value)
    assert list((data / "S01").glob("*.jsonl")) == []


def test_sets_subset_runs_only_those_in_the_seed_order(tmp_path):
    write_calibration(tmp_path / "data", "S01", CAL)
    sets = [
        {"id": f"M{level}", "masker": "MV120", "masker_level_db_sl": level} for level in (5, 10, 15)
    ]
    protocol = write_protocol(tmp_path, sets=sets)
    order = load_protocol(protocol).set_order(9)
    wanted = [order[2], order[0]]
    result = run(tmp_path, protocol, seed=9, sets=tuple(wanted))
    recs = records(result.log_path)
    assert recs[0]["set_order"] == [order[0], order[2]]
    assert [r["set_id"] for r in of_kind(recs, "set_start")] == [order[0], order[2]]
    with pytest.raises(ProtocolError, match=r"--sets names 'M99'.*its sets are"):
        run(tmp_path, protocol, seed=9, sets=("M99",))


@pytest.mark.parametrize("participant", ["", "../S01", "S 01", "-x"])
def test_participant_ids_that_cannot_name_a_folder_are_refused(tmp_path, participant):
    protocol = write_protocol(tmp_path, kind="baseline")
    with pytest.raises(MaskingLabError, match="--participant"):
        run(tmp_path, protocol, participant=participant)


def test_seed_is_drawn_and_logged_when_not_given(tmp_path):
    protocol = write_protocol(tmp_path, kind="baseline")
    result = run(tmp_path, protocol)
    header = records(result.log_path)[0]
    assert isinstance(header["seed"], int) and 0 <= header["seed"] < 2**32
    assert header["set_order"] == load_protocol(protocol).set_order(header["seed"])


def test_same_seed_same_trials_other_seed_other_trials(tmp_path):
    protocol = write_protocol(tmp_path, kind="baseline")
    a = records(run(tmp_path / "a", protocol, seed=21).log_path)
    b = records(run(tmp_path / "b", protocol, seed=21).log_path)
    c = records(run(tmp_path / "c", protocol, seed=22).log_path)
    assert timeless(a) == timeless(b)
    assert timeless(a) != timeless(c)


def test_a_masker_the_device_cannot_drive_aborts_that_set_only(tmp_path):
    write_calibration(tmp_path / "data", "S01", CAL)
    # MV limit 0.3 V = -10.5 dB re 1 V: a masker at 10 dB SL (-16) fits, at 20 dB SL (-6) does not.
    config = write_device_config(tmp_path, channels__MV__max_drive_v=0.3)
    protocol = write_protocol(tmp_path)
    result = run(tmp_path, protocol, seed=1, device_config=config)
    assert result.exit_code == 0
    recs = assert_valid_log(result.log_path)
    assert trials(recs, "A20") == [] and trials(recs, "A10")
    (fault,) = of_kind(recs, "fault")
    assert fault["kind"] == "level_refused" and fault["set_id"] == "A20"
    assert "masker MV120 at 20 dB SL" in fault["message"]
    end = {e["set_id"]: e for e in of_kind(recs, "set_end")}
    assert end["A20"]["status"] == "aborted" and end["A20"]["al_db"] is None
    assert "exceeds the device limit" in end["A20"]["reason"]
    assert end["A10"]["status"] == "completed"
    assert {o.set_id: o.status for o in result.outcomes} == {"A10": "completed", "A20": "aborted"}


def test_a_track_pinned_at_the_device_limit_is_a_ceiling_not_a_threshold(tmp_path):
    truth = yaml.safe_load((REPO / "protocols" / "simulation" / "ground_truth.yaml").read_text())
    truth["unmasked_al_db_v"]["EV270"] = 40.0  # far above the reference rig's 5 V (14 dB re 1 V)
    gt = tmp_path / "truth.yaml"
    gt.write_text(yaml.safe_dump(truth), encoding="utf-8")
    protocol = write_protocol(tmp_path, kind="baseline")
    result = run(tmp_path, protocol, seed=4, ground_truth=gt)
    recs = assert_valid_log(result.log_path)
    end = {e["set_id"]: e for e in of_kind(recs, "set_end")}
    assert end["EV"]["status"] == "ceiling"
    assert end["EV"]["al_db"] is None and end["EV"]["al_db_v"] is None
    assert "ceiling, not a threshold" in end["EV"]["reason"]
    assert trials(recs, "EV")[-1]["level_db_v"] == pytest.approx(20 * math.log10(5.0))
    cal = json.loads((tmp_path / "data" / "S01" / "calibration.json").read_text())
    assert "EV270" not in cal["unmasked_al_db_v"] and "MV120" in cal["unmasked_al_db_v"]
    assert recs[0]["simulated_observer"]["truth"]["unmasked_al_db_v"]["EV270"] == 40.0


def test_progress_line_shows_set_trial_reversals_level_and_time_left(tmp_path):
    protocol = write_protocol(tmp_path, kind="baseline")
    stream = io.StringIO()
    run_session(
        RunOptions(protocol, "S01", data_dir=tmp_path / "d", seed=2, progress=True), stream=stream
    )
    lines = stream.getvalue().splitlines()
    pattern = re.compile(
        r"set [12]/2 (EV|MV) \| trial \d+ \| reversals [0-4]/5 \| level -?\d+\.\d dB re 1 V \| "
        r"~\d+ (s|min) left"
    )
    progress = [line for line in lines if line.startswith("set ") and " | " in line]
    assert progress and all(pattern.fullmatch(line) for line in progress), progress[:3]
    assert any(line.startswith("set done: ") for line in lines)
    quiet = io.StringIO()
    run_session(RunOptions(protocol, "S01", data_dir=tmp_path / "q", seed=2), stream=quiet)
    assert not any(" | trial " in line for line in quiet.getvalue().splitlines())


def test_rest_between_sets_passes_on_the_virtual_clock(tmp_path):
    protocol = write_protocol(tmp_path, kind="baseline", timing={"rest_between_sets_s": 300})
    recs = records(run(tmp_path, protocol, seed=2).log_path)
    first_end, second_start = of_kind(recs, "set_end")[0], of_kind(recs, "set_start")[1]
    assert second_start["t_s"] >= first_end["t_s"] + 300


def test_real_time_option_runs_on_the_real_clock(tmp_path):
    tiny = {"stimulus_s": 0.01, "gap_s": 0.005, "lead_in_s": 0.005}
    protocol = write_protocol(
        tmp_path, kind="baseline", sets=[{"id": "EV", "target": "EV270"}], timing=tiny
    )
    result = run(tmp_path, protocol, seed=2, real_time=True)
    recs = records(result.log_path)
    assert recs[0]["clock"] == "real"
    ts = trials(recs)
    starts = [t["planned_onsets_s"][0] for t in ts]
    assert all(b > a for a, b in itertools.pairwise(starts))


def test_cli_run_prints_the_log_and_one_line_per_set(tmp_path, capsys):
    protocol = write_protocol(tmp_path, kind="baseline")
    code = main(
        [
            "run",
            str(protocol),
            "--participant",
            "S01",
            "--device",
            "sim",
            "--responder",
            "sim",
            "--data",
            str(tmp_path / "data"),
            "--seed",
            "3",
        ]
    )
    out = capsys.readouterr().out
    assert code == 0
    assert f"log: {only_log(tmp_path / 'data')}" in out
    assert re.search(r"^  EV\s+completed\s+AL -?\d+\.\d\d dB re 1 V \(\d+ trials\)$", out, re.M)
    assert re.search(r"^  MV\s+completed", out, re.M)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--participant", "a b"], "--participant 'a b'"),
        (["--participant", "S01", "--sets", "NOPE"], "--sets names 'NOPE'"),
        (["--participant", "S01", "--ground-truth", "/nonexistent.yaml"], "cannot read"),
        (["--participant", "S01", "--device", "bogus"], "--device 'bogus': choose sim"),
    ],
)
def test_cli_bad_input_exits_2_with_a_message_and_no_traceback(tmp_path, capsys, extra, message):
    protocol = write_protocol(tmp_path, kind="baseline")
    args = ["run", str(protocol), "--responder", "sim", "--data", str(tmp_path / "d")]
    if "--device" not in extra:
        args += ["--device", "sim"]
    code = main(args + extra)
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("masking-lab run: error: ") and message in err
    assert "Traceback" not in err


def test_cli_refuses_a_masked_session_without_calibration(tmp_path, capsys):
    protocol = write_protocol(tmp_path)
    code = main(
        [
            "run",
            str(protocol),
            "--participant",
            "S09",
            "--device",
            "sim",
            "--responder",
            "sim",
            "--data",
            str(tmp_path / "d"),
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and "no unmasked AL for EV270, MV120" in err


def test_cli_a_device_that_cannot_be_opened_exits_3_before_anything_is_logged(tmp_path, capsys):
    protocol = write_protocol(tmp_path, kind="baseline")
    code = main(
        ["run", str(protocol), "--participant", "S01", "--device", f"serial:{tmp_path}/nope",
         "--responder", "sim", "--data", str(tmp_path / "d")]
    )  # fmt: skip
    err = capsys.readouterr().err
    assert code == 3
    assert "masking-lab run: device error: cannot open serial port" in err
    assert "Nothing was played" in err and "Traceback" not in err
    assert not (tmp_path / "d").exists() or not list((tmp_path / "d").rglob("*.jsonl"))


def test_signals_wait_until_the_record_is_written():
    before = signal.getsignal(signal.SIGTERM)
    written = []
    with pytest.raises(SessionInterrupted) as info, SessionSignals() as signals:
        with signals.deferred():
            os.kill(os.getpid(), signal.SIGTERM)
            written.append("record")  # still runs: the signal waits for the block to end
        written.append("next trial")  # never runs
    assert written == ["record"]
    assert info.value.signum == signal.SIGTERM
    assert signal.getsignal(signal.SIGTERM) is before
    with pytest.raises(SessionInterrupted), SessionSignals():
        os.kill(os.getpid(), signal.SIGINT)
