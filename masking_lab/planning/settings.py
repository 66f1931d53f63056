"""What ``masking-lab plan`` simulates: the settings grid and the observers' true thresholds.

:class:`StopRule` (reversals run / averaged), :class:`Schedule` (up steps in dB by reversal
count, down/up step ratio) and :class:`PlanSettings` (the grid, the simulated observers and how
precision is judged); parsers for the command-line forms (``"11/8"``, ``"4,4,4,2;2"``,
``"1,0.7393"``); the defaults taken from a protocol (its staircase, stop rule, schedule and
seconds per trial); and :func:`true_thresholds_db`, each simulated observer's true threshold
per set, drawn from a ground truth with the generator given. Pure.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from masking_lab.core.errors import AnalysisError, ProtocolError, StaircaseError
from masking_lab.formats.protocol import ThresholdProtocol, Timing
from masking_lab.procedures.downup_ratio import GARCIA_PEREZ_2AFC_RATIO
from masking_lab.procedures.staircase import StaircaseSettings
from masking_lab.procedures.staircase_batch import Observer
from masking_lab.simulation.observer import GroundTruth

__all__ = [
    "ESTIMATORS",
    "ESTIMATOR_LABELS",
    "GARCIA_PEREZ_RATIO",
    "TRIAL_LIMIT",
    "PlanSettings",
    "Schedule",
    "StopRule",
    "default_schedules",
    "default_stop_rules",
    "ladder_rules",
    "paper_staircase",
    "parse_ratios",
    "parse_schedules",
    "parse_stop_rules",
    "protocol_procedure_text",
    "protocol_schedule",
    "protocol_staircase",
    "protocol_stop_rule",
    "runs_staircase",
    "trial_duration_s",
    "true_thresholds_db",
]

#: García-Pérez (1998): this down/up step ratio makes 1-up 3-down converge on 83.15 % correct
#: in **2AFC** (guess rate 1/2) whatever the step size; in 3IFC it does not
#: (docs/speed-accuracy.md).
GARCIA_PEREZ_RATIO = GARCIA_PEREZ_2AFC_RATIO
ESTIMATORS = ("reversal_mean", "ml")
ESTIMATOR_LABELS = {"reversal_mean": "reversal mean", "ml": "ML fit"}
#: Trials simulated at most per track (only reached by a track that never reverses).
TRIAL_LIMIT = 1000


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


def protocol_staircase(protocol: ThresholdProtocol) -> StaircaseSettings:
    """The staircase settings the protocol's sets share (they may differ only in start level).

    Raises
    ------
    StaircaseError
        If sets differ in anything else.
    """
    staircases = [s.staircase for s in protocol.sets if s.staircase is not None]
    if not staircases:
        return paper_staircase(protocol)
    base = staircases[0]
    for s in protocol.sets[1:]:
        if s.staircase is None:
            continue
        if replace(s.staircase, start_level_db=base.start_level_db) != base:
            raise StaircaseError(
                f"{protocol.path}: set {s.id!r} has staircase settings other than the first "
                "set's; plan supports sets that differ only in start level"
            )
    return base


def paper_staircase(protocol: ThresholdProtocol) -> StaircaseSettings:
    """The paper's staircase (steps 4,4,4,2 dB, 11/8, start 20 dB, cap 150) within the range of
    a protocol whose sets run another procedure, so ``plan`` can set it beside them.

    Examples
    --------
    >>> from masking_lab.formats.resources import shipped
    >>> from masking_lab.formats.protocol import load_protocol
    >>> p = load_protocol(shipped("protocols", "experiment1_questplus.yaml"))
    >>> sc = paper_staircase(p)
    >>> sc.step_sizes_db, sc.n_reversals, sc.min_level_db, sc.max_level_db
    ((4.0, 4.0, 4.0, 2.0), 11, -20, 45)
    """
    lo, hi = -20.0, 45.0
    quests = [s.procedure for s in protocol.sets if s.procedure is not None]
    if quests:
        lo, hi = quests[0].min_level_db, quests[0].max_level_db
    start = min(max(20.0, lo), hi)
    return StaircaseSettings(
        start, step_sizes_db=(4.0, 4.0, 4.0, 2.0), min_level_db=lo, max_level_db=hi, max_trials=150
    )


def runs_staircase(protocol: ThresholdProtocol) -> bool:
    """Whether the protocol's sets run the staircase (else another procedure, e.g. QUEST+).

    Examples
    --------
    >>> from masking_lab.formats.resources import shipped
    >>> from masking_lab.formats.protocol import load_protocol
    >>> runs_staircase(load_protocol(shipped("protocols", "experiment1_questplus.yaml")))
    False
    """
    return any(s.staircase is not None for s in protocol.sets)


def protocol_procedure_text(protocol: ThresholdProtocol) -> str:
    """The protocol's own procedure and settings in words: what ``plan`` calls "this protocol".

    Examples
    --------
    >>> from masking_lab.formats.resources import shipped
    >>> from masking_lab.formats.protocol import load_protocol
    >>> text = protocol_procedure_text(load_protocol(shipped("protocols", "experiment1.yaml")))
    >>> text.split(", ")[0], text.split(", ")[-2:]
    ('staircase 1-up 3-down', ['steps 4,4,4,2 dB', 'trial cap 150'])
    >>> text = protocol_procedure_text(
    ...     load_protocol(shipped("protocols", "experiment1_questplus.yaml")))
    >>> for part in text.split(", "):
    ...     print(part)
    psi-marginal (slope unknown)
    stops at posterior SD ≤ 1.6 dB (at least 10 trials)
    trial cap 120
    """
    quests = [s.procedure for s in protocol.sets if s.procedure is not None]
    if not runs_staircase(protocol) and quests:
        q = quests[0]
        kind = "QUEST+ (slope known)" if len(q.scales_db) == 1 else "psi-marginal (slope unknown)"
        stop = (
            f"stops at posterior SD ≤ {q.target_sd_db:g} dB (at least {q.min_trials} trials)"
            if q.target_sd_db
            else f"runs {q.max_trials} trials"
        )
        cap = f"trial cap {q.max_trials}" if q.max_trials is not None else "no trial cap"
        return f"{kind}, {stop}, {cap}"
    sc = protocol_staircase(protocol)
    steps = ",".join(f"{v:g}" for v in sc.step_sizes_db)
    ratio = "" if sc.down_up_ratio == 1.0 else f", down/up step ratio {sc.down_up_ratio:g}"
    cap = f"trial cap {sc.max_trials}" if sc.max_trials is not None else "no trial cap"
    return (
        f"staircase {sc.n_up}-up {sc.n_down}-down, {sc.n_reversals}/{sc.n_reversals_averaged} "
        f"(stop after {sc.n_reversals} reversals, AL = mean of the last "
        f"{sc.n_reversals_averaged}), steps {steps} dB{ratio}, {cap}"
    )


def protocol_stop_rule(protocol: ThresholdProtocol) -> StopRule:
    """The stop rule the protocol uses (11/8 in the paper)."""
    sc = protocol_staircase(protocol)
    return StopRule(sc.n_reversals, sc.n_reversals_averaged)


def protocol_schedule(protocol: ThresholdProtocol) -> Schedule:
    """The step schedule and ratio the protocol uses."""
    sc = protocol_staircase(protocol)
    return Schedule(sc.step_sizes_db, sc.down_up_ratio)


def default_stop_rules(protocol: ThresholdProtocol) -> tuple[StopRule, ...]:
    """7/4, 9/6, 11/8, 13/10, 15/12 and the protocol's own rule."""
    rules = {StopRule(n, n - 3) for n in (7, 9, 11, 13, 15)} | {protocol_stop_rule(protocol)}
    return tuple(sorted(rules))


def default_schedules(
    protocol: ThresholdProtocol, ratios: Sequence[float] | None = None
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


def ladder_rules(protocol_rule: StopRule, max_reversals: int) -> tuple[StopRule, ...]:
    """Stop rules discarding as many early reversals as the protocol (3 for 11/8)."""
    discard = protocol_rule.n_reversals - protocol_rule.n_averaged
    return tuple(StopRule(n, n - discard) for n in range(max(discard + 1, 3), max_reversals + 1))


# --------------------------------------------------------------------------------------------
# The observers' true thresholds


def true_thresholds_db(
    protocol: ThresholdProtocol,
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
