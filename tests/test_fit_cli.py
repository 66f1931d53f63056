"""`masking-lab fit SHIFTS.csv`: the paper's Table 2, participant tables, degenerate tables."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from masking_lab.commands.cli import main
from masking_lab.formats.masking_params import load_masking_params
from masking_lab.formats.schemas import schema_errors

TABLE2 = Path(__file__).resolve().parents[1] / "data_schema" / "shifts.csv"
PAPER_POOLS = ["--pool", "EV270|MV:120+180", "--pool", "MV|EV270:180+270"]
# Paper Table 2 means (dB) at 5, 10, 15, 20, 25 dB SL.
MEANS = {
    ("EV270", "MV120"): [0.433, 0.322, 2.992, 7.265, 10.107],
    ("EV270", "MV180"): [0.771, 0.808, 3.611, 7.427, 10.502],
    ("EV270", "MV270"): [1.171, 3.608, 6.411, 9.428, 13.301],
    ("MV120", "EV270"): [4.017, 9.506, 13.376, 18.727, 22.891],
    ("MV180", "EV270"): [6.118, 12.158, 18.015, 22.278, 27.612],
    ("MV270", "EV270"): [6.546, 13.235, 18.306, 23.580, 29.195],
}
LEVELS = [5, 10, 15, 20, 25]


def _read_csv(path):
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def _fit(tmp_path, csv_path, *extra, name="out"):
    out = tmp_path / name
    rc = main(["fit", str(csv_path), "--out", str(out), "--quiet", *extra])
    return rc, out


def test_shipped_table2_is_the_papers_table():
    rows = _read_csv_skipping_comments(TABLE2)
    got = {}
    for r in rows:
        got.setdefault((r["target"], r["masker"]), []).append(float(r["shift_db"]))
        assert float(r["masker_frequency_hz"]) == float(r["masker"][2:])
    assert got == MEANS


def _read_csv_skipping_comments(path):
    lines = [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]
    return list(csv.DictReader(lines))


def test_fit_on_table2_reproduces_the_papers_masking_functions(tmp_path):
    rc, out = _fit(tmp_path, TABLE2, *PAPER_POOLS)
    assert rc == 0
    doc = json.loads((out / "masking_params.json").read_text())
    assert schema_errors(doc, "masking_params") == []
    assert doc["provenance"]["source"] == "fit"
    entries = load_masking_params(out / "masking_params.json")
    assert len(entries) == 6
    ev = entries[("EV270", "MV120")]
    assert ev.pooled_pairs == ("EV270|MV120", "EV270|MV180")
    assert ev.masker_frequencies_hz == (120.0, 180.0)
    # Paper: EV ≈ −6.22 + 0.66·x, MV ≈ 1.39 + 1.09·x (least squares gives −6.263, 0.6653).
    assert ev.intercept_db == pytest.approx(-6.22, abs=0.05)
    assert ev.slope == pytest.approx(0.66, abs=0.01)
    assert entries[("EV270", "MV180")].intercept_db == ev.intercept_db
    mv = entries[("MV270", "EV270")]
    assert mv.pooled_pairs == ("MV180|EV270", "MV270|EV270")
    assert mv.masker_frequencies_hz == (180.0, 270.0)
    assert mv.intercept_db == pytest.approx(1.39, abs=0.01)
    assert mv.slope == pytest.approx(1.09, abs=0.01)
    assert ev.knee_db_sl == pytest.approx(6.2628 / 0.66526, rel=1e-4)
    assert ev.fitted_range_db_sl == (5.0, 25.0)
    # EV slopes 0.6–0.7, MV slopes 0.9–1.1 (paper §4); b·d < 1 so the solver has one answer.
    ev_slopes = {e.slope for (t, _), e in entries.items() if t == "EV270"}
    mv_slopes = {e.slope for (t, _), e in entries.items() if t != "EV270"}
    assert all(0.6 <= b <= 0.7 for b in ev_slopes) and all(0.9 <= d <= 1.1 for d in mv_slopes)
    assert max(ev_slopes) * max(mv_slopes) < 1
    report = (out / "report.txt").read_text()
    assert "need per-participant shifts and were not run" in report
    assert _read_csv(out / "anova.csv") == []
    assert (out / "figures" / "masking_EV270_MV.png").is_file()


def test_means_without_pools_fit_each_frequency_and_say_why(tmp_path):
    rc, out = _fit(tmp_path, TABLE2, "--uncertainty", "asymptotic")
    assert rc == 0
    fits = _read_csv(out / "ramp_fits.csv")
    assert len(fits) == 6 and all(r["pooling_rule"] == "none" for r in fits)
    assert "every frequency is fitted alone" in (out / "report.txt").read_text()
    entries = load_masking_params(out / "masking_params.json")
    assert entries[("EV270", "MV270")].slope == pytest.approx(0.6016, abs=1e-4)
    assert entries[("MV120", "EV270")].intercept_db == pytest.approx(-0.3873, abs=1e-4)


def _participant_table(tmp_path, n=10, seed=0, name="participants.csv", sd=1.0):
    """Per-participant shifts: Table 2 means + a participant offset + noise."""
    rng = np.random.default_rng(seed)
    rows = []
    for i in range(n):
        offset = rng.normal(0, sd)
        for (target, masker), means in MEANS.items():
            for level, m in zip(LEVELS, means, strict=True):
                shift = m + offset + rng.normal(0, sd)
                rows.append(
                    {
                        "participant": f"S{i:02d}",
                        "target": target,
                        "masker": masker,
                        "masker_level_db_sl": level,
                        "shift_db": round(shift, 3),
                    }
                )
    path = tmp_path / name
    pd.DataFrame(rows).to_csv(path, index=False)
    return path


def test_participant_table_runs_the_full_statistics(tmp_path):
    pg = pytest.importorskip("pingouin")
    path = _participant_table(tmp_path)
    rc, out = _fit(tmp_path, path, "--n-boot", "300")
    assert rc == 0
    anova = pd.read_csv(out / "anova.csv")
    assert list(anova["experiment"]) == ["EV270|MV"] * 3 + ["MV|EV270"] * 3
    data = pd.read_csv(path)
    data["mv"] = np.where(data["target"] == "EV270", data["masker"], data["target"])
    ev = data[data["target"] == "EV270"]
    ref = pg.rm_anova(
        ev, dv="shift_db", within=["mv", "masker_level_db_sl"], subject="participant", effsize="np2"
    )
    mine = anova[anova["experiment"] == "EV270|MV"]
    assert mine["F"].to_numpy() == pytest.approx(ref["F"].to_numpy(), rel=1e-5)
    assert mine["eps_gg"].to_numpy() == pytest.approx(ref["eps"].to_numpy(), rel=1e-5)
    assert len(_read_csv(out / "posthoc.csv")) == 6
    one = _read_csv(out / "one_sample.csv")
    assert len(one) == 30 and all(r["p"] != "" for r in one)
    assert len(_read_csv(out / "sphericity.csv")) == 6
    entries = load_masking_params(out / "masking_params.json")
    assert all(e.extra["uncertainty"] == "bootstrap" for e in entries.values())


def test_fit_output_is_deterministic(tmp_path):
    path = _participant_table(tmp_path)
    _, a = _fit(tmp_path, path, "--n-boot", "300", "--figures", "none", name="a")
    _, b = _fit(tmp_path, path, "--n-boot", "300", "--figures", "none", name="b")
    for f in sorted(p.name for p in a.iterdir() if p.is_file()):
        assert (a / f).read_bytes() == (b / f).read_bytes(), f
    doc = json.loads((a / "masking_params.json").read_text())
    assert doc["created_utc"] == "1970-01-01T00:00:00Z"
    assert "estimator" not in doc["provenance"]["settings"]


def _write(tmp_path, text, name="shifts.csv"):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("target,masker,shift_db\nEV270,MV120,1\n", "line 1: missing column(s) masker_level_db_sl"),
        (
            "# comment\ntarget,masker,masker_level_db_sl,shift_db,colour\n",
            "line 2: unknown column(s) colour",
        ),
        (
            "target,masker,masker_level_db_sl,shift_db\nEV270,MV120,5,abc\n",
            "line 2: shift_db 'abc' is not a number",
        ),
        (
            "target,masker,masker_level_db_sl,shift_db\nEV270,MV120,5,1\nEV270,XV1,5,1\n",
            "line 3: masker 'XV1' is not a stimulus name",
        ),
        (
            "target,masker,masker_frequency_hz,masker_level_db_sl,shift_db\nMV120,EV270,120,5,1\n",
            "masker_frequency_hz 120 does not match the masker EV270",
        ),
        (
            "target,masker,masker_level_db_sl,shift_db\nEV270,MV120,5,1\nEV270,MV120,5,2\n",
            "line 3: EV270|MV120 at 5 dB SL repeats line 2",
        ),
        ("target,masker,masker_level_db_sl,shift_db\nEV270,MV120,5\n", "line 2: 3 fields"),
        ("# only a comment\n", "the file is empty"),
        ("target,masker,masker_level_db_sl,shift_db\n", "no data rows"),
        (
            "participant,target,masker,masker_level_db_sl,shift_db\n,EV270,MV120,5,1\n",
            "participant is empty",
        ),
        (
            "target,masker,masker_level_db_sl,shift_db\nEV270,MV120,5,inf\n",
            "must be a finite number",
        ),
    ],
)
def test_malformed_tables_exit_2_naming_the_line(tmp_path, capsys, text, message):
    rc, _ = _fit(tmp_path, _write(tmp_path, text))
    assert rc == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_missing_file_and_bad_pool_exit_2(tmp_path, capsys):
    rc, _ = _fit(tmp_path, tmp_path / "nope.csv")
    assert rc == 2 and "cannot read the file" in capsys.readouterr().err
    rc, _ = _fit(tmp_path, TABLE2, "--pool", "experiment9:120+180")
    assert rc == 2 and "names experiment 'experiment9'" in capsys.readouterr().err
    rc, _ = _fit(tmp_path, TABLE2, "--pool", "EV270|MV:120+90")
    assert rc == 2 and "MV90, which is not a frequency level" in capsys.readouterr().err


def test_zero_variance_and_one_participant_are_explained(tmp_path):
    rows = ["participant,target,masker,masker_level_db_sl,shift_db"]
    for p in ("A", "B", "C"):
        for lv, m in zip(LEVELS, MEANS[("EV270", "MV270")], strict=True):
            rows.append(f"{p},EV270,MV270,{lv},{m}")  # every participant identical
    rc, out = _fit(tmp_path, _write(tmp_path, "\n".join(rows) + "\n"), "--n-boot", "200")
    assert rc == 0
    report = (out / "report.txt").read_text()
    assert "error variance of the level effect is zero" in report
    one = _read_csv(out / "one_sample.csv")
    assert all("zero variance" in r["note"] for r in one)
    single = [r for r in rows if not r.startswith(("B,", "C,"))]
    rc, out = _fit(tmp_path, _write(tmp_path, "\n".join(single) + "\n", "one.csv"), name="one")
    assert rc == 0
    assert "at least two participants" in (out / "report.txt").read_text()


def test_all_points_in_the_flat_region_export_no_masking(tmp_path):
    rows = ["target,masker,masker_level_db_sl,shift_db"]
    rows += [
        f"EV270,MV120,{lv},{s}" for lv, s in zip(LEVELS, [-0.2, 0.1, -0.3, 0.0, -0.1], strict=True)
    ]
    rc, out = _fit(tmp_path, _write(tmp_path, "\n".join(rows) + "\n"))
    assert rc == 0
    e = load_masking_params(out / "masking_params.json")[("EV270", "MV120")]
    assert e.status == "no_masking" and (e.intercept_db, e.slope) == (0.0, 0.0)
    assert "flat region" in e.message
    assert e.masking_function().shift_db(25.0) == 0.0


def test_one_masker_level_is_insufficient_data(tmp_path):
    text = "target,masker,masker_level_db_sl,shift_db\nEV270,MV120,15,3.0\n"
    rc, out = _fit(tmp_path, _write(tmp_path, text))
    assert rc == 0
    e = load_masking_params(out / "masking_params.json")[("EV270", "MV120")]
    assert e.status == "insufficient_data" and e.intercept_db is None
    assert "two or more masker levels" in e.message


def test_missing_cell_in_a_participant_table_is_named(tmp_path):
    path = _participant_table(tmp_path, n=4)
    data = pd.read_csv(path)
    keep = ~((data["masker"] == "MV270") & (data["masker_level_db_sl"] == 25))
    data[keep].to_csv(path, index=False)
    rc, out = _fit(tmp_path, path, "--n-boot", "200")
    assert rc == 0
    report = (out / "report.txt").read_text()
    assert "masker_level_db_sl=25.0: the design has a missing cell" in report
    fits = {
        r["group"]: r for r in _read_csv(out / "ramp_fits.csv") if r["experiment"] == "EV270|MV"
    }
    assert all(r["status"] == "fitted" for r in fits.values())


def test_created_utc_from_option_and_source_date_epoch(tmp_path, monkeypatch):
    _, out = _fit(tmp_path, TABLE2, "--created-utc", "2024-06-01T08:00:00Z", "--figures", "none")
    assert (
        json.loads((out / "masking_params.json").read_text())["created_utc"]
        == "2024-06-01T08:00:00Z"
    )
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "0")
    _, out = _fit(tmp_path, TABLE2, "--figures", "none", name="epoch")
    assert (
        json.loads((out / "masking_params.json").read_text())["created_utc"]
        == "1970-01-01T00:00:00Z"
    )
    rc, _ = _fit(tmp_path, TABLE2, "--created-utc", "noon", name="bad")
    assert rc == 2
