"""The second read of `analyze` spread over processes (issue 22): the same parts, in the same
order, as one process reading the logs itself, and an unreadable log is passed over."""

from __future__ import annotations

import json

import pytest

from masking_lab.analysis import study_reading
from masking_lab.analysis.study_reading import StudyLogs, read_parts
from masking_lab.simulation.synthetic_logs import simulate_study


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    root = tmp_path_factory.mktemp("study")
    simulate_study(root, n_participants=2, seed=3, baseline_start_above_db=10.0)
    (root / "P01" / "torn.jsonl").write_bytes(b'{"record":"header","partic')
    (root / "P02" / "gone.jsonl").mkdir()  # a folder named like a log: unreadable
    rels = sorted(p.relative_to(root).as_posix() for p in root.rglob("*.jsonl"))
    return root, rels


def test_parts_read_in_processes_are_the_parts_read_in_process(logs, monkeypatch):
    pytest.importorskip("pyarrow")  # the parquet columns; trials.csv needs nothing more
    root, rels = logs
    status = {(rel, "A"): "completed" for rel in rels}
    serial = list(read_parts(root, rels, status, csv=True, rows=True, workers=1))
    monkeypatch.setattr(study_reading, "_CHUNK", 2)
    parallel = list(read_parts(root, rels, status, csv=True, rows=True, workers=2))
    assert parallel == serial
    assert [p is None for p in serial].count(True) == 2  # the torn header, the folder
    assert sum(len(p.trials_csv.splitlines()) for p in serial if p) > 100
    assert all(p.trials_csv.count("\n") == p.trial_batch.num_rows for p in serial if p)


def test_a_study_gathers_sessions_sets_and_info_in_log_order(logs):
    root, rels = logs
    study = StudyLogs()
    for part in read_parts(root, rels, workers=1):
        if part is not None:
            study.add(part)
    unreadable = ("gone.jsonl", "torn.jsonl")
    assert [s.log for s in study.sessions] == [r for r in rels if not r.endswith(unreadable)]
    assert study.sessions_of == {"P01": 3, "P02": 3}
    assert {log for log, _ in study.sets} <= set(rels) and len(study.sets) > 20
    assert all(st.levels and len(st.levels) == len(st.correct) for st in study.sets.values())


def test_only_logs_with_a_functional_set_are_parsed_again(tmp_path):
    from masking_lab.analysis.log_reading import names_masker_placing_set, read_one
    from masking_lab.analysis.thresholds import EstimatorSettings

    plain = b'{"record":"set_start","procedure":{"kind":"quest_plus"}}\n'
    named = b'{"record":"set_start","procedure":{"kind":"functional_ramp"}}\n'
    escaped = b'{"record":"set_start","procedure":{"kind":"\\u0066unctional_ramp"}}\n'
    # the name elsewhere than a set's procedure holds no functional set
    elsewhere = b'{"record":"set_start","note":"functional_ramp","procedure":{"kind":"x"}}\n'
    # asked in the one read of each log, of its records: typed view and general reader alike
    header = b'{"record":"header","participant":"P1","protocol":{"experiment":"e"}}\n'
    cases = (("a", plain, False), ("b", named, True), ("c", escaped, True), ("d", elsewhere, False))
    for name, body, expected in cases:
        (tmp_path / f"{name}.jsonl").write_bytes(header + body)
        res = read_one(tmp_path / f"{name}.jsonl", f"{name}.jsonl", EstimatorSettings())
        assert res.error is None and res.may_hold_functional is expected, name
        records = [json.loads(line) for line in (header + body).splitlines()]
        assert names_masker_placing_set(records) is expected, name


def test_shift_figures_drawn_in_their_own_process_are_the_ones_drawn_in_process(logs):
    from masking_lab.analysis.figure_pool import FigurePool
    from masking_lab.analysis.lab_outputs import ShiftFigures
    from masking_lab.analysis.log_reading import read_logs
    from masking_lab.analysis.study_status import outliers
    from masking_lab.analysis.thresholds import EstimatorSettings, thresholds_table

    root, rels = logs
    paths = [root / r for r in rels if not r.endswith(("gone.jsonl", "torn.jsonl"))]
    rows = [row for res in read_logs(paths, root, EstimatorSettings()) for row in res.rows]
    thresholds = thresholds_table(rows)
    flags = outliers(thresholds)
    pool = FigurePool()
    pool.widen(2)
    try:
        here = ShiftFigures(thresholds, flags, True, FigurePool(enabled=False)).result()
        there = ShiftFigures(thresholds, flags, True, pool).result()
        assert ShiftFigures(thresholds, flags, False, pool).result() == []
    finally:
        pool.close()
    assert [e for e, _ in here] == ["experiment1", "experiment2"]
    assert there == here and all(png.startswith(b"\x89PNG") for _, png in there)
