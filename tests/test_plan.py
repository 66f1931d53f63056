"""`masking-lab plan`: the grid, the true thresholds, the summaries and the command."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from masking_lab.commands.cli import main
from masking_lab.core.errors import AnalysisError, ProtocolError, StaircaseError
from masking_lab.formats.protocol import load_protocol
from masking_lab.planning import plan as P
from masking_lab.planning.figures import png_bytes, speed_accuracy
from masking_lab.planning.report import answer_text
from masking_lab.procedures.staircase_batch import COMPLETED, RUNNING, TRIAL_CAP, Observer, simulate
from masking_lab.simulation.observer import load_ground_truth

ROOT = Path(__file__).resolve().parents[1]
EXP1 = ROOT / "protocols" / "experiment1.yaml"
BASELINE = ROOT / "protocols" / "baseline.yaml"


@pytest.fixture(scope="module")
def exp1():
    return load_protocol(EXP1)


@pytest.fixture(scope="module")
def truth():
    return load_ground_truth()


# ---------------------------------------------------------------- settings from text


def test_stop_rules_parse_sort_and_deduplicate():
    rules = P.parse_stop_rules("11/8, 7/4,11/8")
    assert [r.label for r in rules] == ["7/4", "11/8"]


@pytest.mark.parametrize("text", ["11", "11/x", "8/11", "0/0", ","])
def test_bad_stop_rules_say_how_to_write_them(text):
    with pytest.raises(StaircaseError, match=r"stop rule|no stop rules|RUN/AVERAGED"):
        P.parse_stop_rules(text)


def test_schedules_cross_ratios_and_label_themselves():
    scheds = P.parse_schedules("4,4,4,2; 2", ratios=(1.0, 0.7393))
    assert [s.label for s in scheds] == ["4,4,4,2", "4,4,4,2 d/u 0.7393", "2", "2 d/u 0.7393"]


@pytest.mark.parametrize("text", ["4,x", "4,-2", ";"])
def test_bad_schedules_are_refused(text):
    with pytest.raises(StaircaseError, match=r"step schedule|positive step|no step schedules"):
        P.parse_schedules(text)


@pytest.mark.parametrize("text", ["1,a", "0", "-1"])
def test_bad_ratios_are_refused(text):
    with pytest.raises(StaircaseError, match="ratios"):
        P.parse_ratios(text)


def test_defaults_include_the_protocols_own_setting(exp1):
    assert P.StopRule(11, 8) in P.default_stop_rules(exp1)
    scheds = P.default_schedules(exp1)
    assert scheds[0] == P.Schedule((4, 4, 4, 2), 1.0)
    assert [s.step_sizes_db for s in scheds] == [(4, 4, 4, 2), (4, 2), (2,)]
    with_gp = P.default_schedules(exp1, ratios=(1.0, P.GARCIA_PEREZ_RATIO))
    assert len(with_gp) == 6


def test_sets_that_differ_beyond_the_start_level_are_refused(exp1):
    odd = replace(exp1.sets[1], staircase=replace(exp1.sets[1].staircase, n_down=2))
    mixed = replace(exp1, sets=(exp1.sets[0], odd))
    with pytest.raises(StaircaseError, match="differ only in start level"):
        P.protocol_staircase(mixed)


def test_trial_duration_is_presentation_answer_and_pause(exp1):
    # paper timing: 1.2 s lead-in, three 1.8 s intervals, two 0.6 s gaps; 0.5 s pause
    assert P.trial_duration_s(exp1.timing, 1.0) == pytest.approx(1.2 + 5.4 + 1.2 + 1.0 + 0.5)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"replicates": 1}, "replicates"),
        ({"ml_replicates": 1}, "ml_replicates"),
        ({"precision_db": 0.0}, "precision_db"),
        ({"response_s": -1.0}, "response_s"),
        ({"max_reversals": 5}, "max_reversals"),
    ],
)
def test_bad_plan_settings_are_refused(kwargs, match):
    with pytest.raises((AnalysisError, StaircaseError), match=match):
        P.PlanSettings(stop_rules=(P.StopRule(11, 8),), schedules=(P.Schedule((2,)),), **kwargs)


# ---------------------------------------------------------------- true thresholds


def test_masked_thresholds_are_the_ground_truth_shifts(exp1, truth):
    thr = P.true_thresholds_db(exp1, truth, 5, np.random.default_rng(0), spread=False)
    ids = [s.id for s in exp1.sets]
    # paper Table 2 ramps: MV120 masks EV270 as max(0, −7.442 + 0.711·x)
    assert thr[ids.index("MV120_25")] == pytest.approx([-7.442 + 0.711 * 25] * 5)
    assert np.all(thr[ids.index("MV120_05")] == 0.0)  # below the knee
    assert thr[ids.index("MV270_10")] == pytest.approx([-2.240 + 0.602 * 10] * 5)


def test_spread_scatters_shifts_above_the_knee_only(exp1, truth):
    thr = P.true_thresholds_db(exp1, truth, 4000, np.random.default_rng(1))
    ids = [s.id for s in exp1.sets]
    above = thr[ids.index("MV120_25")]
    assert above.mean() == pytest.approx(-7.442 + 0.711 * 25, abs=0.1)
    assert above.std() == pytest.approx(truth.shift_sd_db, rel=0.1)
    assert np.all(thr[ids.index("MV120_05")] == 0.0)


def test_baseline_thresholds_are_unmasked_als(truth):
    base = load_protocol(BASELINE)
    thr = P.true_thresholds_db(base, truth, 3, np.random.default_rng(0), spread=False)
    assert thr[[s.id for s in base.sets].index("MV120")] == pytest.approx([-26.0] * 3)


def test_baseline_target_missing_from_the_ground_truth_names_the_key(truth):
    base = load_protocol(BASELINE)
    thin = replace(truth, unmasked_al_db_v={"EV270": -14.0})
    with pytest.raises(ProtocolError, match=r"unmasked_al_db_v\.MV120"):
        P.true_thresholds_db(base, thin, 3, np.random.default_rng(0), truth_source="gt.yaml")


def test_override_gives_every_set_that_threshold(exp1, truth):
    thr = P.true_thresholds_db(exp1, truth, 2, np.random.default_rng(0), override_db=6.5)
    assert np.all(thr == 6.5)
    with pytest.raises(AnalysisError, match="finite"):
        P.true_thresholds_db(exp1, truth, 2, np.random.default_rng(0), override_db=math.inf)


# ---------------------------------------------------------------- summaries


def test_summarize_reports_cost_ends_and_error():
    n_trials = np.array([40, 50, 60, 70, 150])
    status = np.array([COMPLETED, COMPLETED, COMPLETED, COMPLETED, TRIAL_CAP], dtype=np.int8)
    est = np.array([1.0, 2.0, 3.0, 4.0, np.nan])
    true = np.full(5, 2.0)
    s = P.summarize(n_trials, status, est, true, trial_s=6.0)
    assert s["trials_median"] == 60
    assert s["minutes_median"] == pytest.approx(6.0)  # 60 trials × 6 s
    assert s["completed"] == pytest.approx(0.8)
    assert s["trial_cap"] == pytest.approx(0.2)
    assert s["n_al"] == 4
    assert s["bias_db"] == pytest.approx(0.5)  # errors −1, 0, 1, 2
    assert s["sd_db"] == pytest.approx(math.sqrt(5 / 3))
    assert s["rmse_db"] == pytest.approx(math.sqrt(6 / 4))


@pytest.mark.parametrize("reps", [1, 2, 7, 500, 2000])
def test_summarize_sets_gives_each_row_the_numbers_of_numpy_on_that_row_alone(reps):
    # the plan's tables must not change: every number equals the one-row numpy call, bit for bit
    rng = np.random.default_rng(reps)
    n_trials = rng.integers(10, 300, size=(6, reps))
    status = rng.choice([COMPLETED, TRIAL_CAP, RUNNING], size=(6, reps)).astype(np.int8)
    est = np.where(rng.random((6, reps)) < 0.2, np.nan, rng.normal(0.0, 1.3, (6, reps)))
    true = rng.normal(0.0, 2.0, (6, reps))
    rows = P.summarize_sets(n_trials, status, est, true, trial_s=9.3)
    for j, row in enumerate(rows):
        med, p90 = np.percentile(n_trials[j], [50, 90])
        err = (est[j] - true[j])[np.isfinite(est[j])]
        expected = {
            "sessions": reps,
            "completed": float(np.mean(status[j] == COMPLETED)),
            "trial_cap": float(np.mean(status[j] == TRIAL_CAP)),
            "unfinished": float(np.mean(status[j] == RUNNING)),
            "trials_median": float(med),
            "trials_p90": float(p90),
            "trials_mean": float(np.mean(n_trials[j])),
            "minutes_p90": float(p90) * 9.3 / 60.0,
            "n_al": err.size,
            "bias_db": float(err.mean()) if err.size else math.nan,
            "sd_db": float(err.std(ddof=1)) if err.size > 1 else math.nan,
            "rmse_db": float(np.sqrt(np.mean(err**2))) if err.size else math.nan,
        }
        for key, value in expected.items():
            assert row[key] == value or (math.isnan(row[key]) and math.isnan(value)), key


def test_pool_uses_root_mean_square_within_set_sd_and_the_worst_set():
    a = {
        "sessions": 10,
        "completed": 1.0,
        "ceiling": 0,
        "floor": 0,
        "trial_cap": 0,
        "unfinished": 0,
        "n_al": 10,
        "bias_db": 1.0,
        "sd_db": 1.0,
        "rmse_db": 1.5,
    }
    b = {**a, "bias_db": -1.0, "sd_db": 2.0, "completed": 0.5}
    pooled = P.pool([a, b], np.array([10, 20, 30]), trial_s=60.0)
    assert pooled["bias_db"] == 0.0
    assert pooled["sd_db"] == pytest.approx(math.sqrt(2.5))
    assert pooled["worst_sd_db"] == 2.0
    assert pooled["worst_abs_bias_db"] == 1.0
    assert pooled["completed"] == 0.75
    assert pooled["minutes_median"] == 20.0


# ---------------------------------------------------------------- the plan


@pytest.fixture(scope="module")
def small_plan(exp1, truth):
    settings = P.PlanSettings(
        stop_rules=(P.StopRule(7, 4), P.StopRule(11, 8)),
        schedules=(P.Schedule((4, 4, 4, 2)), P.Schedule((2,))),
        observer=Observer(truth.scale_db, truth.lapse),
        replicates=40,
        ml_replicates=8,
        max_reversals=13,
        seed=3,
    )
    thr = P.true_thresholds_db(exp1, truth, 40, np.random.default_rng(9))
    return settings, thr, P.run_plan(exp1, settings, thr)


def test_plan_table_covers_the_grid_and_marks_the_protocol(small_plan):
    _, _, result = small_plan
    keys = {(r["schedule"], r["rule"], r["estimator"]) for r in result.table}
    assert keys == {
        (s, r, e) for s in ("4,4,4,2", "2") for r in ("7/4", "11/8") for e in P.ESTIMATORS
    }
    own = [r for r in result.table if r["own"]]
    assert {(r["schedule"], r["rule"]) for r in own} == {("4,4,4,2", "11/8")}
    assert len(result.per_set) == len(result.table) * 15
    for r in result.table:
        assert r["minutes_median"] == pytest.approx(r["trials_median"] * result.trial_s / 60)
    by = {(r["schedule"], r["rule"], r["estimator"]): r for r in result.table}
    assert (
        by["4,4,4,2", "11/8", "reversal_mean"]["trials_median"]
        > by["4,4,4,2", "7/4", "reversal_mean"]["trials_median"]
    )
    # every ladder rule discards as many reversals as the protocol (3)
    assert [r["rule"] for r in result.ladder[:3]] == ["4/1", "5/2", "6/3"]
    assert {r["n_reversals"] - r["n_averaged"] for r in result.ladder} == {3}


def test_plan_numbers_equal_a_direct_simulation_of_the_rule(exp1, small_plan):
    # The plan derives 11/8 with a 150-trial cap from one long run; re-simulate it directly
    # (its 40 replicates are one chunk, with the first seed of the chunk plan).
    from masking_lab.planning.parallel import chunk_plan
    from masking_lab.planning.plan_chunks import CHUNK_REPLICATES

    settings, thr, result = small_plan
    [(_, seed)] = chunk_plan(settings.seed, 40, CHUNK_REPLICATES)
    base = P.protocol_staircase(exp1)
    starts = np.repeat([s.staircase.start_level_db for s in exp1.sets], 40)
    direct = simulate(
        base,
        thr.reshape(-1),
        settings.observer,
        np.random.default_rng(seed),
        start_level_db=starts,
    )
    truth = thr.reshape(-1)
    for j, spec in enumerate(exp1.sets):
        rows = slice(40 * j, 40 * (j + 1))
        got = next(
            r
            for r in result.per_set
            if r["set"] == spec.id
            and r["schedule"] == "4,4,4,2"
            and r["rule"] == "11/8"
            and r["estimator"] == "reversal_mean"
        )
        assert got["trials_median"] == np.median(direct.n_trials[rows])
        err = (direct.al_db[rows] - truth[rows])[direct.completed[rows]]
        assert got["bias_db"] == pytest.approx(err.mean(), abs=1e-12)
        assert got["sd_db"] == pytest.approx(err.std(ddof=1), abs=1e-12)


def test_answers_pick_the_first_rule_that_is_precise_enough(exp1, small_plan):
    settings, thr, _ = small_plan
    easy = P.run_plan(exp1, replace(settings, precision_db=100.0, ml_replicates=0), thr)
    assert [a.rule.label for a in easy.answers] == ["4/1", "4/1"]
    hard = P.run_plan(exp1, replace(settings, precision_db=0.01, ml_replicates=0), thr)
    assert all(a.rule is None for a in hard.answers)
    text = answer_text(hard.answers[0], hard.settings, 150)
    assert "no stop rule up to 13 reversals reaches ±0.01 dB" in text
    found = answer_text(easy.answers[0], easy.settings, 150)
    assert found.startswith("4,4,4,2: 4/1 (run 4 reversals, average the last 1)")


def test_thresholds_of_the_wrong_shape_are_refused(exp1, small_plan):
    settings, thr, _ = small_plan
    with pytest.raises(AnalysisError, match="shape"):
        P.run_plan(exp1, settings, thr[:3])


def test_figure_renders_to_the_same_png_bytes_twice(small_plan):
    _, _, result = small_plan
    a = png_bytes(speed_accuracy(result, title="t"))
    b = png_bytes(speed_accuracy(result, title="t"))
    assert a[:8] == b"\x89PNG\r\n\x1a\n"
    assert a == b


# ---------------------------------------------------------------- the command


def test_plan_command_on_experiment_1_prints_the_table_and_writes_the_figure(tmp_path, capsys):
    out = tmp_path / "plan"
    code = main(
        [
            "plan",
            str(EXP1),
            "--replicates",
            "25",
            "--ml-replicates",
            "5",
            "--max-reversals",
            "15",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    captured = capsys.readouterr()
    assert "reversal mean (dB)" in captured.out
    assert "*11/8" in captured.out
    assert "Reversals needed for ±1 dB" in captured.out
    assert "Per set, this protocol's setting (4,4,4,2 dB, 11/8)" in captured.out
    assert "plan: schedule 1/3" in captured.err  # progress goes to stderr
    for name in ("plan.txt", "plan_table.csv", "plan_sets.csv", "plan_ladder.csv"):
        assert (out / name).stat().st_size > 0
    assert (out / "plan_speed_accuracy.png").read_bytes()[:4] == b"\x89PNG"
    header = (out / "plan_table.csv").read_text().splitlines()[0].split(",")
    assert {"schedule", "rule", "estimator", "trials_median", "bias_db", "sd_db"} <= set(header)


def test_plan_command_takes_observer_and_grid_settings(tmp_path, capsys):
    code = main(
        [
            "plan",
            str(EXP1),
            "--replicates",
            "10",
            "--ml-replicates",
            "0",
            "--stop-rules",
            "9/6",
            "--schedules",
            "2",
            "--ratios",
            "1,0.7393",
            "--scale-db",
            "3",
            "--lapse",
            "0",
            "--true-threshold-db",
            "5",
            "--max-reversals",
            "9",
            "--out",
            str(tmp_path),
        ]
    )
    assert code == 0
    out = capsys.readouterr().out
    assert "logistic scale 3 dB, lapse 0" in out
    assert "5 dB SL in every set" in out
    assert "2 d/u 0.7393" in out
    # the grid asked for (the header names the protocol's own 11/8 as "this protocol")
    table = out.split("Speed and accuracy of each setting")[1].split("Per set")[0]
    assert "9/6" in table and "11/8" not in table


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--stop-rules", "11-8"], "stop rule '11-8'"),
        (["--ground-truth", "/nonexistent/gt.yaml"], "no such ground-truth file"),
        (["--lapse", "0.5"], "--lapse 0.5"),
        (["--schedules", "4,a"], "step schedule"),
    ],
)
def test_plan_command_bad_input_exits_2_with_a_message(tmp_path, capsys, args, message):
    code = main(["plan", str(EXP1), "--replicates", "5", "--out", str(tmp_path), *args])
    assert code == 2
    err = capsys.readouterr().err
    assert message in err
    assert "Traceback" not in err


def test_plan_command_on_a_missing_protocol_exits_2(tmp_path, capsys):
    assert main(["plan", str(tmp_path / "nope.yaml"), "--out", str(tmp_path)]) == 2
    assert "cannot read the file" in capsys.readouterr().err


def test_plan_command_refuses_zero_replicates(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["plan", str(EXP1), "--replicates", "0"])
    assert exc.value.code == 2
    assert "must be ≥ 1" in capsys.readouterr().err
