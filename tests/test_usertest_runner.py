"""The user-test session: streaming rules, refusals before anything plays, answers, records.

Pure parts (ticks, limits, clipping, dead-band) are checked against hand-computed values and
properties; the session runs on the in-process simulated device here (the emulator and fault
tests are in test_usertest_runner_study.py).
"""

from __future__ import annotations

import dataclasses
import io
import math
import os
import pty
import select
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from usertest_support import (
    RAMPS,
    TINY_TIMING,
    of_kind,
    records,
    timeless,
    trials,
    write_calibration,
    write_ground_truth,
    write_params,
    write_rig,
    write_usertest,
)

from masking_lab.commands.cli import main
from masking_lab.core.errors import (
    CalibrationError,
    LevelError,
    LogError,
    MaskingLabError,
    ProtocolError,
    SolverError,
)
from masking_lab.formats.schemas import schema_errors
from masking_lab.rendering.solver import MutualMasking
from masking_lab.responders.keys import KeyReader
from masking_lab.session.frame import SessionOptions
from masking_lab.simulation.observer import load_ground_truth, make_participant
from masking_lab.usertest.design import load_usertest, trial_list
from masking_lab.usertest.keys_responder import UserTestKeysResponder
from masking_lab.usertest.playback import levels_at, render_objects
from masking_lab.usertest.preparation import baseline_protocol
from masking_lab.usertest.responder_base import (
    StreamResult,
    UserTestInfo,
    UserTrialPresentation,
)
from masking_lab.usertest.runner import (
    UserTestOptions,
    resume_usertest,
    run_usertest,
)
from masking_lab.usertest.sim_responder import (
    REACH_MM,
    UserTestSimResponder,
    played_volts_on_path,
    true_masking,
)
from masking_lab.usertest.stream import (
    Streamer,
    clip_db_v,
    exceedances,
    path_levels_db_sl,
    plan_presentation,
    stimulus_limits,
    tick_offsets_s,
)

INF = math.inf
# The shipped ground truth's population ALs (dB re 1 V): a hand calibration near them.
CAL = {"EV270": -14.0, "MV270": -32.0, "MV180": -30.0, "MV120am40": -24.0}


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    folder = tmp_path_factory.mktemp("lab")
    design_path = write_usertest(folder, repeats=1)
    design = load_usertest(design_path)
    pairs = {
        (mv, "EV270"): MutualMasking(a, b, c, d, mv=mv, ev="EV270")
        for mv, ((a, b), (c, d)) in RAMPS.items()
    }
    return {
        "folder": folder,
        "protocol": design_path,
        "design": design,
        "objects": render_objects(design, pairs),
        "params": write_params(folder / "masking_params.json"),
        # Higher limits: every compensated input of the hand calibration fits (checked below).
        "rig": write_rig(folder, max_level_db_sl=65.0, EV=10.0, MV=10.0),
        "gt_gain": write_ground_truth(folder / "gt_gain.yaml", shift_db=-20.0),
    }


def options(lab, data: Path, **changes) -> UserTestOptions:
    base = dict(
        protocol=lab["protocol"],
        participant="S01",
        device="sim",
        responder="sim",
        data_dir=data,
        params=lab["params"],
        seed=5,
        progress=False,
    )
    base.update(changes)
    return UserTestOptions(**base)


def gain_cal(lab, data: Path, participant: str = "S01") -> None:
    """A calibration equal to the true ALs of the high-gain simulated participant."""
    truth = load_ground_truth(lab["gt_gain"])
    als = make_participant(truth, participant, 0).unmasked_al_db_v
    write_calibration(data, participant, {k: als[k] for k in CAL})


# ---------------------------------------------------------------------------------------------
# Ticks, levels, limits, clipping, dead-band (pure)


def test_ticks_are_100_hz_over_one_presentation():
    ticks = tick_offsets_s(1.8, 100.0)
    assert ticks.size == 180 and ticks[0] == 0.0 and ticks[-1] == pytest.approx(1.79)
    assert np.allclose(np.diff(ticks), 0.01)
    assert tick_offsets_s(0.05, 100.0).size == 5
    with pytest.raises(ValueError, match="update_hz"):
        tick_offsets_s(1.8, 0.0)


@settings(max_examples=60, deadline=None)
@given(
    x=st.one_of(st.floats(-20.0, 120.0), st.just(math.nan)),
    compensated=st.booleans(),
    key=st.sampled_from(["bump_rough", "hole_smooth", "ascending_coarse", "descending_rough"]),
)
def test_vectorised_levels_equal_the_pure_core(lab, x, compensated, key):
    r = lab["objects"][tuple(key.split("_"))]
    ev, mv = path_levels_db_sl(r, [x], compensated=compensated)
    want = levels_at(r, x, compensated=compensated)
    assert (ev[0], mv[0]) == pytest.approx(want)


def test_limits_take_the_stricter_of_rig_and_drive():
    limits = stimulus_limits(
        ["EV270", "MV180"], {"EV270": -14.0, "MV180": -30.0}, {"EV": 30.0, "MV": 30.0},
        {"EV": 5.0, "MV": 10.0},
    )  # fmt: skip
    ev, mv = limits["EV270"], limits["MV180"]
    # 5 V is 13.979 dB re 1 V; with an AL of -14 dB re 1 V that is 27.979 dB SL < 30.
    assert ev.max_db_sl == pytest.approx(20 * math.log10(5.0) + 14.0)
    assert "max_drive_v" in ev.binding
    assert ev.max_db_v == pytest.approx(20 * math.log10(5.0))
    # 10 V at -30 dB re 1 V is 50 dB SL, so the rig's 30 dB SL binds.
    assert mv.max_db_sl == 30.0 and "max_level_db_sl" in mv.binding
    assert mv.max_db_v == pytest.approx(0.0)
    with pytest.raises(CalibrationError, match="MV270"):
        stimulus_limits(["MV270"], {}, {}, {"MV": 10.0})


def test_exceedances_list_exactly_the_points_above_the_limit(lab):
    design, objects = lab["design"], lab["objects"]
    limits = stimulus_limits(
        ["EV270", "MV270", "MV180", "MV120am40"], CAL, {"EV": 30.0, "MV": 30.0},
        {"EV": 5.0, "MV": 10.0},
    )  # fmt: skip
    found = exceedances(design, objects, limits)
    # Uncompensated inputs are the targets (0-10 and 6-12 dB SL): never above the rig.
    assert found and all(e.condition == "compensated" for e in found)
    e = next(e for e in found if (e.geometry, e.texture, e.stimulus) == ("bump", "rough", "MV180"))
    mv, _ = objects[("bump", "rough")].inputs(True)
    assert e.n_points == int(np.sum(mv > 30.0)) and e.n_total == mv.size
    assert e.need_db_sl == pytest.approx(float(mv.max()))
    assert "bump_rough compensated: MV180 needs up to" in e.describe()
    roomy = stimulus_limits(CAL, CAL, {"EV": 65.0, "MV": 65.0}, {"EV": 100.0, "MV": 100.0})
    assert exceedances(design, objects, roomy) == []


def test_clip_reports_the_excess():
    clipped, excess = clip_db_v(np.array([-INF, -3.0, 2.0, 5.0]), 1.0)
    assert clipped.tolist() == [-INF, -3.0, 1.0, 1.0]
    assert excess.tolist() == [0.0, 0.0, 1.0, 4.0]


def test_streamer_sends_changes_beyond_the_deadband_silence_and_refreshes():
    s = Streamer(deadband_db=0.5, refresh_s=0.1)
    sent = []
    levels = [0.0, 0.2, 0.6, 0.7, 0.7, -INF, -INF, 3.0]
    for i, ev in enumerate(levels):
        sent.append([(f.channel, f.level_db_v, f.kind) for f in s.tick(i * 0.01, {"EV": ev})])
    assert sent == [
        [("EV", 0.0, "update")],  # silence → sound
        [],  # 0.2 dB: within the dead-band
        [("EV", 0.6, "update")],  # 0.6 dB from the held 0.0
        [],
        [],
        [("EV", -INF, "update")],  # sound → silence, whatever the size of the step
        [],
        [("EV", 3.0, "update")],
    ]
    # Quiet while sounding: the held level again every 0.1 s (ten 10 ms ticks).
    quiet = [s.tick(0.07 + i * 0.01, {"EV": 3.0}) for i in range(1, 21)]  # last frame: 0.07 s
    refreshed = [i for i, frames in enumerate(quiet, start=1) if frames]
    assert refreshed == [10, 20]
    assert quiet[9][0].kind == "refresh" and quiet[9][0].level_db_v == 3.0
    assert [(f.channel, f.kind) for f in s.silence(0.5)] == [("EV", "zero")]
    assert s.silence(0.6) == []
    with pytest.raises(ValueError, match="NaN"):
        s.tick(1.0, {"EV": math.nan})


@settings(max_examples=80, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.one_of(st.just(-INF), st.floats(-40.0, 20.0)),
            st.one_of(st.just(-INF), st.floats(-40.0, 20.0)),
        ),
        min_size=1,
        max_size=60,
    ),
    st.floats(0.0, 3.0),
)
def test_held_level_tracks_the_wanted_level_within_the_deadband(wanted, deadband):
    s = Streamer(deadband_db=deadband, refresh_s=0.1)
    for i, (ev, mv) in enumerate(wanted):
        s.tick(i * 0.01, {"EV": ev, "MV": mv})
        for ch, w in (("EV", ev), ("MV", mv)):
            held = s.held[ch]
            assert (held == -INF) == (w == -INF)
            if w != -INF:
                assert abs(held - w) < deadband or held == w
    s.silence(1.0)
    assert s.held == {"EV": -INF, "MV": -INF}


def test_a_presentation_plan_clips_holds_and_ends_silent():
    ticks = tick_offsets_s(0.05, 100.0)
    plan = plan_presentation(
        {"EV": np.array([0.0, 1.0, 6.0, 8.0, 2.0]), "MV": np.full(5, -INF)},
        ticks,
        51.0 * ticks,
        0.05,
        max_db_v={"EV": 5.0},
        deadband_db=0.5,
    )
    assert plan.held_db_v["EV"].tolist() == [0.0, 1.0, 5.0, 5.0, 2.0]
    assert plan.excess_db["EV"].tolist() == [0.0, 0.0, 1.0, 3.0, 0.0]
    assert max(f.level_db_v for f in plan.frames) == 5.0
    last = plan.frames[-1]
    assert (last.t_s, last.channel, last.level_db_v, last.kind) == (0.05, "EV", -INF, "zero")
    assert all(f.channel == "EV" for f in plan.frames)


def test_played_volts_are_mapped_onto_the_path():
    path = np.linspace(0.0, 10.0, 11)
    # Two presentations at the same positions (averaged), a gap beyond the reach at the end.
    x = np.array([0.0, 2.0, 4.0, 0.0, 2.0, 4.0, np.nan])
    v = np.array([1.0, 3.0, 5.0, 3.0, 5.0, 7.0, 9.0])
    felt = played_volts_on_path(path, x, v)
    assert felt[:5].tolist() == pytest.approx([2.0, 3.0, 4.0, 5.0, 6.0])
    assert felt[5] == pytest.approx(6.0)  # 1 mm past the last tick: within the reach
    assert REACH_MM == 2.0 and felt[6] == pytest.approx(6.0)
    assert felt[7:].tolist() == [0.0, 0.0, 0.0, 0.0]
    assert played_volts_on_path(path, np.array([np.nan]), np.array([1.0])).tolist() == [0.0] * 11


# ---------------------------------------------------------------------------------------------
# The simulated participant


def test_sim_answers_are_seeded_per_trial_and_follow_what_was_played(lab):
    design, objects = lab["design"], lab["objects"]
    truth = load_ground_truth()
    sim = UserTestSimResponder.from_ground_truth(design, objects, truth, "S01", seed=3)
    person = make_participant(truth, "S01", 0)
    assert sim.true_al_db_v == dict(person.unmasked_al_db_v)
    pair = sim.observer.truth[("MV180", "EV270")]
    assert pair.a_db == pytest.approx(1.304 + person.shift_offset_db)
    assert pair.d == pytest.approx(0.658)
    trial = next(t for t in trial_list(design, 3) if t.object == ("bump", "rough"))
    pres = UserTrialPresentation(trial, 24, 0.0, design.timing, "cue", 51.0, design.sweep_mm)
    r = objects[("bump", "rough")]
    x = np.linspace(0.0, 91.8, 50)
    als = sim.true_al_db_v

    def result(ev_db_sl, mv_db_sl):
        held = {
            "EV": 10 ** ((ev_db_sl + als["EV270"]) / 20) * np.ones_like(x),
            "MV": 10 ** ((mv_db_sl + als["MV180"]) / 20) * np.ones_like(x),
        }
        return StreamResult([0.0], [0.0], x / 51.0, x, held, {"EV": "EV270", "MV": "MV180"}, 0)

    loud = result(10.0, 12.0)
    ev, mv = sim.felt_inputs_db_sl(r, loud)
    assert ev == pytest.approx(np.full(r.x_mm.shape, 10.0))
    assert mv == pytest.approx(np.full(r.x_mm.shape, 12.0))
    a1, a2 = sim.answer(pres, loud), sim.answer(pres, loud)
    assert a1 == a2 and a1.geometry_time_s < a1.texture_time_s
    # Nothing played: nothing felt, so no geometry shape and no texture level to match.
    silent = StreamResult(
        [0.0], [0.0], x / 51.0, x, {"EV": 0 * x, "MV": 0 * x}, {"EV": "EV270", "MV": "MV180"}, 0
    )
    ev, mv = sim.felt_inputs_db_sl(r, silent)
    assert np.all(ev == -INF) and np.all(mv == -INF)


def test_sim_refuses_a_ground_truth_without_what_the_objects_play(lab):
    truth = load_ground_truth()
    lacking = dataclasses.replace(
        truth, masking=tuple(f for f in truth.masking if f.masker != "MV120am40")
    )
    with pytest.raises(ProtocolError, match="EV270 masked by MV120am40"):
        UserTestSimResponder.from_ground_truth(lab["design"], lab["objects"], lacking, "S01", 1)
    no_al = dataclasses.replace(
        truth, unmasked_al_db_v={k: v for k, v in truth.unmasked_al_db_v.items() if k != "MV270"}
    )
    with pytest.raises(ProtocolError, match="no unmasked AL for MV270"):
        UserTestSimResponder.from_ground_truth(lab["design"], lab["objects"], no_al, "S01", 1)


def test_sim_finger_lags_the_cue_and_is_seeded(lab):
    design = lab["design"]
    truth = load_ground_truth()
    sim = UserTestSimResponder.from_ground_truth(design, lab["objects"], truth, "S01", seed=3)
    trial = trial_list(design, 3)[0]
    pres = UserTrialPresentation(trial, 24, 100.0, design.timing, "finger", 51.0, 91.8)
    f1, f2 = sim.finger(pres), sim.finger(pres)
    assert f1(100.0) is None and f1(100.0 + 3.3) is None  # lead-in, first gap
    xs = [f1(100.0 + 1.2 + t) for t in np.arange(0.2, 1.8, 0.1)]
    assert all(x is not None for x in xs) and xs == [
        f2(100.0 + 1.2 + t) for t in np.arange(0.2, 1.8, 0.1)
    ]
    assert np.all(np.diff(xs) > 0)  # moving left to right
    cue = [51.0 * t for t in np.arange(0.2, 1.8, 0.1)]
    assert any(abs(a - b) > 0.1 for a, b in zip(xs, cue, strict=True))  # not the cue itself


def test_true_masking_needs_both_directions(lab):
    truth = load_ground_truth()
    person = make_participant(truth, "S02", 0)
    pairs = true_masking(truth, lab["design"], person)
    assert sorted(pairs) == lab["design"].stimulus_pairs()


# ---------------------------------------------------------------------------------------------
# Refusals before anything is played


def test_missing_calibration_writes_the_baseline_to_run(lab, tmp_path, capsys):
    data = tmp_path / "data"
    write_calibration(data, "S01", {"EV270": -14.0, "MV180": -30.0, "MV270": -32.0})
    with pytest.raises(CalibrationError) as err:
        run_usertest(options(lab, data))
    msg = str(err.value)
    written = data / "baseline_MV120am40.yaml"
    assert "no unmasked AL for MV120am40" in msg and str(written) in msg
    assert "masking-lab run" in msg and "--participant S01" in msg
    assert main(["validate", str(written)]) == 0
    assert "ok" in capsys.readouterr().out
    assert [s["target"] for s in baseline_protocol(["MV120am40"])["sets"]] == ["MV120am40"]
    assert not list((data / "S01").glob("*.jsonl"))  # no session was started


def test_compensation_without_params_or_with_a_missing_pair(lab, tmp_path):
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    with pytest.raises(SolverError, match="pass --params"):
        run_usertest(options(lab, data, params=None))
    partial = write_params(tmp_path / "partial.json", drop=(("EV270", "MV120am40"),))
    with pytest.raises(SolverError) as err:
        run_usertest(options(lab, data, params=partial))
    written = data / "measure_EV270_by_MV120am40.yaml"
    assert written.read_text().startswith("# Written by masking-lab run:")
    assert "EV270 masked by MV120am40 (no entry)" in str(err.value)
    assert str(written) in str(err.value)
    assert main(["validate", str(written)]) == 0
    assert not list((data / "S01").glob("*.jsonl"))


def test_uncompensated_only_needs_no_params(lab, tmp_path):
    protocol = write_usertest(tmp_path, conditions=["uncompensated"], timing=TINY_TIMING)
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    result = run_usertest(options(lab, data, protocol=protocol, params=None))
    assert result.exit_code == 0 and result.n_logged == 12
    header = records(result.log_path)[0]
    assert header["usertest"]["params"] is None


def test_inputs_above_the_rating_are_refused_listing_the_objects(lab, tmp_path):
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    with pytest.raises(LevelError) as err:
        run_usertest(options(lab, data))
    msg = str(err.value)
    assert "bump_rough compensated: MV180 needs up to 58.5 dB SL" in msg
    assert "--allow-clipping" in msg and "--device-config" in msg and "Nothing was played" in msg
    assert "uncompensated" not in msg.split("\n", 1)[1].split("Nothing")[0]
    assert not list((data / "S01").glob("*.jsonl"))


def test_allow_clipping_plays_at_the_limit_and_logs_it_per_trial(lab, tmp_path):
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    result = run_usertest(options(lab, data, allow_clipping=True), stream=io.StringIO())
    assert result.exit_code == 0
    recs = records(result.log_path)
    header = recs[0]
    assert header["usertest"]["allow_clipping"] is True
    clipped_objects = {(c["object"], c["stimulus"]) for c in header["usertest"]["clipped_objects"]}
    assert ("bump_rough", "MV180") in clipped_objects
    limit_ev = 20 * math.log10(5.0) + 14.0  # dB SL: 5 V at the calibrated EV AL
    for t in trials(recs):
        key = (f"{t['geometry']}_{t['texture']}", t["condition"])
        clipped = "clipped" in t
        assert clipped == any((o, cond) == key for o, cond in _clipped_keys(header))
        assert t["played"]["EV"]["max_db_sl"] <= limit_ev + 1e-6
        assert t["played"]["MV"]["max_db_sl"] <= 30.0 + 1e-6
        if clipped:
            assert all(v["n_ticks"] > 0 and v["max_excess_db"] > 0 for v in t["clipped"].values())
    assert any("clipped" in t for t in trials(recs))


def test_gamut_mapped_scenes_play_within_the_limits_and_the_report_names_it(lab, tmp_path):
    # The same session that is refused unmapped (MV180 needs 58.5 dB SL) runs when each object
    # is mapped into the gamut of its stimuli's limits: nothing clipped, the strategy logged.
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    result = run_usertest(options(lab, data, gamut_map="clip"), stream=io.StringIO())
    assert result.exit_code == 0
    recs = records(result.log_path)
    header = recs[0]
    assert header["usertest"]["gamut_map"] == "clip"
    assert header["usertest"]["clipped_objects"] == []
    limit_ev = 20 * math.log10(5.0) + 14.0  # dB SL: 5 V at the calibrated EV AL
    for t in trials(recs):
        assert "clipped" not in t
        assert t["played"]["EV"]["max_db_sl"] <= limit_ev + 1e-6
        assert t["played"]["MV"]["max_db_sl"] <= 30.0 + 1e-6
    assert main(["usertest-report", str(data), "--out", str(tmp_path / "rep")]) == 0
    report = (tmp_path / "rep" / "report.txt").read_text()
    assert "mapped into the rig's gamut (clip)" in report


def test_a_gamut_mapped_session_resumes_with_the_same_mapping(lab, tmp_path):
    from masking_lab.usertest.runner import default_responder

    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    write_calibration(tmp_path / "ref", "S01", CAL)
    ref = run_usertest(options(lab, tmp_path / "ref", gamut_map="compress"), stream=io.StringIO())

    class Interrupting:
        name = "sim"

        def __init__(self, inner):
            self.inner, self.n = inner, 0

        def start_session(self, info):
            self.inner.start_session(info)

        def trial(self, presentation, play):
            self.n += 1
            if self.n == 4:
                raise KeyboardInterrupt
            return self.inner.trial(presentation, play)

        def close(self):
            self.inner.close()

    stopped = run_usertest(
        options(lab, data, gamut_map="compress"),
        make_responder=lambda n, c: Interrupting(default_responder(n, c)),
        stream=io.StringIO(),
    )
    assert stopped.exit_code == 130
    resumed = resume_usertest(stopped.log_path, stream=io.StringIO())
    assert resumed.exit_code == 0
    recs = records(stopped.log_path)
    assert recs[0]["usertest"]["gamut_map"] == "compress"
    played = [t["played"] for t in trials(recs)]
    assert played == [t["played"] for t in trials(records(ref.log_path))][: len(played)]


def _clipped_keys(header):
    return [(c["object"], c["condition"]) for c in header["usertest"]["clipped_objects"]]


def test_bad_input_is_refused_before_anything_plays(lab, tmp_path):
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    with pytest.raises(MaskingLabError, match="--participant"):
        run_usertest(options(lab, data, participant="S 01"))
    with pytest.raises(MaskingLabError, match="sim, keys, psychopy"):
        run_usertest(options(lab, data, responder="mouse"))
    with pytest.raises(MaskingLabError, match="--device"):
        run_usertest(options(lab, data, device="usb"))
    with pytest.raises(MaskingLabError, match="update rate"):
        run_usertest(options(lab, data, update_hz=0.0))
    with pytest.raises(MaskingLabError, match="--seed"):
        run_usertest(options(lab, data, seed=-1))
    finger = write_usertest(tmp_path, name="finger.yaml", tracking="finger")
    with pytest.raises(ProtocolError, match="finger tracking needs a responder"):
        run_usertest(options(lab, data, protocol=finger, responder="keys"))
    bad = tmp_path / "bad.yaml"
    bad.write_text("kind: usertest\nexperiment: x\n", encoding="utf-8")
    with pytest.raises(ProtocolError, match=r"bad\.yaml"):
        run_usertest(options(lab, data, protocol=bad))


# ---------------------------------------------------------------------------------------------
# Sessions on the simulated device


def test_a_session_logs_every_trial_of_the_seeded_order(lab, tmp_path):
    data = tmp_path / "data"
    gain_cal(lab, data)
    opts = options(
        lab, data, ground_truth=lab["gt_gain"], device_config=lab["rig"], responder="sim"
    )
    result = run_usertest(opts, stream=io.StringIO())
    assert result.exit_code == 0 and result.n_logged == result.n_trials == 24
    recs = records(result.log_path)
    assert not schema_errors(recs[0], "session_log")
    for rec in recs[1:]:
        assert not schema_errors(rec, "session_log"), rec["record"]
    order = trial_list(lab["design"], 5)
    ts = trials(recs)
    assert [(t["geometry"], t["texture"], t["condition"]) for t in ts] == [
        (t.geometry, t.texture, t.condition) for t in order
    ]
    assert recs[-1] == {**recs[-1], "record": "session_end", "status": "completed"}
    for t in ts:
        assert t["planned_onsets_s"] == pytest.approx(
            [t["t_s"] + 1.2, t["t_s"] + 3.6, t["t_s"] + 6.0]
        )
        assert t["n_frames"] > 6 and "clipped" not in t
        assert 1 <= t["geometry_answer"] <= 4 and 1 <= t["texture_answer"] <= 3
        assert t["correct_geometry"] == (t["geometry_answer"] == t["geometry_key"])
    # The next trial starts after the 7.8 s trial, the answers and the 0.5 s pause.
    first, second = ts[0], ts[1]
    assert second["t_s"] == pytest.approx(first["t_s"] + 7.8 + first["response_time_s"] + 0.5)
    # Uncompensated objects play their targets: EV 0..10 dB SL (bump), texture at its level.
    unc = next(t for t in ts if t["condition"] == "uncompensated" and t["geometry"] == "bump")
    assert unc["played"]["EV"]["min_db_sl"] == pytest.approx(0.0, abs=0.5)
    assert unc["played"]["EV"]["max_db_sl"] == pytest.approx(10.0, abs=0.5)
    level = 6.0 if unc["texture"] == "smooth" else 12.0
    assert unc["played"]["MV"]["min_db_sl"] == unc["played"]["MV"]["max_db_sl"] == level
    assert "user test: 24 of 24 trials logged" in result.summary_lines()[0]


def test_finger_tracking_follows_the_reported_position(lab, tmp_path):
    protocol = write_usertest(tmp_path, tracking="finger")
    data = tmp_path / "data"
    gain_cal(lab, data)
    opts = options(
        lab, data, protocol=protocol, ground_truth=lab["gt_gain"], device_config=lab["rig"]
    )
    result = run_usertest(opts, stream=io.StringIO())
    assert result.exit_code == 0
    for t in trials(records(result.log_path)):
        assert not schema_errors(t, "session_log")
        assert len(t["touched_mm"]) == 3
        for lo, hi in t["touched_mm"]:
            assert 0.0 <= lo < 10.0 and hi > 60.0
        # The finger touches after the onset: the first frame comes late.
        assert all(a >= p for a, p in zip(t["actual_onsets_s"], t["planned_onsets_s"], strict=True))


def test_interrupt_then_resume_equals_an_uninterrupted_run(lab, tmp_path):
    def opts(data):
        gain_cal(lab, data)
        return options(lab, data, ground_truth=lab["gt_gain"], device_config=lab["rig"])

    ref = run_usertest(opts(tmp_path / "ref"), stream=io.StringIO())
    from masking_lab.usertest.runner import default_responder

    class Interrupting:
        def __init__(self, inner):
            self.inner, self.name, self.n = inner, inner.name, 0

        def start_session(self, info):
            self.inner.start_session(info)

        def trial(self, presentation, play):
            self.n += 1
            if self.n == 7:
                play(None)
                raise KeyboardInterrupt
            return self.inner.trial(presentation, play)

        def close(self):
            self.inner.close()

    data = tmp_path / "data"
    out = io.StringIO()
    stopped = run_usertest(
        opts(data),
        make_responder=lambda n, c: Interrupting(default_responder(n, c)),
        stream=out,
    )
    assert stopped.exit_code == 130 and stopped.n_logged == 6
    assert f"masking-lab resume {stopped.log_path}" in stopped.message
    last = records(stopped.log_path)[-1]
    assert last["record"] == "fault" and last["kind"] == "interrupted"
    assert last["trial_index"] == 6
    # A crash while the next record was being written leaves half a line: resume cuts it.
    with open(stopped.log_path, "a", encoding="utf-8") as fh:
        fh.write('{"record":"usertest_trial","participant":"S0')
    resumed = resume_usertest(
        stopped.log_path, SessionOptions(device_config=lab["rig"]), stream=io.StringIO()
    )
    assert resumed.exit_code == 0 and resumed.n_logged == 24
    recs = records(stopped.log_path)
    assert timeless(recs) == timeless(records(ref.log_path))
    assert of_kind(recs, "resume")[0]["dropped_partial_line"] is True
    # The last complete record says why it stopped: no "unclean_stop" is added.
    assert [f["kind"] for f in of_kind(recs, "fault")] == ["interrupted"]
    with pytest.raises(LogError, match="has finished"):
        resume_usertest(stopped.log_path)


def test_resume_refuses_changed_files_edited_logs_and_threshold_logs(lab, tmp_path):
    protocol = write_usertest(tmp_path, timing=TINY_TIMING)
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)

    class Stop:
        name = "sim"

        def start_session(self, info):
            pass

        def trial(self, presentation, play):
            raise KeyboardInterrupt

        def close(self):
            pass

    def stopped_log():
        result = run_usertest(
            options(lab, data, protocol=protocol, allow_clipping=True),
            make_responder=lambda n, c: Stop(),
            stream=io.StringIO(),
        )
        assert result.exit_code == 130
        return result.log_path

    log = stopped_log()
    original = protocol.read_text(encoding="utf-8")
    protocol.write_text(original + "# edited\n", encoding="utf-8")
    with pytest.raises(LogError, match="changed since this session started"):
        resume_usertest(log)
    out = io.StringIO()
    result = resume_usertest(log, SessionOptions(allow_changed_protocol=True), stream=out)
    assert result.exit_code == 0 and "copies stored in the log" in out.getvalue()
    protocol.write_text(original, encoding="utf-8")

    run_usertest(  # a whole session: its log, without session_end and edited, to resume
        options(lab, data, protocol=protocol, allow_clipping=True), stream=io.StringIO()
    )
    done = sorted((data / "S01").glob("usertest-*.jsonl"))[-1]
    lines = done.read_text(encoding="utf-8").splitlines(keepends=True)
    kept = [ln for ln in lines if '"session_end"' not in ln]
    i = next(i for i, ln in enumerate(kept) if '"trial":1,' in ln)
    other = "hole" if '"geometry":"bump"' in kept[i] else "bump"
    kept[i] = kept[i].replace(f'"geometry":"{_geometry(kept[i])}"', f'"geometry":"{other}"')
    done.write_text("".join(kept), encoding="utf-8")
    with pytest.raises(LogError, match="logged trial 1"):
        resume_usertest(done)

    from masking_lab.usertest.runner import is_usertest_log

    assert is_usertest_log(log) and not is_usertest_log(tmp_path / "nope.jsonl")
    fake = tmp_path / "threshold.jsonl"
    header = records(log)[0]
    del header["kind"]
    fake.write_text(__import__("json").dumps(header) + "\n", encoding="utf-8")
    with pytest.raises(LogError, match="not a user-test session log"):
        resume_usertest(fake)


def _geometry(line: str) -> str:
    return line.split('"geometry":"', 1)[1].split('"', 1)[0]


# ---------------------------------------------------------------------------------------------
# The command line


def test_cli_run_and_resume_dispatch_on_the_protocol_kind(lab, tmp_path, capsys):
    protocol = write_usertest(tmp_path, timing=TINY_TIMING)
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    args = [
        "run", str(protocol), "--participant", "S01", "--device", "sim", "--responder", "sim",
        "--params", str(lab["params"]), "--data", str(data), "--seed", "2", "--no-progress",
    ]  # fmt: skip
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "masking-lab run: error:" in err and "--allow-clipping" in err
    assert main([*args, "--sets", "A"]) == 2
    assert "no sets" in capsys.readouterr().err
    assert main([*args, "--allow-clipping"]) == 0
    out = capsys.readouterr().out
    assert "user test: 24 of 24 trials logged" in out and "compensated" in out
    log = next((data / "S01").glob("usertest-*.jsonl"))
    assert main(["resume", str(log)]) == 2
    assert "has finished" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# Keys on a real pseudo-terminal


class Keypad:
    """The participant's side of a pty: reads prompts, types keys."""

    def __init__(self) -> None:
        self.master, self.slave = pty.openpty()
        self.seen = bytearray()

    def expect(self, text: bytes, timeout: float = 10.0) -> None:
        deadline = time.monotonic() + timeout
        while text not in self.seen:
            left = deadline - time.monotonic()
            assert left > 0, f"never saw {text!r}: {bytes(self.seen)!r}"
            ready, _, _ = select.select([self.master], [], [], left)
            if ready:
                self.seen += os.read(self.master, 4096)

    def type(self, keys: bytes) -> None:
        os.write(self.master, keys)

    def close(self) -> None:
        for fd in (self.master, self.slave):
            os.close(fd)


def _played():
    x = np.zeros(1)
    return StreamResult([1.2], [1.2], x, x, {"EV": x, "MV": x}, {"EV": "EV270", "MV": "MV180"}, 0)


def test_keys_take_the_geometry_then_the_texture(lab):
    design = lab["design"]
    pad = Keypad()
    try:
        keys = UserTestKeysResponder(KeyReader(pad.slave, pad.slave), wait_for_start=True)
        info = UserTestInfo(design.geometries, design.textures, 24, 3, "cue")
        starter = threading.Thread(target=keys.start_session, args=(info,))
        starter.start()
        pad.expect(b"1 bump  2 hole  3 ascending  4 descending")
        pad.expect(b"continuing at trial 4")
        pad.expect(b"space bar")
        pad.type(b" ")
        starter.join(10)
        assert not starter.is_alive()
        trial = trial_list(design, 1)[0]
        pres = UserTrialPresentation(trial, 24, 0.0, design.timing, "cue", 51.0, 91.8)
        out = {}
        played = []

        def play(finger):
            played.append(finger)
            pad.type(b"3")  # typed while the object plays: discarded
            time.sleep(0.05)
            return _played()

        worker = threading.Thread(target=lambda: out.update(r=keys.trial(pres, play)))
        worker.start()
        pad.expect(b"Geometry?")
        pad.type(b"9\x1b[15~2")  # 9 is no geometry key, F5 is an escape sequence
        pad.expect(b"Texture?")
        pad.type(b"4x3")
        worker.join(10)
        assert not worker.is_alive()
        _, answer = out["r"]
        assert played == [None]
        assert (answer.geometry, answer.texture) == (2, 3)
        assert 0 <= answer.geometry_time_s <= answer.texture_time_s
        keys.close()
    finally:
        pad.close()


def test_keys_give_no_answer_after_the_timeout(lab):
    design = lab["design"]
    timing = dataclasses.replace(design.timing, response_timeout_s=0.2)
    pad = Keypad()
    try:
        keys = UserTestKeysResponder(KeyReader(pad.slave, pad.slave), wait_for_start=False)
        trial = trial_list(design, 1)[0]
        pres = UserTrialPresentation(trial, 24, 0.0, timing, "cue", 51.0, 91.8)
        _, answer = keys.trial(pres, lambda finger: _played())
        assert (answer.geometry, answer.texture) == (None, None)
        assert answer.response_time_s == 0.0
        pad.expect(b"No answer in time")
    finally:
        pad.close()


def test_a_keys_session_on_the_participants_terminal(lab, tmp_path):
    protocol = write_usertest(
        tmp_path, geometries=["bump", "hole"], textures=["smooth", "rough"],
        conditions=["uncompensated"], timing=TINY_TIMING,
    )  # fmt: skip
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    pad = Keypad()
    try:
        tty = os.ttyname(pad.slave)
        opts = options(lab, data, protocol=protocol, responder="keys", participant_tty=tty)
        out = {}
        worker = threading.Thread(target=lambda: out.update(r=run_usertest(opts)))
        worker.start()
        pad.expect(b"space bar")
        pad.type(b" ")
        for n in range(1, 5):
            pad.expect(f"Trial {n} of 4".encode())
            pad.expect(b"Geometry? 1 bump  2 hole:", timeout=20)
            pad.seen.clear()
            pad.type(b"1")
            pad.expect(b"Texture?")
            pad.type(b"2")
        worker.join(30)
        assert not worker.is_alive()
    finally:
        pad.close()
    result = out["r"]
    assert result.exit_code == 0
    recs = records(result.log_path)
    assert recs[0]["clock"] == "real" and recs[0]["responder"] == "keys"
    assert [(t["geometry_answer"], t["texture_answer"]) for t in trials(recs)] == [(1, 2)] * 4


def test_a_watchdog_shorter_than_the_stream_refresh_is_refused(lab, tmp_path):
    rig = write_rig(tmp_path, max_level_db_sl=65.0, EV=10.0, MV=10.0)
    text = rig.read_text(encoding="utf-8").replace("watchdog_s: 0.5", "watchdog_s: 0.2")
    rig.write_text(text, encoding="utf-8")
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    with pytest.raises(MaskingLabError, match=r"set serial\.watchdog_s to at least 0\.25 s"):
        run_usertest(options(lab, data, device="emulator", device_config=rig))
    assert not list((data / "S01").glob("*.jsonl"))
