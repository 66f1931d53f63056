"""Psychometric fits made many at once (issue 22): a set's fit must not depend on the sets
batched beside it, nor on the process that made it, so psychometric.csv keeps its bytes."""

from __future__ import annotations

import numpy as np
import pytest

from masking_lab.analysis import pf_table, psychometric
from masking_lab.analysis.pf_table import SetTrials, fit_all, pf_job
from masking_lab.analysis.psychometric import PFJob, fit_pf, fit_pf_many, pf_curve


def _track(rng: np.random.Generator, n_levels: int, n_per: int) -> tuple[list, list]:
    x = np.repeat(np.linspace(-6.0, 6.0, n_levels), n_per)
    truth = (rng.uniform(-2, 2), rng.uniform(0.4, 1.5), rng.uniform(0.0, 0.06))
    r = rng.random(x.size) < pf_curve(x, *truth, 1 / 3)
    return x.tolist(), r.tolist()


def _jobs() -> list[PFJob]:
    """Mixed batches: levels counts, guess rates, fixed and fitted λ, given estimates, and
    sets that cannot be fitted, interleaved."""
    rng = np.random.default_rng(11)
    jobs = []
    for i in range(24):
        x, r = _track(rng, n_levels=3 + i % 5, n_per=6 + i % 7)
        jobs.append(PFJob(x, r, n_boot=60, seed=i))
        if i % 6 == 0:
            jobs.append(PFJob(x, r, guess=0.5, p_target=0.75, lapse=0.02, n_boot=40, seed=i))
        if i % 8 == 0:
            jobs.append(PFJob(x, r, lapse=0.02, n_boot=30, seed=i, estimate=(0.2, 1.0, 0.02)))
    jobs += [PFJob([1.0] * 20, [True] * 20), PFJob([1.0, 2.0], [True, False], n_boot=0)]
    jobs.append(PFJob([float("nan")] * 12, [True, False] * 6))
    return jobs


def _alone(job: PFJob):
    return fit_pf(
        job.levels_db, job.correct, guess=job.guess, p_target=job.p_target, lapse=job.lapse,
        n_boot=job.n_boot, seed=job.seed, estimate=job.estimate,
    )  # fmt: skip


def test_a_batched_fit_is_bit_for_bit_the_fit_alone(monkeypatch):
    jobs = _jobs()
    alone = [_alone(j) for j in jobs]
    assert sum(f.ok for f in alone) > 20 and sum(not f.ok for f in alone) >= 3
    assert any(f.message and "at least" in f.message for f in alone)
    together = fit_pf_many(jobs)
    assert [repr(f) for f in together] == [repr(f) for f in alone]  # repr: NaN-safe, exact
    # Small batches split the same sets differently; the fits stay the same.
    monkeypatch.setattr(psychometric, "_BATCH_ROWS", 50)
    assert [repr(f) for f in fit_pf_many(jobs[::-1])] == [repr(f) for f in alone[::-1]]


def test_fits_spread_over_processes_are_the_fits_made_in_process(monkeypatch):
    monkeypatch.setattr(pf_table, "_PF_CHUNK", 2)  # four chunks, so two workers share them
    rng = np.random.default_rng(5)
    jobs = []
    for i in range(9):
        x, r = _track(rng, n_levels=4 + i % 3, n_per=8)
        jobs.append(pf_job(SetTrials({"level_unit": "db_sl"}, x, r), seed=i, n_boot=30))
    seen: list[tuple[int, int]] = []
    serial = fit_all(jobs, workers=1)
    parallel = fit_all(jobs, workers=2, progress=lambda i, n: seen.append((i, n)))
    assert [repr(f) for f in parallel] == [repr(f) for f in serial]
    assert seen and seen[-1] == (9, 9) and seen == sorted(seen)


def test_chunks_cover_every_job_once_evenly_in_a_multiple_of_the_workers():
    for n in (1, 2, 5, 9, 127, 128, 129, 340, 1000, 4097):
        for workers in (1, 2, 3, 4):
            for chunk in (1, 2, 128):
                bounds = pf_table.chunk_bounds(n, workers, chunk)
                assert [a for a, _ in bounds] == [0] + [b for _, b in bounds[:-1]]
                assert bounds[-1][1] == n
                sizes = [b - a for a, b in bounds]
                assert min(sizes) >= 1 and max(sizes) - min(sizes) <= 1
                assert max(sizes) <= 2 * chunk or len(bounds) == workers
                assert len(bounds) % workers == 0 or len(bounds) == n
    assert pf_table.chunk_bounds(0, 2, 128) == []
    # The demo's 340 sets on two workers: one even chunk each, not 128 + 128 + 84.
    assert pf_table.chunk_bounds(340, 2, 128) == [(0, 170), (170, 340)]


def test_an_empty_batch_and_a_bad_track_are_answered_not_raised():
    assert fit_pf_many([]) == []
    (fit,) = fit_pf_many([PFJob([0.0] * 10, [False] * 10)])
    assert not fit.ok and "wrong" in fit.message
    with pytest.raises(Exception, match="2 levels but 1 answers"):
        fit_pf_many([PFJob([0.0, 1.0], [True])])


def _where_and_trials(job: PFJob, fit: psychometric.PFFit) -> tuple[int, int]:
    """``then`` of the tests below: the process that made the fit, and its trials."""
    import os

    return os.getpid(), len(job.levels_db)


_TEST_PROCESS = __import__("os").getpid()  # a forked worker inherits this value


def _die_in_a_worker(job: PFJob, fit: psychometric.PFFit) -> int:
    """``then`` that kills the worker process it runs in (as the kernel's OOM killer would)."""
    import os
    import signal

    if os.getpid() != _TEST_PROCESS:
        os.kill(os.getpid(), signal.SIGKILL)
    return os.getpid()


def _refuse_level_count_7(job: PFJob, fit: psychometric.PFFit) -> int:
    if fit.n_levels == 7:
        raise ValueError("no plot for 7 levels")
    return fit.n_levels


def _eight_chunks(monkeypatch) -> list[PFJob]:
    monkeypatch.setattr(pf_table, "_PF_CHUNK", 2)
    rng = np.random.default_rng(8)
    jobs = []
    for i in range(16):
        x, r = _track(rng, n_levels=4 + i % 4, n_per=8)
        jobs.append(pf_job(SetTrials({"level_unit": "db_sl"}, x, r), seed=i, n_boot=30))
    return jobs


def _fitted_with_two(monkeypatch, then):
    """The 16 sets of :func:`_eight_chunks` fitted with ``then`` by this process and a worker,
    checked against the fits made alone; also the progress calls."""
    jobs = _eight_chunks(monkeypatch)
    alone = fit_all(jobs, workers=1)
    seen: list[tuple[int, int]] = []
    made = pf_table.fit_all_with(jobs, then, workers=2, progress=lambda i, n: seen.append((i, n)))
    assert [repr(f) for f, _ in made] == [repr(f) for f in alone]
    return jobs, made, seen


def test_then_runs_beside_each_fit_wherever_the_fit_was_made(monkeypatch):
    import os

    jobs, made, seen = _fitted_with_two(monkeypatch, _where_and_trials)
    assert [n for _, (_, n) in made] == [len(j.levels_db) for j in jobs]
    # This process fitted chunks from the end while the worker took them from the start: in
    # the order the sets were chunked (by batch group), the fits' processes are the worker's
    # first, then this one's, and each made some.
    order = sorted(range(len(jobs)), key=lambda i: psychometric.batch_group(jobs[i]))
    assert order != list(range(len(jobs)))  # the sets were regrouped
    where = [made[i][1][0] for i in order]
    here = os.getpid()
    first_here = where.index(here)
    assert all(pid != here for pid in where[:first_here])
    assert all(pid == here for pid in where[first_here:])
    assert 0 < first_here < len(jobs) and first_here % 2 == 0
    assert seen == sorted(seen) and seen[-1] == (16, 16)
    # None: nothing made beside the fits
    assert [extra for _, extra in pf_table.fit_all_with(jobs[:3], None, workers=1)] == [None] * 3


def test_two_chunks_on_two_workers_are_fitted_one_in_each_process(monkeypatch):
    import os

    # The demo's case (340 sets: 2 x 170). Handing the pool two chunks per worker left none
    # for this process, and the demo's fits ran on one core.
    jobs = _eight_chunks(monkeypatch)
    monkeypatch.setattr(pf_table, "_PF_CHUNK", 8)
    assert len(pf_table.chunk_bounds(len(jobs), 2, pf_table._PF_CHUNK)) == 2
    made = pf_table.fit_all_with(jobs, _where_and_trials, workers=2)
    where = [pid for _, (pid, _) in made]
    assert where.count(os.getpid()) == 8 and len(set(where)) == 2
    assert [repr(f) for f, _ in made] == [repr(f) for f in fit_all(jobs, workers=1)]


def test_a_failing_then_is_raised_and_ends_the_pool(monkeypatch):
    jobs = _eight_chunks(monkeypatch)
    with pytest.raises(ValueError, match="no plot for 7 levels"):
        pf_table.fit_all_with(jobs, _refuse_level_count_7, workers=2)
    with pytest.raises(ValueError, match="no plot for 7 levels"):
        pf_table.fit_all_with(jobs, _refuse_level_count_7, workers=1)


def test_sets_are_chunked_by_batch_group_and_come_back_in_their_order(monkeypatch):
    jobs = _eight_chunks(monkeypatch)
    seen_chunks: list[list[tuple[int, float, bool]]] = []
    real = pf_table._fit_chunk

    def spy(chunk, then=None, compiled=False):
        seen_chunks.append([psychometric.batch_group(j) for j in chunk])
        return real(chunk, then, compiled)

    monkeypatch.setattr(pf_table, "_fit_chunk", spy)
    made = pf_table.fit_all_with(jobs, None, workers=1)
    # each chunk holds one group where the groups allow it (16 sets, 4 per level count)
    assert [len(set(c)) for c in seen_chunks] == [1] * 8
    groups = [g for c in seen_chunks for g in c]
    assert groups == sorted(groups)
    assert [f.n_levels for f, _ in made] == [psychometric.batch_group(j)[0] for j in jobs]


# and nothing fails in the pool's own thread (a cancelled future there did, on Python 3.11)
@pytest.mark.filterwarnings("error::pytest.PytestUnhandledThreadExceptionWarning")
def test_the_chunks_of_a_worker_that_died_are_fitted_here(monkeypatch):
    import os

    _, made, seen = _fitted_with_two(monkeypatch, _die_in_a_worker)
    assert {pid for _, pid in made} == {os.getpid()}  # every chunk ended up fitted here
    assert seen == sorted(seen) and seen[-1] == (16, 16)
