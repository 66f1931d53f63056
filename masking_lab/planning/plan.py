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
read or written here (:mod:`masking_lab.commands.plan` does that).

Efficiency: all sets run together as rows of one simulation, every stop rule and the trial cap
are derived exactly from one long run per schedule
(:func:`masking_lab.procedures.staircase_batch.outcome_under`),
and each schedule reuses the same seed, so settings are compared on common random numbers.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from masking_lab.core.errors import AnalysisError, ProtocolError, StaircaseError
from masking_lab.formats.protocol import Protocol, Timing
from masking_lab.procedures.ml_batch import index_levels, ml_threshold_from_counts
from masking_lab.procedures.staircase import StaircaseSettings
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
from masking_lab.simulation.observer import GroundTruth

#: García-Pérez (1998): this down/up step ratio makes 1-up 3-down converge on 83.15 % correct.
GARCIA_PEREZ_RATIO = 0.7393
ESTIMATORS = ("reversal_mean", "ml")
ESTIMATOR_LABELS = {"reversal_mean": "reversal mean", "ml": "ML fit"}
#: Trials simulated at most per track (only reached by a track that never reverses).
TRIAL_LIMIT = 1000

Progress = Callable[[str], None]


@dataclass(frozen=True, order=True)
class StopRule:
    """Stop after ``n_reversals`` reversals; average the last ``n_averaged`` into the AL."""

    n_reversals: int
    n_averaged: int

    def __post_init__(self) -> None:
        if not (isinstance(self.n_reversals, int) and self.n_reversals >= 1):
            raise StaircaseError(f"stop rule: reversals run must be ≥ 1, got {self.n_reversals}")
        if not (isinstance(self.n_averaged, int) and 1 <= self.n_averaged <= self.n_reversals):
            raise StaircaseError(
                f"stop rule {self.n_reversals}/{self.n_averaged}: reversals averaged must be "
                f"between 1 and the reversals run ({self.n_reversals})"
            )

    @property
    def label(self) -> str:
        """``"11/8"``: reversals run / reversals averaged."""
        return f"{self.n_reversals}/{self.n_averaged}"


@dataclass(frozen=True)
class Schedule:
    """Up steps by reversal count (the last repeats) and the down/up step ratio."""

    step_sizes_db: tuple[float, ...]
    down_up_ratio: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "step_sizes_db", tuple(float(s) for s in self.step_sizes_db))
        if not self.step_sizes_db or not all(
            math.isfinite(s) and s > 0 for s in self.step_sizes_db
        ):
            raise StaircaseError(
                f"step schedule {self.step_sizes_db}: needs one or more positive step sizes in dB"
            )
        if not (math.isfinite(self.down_up_ratio) and self.down_up_ratio > 0):
            raise StaircaseError(f"down/up step ratio must be > 0, got {self.down_up_ratio}")

    @property
    def label(self) -> str:
        """``"4,4,4,2"``, with ``" d/u 0.7393"`` appended when the down step differs."""
        steps = ",".join(f"{s:g}" for s in self.step_sizes_db)
        return steps if self.down_up_ratio == 1.0 else f"{steps} d/u {self.down_up_ratio:g}"


@dataclass(frozen=True)
class PlanSettings:
    """What to simulate and how to judge it.

    Attributes
    ----------
    stop_rules : tuple of StopRule
        Rules in the table (each evaluated with both estimators).
    schedules : tuple of Schedule
        Step schedules × down/up ratios.
    observer : Observer
        Psychometric scale and lapse of the simulated observers.
    replicates : int
        Simulated sessions per set for the reversal mean (and the trial counts).
    ml_replicates : int
        Sessions per set fitted by maximum likelihood (0: no ML); the fits cost far more than
        the simulation.
    response_s : float
        Mean response time per trial, s (added to the protocol's trial and inter-trial time).
    precision_db : float
        Target half-width X of the AL's interval, dB ("±X dB").
    z : float
        The interval is ±z·SD (1.96: 95 % of sessions within ±X dB of the true threshold).
    max_reversals : int
        Longest stop rule on the reversal ladder that answers "reversals needed".
    ml_lapse : float
        Lapse rate the ML fit assumes (the analysis's default is 0.02).
    ml_fit_scale : bool
        Fit the psychometric scale per track (as the analysis does) or fix it at the observer's.
    seed : int
        Seed of every simulation (common random numbers across schedules).
    """

    stop_rules: tuple[StopRule, ...]
    schedules: tuple[Schedule, ...]
    observer: Observer = field(default_factory=Observer)
    replicates: int = 2000
    ml_replicates: int = 500
    response_s: float = 1.0
    precision_db: float = 1.0
    z: float = 1.96
    max_reversals: int = 41
    ml_lapse: float = 0.02
    ml_fit_scale: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        if not self.stop_rules:
            raise StaircaseError("give at least one stop rule, e.g. 11/8")
        if not self.schedules:
            raise StaircaseError("give at least one step schedule, e.g. 4,4,4,2")
        if self.replicates < 2:
            raise AnalysisError(f"replicates must be ≥ 2 (an SD needs two), got {self.replicates}")
        if self.ml_replicates != 0 and self.ml_replicates < 2:
            raise AnalysisError(f"ml_replicates must be 0 or ≥ 2, got {self.ml_replicates}")
        for name in ("response_s",):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise AnalysisError(f"{name} must be a finite number ≥ 0 s, got {value}")
        for name in ("precision_db", "z"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise AnalysisError(f"{name} must be a positive number, got {value}")
        longest = max(r.n_reversals for r in self.stop_rules)
        if self.max_reversals < longest:
            raise StaircaseError(
                f"max_reversals={self.max_reversals} is below the longest stop rule ({longest})"
            )


# --------------------------------------------------------------------------------------------
# Settings from text and from the protocol


def parse_stop_rules(text: str) -> tuple[StopRule, ...]:
    """``"7/4,9/6,11/8"`` → stop rules, sorted by reversals run.

    Raises
    ------
    StaircaseError
        Naming the malformed item and the expected form.
    """
    rules = []
    for item in (p.strip() for p in text.split(",")):
        if not item:
            continue
        run, sep, avg = item.partition("/")
        try:
            if not sep:
                raise ValueError
            rules.append(StopRule(int(run), int(avg)))
        except ValueError:
            raise StaircaseError(
                f"stop rule {item!r}: write RUN/AVERAGED, e.g. 11/8 (11 reversals run, last 8 "
                "averaged), several separated by commas"
            ) from None
    if not rules:
        raise StaircaseError("no stop rules given; write e.g. 7/4,9/6,11/8")
    return tuple(sorted(set(rules)))


def parse_schedules(text: str, ratios: Iterable[float] = (1.0,)) -> tuple[Schedule, ...]:
    """``"4,4,4,2;2"`` (schedules separated by ``;``) × down/up ratios → schedules.

    Raises
    ------
    StaircaseError
        Naming the malformed schedule.
    """
    steps_list = []
    for item in (p.strip() for p in text.split(";")):
        if not item:
            continue
        try:
            steps_list.append(tuple(float(v) for v in item.split(",")))
        except ValueError:
            raise StaircaseError(
                f"step schedule {item!r}: write up-step sizes in dB separated by commas, e.g. "
                "4,4,4,2; separate schedules with ';'"
            ) from None
    if not steps_list:
        raise StaircaseError("no step schedules given; write e.g. '4,4,4,2;2'")
    out: list[Schedule] = []
    for steps in steps_list:
        for ratio in ratios:
            sched = Schedule(steps, float(ratio))
            if sched not in out:
                out.append(sched)
    return tuple(out)


def parse_ratios(text: str) -> tuple[float, ...]:
    """``"1,0.7393"`` → down/up step ratios.

    Raises
    ------
    StaircaseError
        If an item is not a positive number.
    """
    try:
        ratios = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise StaircaseError(
            f"down/up ratios {text!r}: write numbers separated by commas, e.g. 1,0.7393"
        ) from None
    if not ratios or not all(math.isfinite(r) and r > 0 for r in ratios):
        raise StaircaseError(f"down/up ratios {text!r}: need positive numbers, e.g. 1,0.7393")
    return ratios


def protocol_staircase(protocol: Protocol) -> StaircaseSettings:
    """The staircase settings the protocol's sets share (they may differ only in start level).

    Raises
    ------
    StaircaseError
        If sets differ in anything else.
    """
    base = protocol.sets[0].staircase
    for s in protocol.sets[1:]:
        if replace(s.staircase, start_level_db=base.start_level_db) != base:
            raise StaircaseError(
                f"{protocol.path}: set {s.id!r} has staircase settings other than the first "
                "set's; plan supports sets that differ only in start level"
            )
    return base


def protocol_stop_rule(protocol: Protocol) -> StopRule:
    """The stop rule the protocol uses (11/8 in the paper)."""
    sc = protocol_staircase(protocol)
    return StopRule(sc.n_reversals, sc.n_reversals_averaged)


def protocol_schedule(protocol: Protocol) -> Schedule:
    """The step schedule and ratio the protocol uses."""
    sc = protocol_staircase(protocol)
    return Schedule(sc.step_sizes_db, sc.down_up_ratio)


def default_stop_rules(protocol: Protocol) -> tuple[StopRule, ...]:
    """7/4, 9/6, 11/8, 13/10, 15/12 and the protocol's own rule."""
    rules = {StopRule(n, n - 3) for n in (7, 9, 11, 13, 15)} | {protocol_stop_rule(protocol)}
    return tuple(sorted(rules))


def default_schedules(
    protocol: Protocol, ratios: Sequence[float] | None = None
) -> tuple[Schedule, ...]:
    """The protocol's schedule, its first step then its last, and its last step throughout."""
    own = protocol_schedule(protocol)
    steps = own.step_sizes_db
    variants = [steps, (steps[0], steps[-1]), (steps[-1],)]
    rs = tuple(ratios) if ratios else (own.down_up_ratio,)
    out: list[Schedule] = []
    for v in variants:
        for r in rs:
            sched = Schedule(v, r)
            if sched not in out:
                out.append(sched)
    return tuple(out)


def trial_duration_s(timing: Timing, response_s: float) -> float:
    """Seconds per trial: the three intervals with lead-in and gaps, the answer, the pause."""
    return timing.trial_s + response_s + timing.inter_trial_s


# --------------------------------------------------------------------------------------------
# The observers' true thresholds


def true_thresholds_db(
    protocol: Protocol,
    truth: GroundTruth,
    replicates: int,
    rng: np.random.Generator,
    *,
    spread: bool = True,
    override_db: float | None = None,
    truth_source: str = "ground truth",
) -> NDArray[np.float64]:
    """True threshold (p = 0.794 level) of each simulated observer, per set, in the protocol's
    level unit.

    Masked protocols are in dB SL re the target's unmasked AL, so the true threshold is the
    ground truth's AL shift at the set's masker level (0 where the pair does not interact);
    baseline protocols are in dB re 1 V and it is the target's unmasked AL. With ``spread``,
    observers differ as :func:`masking_lab.simulation.observer.make_participant` draws them: an
    offset of
    SD ``shift_sd_db`` on shifts above the knee, or ``participant_sd_db`` on unmasked ALs.

    Returns
    -------
    ndarray, shape (n_sets, replicates)
        dB SL (masked) or dB re 1 V (baseline).

    Raises
    ------
    ProtocolError
        If a baseline target has no unmasked AL in the ground truth.
    """
    if override_db is not None:
        if not math.isfinite(override_db):
            raise AnalysisError(f"true threshold must be a finite number of dB, got {override_db}")
        return np.full((len(protocol.sets), replicates), float(override_db))
    out = np.empty((len(protocol.sets), replicates))
    for i, s in enumerate(protocol.sets):
        if protocol.kind == "baseline":
            name = s.target.name
            if name not in truth.unmasked_al_db_v:
                raise ProtocolError(
                    truth_source,
                    f"unmasked_al_db_v.{name}",
                    f"set {s.id!r} measures {name} but the ground truth has no unmasked AL for "
                    "it; add one (dB re 1 V)",
                )
            sd = truth.participant_sd_db if spread else 0.0
            out[i] = truth.unmasked_al_db_v[name] + sd * rng.standard_normal(replicates)
            continue
        assert s.masker is not None and s.masker_level_db_sl is not None
        fn = truth.masking_function(s.target.name, s.masker.name)
        shift = 0.0 if fn is None else float(fn.shift_db(s.masker_level_db_sl))
        offsets = (truth.shift_sd_db if spread else 0.0) * rng.standard_normal(replicates)
        # As SimulatedParticipant: the offset applies above the knee and never makes masking
        # negative.
        out[i] = np.maximum(0.0, shift + offsets) if shift > 0 else 0.0
    return out


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


def ladder_rules(protocol_rule: StopRule, max_reversals: int) -> tuple[StopRule, ...]:
    """Stop rules discarding as many early reversals as the protocol (3 for 11/8)."""
    discard = protocol_rule.n_reversals - protocol_rule.n_averaged
    return tuple(StopRule(n, n - discard) for n in range(max(discard + 1, 3), max_reversals + 1))


def run_plan(
    protocol: Protocol,
    settings: PlanSettings,
    thresholds_db: NDArray[np.float64],
    *,
    progress: Progress | None = None,
) -> PlanResult:
    """Simulate every schedule and summarise every (schedule, stop rule, estimator).

    Parameters
    ----------
    protocol : Protocol
        Sets, staircase bounds, cap, start levels and timing.
    settings : PlanSettings
        The grid and the judgement.
    thresholds_db : array, shape (n_sets, settings.replicates)
        True thresholds (:func:`true_thresholds_db`), in the protocol's level unit.
    progress : callable, optional
        Receives one line per step (the command prints them to stderr).
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
    starts = np.repeat([s.staircase.start_level_db for s in protocol.sets], reps)
    thr = thresholds_db.reshape(-1)
    set_of_row = np.repeat(np.arange(n_sets), reps)
    ml_reps = min(settings.ml_replicates, reps)
    ml_rows = (np.arange(n_sets)[:, None] * reps + np.arange(ml_reps)[None, :]).reshape(-1)
    own_rule, own_sched = protocol_stop_rule(protocol), protocol_schedule(protocol)
    rungs = ladder_rules(own_rule, settings.max_reversals)
    longest_table = max(r.n_reversals for r in settings.stop_rules)
    obs = settings.observer

    table: list[dict] = []
    per_set: list[dict] = []
    ladder: list[dict] = []
    answers: list[Answer] = []
    for k, sched in enumerate(settings.schedules, 1):
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
                pooled["own"] = sched == own_sched and rule == own_rule
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
            row["capped_by_protocol"] = (
                0.0 if cap is None else float(np.mean(out.completed & (out.n_trials > cap)))
            )
            sched_ladder.append(row)
        ladder.extend(sched_ladder)
        answers.append(_answer(sched, rungs, sched_ladder, settings.precision_db))

    return PlanResult(settings, own_rule, own_sched, trial_s, cap, table, per_set, ladder, answers)


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


def answer_text(answer: Answer, settings: PlanSettings, cap: int | None) -> str:
    """One sentence answering "how many reversals do I need for ±X dB" for one schedule."""
    x = settings.precision_db
    crit = f"{settings.z:g}·SD ≤ {x:g} dB in every set, reversal mean"
    if answer.rule is None or answer.row is None:
        b = answer.best
        return (
            f"{answer.schedule.label}: no stop rule up to {settings.max_reversals} reversals "
            f"reaches ±{x:g} dB ({crit}); the closest, {b['rule']}, gives "
            f"±{b['half_width_db']:.2f} dB in {b['trials_median']:.0f} trials "
            f"(~{b['minutes_median']:.1f} min) per set"
        )
    r = answer.row
    text = (
        f"{answer.schedule.label}: {answer.rule.label} (run {answer.rule.n_reversals} reversals, "
        f"average the last {answer.rule.n_averaged}) gives ±{r['half_width_db']:.2f} dB "
        f"({crit}) in {r['trials_median']:.0f} trials, 90 % within {r['trials_p90']:.0f} "
        f"(~{r['minutes_median']:.1f}–{r['minutes_p90']:.1f} min) per set"
    )
    if cap is not None and answer.capped_by_protocol > 0:
        text += (
            f"; the protocol's max_trials={cap} would stop "
            f"{100 * answer.capped_by_protocol:.1f} % of them first"
        )
    return text


def rows_to_csv(rows: Sequence[dict]) -> str:
    """Rows as CSV text (columns in first-seen order; floats to 6 significant digits)."""
    columns: list[str] = []
    for r in rows:
        for k in r:
            if k not in columns:
                columns.append(k)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow(
            [(f"{r[c]:.6g}" if isinstance(r.get(c), float) else r.get(c, "")) for c in columns]
        )
    return buf.getvalue()
