"""Readers say what is wrong (issue 21.3): a shifts CSV naming a column twice, masker levels a
few ulps apart (a singular design), and ground truths whose guess or lapse rate no staircase
can converge under — each a clean error naming the column, the cells or the key."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from masking_lab.commands.cli import main
from masking_lab.core.errors import AnalysisError, ProtocolError
from masking_lab.formats.shifts_csv import levels_told_apart, read_shifts_csv
from masking_lab.simulation.observer import load_ground_truth
from masking_lab.simulation.synthetic_logs import simulate_study

PROTOCOLS = Path(__file__).resolve().parents[1] / "protocols"


def _table(levels: list[float]) -> list[str]:
    rows = ["participant,target,masker,masker_level_db_sl,shift_db"]
    for i, p in enumerate("ABC"):
        for m in ("MV120", "MV180"):
            for x in levels:
                rows.append(f"{p},EV270,{m},{x!r},{0.6 * x - 3 + 0.1 * i:.3f}")
    return rows


def test_a_column_named_twice_is_refused_naming_it(tmp_path, capsys):
    p = tmp_path / "shifts.csv"
    rows = _table([5.0, 10.0, 15.0])
    rows[0] += ",shift_db"
    rows[1:] = [r + ",99" for r in rows[1:]]
    p.write_text("\n".join(rows) + "\n")
    with pytest.raises(AnalysisError, match=r"line 1: column\(s\) shift_db named more than once"):
        read_shifts_csv(p)
    assert main(["fit", str(p), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "shift_db named more than once" in err and "Traceback" not in err


def test_masker_levels_a_few_ulps_apart_are_refused_naming_the_cells(tmp_path, capsys):
    near = float(np.nextafter(10.0, 11.0))
    p = tmp_path / "shifts.csv"
    p.write_text("\n".join(_table([5.0, 10.0, near, 20.0])) + "\n")
    with pytest.raises(AnalysisError, match=r"EV270\|MV120 .*levels 10.0 and 10.000000000000002"):
        read_shifts_csv(p)
    assert main(["fit", str(p), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "no fit can tell them apart" in err and "Traceback" not in err
    # Levels a measurable step apart are a design, not a degeneracy.
    p.write_text("\n".join(_table([5.0, 10.0, 10.001, 20.0])) + "\n")
    assert len(read_shifts_csv(p)[0]) == 24


def test_levels_are_only_compared_within_one_pair():
    t = pd.DataFrame(
        {
            "experiment": ["e", "e"],
            "target": ["EV270", "EV270"],
            "masker": ["MV120", "MV180"],
            "masker_level_db_sl": [5.0, 5.0 + 1e-12],
        }
    )
    levels_told_apart(t, "x")  # different maskers: nothing to tell apart


def test_analyze_refuses_logged_masker_levels_that_cannot_be_told_apart(tmp_path, capsys):
    simulate_study(tmp_path / "data", n_participants=2, seed=3, baseline_start_above_db=10.0)
    log = tmp_path / "data" / "P01" / "P01_experiment1.jsonl"
    lines = log.read_text(encoding="utf-8").splitlines()
    for i, line in enumerate(lines):
        rec = json.loads(line)
        if rec.get("record") == "set_start" and rec.get("masker_level_db_sl") == 10:
            rec["masker_level_db_sl"] = float(np.nextafter(10.0, 11.0))
            lines[i] = json.dumps(rec)
            break
    log.write_text("\n".join(lines) + "\n", encoding="utf-8")
    out = tmp_path / "out"
    assert main(["analyze", str(tmp_path / "data"), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "masker levels 10.0 and 10.000000000000002" in err and "Traceback" not in err


@pytest.mark.parametrize(
    ("psychometric", "key", "bound"),
    [
        ({"guess": 0.999}, "psychometric.guess", "≤ 0.5"),
        ({"guess": 0.5, "lapse": 0.6}, "psychometric.lapse", "≤ 0.1"),
    ],
)
def test_a_ground_truth_no_staircase_can_converge_under_is_refused(
    tmp_path, capsys, psychometric, key, bound
):
    doc = {
        "unmasked_al_db_v": {"EV270": -18.0, "MV120": -26.0},
        "psychometric": {"scale_db": 1.5, **psychometric},
        "masking": [{"target": "EV270", "masker": "MV120", "intercept_db": -7.4, "slope": 0.7}],
    }
    p = tmp_path / "truth.json"
    p.write_text(json.dumps(doc))
    with pytest.raises(ProtocolError, match=key.replace(".", r"\.")):
        load_ground_truth(p)
    assert main(["validate", str(p)]) != 0
    out = capsys.readouterr()
    assert bound in out.out + out.err
    argv = ["plan", str(PROTOCOLS / "experiment1.yaml"), "--ground-truth", str(p)]
    assert main([*argv, "--replicates", "3", "--out", str(tmp_path / "plan")]) == 2
    err = capsys.readouterr().err
    assert key in err and "Traceback" not in err


def test_a_ground_truth_at_the_bounds_plans(tmp_path):
    src = PROTOCOLS / "simulation" / "ground_truth.yaml"
    text = src.read_text(encoding="utf-8")
    text = text.replace("lapse: 0.02", "lapse: 0.1").replace(
        "guess: 0.3333333333333333", "guess: 0.5"
    )
    p = tmp_path / "truth.yaml"
    p.write_text(text, encoding="utf-8")
    truth = load_ground_truth(p)
    assert (truth.lapse, truth.guess) == (0.1, 0.5)
    shutil.copy(PROTOCOLS / "experiment1.yaml", tmp_path / "exp1.yaml")
    argv = ["plan", str(tmp_path / "exp1.yaml"), "--ground-truth", str(p), "--replicates", "3"]
    assert main([*argv, "--ml-replicates", "0", "--out", str(tmp_path / "plan")]) == 0
    assert (tmp_path / "plan" / "plan.txt").is_file()
