"""The issue's check: baseline, then experiment I, through the emulator on a pseudo-terminal.

``masking-lab run protocols/experiment1.yaml --participant S01 --device emulator --responder
sim`` after a baseline run completes all 15 sets; every log line validates against
data_schema/session_log.schema.json; each set's logged level track, replayed into
``psychopy.data.StairHandler`` with the same responses, matches.
"""

from __future__ import annotations

import json

import pytest
from runner_support import REPO, assert_valid_log, of_kind, only_log, trials

from masking_lab.commands.cli import main
from masking_lab.formats.schemas import schema_errors

psychopy_data = pytest.importorskip("psychopy.data", reason="PsychoPy is in the [test] extra")
from psychopy import logging as psychopy_logging  # noqa: E402

psychopy_logging.console.setLevel(psychopy_logging.ERROR)


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """Run both sessions once; hand out the data folder and both logs, validated."""
    data = tmp_path_factory.mktemp("study") / "data"
    common = ["--participant", "S01", "--device", "emulator", "--responder", "sim"]
    common += ["--data", str(data)]
    assert main(["run", str(REPO / "protocols" / "baseline.yaml"), *common, "--seed", "11"]) == 0
    assert main(["run", str(REPO / "protocols" / "experiment1.yaml"), *common]) == 0
    base = assert_valid_log(only_log(data, experiment="baseline"))
    exp1 = assert_valid_log(only_log(data, experiment="experiment1"))
    return data, base, exp1


def stair_handler(start):
    sc = start["staircase"]
    return psychopy_data.StairHandler(
        startVal=sc["start_level_db"],
        stepSizes=list(sc["step_sizes_db"]),
        nUp=sc["n_up"],
        nDown=sc["n_down"],
        nReversals=sc["n_reversals"],
        nTrials=0,
        stepType="lin",
        applyInitialRule=sc["initial_one_down_one_up"],
        minVal=start["min_level_db"],
        maxVal=start["max_level_db"],
    )


def check_against_psychopy(recs, level_key):
    for start in of_kind(recs, "set_start"):
        set_id = start["set_id"]
        (end,) = [e for e in of_kind(recs, "set_end") if e["set_id"] == set_id]
        handler = stair_handler(start)
        logged = trials(recs, set_id)
        for trial, level in zip(logged, handler, strict=False):
            assert trial[level_key] == pytest.approx(level, abs=1e-9), (set_id, trial)
            handler.addResponse(int(trial["correct"]))
        assert handler.thisTrialN == len(logged) - 1
        assert handler.reversalIntensities == pytest.approx(end["reversal_levels_db"])
        if end["status"] == "completed":
            last8 = handler.reversalIntensities[-8:]
            assert end["al_db"] == pytest.approx(sum(last8) / 8)


def test_baseline_then_experiment_one_through_the_emulator(study):
    data, base_recs, exp_recs = study  # every line already validated against the schema

    # The baseline calibrated every stimulus experiment I plays, and experiment I used it.
    cal = json.loads((data / "S01" / "calibration.json").read_text())
    assert schema_errors(cal, "calibration") == []
    ends = {e["set_id"]: e for e in of_kind(base_recs, "set_end")}
    for stim in ("EV270", "MV120", "MV180", "MV270"):
        assert ends[stim]["status"] == "completed"
        assert cal["unmasked_al_db_v"][stim] == pytest.approx(ends[stim]["al_db"])
    assert exp_recs[0]["calibration"] == cal["unmasked_al_db_v"]

    # Every trial went through the pseudo-terminal to the emulated firmware.
    for recs in (base_recs, exp_recs):
        assert recs[0]["device"]["backend"] == "emulator"
        assert recs[0]["device"]["firmware_version"].startswith("fw-")
        assert recs[0]["device"]["port"].startswith("/dev/")
        assert all("device_seq" in t["device_extra"] for t in trials(recs))

    # All 15 sets of experiment I ran to an end, in the seed's order.
    exp_ends = of_kind(exp_recs, "set_end")
    assert len(exp_ends) == 15 and exp_recs[-1]["record"] == "session_end"
    assert [e["set_id"] for e in exp_ends] == exp_recs[0]["set_order"]
    assert {e["status"] for e in exp_ends} <= {"completed", "ceiling", "floor", "trial_cap"}
    assert sum(e["status"] == "completed" for e in exp_ends) >= 13

    check_against_psychopy(base_recs, "level_db_v")
    check_against_psychopy(exp_recs, "level_db_sl")


def test_masked_als_rise_with_masker_level(study):
    """A sanity check of the science end to end: louder maskers, higher EV thresholds."""
    recs = study[2]
    by_level: dict[int, list[float]] = {}
    starts = {s["set_id"]: s for s in of_kind(recs, "set_start")}
    for end in of_kind(recs, "set_end"):
        if end["al_db_sl"] is not None:
            level = int(starts[end["set_id"]]["masker_level_db_sl"])
            by_level.setdefault(level, []).append(end["al_db_sl"])
    means = {k: sum(v) / len(v) for k, v in by_level.items()}
    assert means[25] > means[5] + 4.0, means
