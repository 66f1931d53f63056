"""The bulk forms of analyze's serial tail give what the cell-by-cell forms gave: thresholds.csv
formatted column-wise, the study matrix grouped once, the outlier rule on array slices."""

from __future__ import annotations

import math
import random

import numpy as np
import pandas as pd

from masking_lab.analysis.study_status import (
    _MIN_OTHERS,
    OUTLIER_Z,
    SessionInfo,
    _flag,
    outliers,
    status_matrix,
)
from masking_lab.formats.csv_table import csv_text_columns, csv_text_rows


def _awkward_columns(rng: random.Random, n: int) -> list[list]:
    words = ["P1", "a,b", 'say "hi"', "line\nbreak", "cr\rhere", "", " lead", "é ü", "x;y"]
    return [
        [rng.choice(words) for _ in range(n)],  # str, some needing quotes
        [rng.choice([None, *words]) for _ in range(n)],  # str or None
        [rng.choice([math.nan, -0.0, 1 / 3, 1e-7, 123456789.0, math.inf, -2.5]) for _ in range(n)],
        [rng.choice([None, 0.1, math.nan]) for _ in range(n)],  # float or None
        [rng.randint(-5, 10**12) for _ in range(n)],  # int
        [rng.random() < 0.5 for _ in range(n)],  # bool
        [
            rng.choice([np.float64(0.25), np.bool_(True), 3, "s", None, np.int64(7)])
            for _ in range(n)
        ],
    ]


def test_column_wise_csv_is_the_row_wise_bytes() -> None:
    rng = random.Random(22)
    for n in (0, 1, 7, 300, 9000):
        data = _awkward_columns(rng, n)
        names = [f"c{i}" for i in range(len(data))]
        rows = [list(r) for r in zip(*data, strict=True)]
        assert csv_text_columns(names, data) == csv_text_rows(names, rows)
    # one column: the csv module quotes a lone empty field; the column form does too
    assert csv_text_columns(["a"], [["", "x"]]) == csv_text_rows(["a"], [[""], ["x"]])


def _old_status_matrix(sessions, thresholds):
    """The cell-by-cell form (a table filter per participant x protocol) it replaced."""
    out = []
    by_cell: dict = {}
    for s in sessions:
        by_cell.setdefault((s.participant, s.experiment), []).append(s)
    for p in sorted({s.participant for s in sessions}):
        for e in sorted({s.experiment for s in sessions}):
            logs = by_cell.get((p, e), [])
            if not logs:
                out.append((p, e, "missing", 0, 0, 0, 0))
                continue
            rows = thresholds[thresholds["log"].isin([s.log for s in logs])]
            planned = set().union(*(set(s.set_order) for s in logs)) or set(rows["set_id"])
            done = set(rows.loc[rows["status"].isin(["completed", "superseded"]), "set_id"])
            trials = int(sum(int(t or 0) for t in rows["trials"]))
            refused = rows["status"].eq("aborted").any()
            status = (
                "complete" if planned and planned <= done else "refused" if refused else "partial"
            )
            out.append((p, e, status, len(done & planned), len(planned), trials, len(logs)))
    return out


def test_the_grouped_study_matrix_is_the_filtered_one() -> None:
    rng = random.Random(5)
    sessions, rows = [], []
    statuses = ["completed", "superseded", "aborted", "incomplete", "invalid"]
    for i in range(40):
        p, e = f"P{i % 9}", f"e{i % 3}"
        log = f"{p}/{e}_{i}.jsonl"
        order = tuple(f"S{k}" for k in range(rng.randint(0, 4)))
        sessions.append(SessionInfo(p, e, log, order, rng.random() < 0.5))
        for k in range(rng.randint(0, 5)):
            rows.append(
                {"participant": p, "experiment": e, "set_id": f"S{k}", "log": log,
                 "status": rng.choice(statuses), "trials": rng.choice([0, 12, 40]), "note": None}
            )  # fmt: skip
    rows.append({"participant": "PX", "experiment": "e0", "set_id": "S0", "log": "stray.jsonl",
                 "status": "completed", "trials": 5, "note": None})  # fmt: skip
    table = pd.DataFrame(rows)
    new = [
        (c.participant, c.experiment, c.status, c.sets_done, c.sets_planned, c.trials, c.sessions)
        for c in status_matrix(sessions, table)
    ]
    assert new == _old_status_matrix(sessions, table)
    assert {c[2] for c in new} >= {"complete", "partial", "missing"}


def _old_flag(values, what):
    out = []
    for p, v in values.items():
        others = np.array([x for q, x in values.items() if q != p], dtype=float)
        if others.size < _MIN_OTHERS:
            continue
        med, mad = float(np.mean(others)), float(np.std(others, ddof=1))
        if mad > 0.0 and abs((v - med) / mad) > OUTLIER_Z:
            out.append((p, what, float(v), med, float((v - med) / mad)))
    return out


def test_the_outlier_rule_on_slices_is_the_rule_on_new_arrays() -> None:
    rng = np.random.default_rng(3)
    cases = []
    for n in (3, 5, 6, 8, 60, 333):
        vals = {f"P{i}": float(x) for i, x in enumerate(rng.standard_t(2, n))}
        vals["P0"] = 40.0
        cases.append(vals)
    # every cell equal, all but one equal, and a value placed at z = 3.5 ± an ulp's worth
    cases += [{f"P{i}": 2.5 for i in range(9)}, {**{f"P{i}": 2.5 for i in range(9)}, "P9": 3.0}]
    base = rng.normal(0.0, 1.0, 40)
    others = base[1:]
    for dz in (-1e-9, 0.0, 1e-9):
        at = others.mean() + (OUTLIER_Z + dz) * others.std(ddof=1)
        cases.append({f"P{i}": float(x) for i, x in enumerate([at, *others])})
    flagged = 0
    for vals in cases:
        got = [(o.participant, o.what, o.value_db, o.others_mean_db, o.z) for o in _flag(vals, "w")]
        assert got == _old_flag(vals, "w")
        flagged += len(got)
    assert flagged >= 6  # the rule fired, so the screen let the flagged ones through
    t = pd.DataFrame({"participant": [f"P{i}" for i in range(6)], "experiment": ["e"] * 6,
        "target": ["EV270"] * 6, "masker": ["MV120"] * 6, "masker_level_db_sl": [10.0] * 6,
        "status": ["completed"] * 6, "shift_db": [1.0, 1.2, 0.9, 1.1, 1.0, 9.0],
        "al_db_v": [None] * 6})  # fmt: skip
    assert [o.participant for o in outliers(t)] == ["P5"]


def _old_outliers(t: pd.DataFrame) -> list[tuple]:
    """The rule's AL-shift cells as a DataFrame per cell (before session 35)."""
    done = t[t["status"] == "completed"]
    masked = done[done["masker"].notna() & done["shift_db"].notna()]
    out = []
    keys = ["experiment", "target", "masker", "masker_level_db_sl"]
    for (e, tg, m, _), g in masked.groupby(keys, sort=True):
        lv = float(g["masker_level_db_sl"].iloc[0])
        vals = dict(zip(g["participant"], g["shift_db"].astype(float), strict=True))
        out += _old_flag(vals, f"{e} {tg}|{m} @ {lv:g} dB SL (AL shift)")
    return out


def test_the_outlier_cells_walked_on_lists_are_the_grouped_cells() -> None:
    # cells in shuffled row order, a repeated participant in a cell (the later value counts),
    # missing levels (no cell), unmasked and unfinished rows, heavy tails at several scales
    rng = np.random.default_rng(11)
    rows = []
    for e in ("exp_b", "exp_a"):
        for target, masker in (("EV270", "MV120"), ("EV90", "MV200"), ("EV270", None)):
            for level in (10.0, 2.5, math.nan):
                scale, offset = 10 ** rng.uniform(-3, 3), rng.uniform(-1e3, 1e3)
                for _i in range(int(rng.integers(3, 70))):
                    rows.append({"participant": f"P{rng.integers(0, 80)}", "experiment": e,
                        "target": target, "masker": masker, "masker_level_db_sl": level,
                        "status": "completed" if rng.random() < 0.9 else "aborted",
                        "shift_db": offset + scale * float(rng.standard_t(2)),
                        "al_db_v": -30.0 + float(rng.normal())})  # fmt: skip
    t = pd.DataFrame([rows[i] for i in rng.permutation(len(rows))])
    got = [(o.participant, o.what, o.value_db, o.others_mean_db, o.z) for o in outliers(t)]
    shift_flags = [g for g in got if g[1].endswith("(AL shift)")]
    assert shift_flags == _old_outliers(t)
    assert len(shift_flags) >= 5


def test_the_screen_keeps_every_value_the_rule_flags() -> None:
    # the screen (0.9 of the rule) must pass every value the exact rule flags, at any scale:
    # cells placed at z = 3.5 +- 1e-9 and heavy-tailed cells against the plain rule
    rng = np.random.default_rng(5)
    flagged = 0
    for k in range(3000):
        n = int(rng.integers(3, 40))
        v = rng.standard_t(2, n) * 10 ** rng.uniform(-6, 6) + rng.uniform(-1e6, 1e6)
        if k % 3 == 0:
            v = np.round(v, 1)
        if k % 7 == 0 and n > 4:
            others = v[1:]
            v[0] = others.mean() + (OUTLIER_Z + rng.choice([-1e-9, 0.0, 1e-9])) * others.std(ddof=1)
        vals = {f"P{i}": float(x) for i, x in enumerate(v)}
        got = [(o.participant, o.what, o.value_db, o.others_mean_db, o.z) for o in _flag(vals, "w")]
        assert got == _old_flag(vals, "w")
        flagged += len(got)
    assert flagged > 500
