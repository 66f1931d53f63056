"""The chunks of ``plan``'s staircase simulation (*pure*; the shell runs them anywhere).

A schedule's simulated sessions are cut into chunks of replicates, each simulated with its own
seed (:func:`masking_lab.planning.parallel.chunk_plan`): a chunk's outcomes depend only on its
arguments, so :func:`masking_lab.planning.plan.run_plan` gives the same tables whether the
chunks run in this process, on local worker processes or on a Dask cluster. Every schedule uses
the same chunks and seeds (common random numbers across settings). A chunk returns its
sessions' outcomes under every stop rule, rung and ML fit (arrays of one number per session);
the tracks themselves stay in the worker.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from masking_lab.core.errors import AnalysisError
from masking_lab.formats.protocol import ThresholdProtocol
from masking_lab.planning.parallel import Task, chunk_plan
from masking_lab.planning.settings import (
    TRIAL_LIMIT,
    PlanSettings,
    ladder_rules,
    protocol_staircase,
    protocol_stop_rule,
)
from masking_lab.procedures.ml_batch import index_levels, ml_threshold_from_counts
from masking_lab.procedures.staircase import StaircaseSettings
from masking_lab.procedures.staircase_batch import StopOutcome, outcome_under, simulate

__all__ = [
    "CHUNK_REPLICATES",
    "ML_CHUNK_REPLICATES",
    "chunk_layout",
    "ml_chunk",
    "plan_tasks",
    "schedule_chunk",
]

#: Replicates per set in one chunk of a schedule's simulation, and of its ML fits (whose tracks
#: keep every trial's level): a worker holds one chunk, which bounds its memory (peak ~26 MB
#: and ~56 MB for the 15 sets of experiment I; smaller chunks cost more CPU per session). The
#: tables depend on these sizes and the seed, never on where the chunks run.
CHUNK_REPLICATES = 1000
ML_CHUNK_REPLICATES = 500


Chunk = tuple[int, int, np.random.SeedSequence]


def chunk_layout(settings: PlanSettings) -> tuple[list[Chunk], list[Chunk]]:
    """(first replicate, replicates, seed) of every chunk of the long runs and of the ML runs.

    Every schedule uses the same chunks and seeds: settings compared on common random numbers.
    """
    reps, ml_reps = settings.replicates, min(settings.ml_replicates, settings.replicates)
    long_plan = chunk_plan(settings.seed, reps, CHUNK_REPLICATES)
    ml_plan = chunk_plan([settings.seed, 1], ml_reps, ML_CHUNK_REPLICATES) if ml_reps else []

    def starts(plan: list[tuple[int, np.random.SeedSequence]]) -> list[Chunk]:
        firsts = np.cumsum([0, *(n for n, _ in plan)])[:-1]
        return [(int(a), n, ss) for a, (n, ss) in zip(firsts, plan, strict=True)]

    return starts(long_plan), starts(ml_plan)


def plan_tasks(
    protocol: ThresholdProtocol, settings: PlanSettings, thresholds_db: NDArray[np.float64]
) -> list[Task]:
    """The chunks of :func:`run_plan`'s simulations (every schedule's ML chunks, then every
    schedule's long runs), to run anywhere
    (:func:`masking_lab.planning.parallel.run_tasks`); :func:`assemble_plan` reads their
    results, in this order, into the plan.

    Raises
    ------
    AnalysisError
        If ``thresholds_db`` is not (sets, replicates).
    """
    n_sets, reps = len(protocol.sets), settings.replicates
    if thresholds_db.shape != (n_sets, reps):
        raise AnalysisError(
            f"thresholds must have shape (sets, replicates) = ({n_sets}, {reps}), "
            f"got {thresholds_db.shape}"
        )
    long_chunks, ml_chunks = chunk_layout(settings)
    # The ML fits first: the longest chunks, started first, leave the short ones to fill in.
    schedules = range(1, len(settings.schedules) + 1)
    tasks: list[Task] = [
        (ml_chunk, (protocol, settings, thresholds_db[:, a : a + n], k, ss))
        for k in schedules
        for a, n, ss in ml_chunks
    ]
    tasks += [
        (schedule_chunk, (protocol, settings, thresholds_db[:, a : a + n], k, ss))
        for k in schedules
        for a, n, ss in long_chunks
    ]
    return tasks


def _schedule_settings(
    protocol: ThresholdProtocol, settings: PlanSettings, k: int
) -> StaircaseSettings:
    """Schedule ``k``'s staircase, run to ``max_reversals`` reversals without a trial cap."""
    sched = settings.schedules[k - 1]
    return replace(
        protocol_staircase(protocol),
        step_sizes_db=sched.step_sizes_db,
        down_up_ratio=sched.down_up_ratio,
        n_reversals=settings.max_reversals,
        n_reversals_averaged=1,
        max_trials=None,
    )


def _starts(protocol: ThresholdProtocol, n: int) -> NDArray[np.float64]:
    base = protocol_staircase(protocol)
    return np.repeat([(s.staircase or base).start_level_db for s in protocol.sets], n)


def schedule_chunk(
    protocol: ThresholdProtocol,
    settings: PlanSettings,
    thresholds_db: NDArray[np.float64],
    k: int,
    seed: np.random.SeedSequence,
) -> tuple[list[StopOutcome], list[StopOutcome]]:
    """One chunk of schedule ``k``'s long run: how its sessions end under every stop rule of
    the table (with the protocol's cap) and every rung of the reversal ladder (uncapped).

    ``thresholds_db`` is (sets, chunk replicates); the outcomes' rows are set-major.

    Examples
    --------
    >>> from masking_lab.formats.resources import shipped
    >>> from masking_lab.formats.protocol import load_protocol
    >>> from masking_lab.planning.settings import Schedule, StopRule
    >>> p = load_protocol(shipped("protocols", "baseline.yaml"))
    >>> s = PlanSettings((StopRule(11, 8),), (Schedule((4.0, 2.0)),), replicates=5,
    ...                  ml_replicates=0, max_reversals=12)
    >>> rules, rungs = schedule_chunk(p, s, np.full((4, 5), -30.0), 1, np.random.SeedSequence(0))
    >>> rules[0].n_trials.shape, len(rungs)
    ((20,), 9)
    """
    n = thresholds_db.shape[1]
    long_run = simulate(
        _schedule_settings(protocol, settings, k),
        thresholds_db.reshape(-1),
        settings.observer,
        np.random.default_rng(seed),
        start_level_db=_starts(protocol, n),
        trial_limit=TRIAL_LIMIT,
        store_levels=False,
    )
    cap = protocol_staircase(protocol).max_trials
    rules = [
        outcome_under(long_run, r.n_reversals, r.n_averaged, cap, exact=False)
        for r in settings.stop_rules
    ]
    rungs = [
        outcome_under(long_run, r.n_reversals, r.n_averaged, exact=False)
        for r in ladder_rules(protocol_stop_rule(protocol), settings.max_reversals)
    ]
    return rules, rungs


def ml_chunk(
    protocol: ThresholdProtocol,
    settings: PlanSettings,
    thresholds_db: NDArray[np.float64],
    k: int,
    seed: np.random.SeedSequence,
) -> list[NDArray[np.float64]]:
    """One chunk of schedule ``k``'s ML fits: per stop rule of the table, each session's
    ML threshold (dB; NaN where the session did not complete under the rule and cap).

    Examples
    --------
    >>> from masking_lab.formats.resources import shipped
    >>> from masking_lab.formats.protocol import load_protocol
    >>> from masking_lab.planning.settings import Schedule, StopRule
    >>> p = load_protocol(shipped("protocols", "baseline.yaml"))
    >>> s = PlanSettings((StopRule(11, 8),), (Schedule((4.0, 2.0)),), replicates=5,
    ...                  ml_replicates=5, max_reversals=12)
    >>> [a.shape for a in ml_chunk(p, s, np.full((4, 5), -30.0), 1, np.random.SeedSequence(0))]
    [(20,)]
    """
    obs = settings.observer
    cap = protocol_staircase(protocol).max_trials
    longest = max(r.n_reversals for r in settings.stop_rules)
    run = simulate(
        replace(_schedule_settings(protocol, settings, k), n_reversals=longest),
        thresholds_db.reshape(-1),
        obs,
        np.random.default_rng(seed),
        start_level_db=_starts(protocol, thresholds_db.shape[1]),
        trial_limit=TRIAL_LIMIT,
    )
    index = index_levels(run.levels_db, run.correct)
    out = []
    for rule in settings.stop_rules:
        ml_out = outcome_under(run, rule.n_reversals, rule.n_averaged, cap, exact=False)
        done = np.flatnonzero(ml_out.completed)
        al = np.full(thresholds_db.size, np.nan)
        if done.size:
            fit = ml_threshold_from_counts(
                index.counts(ml_out.n_trials, rows=done),
                scale_db=obs.scale_db,
                lapse=settings.ml_lapse,
                guess=obs.guess,
                fit_scale=settings.ml_fit_scale,
            )
            al[done] = fit.threshold_db
        out.append(al)
    return out
