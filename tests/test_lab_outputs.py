"""What a lab expects from `analyze` in its first week (issue 17): trials.csv against the logs,
psychometric functions against an independent fit, the study matrix on a study with a partial
and a missing session, the ML estimator's intervals, and report.txt/report.html parity."""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from masking_lab.analysis.psychometric import deviance, fit_pf, pf_curve
from masking_lab.analysis.study_status import SessionInfo, status_matrix
from masking_lab.analysis.trials_table import TRIAL_COLUMNS
from masking_lab.commands.cli import main
from masking_lab.simulation.synthetic_logs import simulate_study


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """Three simulated participants: baseline, experiment I and experiment II logs."""
    root = tmp_path_factory.mktemp("study")
    simulate_study(root, n_participants=3, seed=4, baseline_start_above_db=10.0)
    return root


@pytest.fixture(scope="module")
def analyzed(study, tmp_path_factory):
    out = tmp_path_factory.mktemp("out") / "a"
    assert main(["analyze", str(study), "--out", str(out), "--quiet"]) == 0
    return out


def _log_trials(path: Path) -> list[dict]:
    recs = [json.loads(line) for line in path.read_text().splitlines()]
    return [dict(r, line=i + 1) for i, r in enumerate(recs) if r["record"] == "trial"]


def test_trials_csv_has_one_row_per_logged_trial_with_its_values(study, analyzed):
    table = pd.read_csv(analyzed / "trials.csv", keep_default_na=False, na_values=[""])
    assert list(table.columns) == TRIAL_COLUMNS
    logs = sorted(study.rglob("*.jsonl"))
    assert sorted(table["log"].unique()) == sorted(p.relative_to(study).as_posix() for p in logs)
    for path in logs:
        rel = path.relative_to(study).as_posix()
        rows = table[table["log"] == rel].reset_index(drop=True)
        logged = _log_trials(path)
        assert len(rows) == len(logged)
        header = json.loads(path.read_text().splitlines()[0])
        assert set(rows["participant"]) == {header["participant"]}
        assert set(rows["experiment"]) == {header["protocol"]["experiment"]}
        for (_, row), rec in zip(rows.iterrows(), logged, strict=True):
            assert row["set_id"] == rec["set_id"] and row["trial"] == rec["trial_index"]
            assert row["line"] == rec["line"]
            assert row["correct"] == int(rec["correct"]) and row["reversal"] == int(rec["reversal"])
            assert row["target_interval"] == rec["target_interval"]
            assert row["response_interval"] == rec["response_interval"]
            assert row["level_db_v"] == pytest.approx(rec["level_db_v"], abs=1e-4)
            unit_level = rec["level_db_sl"] if row["level_unit"] == "db_sl" else rec["level_db_v"]
            assert row["level_db"] == pytest.approx(unit_level, abs=1e-4)
            assert row["response_time_s"] == pytest.approx(rec["response_time_s"], rel=1e-5)
            for i in range(3):
                assert row[f"planned_onset_{i + 1}_s"] == pytest.approx(
                    rec["planned_onsets_s"][i], rel=1e-5
                )
                assert row[f"actual_onset_{i + 1}_s"] == pytest.approx(
                    rec["actual_onsets_s"][i], rel=1e-5
                )
    # Each set attempt carries its thresholds.csv status, so one filter keeps the used sets.
    thresholds = pd.read_csv(analyzed / "thresholds.csv")
    keys = zip(thresholds["log"], thresholds["set_id"], strict=True)
    status = dict(zip(keys, thresholds["status"], strict=True))
    assert all(status[(r.log, r.set_id)] == r.set_status for r in table.itertuples(index=False))


def test_trials_parquet_matches_the_csv(analyzed):
    pytest.importorskip("pyarrow")
    csv = pd.read_csv(analyzed / "trials.csv", keep_default_na=False, na_values=[""])
    pq = pd.read_parquet(analyzed / "trials.parquet")
    assert list(pq.columns) == TRIAL_COLUMNS and len(pq) == len(csv)
    assert (pq["correct"].to_numpy() == csv["correct"].to_numpy()).all()
    assert np.allclose(pq["level_db"], csv["level_db"], atol=1e-4)
    assert str(pq["trial"].dtype) == "int64"


def test_data_dictionaries_name_every_column(analyzed):
    root = Path(__file__).resolve().parents[1] / "data_schema"
    for name, columns in (
        ("trials.csv.json", TRIAL_COLUMNS),
        ("psychometric.csv.json", list(pd.read_csv(analyzed / "psychometric.csv").columns)),
        ("study_status.csv.json", list(pd.read_csv(analyzed / "study_status.csv").columns)),
    ):
        doc = json.loads((root / name).read_text())
        assert list(doc["columns"]) == columns, name
        assert all(doc["columns"][c].get("description") for c in columns), name


def _grid_mle(x, n, k, guess=1 / 3):
    """Independent maximum likelihood: brute force over a fine (α, β, λ) grid."""
    alphas = np.linspace(x.min() - 2, x.max() + 2, 161)
    betas = np.geomspace(0.05, 10.0, 90)
    lapses = np.linspace(0.0, 0.1, 21)
    a, b, lam = np.meshgrid(alphas, betas, lapses, indexing="ij")
    p = pf_curve(x[None, None, None, :], a[..., None], b[..., None], lam[..., None], guess)
    p = np.clip(p, 1e-12, 1 - 1e-12)
    ll = (k * np.log(p) + (n - k) * np.log1p(-p)).sum(axis=-1)
    i = np.unravel_index(np.argmax(ll), ll.shape)
    return alphas[i[0]], betas[i[1]], lapses[i[2]], float(ll[i])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pf_fit_agrees_with_a_brute_force_likelihood_grid(seed):
    rng = np.random.default_rng(seed)
    x = np.repeat(np.arange(-8.0, 9.0, 2.0), 25)
    truth = (rng.uniform(-2, 2), rng.uniform(0.4, 1.5), rng.uniform(0.0, 0.06))
    r = rng.random(x.size) < pf_curve(x, *truth, 1 / 3)
    fit = fit_pf(x, r, n_boot=0)
    xu = np.unique(x)
    n = np.array([np.sum(x == v) for v in xu], dtype=float)
    k = np.array([np.sum(r[x == v]) for v in xu], dtype=float)
    a, b, lam, ll_grid = _grid_mle(xu, n, k)
    p = np.clip(pf_curve(xu, fit.threshold_db, fit.slope_per_db, fit.lapse, 1 / 3), 1e-12, 1)
    ll_fit = float((k * np.log(p) + (n - k) * np.log1p(-p)).sum())
    assert ll_fit >= ll_grid - 1e-6  # never worse than the best grid point
    assert ll_fit - ll_grid < 0.05  # and the grid's neighbourhood holds the same maximum
    assert fit.threshold_db == pytest.approx(a, abs=0.15)
    assert fit.slope_per_db == pytest.approx(b, rel=0.1)
    assert fit.lapse == pytest.approx(lam, abs=0.01)
    # the deviance is the saturated model's log-likelihood minus the fit's, doubled
    phat = np.clip(k / n, 1e-12, 1 - 1e-12)
    ll_sat = float((k * np.log(phat) + (n - k) * np.log1p(-phat)).sum())
    assert fit.deviance == pytest.approx(2 * (ll_sat - ll_fit), abs=1e-6)


def test_bootstrap_intervals_cover_the_truth_and_the_deviance_p_detects_misfit():
    rng = np.random.default_rng(7)
    x = np.repeat(np.arange(-8.0, 9.0, 2.0), 30)
    r = rng.random(x.size) < pf_curve(x, 0.5, 0.8, 0.02, 1 / 3)
    fit = fit_pf(x, r, n_boot=300, seed=3)
    assert fit.threshold_ci_db[0] < 0.5 < fit.threshold_ci_db[1]
    assert fit.slope_ci_per_db[0] < 0.8 < fit.slope_ci_per_db[1]
    assert fit.lapse_ci[0] <= 0.02 <= fit.lapse_ci[1]
    assert fit.al_ci_db[0] < fit.al_db < fit.al_ci_db[1] and fit.al_sd_db > 0
    assert fit.deviance_p > 0.01 and fit.n_boot >= 270
    assert fit_pf(x, r, n_boot=300, seed=3) == fit  # seeded: the same numbers again
    # Non-monotone answers (chance at the top level) cannot come from the model.
    bad = r.copy()
    top = x == x.max()
    bad[top] = np.arange(top.sum()) % 3 == 0
    misfit = fit_pf(x, bad, n_boot=300, seed=3)
    assert misfit.deviance > fit.deviance and misfit.deviance_p < 0.01


def test_pf_without_an_interior_maximum_is_a_failed_fit_not_a_number():
    assert not fit_pf([1.0] * 20, [True] * 20).ok
    assert "at least 10" in fit_pf([1.0, 2.0], [True, False]).message
    assert float(deviance([4], [4], [1.0])) == pytest.approx(0.0, abs=1e-9)


def test_psychometric_csv_has_a_fit_per_completed_set(analyzed):
    pf = pd.read_csv(analyzed / "psychometric.csv")
    th = pd.read_csv(analyzed / "thresholds.csv")
    done = th[th["status"] == "completed"]
    assert len(pf) == len(done)
    fitted = pf[pf["status"] == "fitted"]
    assert len(fitted) >= 0.9 * len(pf)
    cols = ["threshold_db", "slope_per_db", "lapse", "deviance", "deviance_p"]
    assert fitted[cols].notna().all().all()
    ok = fitted["threshold_ci95_low_db"].notna()
    assert (fitted.loc[ok, "threshold_ci95_low_db"] <= fitted.loc[ok, "threshold_db"] + 1e-9).all()
    assert ((fitted["lapse"] >= 0) & (fitted["lapse"] <= 0.1)).all()
    html = (analyzed / "report.html").read_text()
    assert html.count("<svg") == len(pf) and "psychometric function of P01" in html


def test_ml_estimator_fills_the_sd_and_interval_columns(study, tmp_path):
    # One participant's sets: the columns are filled set by set, the ML fits are the cost, and
    # the psychometric bootstrap and trial tables are not read here.
    data = tmp_path / "data"
    shutil.copytree(study / "P01", data / "P01")
    out = tmp_path / "ml"
    argv = ["analyze", str(data), "--out", str(out), "--estimator", "ml", "--figures", "none"]
    assert main([*argv, "--quiet", "--pf-boot", "0", "--no-trial-tables"]) == 0
    th = pd.read_csv(out / "thresholds.csv")
    done = th[th["status"] == "completed"]
    assert done["al_sd_db"].notna().mean() > 0.9
    have = done[done["al_ci95_low_db"].notna()]
    al = have["al_db_sl"].fillna(have["al_db_v"])
    assert (have["al_ci95_low_db"] <= al + 1e-6).all() and (
        al <= have["al_ci95_high_db"] + 1e-6
    ).all()


def _copy(study: Path, dest: Path) -> Path:
    shutil.copytree(study, dest)
    return dest


def test_status_matrix_on_a_study_with_a_partial_and_a_missing_session(study, tmp_path, capsys):
    data = _copy(study, tmp_path / "data")
    (data / "P02" / "P02_experiment2.jsonl").unlink()  # missing
    log = data / "P03" / "P03_experiment1.jsonl"
    lines = log.read_text().splitlines(keepends=True)
    ends = [i for i, line in enumerate(lines) if '"record":"set_end"' in line.replace(" ", "")]
    keep = lines[: ends[2] + 6]  # three sets done, a few trials into the fourth
    log.write_text("".join(keep))
    trials_kept = sum('"record":"trial"' in line.replace(" ", "") for line in keep)
    assert main(["status", str(data)]) == 0
    shown = capsys.readouterr().out
    row = {ln.split()[0]: ln for ln in shown.splitlines() if ln.strip().startswith("P0")}
    assert "missing" in row["P02"]
    assert f"partial 3/15 sets, {trials_kept} trials" in row["P03"]
    assert row["P01"].count("complete") == 3
    out = tmp_path / "out"
    argv = ["analyze", str(data), "--out", str(out), "--quiet", "--figures", "none"]
    assert main([*argv, "--pf-boot", "0"]) == 0  # psychometric.csv is not read here
    matrix = pd.read_csv(out / "study_status.csv")
    cell = matrix.set_index(["participant", "experiment"])["status"]
    assert cell[("P02", "experiment2")] == "missing"
    assert cell[("P03", "experiment1")] == "partial"
    assert "partial 3/15 sets" in (out / "report.txt").read_text()
    assert "partial 3/15 sets" in (out / "report.html").read_text()


def test_status_matrix_marks_a_refused_set():
    s = [SessionInfo("P1", "e1", "a.jsonl", ("A", "B"), True)]
    t = pd.DataFrame(
        {
            "participant": ["P1", "P1"],
            "experiment": ["e1", "e1"],
            "set_id": ["A", "B"],
            "status": ["completed", "aborted"],
            "trials": [40, 0],
            "log": ["a.jsonl", "a.jsonl"],
            "note": [None, "level above the rig's limit"],
        }
    )
    (cell,) = status_matrix(s, t)
    assert cell.status == "refused" and cell.sets_done == 1


def _text_headings(text: str) -> list[str]:
    lines = text.splitlines()
    return [
        lines[i - 1]
        for i in range(1, len(lines))
        if lines[i] and set(lines[i]) == {"-"} and len(lines[i]) == len(lines[i - 1])
    ]


def _html_headings(html: str, level: str) -> list[str]:
    return [
        re.sub(r"<[^>]+>", "", h).strip()
        for h in re.findall(rf"<{level}[^>]*>(.*?)</{level}>", html)
    ]


def test_every_text_section_is_a_heading_of_the_html_report(analyzed):
    text = (analyzed / "report.txt").read_text()
    html = (analyzed / "report.html").read_text()
    sections = _text_headings(text)
    assert {"Study status", "Psychometric functions", "Outlier flags", "Figures"} <= set(sections)
    assert set(sections) <= set(_html_headings(html, "h2")), set(sections) - set(
        _html_headings(html, "h2")
    )
    # The model comparison of the pooling step is in both.
    if "Model comparison" in text:
        assert any(h.startswith("Model comparison") for h in _html_headings(html, "h3"))


def test_the_report_links_every_figure_it_wrote(analyzed):
    html = (analyzed / "report.html").read_text()
    text = (analyzed / "report.txt").read_text()
    written = sorted(p.relative_to(analyzed).as_posix() for p in analyzed.rglob("*.png"))
    assert written
    for rel in written:
        assert f'href="{rel}"' in html and rel in text


def test_the_figures_section_lists_only_figures(analyzed):
    # It once listed thresholds.csv and problems.csv as "staircase tracks of one session".
    text = (analyzed / "report.txt").read_text()
    section = text.split("\nFigures\n-------\n", 1)[1].split("\n\n", 1)[0]
    listed = [line.strip().split(":", 1)[0] for line in section.splitlines() if line.strip()]
    assert listed
    for rel in listed:
        assert rel.endswith(".png") and (analyzed / rel).is_file(), rel


def test_a_slope_at_its_limit_is_noted_as_a_lower_bound():
    # Every answer below 0 dB is a guess gone wrong, every one above is right: a step.
    x = np.repeat(np.arange(-6.0, 7.0, 2.0), 8)
    r = x > 0
    r[::5] = x[::5] < 0  # a few lucky guesses below and lapses above, so the fit exists
    fit = fit_pf(x, r, n_boot=0)
    assert fit.ok and fit.slope_per_db == pytest.approx(10.0)
    assert "slope is only a lower bound" in fit.message
    gradual = np.random.default_rng(3).random(x.size) < pf_curve(x, 0.0, 0.5, 0.02, 1 / 3)
    fit = fit_pf(x, gradual, n_boot=0)
    assert fit.ok and fit.slope_per_db < 9.0 and fit.message is None


def test_outputs_with_figures_drawn_in_a_worker_are_the_in_process_bytes(study, analyzed, tmp_path):
    """`analyze` draws its figures in a worker process (FigurePool); drawn in-process, every
    output file, figures and the reports embedding them included, is the same bytes."""
    from masking_lab.analysis.batch import run_analyze
    from masking_lab.analysis.figure_pool import FigurePool
    from masking_lab.analysis.settings import AnalysisSettings

    here = tmp_path / "here"
    run_analyze(study, here, AnalysisSettings(), figure_pool=FigurePool(enabled=False))
    names = sorted(p.relative_to(analyzed).as_posix() for p in analyzed.rglob("*") if p.is_file())
    assert names == sorted(p.relative_to(here).as_posix() for p in here.rglob("*") if p.is_file())
    assert "figures/shifts_experiment1.png" in names and "figures/masking_experiment1.png" in names
    for name in names:
        assert (here / name).read_bytes() == (analyzed / name).read_bytes(), name


def test_shift_figures_are_collected_when_the_report_asks_for_them(study, analyzed, tmp_path):
    """With the run's figure pool, write_lab_outputs returns while the AL-shift figures are
    still drawn (the statistics overlap them); finished() writes them and embeds the same
    bytes, the files the analysis lists and the in-process run wrote."""
    from masking_lab.analysis.figure_pool import FigurePool
    from masking_lab.analysis.lab_outputs import write_lab_outputs
    from masking_lab.analysis.log_reading import read_logs
    from masking_lab.analysis.thresholds import EstimatorSettings, thresholds_table
    from masking_lab.formats.html_report import data_uri

    paths = sorted(study.rglob("*.jsonl"))
    results = list(read_logs(paths, study, EstimatorSettings()))
    thresholds = thresholds_table([row for res in results for row in res.rows])
    logs = [res.rel for res in results]
    pool = FigurePool(enabled=True)
    try:
        lab = write_lab_outputs(
            study, tmp_path, logs, thresholds, trial_tables=False, figure_pool=pool
        )
        shifts = [p for p in lab.files if p.name.startswith("shifts_")]
        assert [p.name for p in shifts] == ["shifts_experiment1.png", "shifts_experiment2.png"]
        assert not any(p.exists() for p in shifts) and lab.section.embedded == ()
        section = lab.finished()
    finally:
        pool.close()
    assert lab.embed_shifts is None and lab.finished() is section  # collected once
    assert [rel for rel, _ in section.embedded] == [f"figures/{p.name}" for p in shifts]
    for (_, uri), path in zip(section.embedded, shifts, strict=True):
        assert path.read_bytes() == (analyzed / "figures" / path.name).read_bytes()
        assert uri == data_uri(path.read_bytes())


def test_trial_rows_keep_finite_numbers_and_drop_everything_else():
    from masking_lab.analysis import trials_table as tt

    assert [tt._num(v) for v in (1.5, 2, True, "3", None, math.inf, -math.inf, math.nan)] == [
        1.5, 2.0, None, None, None, None, None, None,
    ]  # fmt: skip
    assert type(tt._num(2)) is float and tt._num(np.float64(0.5)) == 0.5  # a float subclass
    assert [tt._int(v) for v in (3, True, 3.0, None)] == [3, None, None, None]
    assert tt._onsets([1, 2.5, math.nan]) == [1.0, 2.5, None]
    assert tt._onsets([1.0]) == [1.0, None, None] and tt._onsets("123") == [None] * 3
    assert tt._onsets([1.0, 2.0, 3.0, 4.0]) == [1.0, 2.0, 3.0]
