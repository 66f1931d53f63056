"""`masking-lab analyze` end to end on simulated studies: outputs, ground truth, determinism,
tolerance of damaged logs, degenerate studies, progress."""

from __future__ import annotations

import csv
import io
import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.stats import norm

from masking_lab.analysis.batch import progress_printer, run_analyze
from masking_lab.analysis.ramp_fit import ramp_least_squares
from masking_lab.analysis.settings import AnalysisSettings
from masking_lab.commands.cli import main
from masking_lab.core.errors import AnalysisError
from masking_lab.formats.masking_params import load_masking_params
from masking_lab.formats.schemas import schema_errors
from masking_lab.simulation.observer import load_ground_truth
from masking_lab.simulation.synthetic_logs import simulate_study

LEVELS = np.array([5.0, 10.0, 15.0, 20.0, 25.0])
PROTOCOLS = Path(__file__).resolve().parents[1] / "protocols"
OUTPUTS = [
    "thresholds.csv",
    "anova.csv",
    "sphericity.csv",
    "posthoc.csv",
    "one_sample.csv",
    "ramp_fits.csv",
    "problems.csv",
    "masking_params.json",
    "report.txt",
    "figures/masking_experiment1.png",
    "figures/masking_experiment2.png",
]


# psychometric.csv (its bootstrap) and trials.csv are in no test's assertions here: runs that
# do not exist for them skip them (test_lab_outputs and test_analyze_single_read cover them).
NO_TRIAL_TABLES = ("--pf-boot", "0", "--no-trial-tables")


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """Ten simulated participants: baseline, experiment I and experiment II logs."""
    root = tmp_path_factory.mktemp("study")
    simulate_study(root, n_participants=10, seed=0, baseline_start_above_db=10.0)
    return root


@pytest.fixture(scope="module")
def analyzed(study, tmp_path_factory):
    out = tmp_path_factory.mktemp("out")
    argv = ["analyze", str(study), "--out", str(out), "--figures", "summary", "--quiet"]
    assert main([*argv, "--ci-level", "0.99", *NO_TRIAL_TABLES]) == 0
    return out


def _read_csv(path):
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def _population_shift(fn, x, sd):
    """Population mean AL shift of the simulation: E[max(0, s + o)], o ~ N(0, sd), where s > 0."""
    s = np.maximum(0.0, fn.intercept_db + fn.slope * x)
    expected = s * norm.cdf(s / sd) + sd * norm.pdf(s / sd)
    return np.where(s > 0, expected, 0.0)


def test_analyze_writes_every_output(analyzed):
    for name in OUTPUTS:
        assert (analyzed / name).is_file(), name
    thresholds = _read_csv(analyzed / "thresholds.csv")
    assert len(thresholds) == 10 * (4 + 15 + 15)
    assert {r["status"] for r in thresholds} == {"completed"}
    anova = _read_csv(analyzed / "anova.csv")
    assert list(anova[0]) == [
        "experiment",
        "effect",
        "F",
        "df1",
        "df2",
        "p",
        "eps_gg",
        "p_gg",
        "np2",
    ]
    assert [(r["experiment"], r["effect"]) for r in anova] == [
        (e, f)
        for e in ("experiment1", "experiment2")
        for f in ("frequency", "level", "frequency:level")
    ]
    assert len(_read_csv(analyzed / "one_sample.csv")) == 30
    assert len(_read_csv(analyzed / "posthoc.csv")) == 6
    report = (analyzed / "report.txt").read_text()
    for phrase in ("Two-way repeated-measures ANOVA", "Bonferroni", "Pooling (paired)", "knee"):
        assert phrase in report


def test_anova_matches_pingouin_on_the_analysed_thresholds(analyzed):
    pg = pytest.importorskip("pingouin")
    shifts = pd.read_csv(analyzed / "thresholds.csv")
    ours = pd.read_csv(analyzed / "anova.csv")
    for exp in ("experiment1", "experiment2"):
        sub = shifts[shifts["experiment"] == exp]
        ref = pg.rm_anova(
            sub,
            dv="shift_db",
            within=["mv_stimulus", "masker_level_db_sl"],
            subject="participant",
            effsize="np2",
        )
        mine = ours[ours["experiment"] == exp].reset_index(drop=True)
        # CSV keeps 6 significant digits.
        assert mine["F"].to_numpy() == pytest.approx(ref["F"].to_numpy(), rel=1e-5)
        assert mine["p_gg"].to_numpy() == pytest.approx(ref["p_GG_corr"].to_numpy(), rel=1e-4)
        assert mine["np2"].to_numpy() == pytest.approx(ref["np2"].to_numpy(), rel=1e-5)


def test_masking_params_validates_and_recovers_the_ground_truth(analyzed):
    doc = json.loads((analyzed / "masking_params.json").read_text())
    assert schema_errors(doc, "masking_params") == []
    entries = load_masking_params(analyzed / "masking_params.json")
    truth = load_ground_truth()
    paper_pairs = {("EV270", f"MV{f}") for f in (120, 180, 270)}
    paper_pairs |= {(f"MV{f}", "EV270") for f in (120, 180, 270)}
    assert set(entries) == paper_pairs
    assert len(doc["provenance"]["inputs"]) == 30
    for (target, masker), e in entries.items():
        assert e.status == "fitted" and e.extra["uncertainty"] == "bootstrap"
        assert e.extra["ci_level"] == 0.99
        assert f"{target}|{masker}" in e.pooled_pairs
        # Ground truth of the entry: the ramp that best describes the population's mean shifts
        # of the pooled pairs (for an unpooled pair that is its true ramp).
        pairs = [p.split("|") for p in e.pooled_pairs]
        x = np.concatenate([LEVELS] * len(pairs))
        y = np.concatenate(
            [
                _population_shift(truth.masking_function(t, m), LEVELS, truth.shift_sd_db)
                for t, m in pairs
            ]
        )
        a_true, b_true = ramp_least_squares(x, y)
        assert e.intercept_ci_db[0] <= a_true <= e.intercept_ci_db[1], (target, masker, a_true)
        assert e.slope_ci[0] <= b_true <= e.slope_ci[1], (target, masker, b_true)
    # Direction of the science: MV is masked harder (steeper) than EV.
    assert entries[("MV270", "EV270")].slope > entries[("EV270", "MV270")].slope


def test_same_input_same_bytes(study, analyzed, tmp_path):
    # Analyse a copy in another folder: inputs are recorded relative to the data folder, the
    # bootstrap is seeded, figures carry no date — every output is byte-identical except the
    # report's line naming the data folder.
    moved = tmp_path / "moved"
    shutil.copytree(study, moved)
    out = tmp_path / "again"
    argv = ["analyze", str(moved), "--out", str(out), "--figures", "summary", "--quiet"]
    assert main([*argv, "--ci-level", "0.99", *NO_TRIAL_TABLES]) == 0
    for name in OUTPUTS:
        if name != "report.txt":
            assert (out / name).read_bytes() == (analyzed / name).read_bytes(), name
    old = (analyzed / "report.txt").read_text().splitlines()
    new = (out / "report.txt").read_text().splitlines()
    differ = [(a, b) for a, b in zip(old, new, strict=True) if a != b]
    assert differ == [(f"  data folder: {study}", f"  data folder: {moved}")]


def test_created_utc_is_derived_from_the_data_or_a_setting(analyzed, study, tmp_path, monkeypatch):
    doc = json.loads((analyzed / "masking_params.json").read_text())
    headers = [json.loads(p.read_text().split("\n", 1)[0]) for p in study.rglob("*.jsonl")]
    assert doc["created_utc"] == max(h["created_utc"] for h in headers)
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    out = tmp_path / "epoch"
    assert (
        main(
            [
                "analyze",
                str(study),
                "--out",
                str(out),
                "--figures",
                "none",
                "--quiet",
                "--n-boot",
                "200",
                *NO_TRIAL_TABLES,
            ]
        )
        == 0
    )
    assert (
        json.loads((out / "masking_params.json").read_text())["created_utc"]
        == "2023-11-14T22:13:20Z"
    )
    out = tmp_path / "given"
    argv = [
        "analyze",
        str(study),
        "--out",
        str(out),
        "--figures",
        "none",
        "--quiet",
        "--n-boot",
        "200",
    ]
    assert main([*argv, "--created-utc", "2025-01-02T03:04:05Z", *NO_TRIAL_TABLES]) == 0
    assert (
        json.loads((out / "masking_params.json").read_text())["created_utc"]
        == "2025-01-02T03:04:05Z"
    )


def _copy_study(study, dest, participants=None, experiments=None):
    for path in sorted(study.rglob("*.jsonl")):
        pid, exp = path.stem.split("_", 1)
        if participants is not None and pid not in participants:
            continue
        if experiments is not None and exp not in experiments:
            continue
        target = dest / path.relative_to(study)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(path, target)
    return dest


def test_damaged_logs_are_reported_and_skipped_not_fatal(study, tmp_path, capsys):
    data = _copy_study(study, tmp_path / "data", participants={"P01", "P02", "P03"})
    log = data / "P02" / "P02_experiment1.jsonl"
    with open(log, "a", encoding="utf-8") as fh:
        fh.write('{"record": "trial", "set_id": "MV1')  # crash mid-write
    mid = data / "P03" / "P03_experiment2.jsonl"
    lines = mid.read_text().split("\n")
    lines.insert(5, "#### garbage ####")
    mid.write_text("\n".join(lines))
    (data / "empty.jsonl").write_text("")
    (data / "notes.jsonl").write_text('{"record": "trial"}\n')
    out = tmp_path / "out"
    argv = ["analyze", str(data), "--out", str(out), "--figures", "none", "--quiet"]
    # The trial tables stay: their second read of the damaged logs must not break either.
    rc = main([*argv, "--n-boot", "200", "--pf-boot", "0"])
    assert rc == 0
    problems = _read_csv(out / "problems.csv")
    by_log = {(p["log"], p["action"]) for p in problems}
    assert ("P02/P02_experiment1.jsonl", "line ignored") in by_log
    assert ("P03/P03_experiment2.jsonl", "line ignored") in by_log
    assert ("empty.jsonl", "file skipped") in by_log
    assert ("notes.jsonl", "file skipped") in by_log
    report = (out / "report.txt").read_text()
    assert "logs found: 11; analysed: 9; skipped: 2" in report
    assert "truncated last line" in report
    doc = json.loads((out / "masking_params.json").read_text())
    assert {s["path"] for s in doc["provenance"]["skipped_inputs"]} == {
        "empty.jsonl",
        "notes.jsonl",
    }
    assert "warning" in capsys.readouterr().err


def test_one_participant_fits_but_says_which_tests_could_not_run(study, tmp_path, capsys):
    data = _copy_study(study, tmp_path / "data", participants={"P01"})
    out = tmp_path / "out"
    argv = ["analyze", str(data), "--out", str(out), "--figures", "none", "--quiet"]
    assert main([*argv, *NO_TRIAL_TABLES]) == 0
    report = (out / "report.txt").read_text()
    assert "at least two participants" in report
    assert "one participant: no bootstrap" in report
    assert _read_csv(out / "anova.csv") == []
    one_sample = _read_csv(out / "one_sample.csv")
    assert all(r["t"] == "" and r["note"] == "one value only: no test" for r in one_sample)
    entries = load_masking_params(out / "masking_params.json")
    assert all(e.extra["uncertainty"] == "asymptotic" for e in entries.values())

    def refuse(constant):
        raise AssertionError(f"{constant} in masking_params.json")

    json.loads((out / "masking_params.json").read_text(), parse_constant=refuse)
    assert "ANOVA not run" in capsys.readouterr().err


def test_ceilings_are_excluded_and_a_missing_cell_is_named(study, tmp_path):
    data = _copy_study(study, tmp_path / "data", participants={"P01", "P02", "P03", "P04"})
    # Every participant's MV270 at 25 dB SL ended at the ceiling: the cell is missing.
    for path in data.rglob("*_experiment1.jsonl"):
        lines = path.read_text().split("\n")
        for i, line in enumerate(lines):
            if line.startswith('{"record":"set_end","set_id":"MV270_25"'):
                rec = json.loads(line)
                rec.update(status="ceiling", al_db=None, al_db_v=None, al_db_sl=None)
                lines[i] = json.dumps(rec, separators=(",", ":"))
        path.write_text("\n".join(lines))
    out = tmp_path / "out"
    assert (
        main(
            [
                "analyze",
                str(data),
                "--out",
                str(out),
                "--figures",
                "none",
                "--quiet",
                "--n-boot",
                "200",
                *NO_TRIAL_TABLES,
            ]
        )
        == 0
    )
    rows = _read_csv(out / "thresholds.csv")
    ceilings = [r for r in rows if r["status"] == "ceiling"]
    assert len(ceilings) == 4 and all(r["shift_db"] == "" for r in ceilings)
    report = (out / "report.txt").read_text()
    assert "excluded from the statistics" in report
    assert "mv_stimulus=MV270, masker_level_db_sl=25.0: the design has a missing cell" in report
    assert [r["experiment"] for r in _read_csv(out / "anova.csv")] == ["experiment2"] * 3
    fits = {(r["experiment"], r["group"]): r for r in _read_csv(out / "ramp_fits.csv")}
    assert any(g[0] == "experiment1" and "MV270" in g[1] for g in fits)  # still fitted, on 4 levels


def test_participant_without_baseline(study, tmp_path):
    data = _copy_study(study, tmp_path / "data", participants={"P01", "P02", "P03"})
    (data / "P02" / "P02_baseline.jsonl").unlink()
    out = tmp_path / "out"
    argv = [
        "analyze",
        str(data),
        "--out",
        str(out),
        "--figures",
        "none",
        "--quiet",
        "--n-boot",
        "200",
    ]
    assert main([*argv, "--unmasked-al", "baseline", *NO_TRIAL_TABLES]) == 0
    rows = _read_csv(out / "thresholds.csv")
    p2 = [r for r in rows if r["participant"] == "P02"]
    assert p2 and all(r["status"] == "no_baseline" for r in p2)
    report = (out / "report.txt").read_text()
    assert "P02 has no completed baseline AL for EV270" in report
    assert "participants: 2 (P01, P03)" in report
    # With the default (auto) the header calibration stands in and says so.
    out2 = tmp_path / "auto"
    assert (
        main(
            [
                "analyze",
                str(data),
                "--out",
                str(out2),
                "--figures",
                "none",
                "--quiet",
                "--n-boot",
                "200",
                *NO_TRIAL_TABLES,
            ]
        )
        == 0
    )
    p2 = [
        r for r in _read_csv(out2 / "thresholds.csv") if r["participant"] == "P02" and r["masker"]
    ]
    assert {r["unmasked_source"] for r in p2} == {"calibration"}


def test_track_figures_per_session_and_ml_estimator(study, tmp_path):
    data = _copy_study(
        study, tmp_path / "data", participants={"P01"}, experiments={"baseline", "experiment1"}
    )
    out = tmp_path / "out"
    argv = ["analyze", str(data), "--out", str(out), "--quiet", "--n-boot", "200"]
    assert main([*argv, "--estimator", "ml", "--figures", "all", "--pf-boot", "0"]) == 0
    tracks = sorted(p.name for p in (out / "figures" / "tracks").glob("*.png"))
    assert [t.split("_")[:2] for t in tracks] == [["P01", "baseline"], ["P01", "experiment1"]]
    assert (out / "figures" / "tracks" / tracks[0]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    ml = pd.read_csv(out / "thresholds.csv")
    assert set(ml["estimator"]) == {"ml"}
    out_rev = tmp_path / "rev"
    argv = ["analyze", str(data), "--out", str(out_rev), "--quiet", "--figures", "none"]
    assert main([*argv, "--n-boot", "200", *NO_TRIAL_TABLES]) == 0
    rev = pd.read_csv(out_rev / "thresholds.csv")
    both = ml.merge(rev, on=["participant", "experiment", "set_id"], suffixes=("_ml", "_rev"))
    done = both[(both["status_ml"] == "completed") & (both["status_rev"] == "completed")]
    assert len(done) >= 0.9 * len(both)
    # Same quantity, two estimators: per set they differ by staircase noise, on average little.
    diff = (done["al_db_v_ml"] - done["al_db_v_rev"]).to_numpy()
    assert abs(diff.mean()) < 1.0 and np.abs(diff).max() < 6.0


def test_progress_display(study, tmp_path):
    calls = []
    data = _copy_study(study, tmp_path / "data", participants={"P01", "P02"})
    run_analyze(
        data,
        tmp_path / "out",
        AnalysisSettings(figures="none", n_boot=200, pf_boot=0, trial_tables=False),
        progress=lambda i, n: calls.append((i, n)),
    )
    assert calls == [(i, 6) for i in range(1, 7)]
    stream = io.StringIO()
    show = progress_printer(stream, "logs read")
    for i in range(1, 4):
        show(i, 3)
    assert stream.getvalue() == "\r[1/3] logs read\r[2/3] logs read\r[3/3] logs read\n"


def test_no_progress_when_not_a_terminal(study, tmp_path, capsys):
    data = _copy_study(study, tmp_path / "data", participants={"P01", "P02"})
    argv = ["analyze", str(data), "--out", str(tmp_path / "o"), "--figures", "none"]
    assert main([*argv, "--n-boot", "200", *NO_TRIAL_TABLES]) == 0
    assert "logs read" not in capsys.readouterr().err


@pytest.mark.parametrize(
    ("setup", "message"),
    [
        (lambda d: None, "no such folder"),
        (lambda d: d.write_text("{}\n"), "a file, not a folder"),
        (lambda d: d.mkdir(), "no session logs"),
        (lambda d: (d.mkdir(), (d / "x.jsonl").write_text("garbage\n")), "none of the 1 log file"),
    ],
)
def test_unusable_data_folders_exit_2_with_a_message(tmp_path, capsys, setup, message):
    data = tmp_path / "data"
    setup(data)
    assert main(["analyze", str(data), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


@pytest.mark.parametrize(
    "command",
    [
        ["analyze", "", "--out", "OUT", "--quiet"],
        ["status", ""],  # read the current folder recursively before the shared check
        ["usertest-report", "", "--out", "OUT"],
        ["analyze", "  ", "--out", "OUT", "--quiet"],
    ],
)
def test_an_empty_data_folder_name_is_refused_not_read_as_the_current_folder(
    tmp_path, capsys, monkeypatch, study, command
):
    monkeypatch.chdir(tmp_path)  # a folder with logs below it would otherwise be analysed
    shutil.copytree(study, tmp_path / "logs")
    argv = [str(tmp_path / "out") if a == "OUT" else a for a in command]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "empty name" in err and "give the folder holding session logs" in err
    assert not (tmp_path / "out").exists()


def test_only_baseline_logs_write_thresholds_then_explain(study, tmp_path, capsys):
    data = _copy_study(study, tmp_path / "data", participants={"P01"}, experiments={"baseline"})
    out = tmp_path / "out"
    assert main(["analyze", str(data), "--out", str(out), "--quiet"]) == 2
    assert "no completed masked set" in capsys.readouterr().err
    assert len(_read_csv(out / "thresholds.csv")) == 4


def test_bad_settings_are_refused():
    with pytest.raises(AnalysisError, match="bootstrap replicates"):
        AnalysisSettings(n_boot=5)
    with pytest.raises(AnalysisError, match="created_utc"):
        AnalysisSettings(created_utc="today")
    with pytest.raises(AnalysisError, match="two or more levels"):
        AnalysisSettings(pool_groups=("MV120",))


def test_logs_of_the_real_runner_are_analysed(tmp_path, capsys):
    """Format contract with `masking-lab run` (simulated device and observer, virtual time)."""
    data = tmp_path / "data"
    runs = [
        ("baseline", "EV270,MV120,MV270"),
        ("experiment1", "MV120_10,MV120_25,MV270_10,MV270_25"),
    ]
    for participant in ("S01", "S02"):
        for protocol, sets in runs:
            argv = ["run", str(PROTOCOLS / f"{protocol}.yaml"), "--participant", participant]
            argv += ["--device", "sim", "--responder", "sim", "--data", str(data)]
            argv += ["--seed", "3", "--no-progress", "--sets", sets]
            if main(argv) != 0:
                pytest.skip(f"the runner could not run here: {capsys.readouterr().err[-300:]}")
    out = tmp_path / "out"
    assert main(["analyze", str(data), "--out", str(out), "--figures", "none", "--quiet"]) == 0
    rows = _read_csv(out / "thresholds.csv")
    assert len(rows) == 2 * (3 + 4)
    assert {r["status"] for r in rows} == {"completed"}
    masked = [r for r in rows if r["masker"]]
    assert {r["unmasked_source"] for r in masked} == {"baseline"}
    entries = load_masking_params(out / "masking_params.json")
    assert set(entries) == {("EV270", "MV120"), ("EV270", "MV270")}
    assert all(e.status == "fitted" for e in entries.values())


def test_user_test_logs_are_skipped_with_a_pointer(study, tmp_path):
    # Two participants suffice: the user-test log is skipped whatever else is in the folder.
    data = _copy_study(study, tmp_path / "data", participants={"P01", "P02"})
    header = {
        "record": "header",
        "kind": "usertest",
        "participant": "S01",
        "protocol": {"experiment": "usertest"},
    }
    (data / "usertest-S01.jsonl").write_text(json.dumps(header) + "\n")
    out = tmp_path / "out"
    argv = ["analyze", str(data), "--out", str(out), "--figures", "none", "--quiet"]
    assert main([*argv, "--n-boot", "200", *NO_TRIAL_TABLES]) == 0
    problems = _read_csv(out / "problems.csv")
    skipped = [p for p in problems if p["log"] == "usertest-S01.jsonl"]
    assert skipped and "usertest-report" in skipped[0]["problem"]
    assert skipped[0]["action"] == "file skipped"
