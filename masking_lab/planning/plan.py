"""Speed against accuracy before a participant sits down (the core of ``masking-lab plan``).

For each set of a protocol, simulated observers (:mod:`masking_lab.procedures.staircase_batch`) run
the staircase
under a grid of settings — stop rules (reversals run / reversals averaged), step schedules,
down/up step ratios — and each track's AL is estimated two ways: the paper's mean of the last
reversals, and a maximum-likelihood fit over all trials (:mod:`masking_lab.procedures.ml_batch`, the
analysis's estimator). For every setting this module reports what a session costs (trials and
minutes, median and 90th percentile, at the protocol's timing) and what it buys (bias and SD of
the AL in dB against each observer's true threshold, and how often a track ends at a ceiling,
floor or trial cap instead of a threshold). A ladder of stop rules answers "how many reversals
do I need for ±X dB".

Pure: the random numbers come from the seed given, progress goes to a callback, nothing is
read or written here (:mod:`masking_lab.commands.plan` does that). The grid of settings is in
:mod:`masking_lab.planning.settings` (its names are re-exported here); tables and text are
formatted by :mod:`masking_lab.planning.report`.

Efficiency: all sets run together as rows of one simulation, every stop rule and the trial cap
are derived exactly from one long run per schedule
(:func:`masking_lab.procedures.staircase_batch.outcome_under`). The sessions are simulated in
chunks of replicates (:mod:`masking_lab.planning.plan_chunks`), each with its own seed, run
wherever ``scheduler`` says (:mod:`masking_lab.planning.parallel`): the tables depend on the
seed only. Each schedule reuses the same chunk seeds, so settings are compared on common random
numbers.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from masking_lab.core.errors import AnalysisError
from masking_lab.formats.protocol import ThresholdProtocol
from masking_lab.planning.parallel import run_tasks
from masking_lab.planning.plan_chunks import chunk_layout, plan_tasks
from masking_lab.planning.settings import (
    ESTIMATOR_LABELS,
    ESTIMATORS,
    GARCIA_PEREZ_RATIO,
    TRIAL_LIMIT,
    PlanSettings,
    Schedule,
    StopRule,
    default_schedules,
    default_stop_rules,
    ladder_rules,
    parse_ratios,
    parse_schedules,
    parse_stop_rules,
    protocol_schedule,
    protocol_staircase,
    protocol_stop_rule,
    runs_staircase,
    trial_duration_s,
    true_thresholds_db,
)
from masking_lab.procedures.fisher import cramer_rao_trials
from masking_lab.procedures.staircase_batch import (
    CEILING,
    COMPLETED,
    FLOOR,
    RUNNING,
    TRIAL_CAP,
    Observer,
    StopOutcome,
)

__all__ = [
    "ESTIMATORS",
    "ESTIMATOR_LABELS",
    "GARCIA_PEREZ_RATIO",
    "TRIAL_LIMIT",
    "Answer",
    "PlanResult",
    "PlanSettings",
    "Progress",
    "Schedule",
    "SchedulePart",
    "StopRule",
    "assemble_plan",
    "default_schedules",
    "default_stop_rules",
    "efficiency_fields",
    "error_summary",
    "ladder_rules",
    "parse_ratios",
    "parse_schedules",
    "parse_stop_rules",
    "plan_tasks",
    "pool",
    "protocol_schedule",
    "protocol_staircase",
    "protocol_stop_rule",
    "run_plan",
    "summarize",
    "summarize_sets",
    "trial_duration_s",
    "true_thresholds_db",
]

Progress = Callable[[str], None]


# --------------------------------------------------------------------------------------------
# Summaries


def summarize(
    n_trials: NDArray[np.int64],
    status_code: NDArray[np.int8],
    estimate_db: NDArray[np.float64] | None,
    true_db: NDArray[np.float64],
    trial_s: float,
) -> dict[str, float]:
    """Session cost and AL error of a group of simulated sessions.

    Parameters
    ----------
    n_trials, status_code : arrays, shape (R,)
        Per session (status codes of :data:`masking_lab.procedures.staircase_batch.STATUSES`).
    estimate_db : array, shape (R,), or None
        AL estimate per session, dB (NaN where there is none); None skips the error columns.
    true_db : array, shape (R,)
        True threshold per session, dB.
    trial_s : float
        Seconds per trial.

    Returns
    -------
    dict
        ``sessions``; fractions ``completed``, ``ceiling``, ``floor``, ``trial_cap``,
        ``unfinished``; ``trials_median``, ``trials_p90``, ``minutes_median``, ``minutes_p90``;
        and, over sessions with an estimate, ``n_al``, ``bias_db`` (mean of estimate − true),
        ``sd_db`` (SD, ddof 1), ``rmse_db``.
    """
    return summarize_sets(
        n_trials[None],
        status_code[None],
        None if estimate_db is None else estimate_db[None],
        true_db[None],
        trial_s,
    )[0]


def summarize_sets(
    n_trials: NDArray[np.int64],
    status_code: NDArray[np.int8],
    estimate_db: NDArray[np.float64] | None,
    true_db: NDArray[np.float64],
    trial_s: float,
) -> list[dict[str, float]]:
    """:func:`summarize` of each row of 2-D arrays (one row per set, shape (sets, R)).

    The percentiles and fractions of all rows come from one numpy call each (a plan asks for
    ~3,000 summaries); every number is the one :func:`summarize` gives for that row alone.

    Examples
    --------
    >>> n = np.array([[10, 20, 30], [40, 50, 60]])
    >>> rows = summarize_sets(n, np.zeros((2, 3), np.int8), None, np.zeros((2, 3)), 6.0)
    >>> [r["trials_median"] for r in rows], rows[1]["minutes_p90"]
    ([20.0, 50.0], 5.8)
    """
    n = int(n_trials.shape[1])
    q = np.percentile(n_trials, [50, 90], axis=1)
    fractions = {
        key: np.mean(status_code == code, axis=1)
        for key, code in (
            ("completed", COMPLETED),
            ("ceiling", CEILING),
            ("floor", FLOOR),
            ("trial_cap", TRIAL_CAP),
            ("unfinished", RUNNING),
        )
    }
    means = np.mean(n_trials, axis=1)
    rows = []
    for j in range(n_trials.shape[0]):
        med, p90 = float(q[0, j]), float(q[1, j])
        out: dict[str, float] = {"sessions": n}
        out |= {key: float(f[j]) for key, f in fractions.items()}
        out |= {
            "trials_median": med,
            "trials_p90": p90,
            "trials_mean": float(means[j]),
            "minutes_median": med * trial_s / 60.0,
            "minutes_p90": p90 * trial_s / 60.0,
        }
        if estimate_db is not None:
            out |= error_summary(estimate_db[j], true_db[j])
        rows.append(out)
    return rows


def error_summary(estimate_db: NDArray[np.float64], true_db: NDArray[np.float64]) -> dict:
    """``n_al``, ``bias_db``, ``sd_db`` (ddof 1) and ``rmse_db`` of the AL estimates (dB, NaN
    where a session has none) against the true thresholds (dB), as :func:`summarize` has them.

    Examples
    --------
    >>> error_summary(np.array([1.0, np.nan, 3.0]), np.array([0.0, 0.0, 2.0]))
    {'n_al': 2, 'bias_db': 1.0, 'sd_db': 0.0, 'rmse_db': 1.0}
    """
    err = (estimate_db - true_db)[np.isfinite(estimate_db)]
    return {
        "n_al": int(err.size),
        "bias_db": float(err.mean()) if err.size else math.nan,
        "sd_db": float(err.std(ddof=1)) if err.size > 1 else math.nan,
        "rmse_db": float(np.sqrt(np.mean(err**2))) if err.size else math.nan,
    }


def pool(per_set: Sequence[dict[str, float]], trials: NDArray[np.int64], trial_s: float) -> dict:
    """Pool per-set summaries: fractions and bias averaged over sets, SD as the root mean
    within-set variance (the between-set spread of bias is not precision), the worst set's SD
    and |bias|, and trial percentiles over all sessions."""
    med, p90 = (float(v) for v in np.percentile(trials, [50, 90]))
    out: dict[str, Any] = {
        "sessions": int(sum(r["sessions"] for r in per_set)),
        "trials_median": med,
        "trials_p90": p90,
        "trials_mean": float(np.mean(trials)),
        "minutes_median": med * trial_s / 60.0,
        "minutes_p90": p90 * trial_s / 60.0,
    }
    for key in ("completed", "ceiling", "floor", "trial_cap", "unfinished"):
        out[key] = float(np.mean([r[key] for r in per_set]))
    if "sd_db" in per_set[0]:
        sds = np.array([r["sd_db"] for r in per_set])
        biases = np.array([r["bias_db"] for r in per_set])
        rmses = np.array([r["rmse_db"] for r in per_set])
        ok = np.isfinite(sds)
        out["n_al"] = int(sum(r["n_al"] for r in per_set))
        out["bias_db"] = float(np.mean(biases[ok])) if ok.any() else math.nan
        out["sd_db"] = float(np.sqrt(np.mean(sds[ok] ** 2))) if ok.any() else math.nan
        out["rmse_db"] = float(np.sqrt(np.mean(rmses[ok] ** 2))) if ok.any() else math.nan
        out["worst_sd_db"] = float(np.max(sds[ok])) if ok.any() else math.nan
        out["worst_abs_bias_db"] = float(np.max(np.abs(biases[ok]))) if ok.any() else math.nan
        out["sets_without_al"] = int(np.sum(~ok))
    return out


def efficiency_fields(sd_db: float, trials_mean: float, observer: Observer) -> dict[str, float]:
    """``cr_trials`` (the bound's trials for ``sd_db``) and ``efficiency`` = that / trials.

    Examples
    --------
    >>> f = efficiency_fields(1.08, 52.0, Observer(1.5, 0.02))
    >>> round(f["cr_trials"], 1), round(f["efficiency"], 2)
    (16.1, 0.31)
    """
    if not (math.isfinite(sd_db) and sd_db > 0 and math.isfinite(trials_mean)):
        return {"cr_trials": math.nan, "efficiency": math.nan}
    model = {"scale_db": observer.scale_db, "lapse": observer.lapse, "guess": observer.guess}
    cr = float(cramer_rao_trials(sd_db, **model))
    return {"cr_trials": cr, "efficiency": cr / trials_mean if trials_mean > 0 else math.nan}


# --------------------------------------------------------------------------------------------
# The plan


@dataclass(frozen=True)
class Answer:
    """Reversals needed for ±``precision_db`` with one schedule and the reversal mean.

    ``rule`` is None when no rule up to ``max_reversals`` reaches it; ``best`` is then the
    ladder's last rung (the closest it got).

    Attributes
    ----------
    schedule : Schedule
    rule : StopRule or None
        Smallest rule with z·SD ≤ precision in every set (worst set).
    row : dict or None
        The ladder row of ``rule``.
    best : dict
        The ladder row with the smallest worst-set half-width.
    capped_by_protocol : float
        Fraction of sessions the protocol's trial cap would stop before ``rule`` completes.
    """

    schedule: Schedule
    rule: StopRule | None
    row: dict | None
    best: dict
    capped_by_protocol: float


@dataclass(frozen=True)
class PlanResult:
    """Everything ``plan`` reports.

    Attributes
    ----------
    settings : PlanSettings
    protocol_rule, protocol_schedule : StopRule, Schedule
        The protocol's own setting (highlighted in tables and figures).
    trial_s : float
        Seconds per trial used for minutes.
    max_trials : int or None
        The protocol's trial cap (applied to the table, reported for the ladder).
    table : list of dict
        One row per (schedule, stop rule, estimator), pooled over sets (see :func:`pool`).
    per_set : list of dict
        The same per set (see :func:`summarize`), with ``set`` naming it.
    ladder : list of dict
        Reversal-mean rows for stop rules 3…``max_reversals`` run (3 fewer averaged, like
        11/8), without a trial cap, with ``capped_by_protocol``.
    answers : list of Answer
        One per schedule.
    """

    settings: PlanSettings
    protocol_rule: StopRule
    protocol_schedule: Schedule
    trial_s: float
    max_trials: int | None
    table: list[dict]
    per_set: list[dict]
    ladder: list[dict]
    answers: list[Answer]


def run_plan(
    protocol: ThresholdProtocol,
    settings: PlanSettings,
    thresholds_db: NDArray[np.float64],
    *,
    progress: Progress | None = None,
    scheduler: str | None = "synchronous",
) -> PlanResult:
    """Simulate every schedule and summarise every (schedule, stop rule, estimator).

    Parameters
    ----------
    protocol : ThresholdProtocol
        Sets, staircase bounds, cap, start levels and timing.
    settings : PlanSettings
        The grid and the judgement.
    thresholds_db : array, shape (n_sets, settings.replicates)
        True thresholds (:func:`true_thresholds_db`), in the protocol's level unit.
    progress : callable, optional
        Receives one line per step (the command prints them to stderr).
    scheduler : str or None
        Where the chunks run (:func:`masking_lab.planning.parallel.run_chunks`): the same
        result on any.
    """
    say = progress or (lambda _msg: None)
    tasks = plan_tasks(protocol, settings, thresholds_db)
    say(f"staircase plan: {len(tasks)} chunks of simulated sessions")
    results = run_tasks(tasks, scheduler=scheduler)
    return assemble_plan(protocol, settings, thresholds_db, results, progress=say)


def assemble_plan(
    protocol: ThresholdProtocol,
    settings: PlanSettings,
    thresholds_db: NDArray[np.float64],
    results: Sequence[Any],
    *,
    progress: Progress | None = None,
) -> PlanResult:
    """The plan from the results of :func:`plan_tasks` (same arguments), in their order."""
    say = progress or (lambda _msg: None)
    long_chunks, ml_chunks = chunk_layout(settings)
    n_sched = len(settings.schedules)
    if len(results) != (len(long_chunks) + len(ml_chunks)) * n_sched:
        raise AnalysisError(
            f"expected {len(long_chunks) + len(ml_chunks)} chunk results per schedule"
        )
    n_ml = len(ml_chunks) * n_sched
    n_sets = len(protocol.sets)
    parts = []
    for k in range(1, n_sched + 1):
        mls = results[(k - 1) * len(ml_chunks) : k * len(ml_chunks)]
        longs = results[n_ml + (k - 1) * len(long_chunks) : n_ml + k * len(long_chunks)]
        rules = [_joined([c[0][i] for c in longs], n_sets) for i in range(len(settings.stop_rules))]
        rungs = [_joined([c[1][i] for c in longs], n_sets) for i in range(len(longs[0][1]))]
        ml_al = [
            np.concatenate([c[i].reshape(n_sets, -1) for c in mls], axis=1).reshape(-1)
            for i in range(len(settings.stop_rules))
        ] if mls else None  # fmt: skip
        sched = settings.schedules[k - 1].label
        say(
            f"schedule {k}/{len(settings.schedules)} ({sched}): stop rules and reversal ladder "
            f"3…{settings.max_reversals}"
        )
        parts.append(_schedule_part(protocol, settings, thresholds_db, k, rules, rungs, ml_al))
    base = protocol_staircase(protocol)
    return PlanResult(
        settings,
        protocol_stop_rule(protocol),
        protocol_schedule(protocol),
        trial_duration_s(protocol.timing, settings.response_s),
        base.max_trials,
        [r for p in parts for r in p.table],
        [r for p in parts for r in p.per_set],
        [r for p in parts for r in p.ladder],
        [p.answer for p in parts],
    )


def _joined(chunks: Sequence[StopOutcome], n_sets: int) -> StopOutcome:
    """Chunk outcomes (rows set-major within each) → one, rows set-major over all replicates."""

    def cat(name: str) -> NDArray:
        return np.concatenate(
            [getattr(c, name).reshape(n_sets, -1) for c in chunks], axis=1
        ).reshape(-1)

    return StopOutcome(cat("n_trials"), cat("status_code"), cat("al_db"))


@dataclass(frozen=True)
class SchedulePart:
    """One schedule's share of a :class:`PlanResult` (its rows, in order, and its answer)."""

    table: list[dict]
    per_set: list[dict]
    ladder: list[dict]
    answer: Answer


def _schedule_part(
    protocol: ThresholdProtocol,
    settings: PlanSettings,
    thresholds_db: NDArray[np.float64],
    k: int,
    rule_outs: Sequence[StopOutcome],
    rung_outs: Sequence[StopOutcome],
    ml_als: Sequence[NDArray[np.float64]] | None,
) -> SchedulePart:
    """Schedule ``k``'s rows from its sessions' outcomes (rows set-major over all replicates)."""
    n_sets = len(protocol.sets)
    reps = settings.replicates
    trial_s = trial_duration_s(protocol.timing, settings.response_s)
    cap = protocol_staircase(protocol).max_trials
    thr = thresholds_db.reshape(-1)
    ml_reps = min(settings.ml_replicates, reps)
    # Rows are set-major: set j's sessions are the slice j·reps … (j+1)·reps, and its ML
    # fits the first ml_reps of them (slices, not masks: the same numbers, in order, cheaper).
    whole = [slice(j * reps, (j + 1) * reps) for j in range(n_sets)]
    ml_part = [slice(j * reps, j * reps + ml_reps) for j in range(n_sets)]
    ml_own = [slice(j * ml_reps, (j + 1) * ml_reps) for j in range(n_sets)]
    own_rule, own_sched = protocol_stop_rule(protocol), protocol_schedule(protocol)
    own_is_staircase = runs_staircase(protocol)
    rungs = ladder_rules(own_rule, settings.max_reversals)
    obs = settings.observer
    sched = settings.schedules[k - 1]

    table: list[dict] = []
    per_set: list[dict] = []
    for i, rule in enumerate(settings.stop_rules):
        out = rule_outs[i]
        # (estimate per session, the sessions' slice of set j, that set's slice of the estimates)
        estimates: dict[str, tuple[NDArray[np.float64], list[slice], list[slice]]] = {
            "reversal_mean": (out.al_db, whole, whole),
        }
        if ml_als is not None:
            estimates["ml"] = (ml_als[i], ml_part, ml_own)
        # Session cost comes from the full sample whatever the estimator.
        costs = summarize_sets(
            out.n_trials.reshape(n_sets, reps), out.status_code.reshape(n_sets, reps), None,
            thr.reshape(n_sets, reps), trial_s,
        )  # fmt: skip
        for est, (al, rows, own) in estimates.items():
            sets_rows = []
            for j, spec in enumerate(protocol.sets):
                row = dict(costs[j])
                row.update(error_summary(al[own[j]], thr[rows[j]]))
                sets_rows.append(row)
                per_set.append(_label(row, sched, rule, est, spec.id))
            pooled = pool(sets_rows, out.n_trials, trial_s)
            pooled["meets_precision"] = bool(
                settings.z * pooled["worst_sd_db"] <= settings.precision_db
            )
            # "this protocol" only when the protocol runs this staircase (a QUEST+
            # protocol gets the paper's staircase beside it, not as its own).
            pooled["own"] = own_is_staircase and sched == own_sched and rule == own_rule
            pooled |= efficiency_fields(pooled["sd_db"], pooled["trials_mean"], obs)
            table.append(_label(pooled, sched, rule, est, None))

    ladder = []
    for rung, out in zip(rungs, rung_outs, strict=True):
        sets_rows = summarize_sets(
            out.n_trials.reshape(n_sets, reps), out.status_code.reshape(n_sets, reps),
            out.al_db.reshape(n_sets, reps), thr.reshape(n_sets, reps), trial_s,
        )  # fmt: skip
        row = _label(pool(sets_rows, out.n_trials, trial_s), sched, rung, "reversal_mean")
        row["half_width_db"] = settings.z * row["worst_sd_db"]
        row |= efficiency_fields(row["sd_db"], row["trials_mean"], obs)
        row["capped_by_protocol"] = (
            0.0 if cap is None else float(np.mean(out.completed & (out.n_trials > cap)))
        )
        ladder.append(row)
    answer = _answer(sched, rungs, ladder, settings.precision_db)
    return SchedulePart(table, per_set, ladder, answer)


def _label(
    row: dict, sched: Schedule, rule: StopRule, estimator: str, set_id: str | None = None
) -> dict:
    head: dict[str, Any] = {} if set_id is None else {"set": set_id}
    head.update(
        {
            "schedule": ",".join(f"{s:g}" for s in sched.step_sizes_db),
            "down_up_ratio": sched.down_up_ratio,
            "rule": rule.label,
            "n_reversals": rule.n_reversals,
            "n_averaged": rule.n_averaged,
            "estimator": estimator,
        }
    )
    return {**head, **row}


def _answer(
    sched: Schedule, rungs: Sequence[StopRule], rows: Sequence[dict], precision_db: float
) -> Answer:
    finite = [r for r in rows if math.isfinite(r["half_width_db"])]
    best = min(finite, key=lambda r: r["half_width_db"]) if finite else rows[-1]
    for rung, row in zip(rungs, rows, strict=True):
        if math.isfinite(row["half_width_db"]) and row["half_width_db"] <= precision_db:
            return Answer(sched, rung, row, best, row["capped_by_protocol"])
    return Answer(sched, None, None, best, best["capped_by_protocol"])
