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
(:func:`masking_lab.procedures.staircase_batch.outcome_under`),
and each schedule reuses the same seed, so settings are compared on common random numbers.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from masking_lab.core.errors import AnalysisError
from masking_lab.formats.protocol import ThresholdProtocol
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
from masking_lab.procedures.ml_batch import index_levels, ml_threshold_from_counts
from masking_lab.procedures.staircase_batch import (
    CEILING,
    COMPLETED,
    FLOOR,
    RUNNING,
    TRIAL_CAP,
    Observer,
    StopOutcome,
    outcome_under,
    simulate,
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
    "default_schedules",
    "default_stop_rules",
    "efficiency_fields",
    "ladder_rules",
    "parse_ratios",
    "parse_schedules",
    "parse_stop_rules",
    "plan_schedule",
    "pool",
    "protocol_schedule",
    "protocol_staircase",
    "protocol_stop_rule",
    "run_plan",
    "summarize",
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
    n = int(n_trials.size)
    med, p90 = (float(v) for v in np.percentile(n_trials, [50, 90]))
    out: dict[str, float] = {
        "sessions": n,
        "completed": float(np.mean(status_code == COMPLETED)),
        "ceiling": float(np.mean(status_code == CEILING)),
        "floor": float(np.mean(status_code == FLOOR)),
        "trial_cap": float(np.mean(status_code == TRIAL_CAP)),
        "unfinished": float(np.mean(status_code == RUNNING)),
        "trials_median": med,
        "trials_p90": p90,
        "trials_mean": float(np.mean(n_trials)),
        "minutes_median": med * trial_s / 60.0,
        "minutes_p90": p90 * trial_s / 60.0,
    }
    if estimate_db is not None:
        err = (estimate_db - true_db)[np.isfinite(estimate_db)]
        out["n_al"] = int(err.size)
        out["bias_db"] = float(err.mean()) if err.size else math.nan
        out["sd_db"] = float(err.std(ddof=1)) if err.size > 1 else math.nan
        out["rmse_db"] = float(np.sqrt(np.mean(err**2))) if err.size else math.nan
    return out


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
    done: Mapping[int, Callable[[], SchedulePart]] | None = None,
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
    done : mapping of int to callable, optional
        Schedules (by number, from 1) computed elsewhere (``plan`` runs one in a second
        process): each callable returns that schedule's :func:`plan_schedule`, waiting for it,
        and is called when the schedules before it are done; the others are computed here.
    """
    say = progress or (lambda _msg: None)
    elsewhere = done or {}
    parts: dict[int, SchedulePart] = {}
    n_sched = len(settings.schedules)
    for k in range(1, n_sched + 1):
        if k in elsewhere:
            parts[k] = elsewhere[k]()
            say(f"schedule {k}/{n_sched}: simulated in a second process")
        else:
            parts[k] = plan_schedule(protocol, settings, thresholds_db, k, progress=say)
    base = protocol_staircase(protocol)
    trial_s = trial_duration_s(protocol.timing, settings.response_s)
    ordered = [parts[k] for k in range(1, n_sched + 1)]
    return PlanResult(
        settings,
        protocol_stop_rule(protocol),
        protocol_schedule(protocol),
        trial_s,
        base.max_trials,
        [r for p in ordered for r in p.table],
        [r for p in ordered for r in p.per_set],
        [r for p in ordered for r in p.ladder],
        [p.answer for p in ordered],
    )


@dataclass(frozen=True)
class SchedulePart:
    """One schedule's share of a :class:`PlanResult` (its rows, in order, and its answer)."""

    table: list[dict]
    per_set: list[dict]
    ladder: list[dict]
    answer: Answer


def plan_schedule(
    protocol: ThresholdProtocol,
    settings: PlanSettings,
    thresholds_db: NDArray[np.float64],
    k: int,
    *,
    progress: Progress | None = None,
) -> SchedulePart:
    """Schedule number ``k`` (from 1) of :func:`run_plan`: its simulation, fits and rows.

    Every schedule draws from the same seed (common random numbers), so a schedule's part
    depends on nothing but these arguments and may be computed in another process.

    Examples
    --------
    >>> from masking_lab.formats.resources import shipped
    >>> from masking_lab.formats.protocol import load_protocol
    >>> p = load_protocol(shipped("protocols", "baseline.yaml"))
    >>> s = PlanSettings((StopRule(11, 8),), (Schedule((4.0, 2.0)),), replicates=20,
    ...                  ml_replicates=0, max_reversals=12)
    >>> part = plan_schedule(p, s, np.full((4, 20), -30.0), 1)
    >>> len(part.table), part.table[0]["estimator"]
    (1, 'reversal_mean')
    """
    say = progress or (lambda _msg: None)
    base = protocol_staircase(protocol)
    n_sets = len(protocol.sets)
    reps = settings.replicates
    if thresholds_db.shape != (n_sets, reps):
        raise AnalysisError(
            f"thresholds must have shape (sets, replicates) = ({n_sets}, {reps}), "
            f"got {thresholds_db.shape}"
        )
    trial_s = trial_duration_s(protocol.timing, settings.response_s)
    cap = base.max_trials
    starts = np.repeat([(s.staircase or base).start_level_db for s in protocol.sets], reps)
    thr = thresholds_db.reshape(-1)
    set_of_row = np.repeat(np.arange(n_sets), reps)
    ml_reps = min(settings.ml_replicates, reps)
    ml_rows = (np.arange(n_sets)[:, None] * reps + np.arange(ml_reps)[None, :]).reshape(-1)
    own_rule, own_sched = protocol_stop_rule(protocol), protocol_schedule(protocol)
    own_is_staircase = runs_staircase(protocol)
    rungs = ladder_rules(own_rule, settings.max_reversals)
    longest_table = max(r.n_reversals for r in settings.stop_rules)
    obs = settings.observer

    table: list[dict] = []
    per_set: list[dict] = []
    ladder: list[dict] = []
    answers: list[Answer] = []
    sched = settings.schedules[k - 1]
    head = f"schedule {k}/{len(settings.schedules)} ({sched.label})"
    sc = replace(
        base,
        step_sizes_db=sched.step_sizes_db,
        down_up_ratio=sched.down_up_ratio,
        n_reversals=settings.max_reversals,
        n_reversals_averaged=1,
        max_trials=None,
    )
    say(f"{head}: simulating {thr.size} sessions to {settings.max_reversals} reversals")
    long_run = simulate(
        sc,
        thr,
        obs,
        np.random.default_rng(settings.seed),
        start_level_db=starts,
        trial_limit=TRIAL_LIMIT,
        store_levels=False,
    )
    ml_index = None
    ml_run = None
    if ml_reps:
        say(f"{head}: simulating {ml_rows.size} sessions for the ML fits")
        ml_run = simulate(
            replace(sc, n_reversals=longest_table),
            thr[ml_rows],
            obs,
            np.random.default_rng(settings.seed + 1),
            start_level_db=starts[ml_rows],
            trial_limit=TRIAL_LIMIT,
        )
        ml_index = index_levels(ml_run.levels_db, ml_run.correct)

    for rule in settings.stop_rules:
        out = outcome_under(long_run, rule.n_reversals, rule.n_averaged, cap, exact=False)
        estimates: dict[str, tuple[StopOutcome, NDArray[np.float64], NDArray]] = {
            "reversal_mean": (out, out.al_db, np.arange(thr.size)),
        }
        if ml_run is not None and ml_index is not None:
            say(f"{head}: ML fits for stop rule {rule.label}")
            ml_out = outcome_under(ml_run, rule.n_reversals, rule.n_averaged, cap, exact=False)
            done = np.flatnonzero(ml_out.completed)
            ml_al = np.full(ml_rows.size, np.nan)
            if done.size:
                fit = ml_threshold_from_counts(
                    ml_index.counts(ml_out.n_trials, rows=done),
                    scale_db=obs.scale_db,
                    lapse=settings.ml_lapse,
                    guess=obs.guess,
                    fit_scale=settings.ml_fit_scale,
                )
                ml_al[done] = fit.threshold_db
            estimates["ml"] = (ml_out, ml_al, ml_rows)
        for est, (o, al, rows) in estimates.items():
            sets_rows = []
            for j, spec in enumerate(protocol.sets):
                mine = set_of_row[rows] == j
                # Session cost comes from the full sample whatever the estimator.
                cost = set_of_row == j
                row = summarize(out.n_trials[cost], out.status_code[cost], None, thr, trial_s)
                err = summarize(
                    o.n_trials[mine], o.status_code[mine], al[mine], thr[rows][mine], trial_s
                )
                row.update({key: err[key] for key in ("n_al", "bias_db", "sd_db", "rmse_db")})
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

    say(f"{head}: reversal ladder 3…{settings.max_reversals}")
    sched_ladder = []
    for rung in rungs:
        out = outcome_under(long_run, rung.n_reversals, rung.n_averaged, exact=False)
        sets_rows = [
            summarize(
                out.n_trials[set_of_row == j],
                out.status_code[set_of_row == j],
                out.al_db[set_of_row == j],
                thr[set_of_row == j],
                trial_s,
            )
            for j in range(n_sets)
        ]
        row = _label(pool(sets_rows, out.n_trials, trial_s), sched, rung, "reversal_mean")
        row["half_width_db"] = settings.z * row["worst_sd_db"]
        row |= efficiency_fields(row["sd_db"], row["trials_mean"], obs)
        row["capped_by_protocol"] = (
            0.0 if cap is None else float(np.mean(out.completed & (out.n_trials > cap)))
        )
        sched_ladder.append(row)
    ladder.extend(sched_ladder)
    answers.append(_answer(sched, rungs, sched_ladder, settings.precision_db))

    return SchedulePart(table, per_set, ladder, answers[0])


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
