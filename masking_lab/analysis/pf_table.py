"""``psychometric.csv``: a psychometric function per set attempt (*shell side of the fits*).

:func:`pf_job` turns one set's trials (:class:`SetTrials`, gathered by :func:`set_trials` from
a parsed log) into the fit its row reports, :func:`fit_all` makes every fit of a study at
once (batched by :func:`masking_lab.analysis.psychometric.fit_pf_many`, in parallel processes
for many sets: each fit is the same whichever batch or process makes it), and :func:`pf_row`
lays one fit out in :data:`PF_COLUMNS` (levels and thresholds in dB of the set's unit, slopes
in 1/dB).
"""

from __future__ import annotations

import functools
import os
import zlib
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import Any, TypeVar

from masking_lab.analysis.freed_memory import reused_blocks
from masking_lab.analysis.pf_likelihood import warm_compiled
from masking_lab.analysis.psychometric import PFFit, PFJob, batch_group, fit_pf_many
from masking_lab.core.errors import MaskingLabError
from masking_lab.core.psychometric import GUESS_3IFC
from masking_lab.core.worker_processes import result_or_here, worker_pool
from masking_lab.formats.session_log import SessionLog

__all__ = [
    "PF_BOOTSTRAP",
    "PF_COLUMNS",
    "SetTrials",
    "chunk_bounds",
    "fit_all",
    "fit_all_with",
    "pf_job",
    "pf_row",
    "pf_seed",
    "set_trials",
]

T = TypeVar("T")

PF_BOOTSTRAP = 200  # parametric-bootstrap data sets per psychometric function
PF_PARALLEL_FROM = 256  # fewer sets than this are fitted in-process (workers cost ~0.3 s)
_PF_CHUNK = 128  # sets per worker task: batches large enough for numpy, small for progress
# Bootstrap data sets from which a run's climbs run compiled (pf_likelihood.warm_compiled):
# loading numba costs ~0.4 s and ~110 MB a process (and the first run after an install ~3.5 s
# more, compiling into numba's cache). Measured with analyze (trial tables, 2 cores): at 100
# sessions (225,000) no faster, at 300 (678,000) 4-12 % faster, at 1,000 (2.26 million) 32 %.
PF_COMPILED_FROM = 500_000
PF_COLUMNS = [
    "participant",
    "experiment",
    "set_id",
    "target",
    "masker",
    "masker_level_db_sl",
    "level_unit",
    "procedure",
    "n_trials",
    "n_levels",
    "guess",
    "p_target",
    "threshold_db",
    "threshold_ci95_low_db",
    "threshold_ci95_high_db",
    "slope_per_db",
    "slope_ci95_low_per_db",
    "slope_ci95_high_per_db",
    "lapse",
    "lapse_ci95_low",
    "lapse_ci95_high",
    "al_db",
    "al_sd_db",
    "al_ci95_low_db",
    "al_ci95_high_db",
    "deviance",
    "deviance_df",
    "deviance_p",
    "n_bootstrap",
    "status",
    "note",
    "session_id",
    "log",
]


@dataclass
class SetTrials:
    """One set attempt's trials for the psychometric fit."""

    start: Mapping[str, Any]
    levels: list[float] = field(default_factory=list)
    correct: list[bool] = field(default_factory=list)


def set_trials(log: SessionLog) -> dict[str, SetTrials]:
    """Each started set's trials in a parsed log (levels in dB of the set's unit): set id →
    :class:`SetTrials`; trials without a numeric level or a true/false answer are left out."""
    out: dict[str, SetTrials] = {}
    for rec in log.records:
        sid = rec.get("set_id")
        if rec.get("record") == "set_start" and isinstance(sid, str):
            out.setdefault(sid, SetTrials(rec)).start = rec
        elif rec.get("record") == "trial" and sid in out:
            st = out[sid]
            key = "level_db_sl" if st.start.get("level_unit") == "db_sl" else "level_db_v"
            lv, ok = rec.get(key), rec.get("correct")
            if isinstance(lv, int | float) and not isinstance(lv, bool) and isinstance(ok, bool):
                st.levels.append(float(lv))
                st.correct.append(ok)
    return out


@functools.lru_cache(maxsize=256)
def _target_p(n_up: int, n_down: int, down_up_ratio: float) -> float:
    """The staircase's target p (a root search, ~7 ms): a study has a handful of rules and
    thousands of sets, so each rule is solved once (bounded: the rules come from files)."""
    from masking_lab.procedures.staircase import implied_target_p_for

    return implied_target_p_for(n_up, n_down, down_up_ratio)


def _model(start: Mapping[str, Any]) -> tuple[str, float, float]:
    """The set's procedure kind, guess rate and the p its AL is read at."""
    proc = start.get("procedure")
    if isinstance(proc, Mapping):
        # the registry rebuilds any kind's settings; a kind without a guess rate or threshold
        # point (or unreadable settings) is read as a 3IFC track at the 1-up-3-down point
        from masking_lab.procedures.registry import settings_from_start

        try:
            s = settings_from_start(start, None)
            guess = float(getattr(s, "guess", GUESS_3IFC))
            return str(proc.get("kind")), guess, float(getattr(s, "p_at_threshold", 0.5 ** (1 / 3)))
        except (MaskingLabError, TypeError, ValueError):
            return str(proc.get("kind")), GUESS_3IFC, 0.5 ** (1 / 3)
    raw_st = start.get("staircase")
    st = raw_st if isinstance(raw_st, Mapping) else {}
    try:
        p = _target_p(
            int(st.get("n_up", 1)), int(st.get("n_down", 3)), float(st.get("down_up_ratio", 1.0))
        )
    except (TypeError, ValueError, ArithmeticError):
        p = 0.5 ** (1 / 3)
    return "staircase", GUESS_3IFC, p


def pf_seed(participant: Any, experiment: Any, set_id: Any, log: str) -> int:
    """The bootstrap seed of a set's psychometric function: the same set of the same log, the
    same draws, whichever run, batch or process fits it.

    Examples
    --------
    >>> pf_seed("P1", "experiment1", "MV120_10", "P1/a.jsonl") == pf_seed(
    ...     "P1", "experiment1", "MV120_10", "P1/a.jsonl")
    True
    """
    return zlib.crc32(f"{participant}|{experiment}|{set_id}|{log}".encode())


def pf_job(st: SetTrials, seed: int, n_boot: int = PF_BOOTSTRAP) -> PFJob:
    """The fit of one set's trials for ``psychometric.csv``: λ fitted in [0, 0.1].

    Examples
    --------
    >>> job = pf_job(SetTrials({"level_unit": "db_sl"}, [0.0, 2.0], [False, True]), seed=1)
    >>> job.lapse is None, job.n_boot, round(job.p_target, 3)
    (True, 200, 0.794)
    """
    _, guess, p_target = _model(st.start)
    return PFJob(st.levels, st.correct, guess, p_target, None, n_boot, seed)


def pf_row(
    base: Mapping[str, Any],
    st: SetTrials,
    seed: int,
    n_boot: int = PF_BOOTSTRAP,
    fit: PFFit | None = None,
) -> dict:
    """The ``psychometric.csv`` row of one set: the fit of its trials, λ fitted in [0, 0.1].

    ``fit`` is that fit when already made (:func:`pf_job` through
    :func:`~masking_lab.analysis.psychometric.fit_pf_many`); else it is made here.

    Examples
    --------
    >>> st = SetTrials({"level_unit": "db_sl"}, [0.0, 2.0, 4.0] * 10, [False, True, True] * 10)
    >>> row = pf_row({"participant": "P1"}, st, seed=1, n_boot=0)
    >>> row["status"], row["n_levels"], row["deviance_df"]
    ('fitted', 3, 0)
    """
    kind, guess, p_target = _model(st.start)
    if fit is None:
        fit = fit_pf_many([pf_job(st, seed, n_boot)])[0]

    def ci(v: tuple[float, float] | None, i: int) -> float | None:
        return None if v is None else v[i]

    return {
        **base,
        "level_unit": "db_sl" if st.start.get("level_unit") == "db_sl" else "db_v",
        "procedure": kind,
        "n_trials": fit.n_trials,
        "n_levels": fit.n_levels,
        "guess": guess,
        "p_target": p_target,
        "threshold_db": fit.threshold_db,
        "threshold_ci95_low_db": ci(fit.threshold_ci_db, 0),
        "threshold_ci95_high_db": ci(fit.threshold_ci_db, 1),
        "slope_per_db": fit.slope_per_db,
        "slope_ci95_low_per_db": ci(fit.slope_ci_per_db, 0),
        "slope_ci95_high_per_db": ci(fit.slope_ci_per_db, 1),
        "lapse": fit.lapse,
        "lapse_ci95_low": ci(fit.lapse_ci, 0),
        "lapse_ci95_high": ci(fit.lapse_ci, 1),
        "al_db": fit.al_db,
        "al_sd_db": fit.al_sd_db,
        "al_ci95_low_db": ci(fit.al_ci_db, 0),
        "al_ci95_high_db": ci(fit.al_ci_db, 1),
        "deviance": fit.deviance,
        "deviance_df": max(fit.n_levels - 3, 0),
        "deviance_p": fit.deviance_p,
        "n_bootstrap": fit.n_boot,
        "status": "fitted" if fit.ok else "failed",
        "note": fit.message,
        "_fit": fit,
    }


def fit_all(
    jobs: Sequence[PFJob],
    *,
    workers: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> list[PFFit]:
    """:func:`~masking_lab.analysis.psychometric.fit_pf_many` of every job, in chunks spread
    over processes for many sets (each fit is the same whichever chunk holds it).

    Examples
    --------
    >>> fit_all([])
    []
    """
    return [fit for fit, _ in fit_all_with(jobs, None, workers=workers, progress=progress)]


def fit_all_with(
    jobs: Sequence[PFJob],
    then: Callable[[PFJob, PFFit], T] | None,
    *,
    workers: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> list[tuple[PFFit, T | None]]:
    """Each job's fit (as :func:`fit_all`) and ``then(job, fit)``, made where the fit was made.

    ``then`` (a module-level function, so that it reaches a worker) is the per-fit work that
    would otherwise follow the fits in this process alone: the report's plot of each set.

    The sets are fitted in chunks of :data:`_PF_CHUNK`, sorted so that sets with the same
    :func:`~masking_lab.analysis.psychometric.batch_group` share chunks. ``workers − 1``
    forked processes take chunks from the first on, two per process at a time; this process
    fits chunks too, from the last one backwards, so all finish together however the cores
    are shared (with the figure workers, say). A chunk's fits do not depend
    on where it was fitted, so the chunks of a worker that died (killed for memory, say) are
    fitted here, as the figure pool draws a dead worker's figures. From
    :data:`PF_COMPILED_FROM` bootstrap data sets on, the climbs run compiled (the same
    numbers), loaded in this process before the workers fork.

    Parameters
    ----------
    jobs : sequence of PFJob
        One per set.
    then : callable or None
        ``then(job, fit)``; None gives None beside every fit.
    workers : int, optional
        Processes, this one included; default: the CPU count from :data:`PF_PARALLEL_FROM`
        sets on, else 1.
    progress : callable, optional
        Called with (sets fitted, sets to fit), the count rising.

    Returns
    -------
    list of (PFFit, result of ``then``)
        In the order of ``jobs``.

    Examples
    --------
    >>> st = SetTrials({"level_unit": "db_sl"}, [0.0, 2.0, 4.0] * 10, [False, True, True] * 10)
    >>> trials = lambda job, fit: len(job.levels_db)  # in this process: any callable
    >>> [(fit.n_levels, n) for fit, n in fit_all_with([pf_job(st, 1, 0)], trials)]
    [(3, 30)]
    """
    n = len(jobs)
    if workers is None:
        workers = (os.cpu_count() or 1) if n >= PF_PARALLEL_FROM else 1
    # Sets that climb as one batch side by side, so that a chunk's batches are full (a study's
    # sets differ in their number of levels: in the order of the logs, a chunk of 128 sets
    # made a dozen small batches, each paying numpy's per-call cost).
    order = sorted(range(n), key=lambda i: batch_group(jobs[i]))
    ordered = [jobs[i] for i in order]
    chunks = [ordered[a:b] for a, b in chunk_bounds(n, workers, _PF_CHUNK)]
    # loaded here, before the workers fork, so that each has it
    compiled = sum(j.n_boot for j in jobs) >= PF_COMPILED_FROM and warm_compiled()
    made: list[tuple[PFFit, T | None]] = []
    if workers <= 1 or len(chunks) < 2:
        for chunk in chunks:
            made += _fit_chunk(chunk, then, compiled)
            if progress:
                progress(len(made), n)
        return _unsorted(made, order)
    results: list[list[tuple[PFFit, T | None]] | None] = [None] * len(chunks)
    done = 0
    pool_size = min(workers, len(chunks)) - 1
    # The pool takes chunks from the front, two per worker in hand (one running, one queued);
    # this process takes them from the back, topping the pool up after each, and always keeps
    # one for itself (the demo's two chunks went both to the pool: its fits ran on one core).
    # Short of an error nothing is cancelled: Python 3.11's pool, once broken, fails on a
    # cancelled future in its own thread.
    futures: dict[int, Future[list[tuple[PFFit, T | None]]]] = {}
    front, back, broken = 0, len(chunks), False
    # on an error the pool's block interrupts the chunks still running (worker_pool)
    with worker_pool(pool_size) as pool:
        while front < back:
            in_hand = sum(not f.done() for f in futures.values())
            while front < back - 1 and not broken and in_hand < 2 * pool_size:
                try:
                    futures[front] = pool.submit(_fit_chunk, chunks[front], then, compiled)
                except BrokenProcessPool:
                    broken = True
                    break
                front, in_hand = front + 1, in_hand + 1
            if front < back:
                back -= 1
                results[back] = _fit_chunk(chunks[back], then, compiled)
                done += len(chunks[back])
                if progress:
                    progress(done, n)
        for i, fut in sorted(futures.items()):
            # a worker that died (killed for memory, say) leaves its chunks to this process
            results[i] = result_or_here(fut, _fit_chunk, chunks[i], then, compiled)
            done += len(chunks[i])
            if progress:
                progress(done, n)
    for part in results:
        assert part is not None
        made += part
    return _unsorted(made, order)


def _unsorted(made: list[Any], order: list[int]) -> list[Any]:
    """``made[k]`` belongs to job ``order[k]``: back in the order of the jobs."""
    out: list[Any] = [None] * len(made)
    for k, i in enumerate(order):
        out[i] = made[k]
    return out


def _fit_chunk(
    jobs: list[PFJob], then: Callable[[PFJob, PFFit], T] | None = None, compiled: bool = False
) -> list[tuple[PFFit, T | None]]:
    """One chunk's fits (and ``then`` of each), their numpy temporaries reused from the heap
    (in a worker too); ``compiled``: climbed by the compiled loops (the same numbers)."""
    with reused_blocks():
        fits = fit_pf_many(jobs, compiled=compiled)
    if then is None:
        return [(fit, None) for fit in fits]
    return [(fit, then(job, fit)) for job, fit in zip(jobs, fits, strict=True)]


def chunk_bounds(n: int, workers: int, chunk: int) -> list[tuple[int, int]]:
    """``(start, stop)`` of the chunks that ``n`` jobs are fitted in: about ``chunk`` jobs each
    (at most twice that), as many chunks as a multiple of ``workers``, sizes differing by at
    most one.

    Even chunks keep every worker busy to the end: the demo's 340 sets as 128 + 128 + 84 on two
    workers leave one idle while the other fits its second chunk; 2 × 170 do not (and larger
    batches cost numpy less per set).

    Parameters
    ----------
    n : int
        Jobs (sets).
    workers : int
        Processes that fit the chunks.
    chunk : int
        Jobs per chunk aimed at.

    Returns
    -------
    list of (int, int)
        Consecutive slices covering ``range(n)``.

    Examples
    --------
    >>> chunk_bounds(340, 2, 128)
    [(0, 170), (170, 340)]
    >>> chunk_bounds(5, 1, 2), chunk_bounds(0, 2, 128)
    ([(0, 2), (2, 4), (4, 5)], [])
    """
    if n <= 0:
        return []
    w = max(1, workers)
    k = max(w, -(-n // max(1, chunk)) // w * w)
    k = min(n, k)
    size, extra = divmod(n, k)
    bounds, start = [], 0
    for i in range(k):
        stop = start + size + (i < extra)
        bounds.append((start, stop))
        start = stop
    return bounds
