"""Campaign findings fixed after the merge (issue 21): a resumed log whose trial has no usable
'correct', and a header whose simulated observer lost its truth, are clean errors."""

from __future__ import annotations

import pytest

from masking_lab.core.clock import VirtualClock
from masking_lab.core.errors import LogError
from masking_lab.session.opening import ResponderContext
from masking_lab.session.procedure_records import settings_from_record
from masking_lab.session.threshold_plan import check_trials


class _Rec:
    def __init__(self, start, trials):
        self.start, self.trials = start, trials


@pytest.mark.parametrize("correct", [None, "yes", 1])
def test_a_trial_without_a_true_or_false_answer_cannot_be_resumed(tmp_path, correct):
    from masking_lab.formats.protocol import load_protocol
    from masking_lab.formats.resources import shipped

    protocol = load_protocol(shipped("protocols", "baseline.yaml"))
    spec = protocol.sets[0]
    level = settings_from_record({}, spec).start().next_level()  # the logged level is right
    key = "level_db_sl" if protocol.level_unit == "db_sl" else "level_db_v"
    trial = {"trial_index": 0, key: level}
    if correct is not None:
        trial["correct"] = correct
    with pytest.raises(LogError, match="'correct' is"):
        check_trials(tmp_path / "log.jsonl", protocol, {spec.id: _Rec({}, [trial])})


@pytest.mark.parametrize(
    "observer",
    [
        {"population_seed": 3},
        {"truth": "x", "population_seed": 3},
        {"truth": {}, "population_seed": "3"},
    ],
)
def test_a_simulated_observer_without_its_truth_is_a_clean_error(observer):
    context = ResponderContext("P01", 1, VirtualClock(), simulated_observer=observer)
    with pytest.raises(LogError, match="simulated_observer lacks"):
        context.simulated_truth()


# -- campaign finding: protocols that validated but took minutes of computing to run -----------


def _protocol(tmp_path, **procedure):
    import yaml

    from masking_lab.formats.resources import shipped

    data = yaml.safe_load(shipped("protocols", "experiment1_questplus.yaml").read_text())
    data["procedure"].update(procedure)
    path = tmp_path / "protocol.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def test_a_session_whose_placements_would_take_minutes_is_refused_by_validate(tmp_path, capsys):
    from masking_lab.commands.cli import main

    # 3,251 levels × 3,251 thresholds fit in memory, but 500 trials × 15 sets scanning them
    # took minutes of computing in the simulator (slope and lapse known: the marginalised
    # default grid would exceed the memory limit first).
    path = _protocol(tmp_path, level_step_db=0.02, max_trials=500, scales_db=1.5, lapses=0.02)
    assert main(["validate", str(path)]) == 1
    err = capsys.readouterr()
    text = err.out + err.err
    assert "sets (line" in text and "table cells" in text and "limit is 1e+09" in text
    assert "Traceback" not in text


def test_too_many_trials_in_one_session_are_refused(tmp_path):
    import yaml

    from masking_lab.core.errors import ProtocolError
    from masking_lab.formats.protocol import load_protocol
    from masking_lab.formats.resources import shipped

    data = yaml.safe_load(shipped("protocols", "experiment1.yaml").read_text())
    data["staircase"]["max_trials"] = 5000  # 15 sets × 5,000 trials
    path = tmp_path / "long.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    with pytest.raises(ProtocolError, match="up to 75000 trials; the limit is 10000"):
        load_protocol(path)
    data["sets"] = data["sets"][:2]  # 10,000 trials: at the limit, accepted
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    assert len(load_protocol(path).sets) == 2


def test_the_shipped_protocols_are_within_the_session_limits():
    from masking_lab.formats.protocol import load_protocol
    from masking_lab.formats.resources import shipped
    from masking_lab.procedures.limits import (
        MAX_SESSION_TRIALS,
        MAX_SESSION_WORK,
        trial_work,
    )

    for name in ("baseline", "experiment1", "experiment2", "experiment1_questplus"):
        p = load_protocol(shipped("protocols", f"{name}.yaml"))
        assert sum(s.trial_cap for s in p.sets) <= MAX_SESSION_TRIALS
        assert sum(s.trial_cap * trial_work(s.settings) for s in p.sets) <= MAX_SESSION_WORK
    p = load_protocol(shipped("protocols", "experiment1_functional.yaml"))
    assert 0 < sum(s.trial_cap * trial_work(s.settings) for s in p.sets) <= MAX_SESSION_WORK


# -- campaign finding (seed 41): a hostile level in a log overflowed the played-level check ----


@pytest.mark.parametrize(
    "fields",
    [
        {"level_db_v": 1e5},  # 10 ** (1e5 / 20) overflows a float
        {"level_db_v": -1e5, "played_target_v": 1e300},
        {"device_extra": {"requested_target_v": 1e308}, "played_target_v": 1e-300},
        {"device_extra": {"requested_target_v": float("inf")}},
        {"played_target_v": float("nan")},
    ],
)
def test_hostile_played_levels_are_a_note_or_nothing_never_a_traceback(fields):
    from masking_lab.analysis.played_levels import played_level_problems

    trial = {"record": "trial", "set_id": "A", "trial_index": 0, "level_db_v": -40.0}
    trial["played_target_v"] = 0.0105
    trial.update(fields)
    notes = played_level_problems([trial], [7])
    assert notes == [] or notes[0].startswith("line 7: 1 trial(s) played more than 0.1 dB off")
    if fields.get("level_db_v") == 1e5:
        assert notes  # 0.0105 V is far below a 1e5 dB request: named, not skipped


# -- campaign finding (seed 44, hostile boards): a HELLO sample rate no board can have ---------


@pytest.mark.parametrize("fs", ["nan", "inf", "-1", "0", "1e999", "1e308"])
def test_a_hello_whose_sample_rate_is_not_a_positive_finite_number_is_refused(fs):
    from masking_lab.device import protocol as proto

    line = proto.encode_ok(1, {"proto": 1, "max_ev": 5.0, "max_mv": 10.0, "wd_ms": 0})
    body = line[: line.rindex(b"*")].decode() + f" fs={fs}"
    frame = proto.decode(body.encode() + b"*" + f"{proto.crc16(body.encode()):04X}".encode())
    with pytest.raises(proto.FrameError, match=r"fs|number"):
        proto.parse_hello(frame)
    good = body.replace(f"fs={fs}", "fs=20000")
    ok = proto.decode(good.encode() + b"*" + f"{proto.crc16(good.encode()):04X}".encode())
    assert proto.parse_hello(ok).max_v["EV"] == 5.0


# -- campaign findings (seed 46): a deeply nested log line, a converter whose LSB is nothing ---


def test_a_log_line_nested_deeper_than_the_fast_decoder_recurses_is_a_problem_not_a_traceback(
    tmp_path,
):
    from masking_lab.analysis.log_reading import fast_parse
    from masking_lab.commands.cli import main
    from masking_lab.simulation.synthetic_logs import simulate_study

    simulate_study(tmp_path / "data", n_participants=1, seed=5, baseline_start_above_db=10.0)
    log = next((tmp_path / "data").rglob("*experiment1.jsonl"))
    lines = log.read_bytes().split(b"\n")
    k = next(i for i, line in enumerate(lines) if b'"record":"trial"' in line)
    deep = b"[" * 100_000 + b"]" * 100_000
    lines[k] = lines[k][:-1] + b',"x":' + deep + b"}"
    log.write_bytes(b"\n".join(lines))
    assert (
        fast_parse(log.read_bytes(), log) is None
    )  # msgspec recursed: the general reader reads it
    out = tmp_path / "out"
    assert main(["analyze", str(tmp_path / "data"), "--out", str(out), "--quiet"]) == 0
    problems = (out / "problems.csv").read_text(encoding="utf-8")
    assert log.name in problems and f"line {k + 1}" in problems


def test_a_converter_full_scale_whose_lsb_underflows_is_refused_with_its_field(tmp_path, capsys):
    from masking_lab.commands.cli import main
    from masking_lab.formats.resources import shipped

    rig = shipped("protocols", "devices/default.yaml").read_text(encoding="utf-8")
    assert rig.count("full_scale_v: 10.0") == 2
    (tmp_path / "rig.yaml").write_text(rig.replace("full_scale_v: 10.0", "full_scale_v: 5e-324"))
    protocol = str(shipped("protocols", "baseline.yaml"))
    for argv in (
        ["validate", protocol, "--device-config", str(tmp_path / "rig.yaml")],
        ["run", protocol, "--participant", "P1", "--device", "sim", "--responder", "sim",
         "--device-config", str(tmp_path / "rig.yaml"), "--data", str(tmp_path / "data")],
    ):  # fmt: skip
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "channels.EV.converter.full_scale_v (line" in err and "Traceback" not in err
    assert not (tmp_path / "data").exists() or not any((tmp_path / "data").rglob("*.jsonl"))
