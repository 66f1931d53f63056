"""How `analyze` and `fit` run their statistics (issue 22): on one BLAS thread."""

from __future__ import annotations

import os
from pathlib import Path

import numpy  # noqa: F401  (loads the BLAS pool that threadpoolctl lists)
import pytest
import threadpoolctl

from masking_lab.analysis import experiment
from masking_lab.commands.cli import main
from masking_lab.simulation.synthetic_logs import simulate_study

TABLE2 = Path(__file__).resolve().parents[1] / "data_schema" / "shifts.csv"


def _blas_threads() -> set[int]:
    return {p["num_threads"] for p in threadpoolctl.threadpool_info() if p["user_api"] == "blas"}


@pytest.fixture
def seen_threads(monkeypatch, tmp_path):
    """The BLAS thread counts each analyze_shifts call ran with, read after the run: written
    to a file, as `analyze` computes its statistics in a worker process of its own."""
    # numpy's wheels bundle OpenBLAS: a pool threadpoolctl cannot see would be a broken install
    assert _blas_threads(), "no BLAS pool that threadpoolctl can see"
    record = tmp_path / "blas_threads.txt"
    real = experiment.analyze_shifts

    def spy(*args, **kwargs):
        with record.open("a") as fh:
            print(os.getpid(), *sorted(_blas_threads()), file=fh)
        return real(*args, **kwargs)

    monkeypatch.setattr(experiment, "analyze_shifts", spy)
    return lambda: [{int(n) for n in line.split()[1:]} for line in record.read_text().splitlines()]


def _statistics_pids(tmp_path) -> list[int]:
    return [int(line.split()[0]) for line in (tmp_path / "blas_threads.txt").open()]


def test_analyze_computes_its_statistics_in_a_worker_only_beside_a_second_read_in_process(
    seen_threads, tmp_path
):
    """A small study's second read (trial tables) runs in the analysing process: the
    statistics run beside it in a worker. Without trial tables there is nothing to overlap,
    and a large study's second read has workers on every core: the statistics stay here."""
    simulate_study(tmp_path / "data", n_participants=2, seed=3)
    argv = ["analyze", str(tmp_path / "data"), "--quiet", "--figures", "none", "--n-boot", "100"]
    assert main([*argv, "--out", str(tmp_path / "with")]) == 0
    assert main([*argv, "--out", str(tmp_path / "without"), "--no-trial-tables"]) == 0
    beside, here = _statistics_pids(tmp_path)
    assert beside != os.getpid() and here == os.getpid()
    assert seen_threads() == [{1}, {1}]


def test_analyze_runs_its_statistics_on_one_blas_thread(seen_threads, tmp_path):
    simulate_study(tmp_path / "data", n_participants=2, seed=3)
    argv = ["analyze", str(tmp_path / "data"), "--out", str(tmp_path / "out"), "--quiet"]
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        assert main([*argv, "--figures", "none", "--no-trial-tables", "--n-boot", "100"]) == 0
        assert _blas_threads() == {2}  # the caller's limit is back
    assert seen_threads() == [{1}]


def test_fit_runs_its_statistics_on_one_blas_thread(seen_threads, tmp_path):
    argv = ["fit", str(TABLE2), "--out", str(tmp_path / "out"), "--quiet", "--figures", "none"]
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        assert main([*argv, "--n-boot", "100"]) == 0
        assert _blas_threads() == {2}
    assert seen_threads() == [{1}]


def test_analyze_freezes_what_it_read_and_thaws_it_after(tmp_path, monkeypatch):
    """The read results are frozen out of the cyclic collector for the run, and nothing stays
    frozen after it (a caller running analyze in-process keeps its collector whole)."""
    import gc

    from masking_lab.analysis import batch

    frozen: list[int] = []
    real = batch.duplicate_sessions

    def spy(results):
        frozen.append(gc.get_freeze_count())
        return real(results)

    monkeypatch.setattr(batch, "duplicate_sessions", spy)
    simulate_study(tmp_path / "data", n_participants=2, seed=3)
    argv = ["--quiet", "--figures", "none", "--no-trial-tables", "--n-boot", "100"]
    assert gc.get_freeze_count() == 0
    assert main(["analyze", str(tmp_path / "data"), "--out", str(tmp_path / "out"), *argv]) == 0
    assert frozen[-1] > 0 and gc.get_freeze_count() == 0
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "x.jsonl").write_text("not a log\n")
    assert main(["analyze", str(bad), "--out", str(tmp_path / "out2"), *argv]) == 2
    assert len(frozen) == 2 and frozen[-1] > 0 and gc.get_freeze_count() == 0
