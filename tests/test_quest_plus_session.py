"""QUEST+ sets in real sessions: protocol keys, the runner's log, resume and interleaving.

Sessions run in virtual time with the simulated device and responder; "kill" is a log cut at a
record boundary (the runner fsyncs every record, so that is what a SIGKILL leaves).
"""

from __future__ import annotations

import io
import itertools
import math
import signal
import time

import pytest
import yaml
from runner_support import (
    assert_valid_log,
    cli,
    cli_popen,
    of_kind,
    records,
    timeless,
    trials,
    write_calibration,
    write_protocol,
)

from masking_lab.core.errors import LevelError, ProtocolError
from masking_lab.core.stimulus import parse_stimulus
from masking_lab.formats.protocol import SetSpec, Timing, load_protocol
from masking_lab.procedures.quest_plus import QuestPlusSettings
from masking_lab.procedures.staircase import StaircaseSettings
from masking_lab.session.runner import RunOptions, resume_session, run_session
from masking_lab.session.trials import plan_set, plan_trial

CAL = {"EV270": -14.0, "MV120": -26.0}
STAIRCASE = {"kind": "staircase"}
QUEST = {
    "kind": "quest_plus",
    "min_level_db": -20,
    "max_level_db": 40,
    "level_step_db": 1.0,
    "target_sd_db": 2.0,
    "min_trials": 5,
    "max_trials": 40,
}


def quest_protocol(folder, *, interleave=False, drop_staircase=True, sets=None, **procedure):
    path = write_protocol(folder, sets=sets)
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    if drop_staircase:
        del data["staircase"]
    data["procedure"] = {**QUEST, **procedure}
    data["order"]["interleave"] = interleave
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def run(folder, protocol, seed=7):
    write_calibration(folder / "data", "S01", CAL)
    result = run_session(
        RunOptions(protocol, "S01", data_dir=folder / "data", seed=seed), stream=io.StringIO()
    )
    assert result.exit_code == 0, result.message
    return result


def test_protocol_procedure_per_experiment_and_per_set(tmp_path):
    sets = [
        {"id": "A10", "masker": "MV120", "masker_level_db_sl": 10},
        {
            "id": "A20",
            "masker": "MV120",
            "masker_level_db_sl": 20,
            "procedure": {"kind": "staircase"},
        },
        {"id": "A25", "masker": "MV120", "masker_level_db_sl": 25, "procedure": {"max_trials": 30}},
    ]
    p = load_protocol(quest_protocol(tmp_path, drop_staircase=False, sets=sets))
    a10, a20, a25 = p.sets
    assert isinstance(a10.settings, QuestPlusSettings) and a10.settings.max_trials == 40
    assert isinstance(a20.settings, StaircaseSettings)  # the set's own kind wins
    assert isinstance(a25.settings, QuestPlusSettings) and a25.settings.max_trials == 30
    assert a25.settings.target_sd_db == 2.0  # the rest merged from the protocol's block
    # The staircase stays the default procedure.
    plain = load_protocol(write_protocol(tmp_path, name="plain.yaml"))
    assert all(isinstance(s.settings, StaircaseSettings) for s in plain.sets)
    assert not plain.interleave


@pytest.mark.parametrize(
    ("change", "where", "says"),
    [
        ({"max_trial": 3}, "procedure.max_trial", "did you mean 'max_trials'"),
        ({"min_trials": 50}, "procedure.min_trials", "exceeds max_trials=40"),
        ({"lapses": [0.9]}, "procedure.lapses", "lapse"),
        ({"kind": "psi"}, "procedure.kind", "must be one of"),
        ({"prior": "normal"}, "procedure.prior_mean_db", "normal prior needs"),
    ],
)
def test_bad_procedure_keys_name_the_key(tmp_path, change, where, says):
    path = quest_protocol(tmp_path, **change)
    with pytest.raises(ProtocolError) as info:
        load_protocol(path)
    assert where in str(info.value) and says in str(info.value)
    assert str(info.value).count(where) == 1  # a protocol-wide block is reported once


def test_a_staircase_set_without_a_staircase_block_is_refused(tmp_path):
    sets = [
        {
            "id": "A10",
            "masker": "MV120",
            "masker_level_db_sl": 10,
            "procedure": {"kind": "staircase"},
        }
    ]
    with pytest.raises(ProtocolError, match="no `staircase:` block"):
        load_protocol(quest_protocol(tmp_path, sets=sets))


def test_quest_plus_session_logs_its_posterior_and_replays_to_its_levels(tmp_path):
    result = run(tmp_path, quest_protocol(tmp_path))
    recs = assert_valid_log(result.log_path)
    starts = {r["set_id"]: r for r in of_kind(recs, "set_start")}
    for end in of_kind(recs, "set_end"):
        start = starts[end["set_id"]]
        assert start["procedure"]["kind"] == "quest_plus" and "staircase" not in start
        settings = QuestPlusSettings.from_mapping(start["procedure"])
        logged = trials(recs, end["set_id"])
        track = settings.start()
        for t in logged:  # the runner played exactly what the pure track places
            assert t["level_db_sl"] == track.next_level()
            track = track.update(t["correct"])
            assert t["posterior"] == {
                "mean_db": track.posterior_mean_db,
                "sd_db": track.posterior_sd_db,
            }
            assert all(math.isfinite(v) for v in t["posterior"].values())
        assert end["status"] == track.status and end["n_trials"] == len(logged)
        assert end["method"] == "posterior_mean" and end["sd_db"] == track.posterior_sd_db
        if end["status"] == "completed":
            assert end["sd_db"] <= 2.0 and len(logged) >= 5
            assert end["al_db"] == track.posterior_mean_db
            assert end["al_db_v"] == pytest.approx(end["al_db"] + CAL["EV270"])
    assert {o.status for o in result.outcomes} == {"completed"}


@pytest.fixture(scope="module", params=[False, True], ids=["blocked", "interleaved"])
def reference(request, tmp_path_factory):
    folder = tmp_path_factory.mktemp("ref")
    sets = [{"id": f"A{v}", "masker": "MV120", "masker_level_db_sl": v} for v in (5, 10, 20)]
    protocol = quest_protocol(folder, interleave=request.param, sets=sets)
    result = run(folder, protocol, seed=11)
    text = result.log_path.read_text(encoding="utf-8")
    return request.param, text.splitlines(keepends=True), records(result.log_path)


def test_interleaving_mixes_the_sets_and_blocking_does_not(reference):
    interleaved, _, recs = reference
    sequence = [r["set_id"] for r in of_kind(recs, "trial")]
    switches = sum(a != b for a, b in itertools.pairwise(sequence))
    if interleaved:
        assert switches > 10  # ~2/3 of consecutive trials change set
        # every set_start is written before the first trial
        kinds = [r["record"] for r in recs]
        assert kinds[1:4] == ["set_start"] * 3
    else:
        assert switches == 2


@pytest.mark.parametrize("fraction", [0.15, 0.5, 0.85])
def test_a_killed_session_resumes_with_the_same_stimuli(tmp_path, reference, fraction):
    """Cut mid-set (or mid-interleave) → resume → the same trials as the uninterrupted run."""
    _, lines, ref = reference
    trial_lines = [i for i, r in enumerate(ref) if r["record"] == "trial"]
    n = trial_lines[int(fraction * len(trial_lines))] + 1
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    path = data / "S01" / "exp-S01-20240101T000000Z.jsonl"
    path.write_text("".join(lines[:n]), encoding="utf-8")
    result = resume_session(path, stream=io.StringIO())
    assert result.exit_code == 0
    recs = assert_valid_log(path)
    assert timeless(recs) == timeless(ref)
    added = recs[n:]
    assert added[0]["kind"] == "unclean_stop" and added[1]["record"] == "resume"


@pytest.mark.parametrize("interleave", [False, True])
def test_progress_shows_the_posterior_and_a_time_left_that_runs_down(tmp_path, interleave):
    write_calibration(tmp_path / "data", "S01", CAL)
    out = io.StringIO()
    options = RunOptions(
        quest_protocol(tmp_path, interleave=interleave),
        "S01",
        data_dir=tmp_path / "data",
        seed=3,
        progress=True,
    )
    assert run_session(options, stream=out).exit_code == 0
    lines = [ln for ln in out.getvalue().splitlines() if ln.startswith("set ") and "|" in ln]
    assert "posterior: prior dB SL" in lines[0]
    assert all("reversals" not in ln for ln in lines)
    assert any("posterior" in ln and " ± " in ln for ln in lines[1:])

    def minutes(line: str) -> float:
        left = line.rsplit("|", 1)[1].split("left")[0].strip().lstrip("~")
        value, unit = left.split()[0], left.split()[1]
        return float(value) / (60.0 if unit == "s" else 1.0)

    assert minutes(lines[0]) > minutes(lines[-1])
    assert minutes(lines[-1]) < 1.0


def test_sigkill_mid_interleave_then_cli_resume_gives_the_uninterrupted_stimuli(tmp_path):
    """A real ``masking-lab run`` process killed mid-interleave, resumed by ``masking-lab
    resume``: the same sets, levels, target intervals and answers as an uninterrupted run."""
    tiny = {"stimulus_s": 0.01, "gap_s": 0.005, "lead_in_s": 0.005}
    sets = [{"id": f"A{v}", "masker": "MV120", "masker_level_db_sl": v} for v in (5, 10, 20)]
    protocol = quest_protocol(tmp_path, interleave=True, sets=sets)
    data = yaml.safe_load(protocol.read_text(encoding="utf-8"))
    data["timing"].update(tiny)
    protocol.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    reference = run(tmp_path / "ref", protocol, seed=5)
    data_dir = tmp_path / "killed"
    write_calibration(data_dir, "S01", CAL)
    args = ["run", str(protocol), "--participant", "S01", "--device", "sim", "--real-time"]
    proc = cli_popen(*args, "--responder", "sim", "--seed", "5", "--data", str(data_dir))
    deadline = time.monotonic() + 60
    log = None
    while time.monotonic() < deadline:
        logs = list((data_dir / "S01").glob("*.jsonl"))
        if logs and len(trials(records(logs[0]))) >= 12:
            log = logs[0]
            break
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.01)
    assert log is not None, "the run never logged 12 trials"
    proc.kill()
    proc.communicate(timeout=10)
    assert proc.returncode == -signal.SIGKILL
    done = cli("resume", str(log), timeout=120)
    assert done.returncode == 0, done.stderr
    recs = assert_valid_log(log)
    kinds = ("set_start", "trial", "set_end")
    ref = records(reference.log_path)
    assert timeless([r for r in recs if r["record"] in kinds]) == timeless(
        [r for r in ref if r["record"] in kinds]
    )
    assert [f["kind"] for f in of_kind(recs, "fault")] == ["unclean_stop"]


def test_the_device_limit_caps_the_quest_plus_grid_on_its_own_steps():
    def spec(**kw):
        quest = QuestPlusSettings(-20.0, 45.0, level_step_db=0.5, max_trials=30, **kw)
        ev, mv = parse_stimulus("EV270"), parse_stimulus("MV120")
        return SetSpec("A10", ev, mv, 10.0, None, quest)

    # EV limit 1 V = 0 dB re 1 V = 14 dB SL above the calibrated AL of −14 dB re 1 V.
    plan = plan_set(spec(), "db_sl", CAL, {"EV": 1.0, "MV": 10.0})
    top = plan.procedure.max_level_db
    assert top == 14.0 and plan.procedure.threshold_range_db == (-20.0, 14.0)
    track = plan.procedure.start()
    while not track.finished:  # every level the track places is playable
        plan_trial(plan, track.next_level(), 1, Timing())
        track = track.update(track.next_level() > 10.0)
    # An explicit threshold grid is kept; a limit under one step above the bottom is refused.
    kept = plan_set(spec(threshold_max_db=45.0), "db_sl", CAL, {"EV": 1.0, "MV": 10.0})
    assert kept.procedure.threshold_range_db == (-20.0, 45.0)
    with pytest.raises(LevelError, match="less than one grid step"):
        plan_set(spec(), "db_sl", CAL, {"EV": 10 ** (-33.8 / 20), "MV": 10.0})


def test_the_session_places_its_trials_on_one_blas_thread(tmp_path, monkeypatch):
    """A session's placements run with BLAS pinned to one thread (a busy core cannot stall a
    trial); the process's own limit comes back afterwards."""
    threadpoolctl = pytest.importorskip("threadpoolctl")
    from masking_lab.procedures import quest_plus

    def blas_threads():
        return {
            p["num_threads"] for p in threadpoolctl.threadpool_info() if p["user_api"] == "blas"
        }

    if not blas_threads():
        pytest.skip("this numpy has no BLAS thread pool")
    seen = []
    original = quest_plus.best_levels

    def spying(*args, **kwargs):
        seen.append(blas_threads())
        return original(*args, **kwargs)

    monkeypatch.setattr(quest_plus, "best_levels", spying)
    sets = [{"id": "A5", "masker": "MV120", "masker_level_db_sl": 5}]
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        run(tmp_path, quest_protocol(tmp_path, sets=sets))
        assert blas_threads() == {2}
    assert len(seen) >= 5 and all(s == {1} for s in seen)
