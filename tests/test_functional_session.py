"""The functional (ramp) procedure at the rig: protocols choose it, the runner logs every
trial's masker and target level with the ramp's posterior, a killed interleaved session
resumes to the same trials, and masker levels stay within the range asked for and the rig's
ratings. Sessions run in virtual time with the in-process simulated device and observer."""

from __future__ import annotations

import io
import itertools
import math

import numpy as np
import pytest
import yaml
from runner_support import (
    FAST_TIMING,
    assert_valid_log,
    of_kind,
    records,
    timeless,
    trials,
    write_calibration,
)

from masking_lab.core.errors import LevelError, ProtocolError
from masking_lab.formats.protocol import load_protocol
from masking_lab.formats.resources import shipped
from masking_lab.procedures.base import replay
from masking_lab.procedures.functional import FunctionalRampSettings, ramp_tables
from masking_lab.session.runner import RunOptions, resume_session, run_session
from masking_lab.session.trials import plan_set, plan_trial

CAL = {"EV270": -18.0, "MV120": -26.0, "MV180": -30.0}
SMALL = {
    "kind": "functional_ramp",
    "masker_min_db_sl": 5,
    "masker_max_db_sl": 25,
    "masker_step_db": 10,
    "min_level_db": -6,
    "max_level_db": 26,
    "level_step_db": 2,
    "intercept_step_db": 2,
    "slope_step": 0.1,
    "unmasked_offsets_db": [0],
    "scales_db": [1.5],
    "lapses": [0.02],
    "max_trials": 14,
}


def functional_protocol(folder, *, interleave=True, **procedure):
    data = {
        "schema_version": 1,
        "experiment": "exp",
        "kind": "masked",
        "target": "EV270",
        "procedure": {**SMALL, **procedure},
        "timing": FAST_TIMING,
        "order": {"randomize": True, "interleave": interleave},
        "sets": [{"id": "MV120", "masker": "MV120"}, {"id": "MV180", "masker": "MV180"}],
    }
    path = folder / "functional.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def run(folder, protocol, seed=5):
    write_calibration(folder / "data", "S01", CAL)
    result = run_session(
        RunOptions(protocol, "S01", data_dir=folder / "data", seed=seed), stream=io.StringIO()
    )
    assert result.exit_code == 0, result.message
    return result


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    folder = tmp_path_factory.mktemp("functional")
    result = run(folder, functional_protocol(folder))
    text = result.log_path.read_text(encoding="utf-8")
    return text.splitlines(keepends=True), records(result.log_path), result


def test_the_log_holds_each_trials_masker_and_the_ramp_posterior_and_replays(reference):
    _, recs, result = reference
    assert_valid_log(result.log_path)
    settings = FunctionalRampSettings.from_mapping(SMALL)
    for start in of_kind(recs, "set_start"):
        assert start["procedure"]["kind"] == "functional_ramp"
        assert start["masker_level_db_sl"] is None
        logged = trials(recs, start["set_id"])
        track = replay(settings, [t["correct"] for t in logged])
        assert [t["level_db_sl"] for t in logged] == list(track.levels_db)
        assert [t["masker_level_db_sl"] for t in logged] == list(track.maskers_db_sl)
        assert logged[-1]["ramp"]["intercept_db"] == track.moments()["intercept_db"]
        for t in logged:
            assert 5 <= t["masker_level_db_sl"] <= 25
            assert all(math.isfinite(v) for v in t["ramp"].values())
            # the masker's drive is its calibrated AL plus the trial's level, as the converter
            # plays it: within half an LSB at the attenuation step the host picked
            want_v = 10 ** ((CAL[start["masker"]] + t["masker_level_db_sl"]) / 20)
            step_db = (t.get("device_extra") or {}).get("masker_att_db", 0.0)
            lsb_v = 20.0 / 4096 / 10 ** (step_db / 20)  # the reference rig: 12 bits, ±10 V
            assert abs(t["played_masker_v"] - want_v) <= lsb_v / 2 + 1e-9
        end = of_kind([r for r in recs if r.get("set_id") == start["set_id"]], "set_end")[0]
        assert end["status"] == "completed" and end["al_db"] is None
        assert end["method"] == "ramp_posterior"
        assert set(end["ramp"]) >= {"intercept_db", "intercept_sd_db", "slope", "slope_sd"}
    assert all("ramp a" in o.summary() for o in result.outcomes)
    # more than one masker level per set: the procedure places the masker
    assert all(
        len({t["masker_level_db_sl"] for t in trials(recs, s)}) > 1 for s in CAL if s != "EV270"
    )


def test_the_sets_interleave(reference):
    _, recs, _ = reference
    sequence = [r["set_id"] for r in of_kind(recs, "trial")]
    assert sum(a != b for a, b in itertools.pairwise(sequence)) > 4


@pytest.mark.parametrize("fraction", [0.2, 0.6])
def test_a_killed_session_resumes_with_the_same_trials(tmp_path, reference, fraction):
    lines, ref, _ = reference
    trial_lines = [i for i, r in enumerate(ref) if r["record"] == "trial"]
    n = trial_lines[int(fraction * len(trial_lines))] + 1
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    path = data / "S01" / "exp-S01-20240101T000000Z.jsonl"
    path.write_text("".join(lines[:n]), encoding="utf-8")
    result = resume_session(path, stream=io.StringIO())
    assert result.exit_code == 0
    assert timeless(assert_valid_log(path)) == timeless(ref)


def test_masker_levels_stop_at_the_rigs_rating(tmp_path):
    protocol = load_protocol(functional_protocol(tmp_path))
    spec = protocol.sets[0]
    # MV at most 0.35 V: -9.1 dB re 1 V, 16.9 dB SL over the masker's AL of -26 dB re 1 V.
    plan = plan_set(spec, "db_sl", CAL, {"EV": 5.0, "MV": 0.35})
    assert plan.procedure.masker_max_db_sl == 15.0  # the grid 5, 15, 25 stops at 15
    assert ramp_tables(plan.procedure).maskers_db_sl.max() == 15.0
    with pytest.raises(LevelError, match="masker"):
        plan_trial(plan, 0.0, 1, protocol.timing, masker_level_db_sl=25.0)
    roomy = plan_set(spec, "db_sl", CAL, {"EV": 5.0, "MV": 5.0})
    assert roomy.procedure.masker_max_db_sl == 25.0
    trial = plan_trial(roomy, 0.0, 1, protocol.timing, masker_level_db_sl=15.0)
    assert trial.masker_amplitude_v == pytest.approx(10 ** ((CAL["MV120"] + 15) / 20))


def test_a_rig_that_cannot_reach_two_masker_levels_refuses_the_set(tmp_path):
    protocol = load_protocol(functional_protocol(tmp_path))
    with pytest.raises(LevelError, match="two"):
        plan_set(protocol.sets[0], "db_sl", CAL, {"EV": 5.0, "MV": 0.05})


@pytest.mark.parametrize(
    ("change", "where"),
    [
        (
            {"sets": [{"id": "A", "masker": "MV120", "masker_level_db_sl": 10}]},
            "masker_level_db_sl",
        ),
        ({"sets": [{"id": "A", "masker": "MV120", "start_level_db": 3}]}, "start_level_db"),
        ({"procedure": {**SMALL, "level_step_db": 1e-6}}, "level_step_db"),
        ({"procedure": {**SMALL, "slope_min": 2.0, "slope_max": 1.0}}, "slope_min"),
        ({"procedure": {**SMALL, "masker_min_db_sl": 60, "masker_max_db_sl": 80}}, "masker"),
    ],
)
def test_bad_functional_protocols_are_refused_at_their_key(tmp_path, change, where):
    path = functional_protocol(tmp_path)
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    data.update(change)
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    with pytest.raises(ProtocolError, match=where):
        load_protocol(path, max_level_db_sl={"EV": 30.0, "MV": 40.0})


def test_the_shipped_protocol_measures_the_papers_pair_within_memory():
    protocol = load_protocol(shipped("protocols", "experiment1_functional.yaml"))
    assert {s.masker.name for s in protocol.sets} == {"MV120", "MV180", "MV270"}
    assert {s.target.name for s in protocol.sets} == {"EV270"}
    assert protocol.interleave and sum(s.trial_cap for s in protocol.sets) <= 262
    settings = protocol.sets[0].settings
    t = ramp_tables(settings)
    assert t.p_correct.nbytes < 64 * 2**20
    assert np.unique(t.maskers_db_sl).tolist() == [5.0, 10.0, 15.0, 20.0, 25.0]


def test_progress_shows_the_ramp_and_the_masker_level(tmp_path):
    write_calibration(tmp_path / "data", "S01", CAL)
    out = io.StringIO()
    options = RunOptions(
        functional_protocol(tmp_path), "S01", data_dir=tmp_path / "data", seed=4, progress=True
    )
    assert run_session(options, stream=out).exit_code == 0
    lines = [line for line in out.getvalue().splitlines() if line.startswith("set ")]
    progress = [line for line in lines if line.endswith(" left")]
    assert any("ramp: prior | masker" in line for line in progress)
    assert any("ramp a " in line and " dB, b " in line and "| masker " in line for line in progress)
    done = [line for line in lines if line.startswith("set done:")]
    assert len(done) == 2 and all("ramp a " in line and "dB/dB" in line for line in done)
