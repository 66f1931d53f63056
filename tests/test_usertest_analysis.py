"""`usertest-report`: user-test logs written by hand → rates, paired tests, confusion, figure.

Three participants, 2 geometries × 2 textures, four trials per condition each; every expected
number below was counted by hand from the answers in ``ANSWERS``.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from masking_lab.commands.cli import main
from masking_lab.core.errors import AnalysisError
from masking_lab.formats.schemas import schema_errors
from masking_lab.usertest.report import collect_usertest, write_usertest_report

GEOMETRIES = ["bump", "hole"]
TEXTURES = ["smooth", "rough"]

# participant → condition → (geometry, texture, geometry answer, texture answer)
ANSWERS = {
    "A": {
        "compensated": [
            ("bump", "smooth", 1, 1),  # both right
            ("hole", "rough", 2, 2),  # both right
            ("bump", "rough", 1, 1),  # texture wrong
            ("hole", "smooth", 1, 1),  # geometry wrong
        ],
        "uncompensated": [
            ("bump", "smooth", 2, 1),  # geometry wrong
            ("hole", "rough", 2, None),  # no texture answer: wrong
            ("bump", "rough", 1, 2),  # both right
            ("hole", "smooth", 2, 1),  # both right
        ],
    },
    "B": {
        "compensated": [
            ("bump", "smooth", 1, 1),
            ("hole", "rough", 2, 2),
            ("bump", "rough", 1, 2),
            ("hole", "smooth", 2, 1),
        ],
        "uncompensated": [
            ("bump", "smooth", 1, 1),  # both right
            ("hole", "rough", 1, 2),  # geometry wrong
            ("bump", "rough", 2, 2),  # geometry wrong
            ("hole", "smooth", 2, 2),  # texture wrong
        ],
    },
    "C": {
        "compensated": [
            ("bump", "smooth", 1, 1),
            ("hole", "rough", 2, 2),
            ("bump", "rough", 1, 2),
            ("hole", "smooth", 1, 1),  # geometry wrong
        ],
        "uncompensated": [
            ("bump", "smooth", 1, 2),  # texture wrong
            ("hole", "rough", 1, 1),  # both wrong
            ("bump", "rough", 1, 2),  # both right
            ("hole", "smooth", 2, 1),  # both right
        ],
    },
}

# Counted by hand: (both, geometry, texture, unanswered) per participant and condition.
RATES = {
    ("A", "compensated"): (0.5, 0.75, 0.75, 0),
    ("A", "uncompensated"): (0.5, 0.75, 0.75, 1),
    ("B", "compensated"): (1.0, 1.0, 1.0, 0),
    ("B", "uncompensated"): (0.25, 0.5, 0.75, 0),
    ("C", "compensated"): (0.75, 0.75, 1.0, 0),
    ("C", "uncompensated"): (0.5, 0.75, 0.5, 0),
}


def header(participant: str, *, geometries=GEOMETRIES, textures=TEXTURES, kind="usertest"):
    h = {
        "record": "header",
        "schema_version": 1,
        "session_id": f"usertest-{participant}",
        "created_utc": "2024-01-01T00:00:00Z",
        "software_version": "test",
        "protocol": {
            "path": "/x/usertest.yaml",
            "sha256": "0" * 64,
            "experiment": "usertest",
            "content": {"geometries": geometries, "textures": textures, "kind": "usertest"},
        },
        "participant": participant,
        "calibration": {},
        "device": {"backend": "sim", "model": "m", "firmware_version": "f"},
        "seed": 1,
        "set_order": [],
        "clock": "virtual",
        "usertest": {
            "protocol_text": "",
            "scenes": [],
            "masking": [],
            "n_trials": 8,
            "stream": {},
            "allow_clipping": False,
        },
    }
    if kind is not None:
        h["kind"] = kind
    return h


def trial_records(participant: str) -> list[dict]:
    recs = []
    i = 0
    for condition, rows in ANSWERS[participant].items():
        for g, t, ga, ta in rows:
            recs.append(
                {
                    "record": "usertest_trial",
                    "participant": participant,
                    "trial": i,
                    "geometry": g,
                    "texture": t,
                    "condition": condition,
                    "repeat": 1,
                    "geometry_answer": ga,
                    "texture_answer": ta,
                }
            )
            i += 1
    return recs


def write_log(path: Path, recs: list[dict], *, ended: bool = True) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [json.dumps(r) for r in recs]
    if ended:
        lines.append(json.dumps({"record": "session_end", "status": "completed"}))
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


@pytest.fixture()
def data(tmp_path):
    folder = tmp_path / "data"
    for p in ("A", "B"):
        write_log(folder / p / f"usertest-{p}.jsonl", [header(p), *trial_records(p)])
    # C stopped after its trials were logged (no session_end): included, with a note.
    write_log(folder / "C" / "usertest-C.jsonl", [header("C"), *trial_records("C")], ended=False)
    # A threshold session and a file that is no log at all: skipped, with why.
    write_log(folder / "A" / "baseline-A.jsonl", [header("A", kind=None)])
    (folder / "notes.jsonl").write_text("hello\n", encoding="utf-8")
    return folder


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(encoding="utf-8", newline="") as fh:
        return list(csv.DictReader(fh))


def test_hand_written_logs_are_valid_session_log_records():
    for rec in [header("A"), *trial_records("A")]:
        assert not schema_errors(rec, "session_log"), rec


def test_rates_per_participant_and_condition(data, tmp_path):
    report = write_usertest_report(data, tmp_path / "out")
    rows = read_csv(tmp_path / "out" / "rates.csv")
    assert len(rows) == 6
    for r in rows:
        both, geometry, texture, unanswered = RATES[(r["participant"], r["condition"])]
        assert float(r["both"]) == both and float(r["geometry"]) == geometry
        assert float(r["texture"]) == texture and int(r["n_no_answer"]) == unanswered
        assert int(r["n_trials"]) == 4
    assert len(report.data.sessions) == 3


def test_summary_and_paired_tests_match_an_independent_computation(data, tmp_path):
    write_usertest_report(data, tmp_path / "out")
    summary = {
        (r["condition"], r["measure"]): r for r in read_csv(tmp_path / "out" / "summary.csv")
    }
    tests = {r["measure"]: r for r in read_csv(tmp_path / "out" / "tests.csv")}
    for k, measure in enumerate(("both", "geometry", "texture")):
        comp = [RATES[(p, "compensated")][k] for p in "ABC"]
        unc = [RATES[(p, "uncompensated")][k] for p in "ABC"]
        for cond, values in (("compensated", comp), ("uncompensated", unc)):
            row = summary[(cond, measure)]
            assert float(row["mean"]) == pytest.approx(np.mean(values), abs=1e-6)
            assert float(row["sd"]) == pytest.approx(np.std(values, ddof=1), abs=1e-6)
            assert int(row["n"]) == 3
        want = stats.ttest_rel(comp, unc)
        row = tests[measure]
        assert float(row["t"]) == pytest.approx(want.statistic, rel=1e-5)
        assert float(row["p"]) == pytest.approx(want.pvalue, rel=1e-5)
        assert int(row["df"]) == 2
        diff = np.subtract(comp, unc)
        assert float(row["mean_difference"]) == pytest.approx(diff.mean(), abs=1e-6)
        assert float(row["dz"]) == pytest.approx(diff.mean() / np.std(diff, ddof=1), rel=1e-5)


def test_confusion_matrices_count_presented_against_answered(data, tmp_path):
    write_usertest_report(data, tmp_path / "out")
    geo = read_csv(tmp_path / "out" / "confusion_compensated_geometry.csv")
    assert geo == [
        {"geometry presented": "bump", "bump": "6", "hole": "0", "no answer": "0"},
        {"geometry presented": "hole", "bump": "2", "hole": "4", "no answer": "0"},
    ]
    tex = read_csv(tmp_path / "out" / "confusion_uncompensated_texture.csv")
    # Smooth presented 6×: answered smooth by A twice, B and C once; rough by B and C once.
    # Rough presented 6×: A no answer once and rough once, B rough twice, C smooth and rough.
    assert tex == [
        {"texture presented": "smooth", "smooth": "4", "rough": "2", "no answer": "0"},
        {"texture presented": "rough", "smooth": "1", "rough": "4", "no answer": "1"},
    ]


def test_the_report_lists_inputs_skips_and_notes(data, tmp_path):
    report = write_usertest_report(data, tmp_path / "out")
    text = (tmp_path / "out" / "report.txt").read_text(encoding="utf-8")
    assert "3 user-test session(s), 3 participant(s), 24 trials; 2 other file(s) skipped" in text
    assert "skipped A/baseline-A.jsonl: not a user-test log" in text
    assert "skipped notes.jsonl" in text
    assert "C/usertest-C.jsonl: incomplete session (8 of 8 trials logged)" in text
    assert "C/usertest-C.jsonl: C, 8/8 trials, INCOMPLETE" in text
    assert "Confusion, geometry, compensated" in text
    sessions = read_csv(tmp_path / "out" / "sessions.csv")
    assert [(s["participant"], s["ended"]) for s in sessions] == [
        ("A", "true"),
        ("B", "true"),
        ("C", "false"),
    ]
    names = [p.name for p in report.written]
    assert names[-2:] == ["report.txt", "figure8a.png"]


def test_outputs_are_byte_identical_across_runs(data, tmp_path):
    one = write_usertest_report(data, tmp_path / "one")
    two = write_usertest_report(data, tmp_path / "two")
    assert [p.name for p in one.written] == [p.name for p in two.written]
    for a, b in zip(one.written, two.written, strict=True):
        assert a.read_bytes() == b.read_bytes(), a.name
    png = (tmp_path / "one" / "figure8a.png").read_bytes()
    assert png.startswith(b"\x89PNG\r\n\x1a\n") and b"Software" not in png


def test_one_participant_reports_no_paired_test(tmp_path):
    folder = tmp_path / "data"
    write_log(folder / "usertest-A.jsonl", [header("A"), *trial_records("A")])
    report = write_usertest_report(folder, tmp_path / "out", figure=False)
    assert not (tmp_path / "out" / "figure8a.png").exists()
    tests = read_csv(tmp_path / "out" / "tests.csv")
    assert all(t["t"] == "" and "≥ 2 participants" in t["note"] for t in tests)
    text = (tmp_path / "out" / "report.txt").read_text(encoding="utf-8")
    assert "not tested" in text and "(n = 1)" in text
    assert math.isnan(report.analysis.summary["sd"].iloc[0])


def test_participants_with_one_condition_each_report_no_test_and_no_nan(tmp_path):
    # A did only the compensated block, B only the uncompensated: no pair to compare.
    folder = tmp_path / "data"
    for p, condition in (("A", "compensated"), ("B", "uncompensated")):
        recs = [r for r in trial_records(p) if r["condition"] == condition]
        write_log(folder / f"usertest-{p}.jsonl", [header(p), *recs])
    report = write_usertest_report(folder, tmp_path / "out", figure=False)
    for t in report.analysis.tests:
        assert t.n == 0 and t.t is None and t.mean_difference is None
        assert "no participant has both conditions" in t.note
    for name in ("tests.csv", "summary.csv", "rates.csv", "report.txt"):
        assert "nan" not in (tmp_path / "out" / name).read_text(encoding="utf-8").lower(), name
    text = (tmp_path / "out" / "report.txt").read_text(encoding="utf-8")
    assert "not tested: no participant has both conditions" in text


def test_a_log_with_a_trial_twice_is_skipped(data, tmp_path):
    recs = trial_records("A")
    write_log(data / "D" / "usertest-D.jsonl", [header("D"), *recs, recs[2]])
    out = collect_usertest(data)
    assert {"log": "D/usertest-D.jsonl", "reason": "trial 2 is logged twice; the log was edited "
            "or merged"} in out.skipped  # fmt: skip
    assert {s.participant for s in out.sessions} == {"A", "B", "C"}


def test_repeated_participants_are_pooled_and_said_so(data):
    write_log(data / "A" / "usertest-A-2.jsonl", [header("A"), *trial_records("A")])
    out = collect_usertest(data)
    assert "participant A has 2 user-test sessions; their trials are pooled" in out.notes


def test_nothing_to_analyse_is_an_error_naming_the_folder(tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(AnalysisError, match="no session logs"):
        collect_usertest(empty)
    write_log(empty / "baseline.jsonl", [header("A", kind=None)])
    with pytest.raises(AnalysisError, match="none of them a user test"):
        collect_usertest(empty)
    assert main(["usertest-report", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    assert "no such folder" in capsys.readouterr().err


def test_designs_with_other_answer_keys_are_not_mixed(data):
    write_log(
        data / "E" / "usertest-E.jsonl",
        [header("E", geometries=["bump", "hole", "ascending"]), *trial_records("A")],
    )
    with pytest.raises(AnalysisError, match="analyse the two designs from separate folders"):
        collect_usertest(data)


def test_an_answer_outside_the_keys_is_an_error_naming_the_record(data, tmp_path, capsys):
    recs = trial_records("B")
    recs[1]["geometry_answer"] = 3  # only 2 geometries
    write_log(data / "B" / "usertest-B.jsonl", [header("B"), *recs])
    assert main(["usertest-report", str(data), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "geometry_answer is 3; it must be a key 1..2" in err


def test_cli_prints_rates_tests_and_files(data, tmp_path, capsys):
    assert main(["usertest-report", str(data), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert "user test: 3 session(s), 24 trials, 2 other file(s) skipped" in out
    assert "compensated   both     0.750" in out  # (0.5 + 1.0 + 0.75) / 3
    assert "uncompensated both     0.417" in out  # (0.5 + 0.25 + 0.5) / 3
    assert "both: t(2) =" in out
    assert f"wrote {tmp_path / 'out' / 'figure8a.png'}" in out


def test_equal_differences_in_every_participant_are_not_tested(tmp_path):
    # 12 trials per condition; each participant gets one more texture right with compensation
    # (12 vs 11, 11 vs 10, 10 vs 9 of 12): the differences are all 1/12, up to float rounding.
    folder = tmp_path / "data"
    for p, right in (("A", 12), ("B", 11), ("C", 10)):
        recs = []
        for condition, n_right in (("compensated", right), ("uncompensated", right - 1)):
            for i in range(12):
                g, t = GEOMETRIES[i % 2], TEXTURES[(i // 2) % 2]
                answer = TEXTURES.index(t) + 1 if i < n_right else 3 - (TEXTURES.index(t) + 1)
                recs.append(
                    {
                        "record": "usertest_trial",
                        "participant": p,
                        "trial": len(recs),
                        "geometry": g,
                        "texture": t,
                        "condition": condition,
                        "repeat": 1,
                        "geometry_answer": GEOMETRIES.index(g) + 1,
                        "texture_answer": answer,
                    }
                )
        write_log(folder / f"usertest-{p}.jsonl", [header(p), *recs])
    report = write_usertest_report(folder, tmp_path / "out", figure=False)
    texture = next(t for t in report.analysis.tests if t.measure == "texture")
    assert texture.t is None and texture.p is None
    assert texture.mean_difference == pytest.approx(1 / 12)
    assert "every participant's difference is the same" in texture.note
