"""Procedures side by side: the staircase's settings against QUEST+, and both against the bound.

``masking-lab plan`` simulates the protocol's staircase settings (:mod:`masking_lab.planning.
plan`); this module adds QUEST+ (:mod:`masking_lab.procedures.quest_plus_batch`) on the same
simulated observers and true thresholds, and rates every setting of every procedure against the
Cramér-Rao bound of the protocol's observer (:mod:`masking_lab.procedures.fisher`): the
**efficiency** of a setting is the trials the bound needs for the SD it achieved divided by the
mean trials it used (the paper's 11/8 staircase: ~30 %).

QUEST+ runs once per variant to the strictest posterior-SD target of a ladder; a track's levels
do not depend on its stop rule until it stops, so every looser target is read off that run
exactly (:meth:`~masking_lab.procedures.quest_plus_batch.SimulatedQuestPlus.trials_to_sd`).
The tracks run in chunks, each with its own seed (:func:`quest_tasks`), anywhere
(:mod:`masking_lab.planning.parallel`), a lone chunk split by sets into parts that run the
chunk's tracks; a part hands back its tracks' posterior mean and SD per trial, not the track.
Each target is then summarised like a staircase rule: trials and minutes (median, p90, mean),
bias, SD and RMSE of the AL against the true threshold, and how often a track ends at a bound
or the trial cap. "Fewest trials for ±X dB" is answered across procedures from uncapped rows.

Pure: randomness from the seed given, progress to a callback, no I/O. Units: dB in the
protocol's level unit, minutes, trials.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from itertools import pairwise
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from masking_lab.formats.protocol import ThresholdProtocol
from masking_lab.planning.parallel import Task, chunk_plan, run_tasks
from masking_lab.planning.plan import PlanResult, efficiency_fields, pool, summarize
from masking_lab.planning.settings import PlanSettings, trial_duration_s
from masking_lab.procedures.fisher import max_information
from masking_lab.procedures.quest_plus import QuestPlusSettings, stop_status
from masking_lab.procedures.quest_plus_batch import (
    SimulatedQuestPlus,
    simulate_quest_plus,
    trials_to_sd,
)
from masking_lab.procedures.staircase_batch import (
    CEILING,
    COMPLETED,
    FLOOR,
    RUNNING,
    TRIAL_CAP,
    Observer,
)

__all__ = [
    "PSI_SCALES_DB",
    "QUEST_CHUNK_REPLICATES",
    "QUEST_PART_SETS",
    "QUEST_SPLIT_BELOW",
    "SD_LADDER_DB",
    "ProcedureComparison",
    "QuestChunk",
    "QuestPart",
    "chunk_outcome",
    "compare_procedures",
    "default_quest_replicates",
    "protocol_quest_plus",
    "quest_chunk",
    "quest_tasks",
]

#: Posterior-SD stop rules read off each QUEST+ run, dB.
SD_LADDER_DB = (3.0, 2.0, 1.5, 1.25, 1.08, 1.0, 0.9, 0.8, 0.7, 0.6, 0.5, 0.45, 0.4)
#: The psi-marginal's slope grid: logistic scales from 0.5 to 6 dB (docs/procedures.md).
PSI_SCALES_DB = tuple(float(v) for v in np.round(np.geomspace(0.5, 6.0, 10), 3))
#: Trials simulated at most per QUEST+ track (the ladder's strictest target needs ~100).
QUEST_TRIAL_LIMIT = 300

_CODES = {"completed": COMPLETED, "ceiling": CEILING, "floor": FLOOR, "trial_cap": TRIAL_CAP}

Progress = Callable[[str], None]


@dataclass(frozen=True)
class ProcedureComparison:
    """Every procedure's settings against each other and the bound.

    Attributes
    ----------
    rows : list of dict
        One per (procedure, setting), pooled over sets as :func:`masking_lab.planning.plan.pool`
        does, with ``procedure``, ``setting``, ``estimator``, ``trials_mean``, ``cr_trials``,
        ``efficiency``, ``own`` (the protocol's own setting) and ``capped`` (False for the
        uncapped rows that answer "fewest trials").
    per_set : list of dict
        The QUEST+ rows per set (``set`` names it).
    bound : dict
        ``information`` (I*, dB⁻²), ``p_correct`` where it peaks, ``scale_db``, ``lapse``,
        ``guess`` of the observer the bound is for.
    fewest : list of dict
        Per procedure family, the cheapest uncapped row whose worst-set z·SD ≤ ``precision_db``
        (or, with ``met`` False, the most precise it reached).
    precision_db, z : float
        The question asked.
    """

    rows: list[dict]
    per_set: list[dict]
    bound: dict[str, float]
    fewest: list[dict]
    precision_db: float
    z: float


#: QUEST+ tracks per set in ``plan``'s procedures comparison by default.
QUEST_REPLICATES = 400
#: The same for a protocol whose QUEST+ marginalises slope or lapse: its every placement weighs
#: each nuisance point (28 on the shipped grid), about 30 times a known-slope track's work.
MARGINAL_QUEST_REPLICATES = 40


def default_quest_replicates(protocol: ThresholdProtocol) -> int:
    """QUEST+ tracks per set for ``plan``'s comparison when ``--quest-replicates`` is not given.

    Examples
    --------
    >>> from masking_lab.formats.resources import shipped
    >>> from masking_lab.formats.protocol import load_protocol
    >>> [default_quest_replicates(load_protocol(shipped("protocols", f"{name}.yaml")))
    ...  for name in ("experiment1", "experiment1_questplus")]
    [400, 40]
    """
    own = protocol_quest_plus(protocol)
    if own is not None and (len(own.scales_db) > 1 or len(own.lapses) > 1):
        return MARGINAL_QUEST_REPLICATES
    return QUEST_REPLICATES


def protocol_quest_plus(protocol: ThresholdProtocol) -> QuestPlusSettings | None:
    """The QUEST+ settings the protocol's QUEST+ sets share (None if it has none).

    Examples
    --------
    >>> from masking_lab.formats.resources import shipped
    >>> from masking_lab.formats.protocol import load_protocol
    >>> p = load_protocol(shipped("protocols", "experiment1_questplus.yaml"))
    >>> protocol_quest_plus(p).target_sd_db
    1.6
    """
    quests = [s.procedure for s in protocol.sets if s.procedure is not None]
    return quests[0] if quests else None


def _variants(
    protocol: ThresholdProtocol, observer: Observer, psi: bool, max_trials: int | None = None
) -> list[tuple[str, QuestPlusSettings]]:
    own = protocol_quest_plus(protocol)
    if own is None:
        # A staircase protocol: QUEST+ within its level range, capped as its staircase is
        # (or at ``max_trials``), never at a number fixed here.
        sc = protocol.sets[0].staircase
        lo = -20.0 if sc is None or sc.min_level_db is None else float(sc.min_level_db)
        hi = 45.0 if sc is None or sc.max_level_db is None else float(sc.max_level_db)
        cap = max_trials if max_trials is not None else (None if sc is None else sc.max_trials)
        # Told the observer's slope and lapse, as the Cramér-Rao bound it is set beside is
        # (the defaults would marginalise both).
        own = QuestPlusSettings(
            lo, hi, scales_db=(observer.scale_db,), lapses=(observer.lapse,), target_sd_db=1.08,
            min_trials=10, max_trials=cap,
        )  # fmt: skip
    elif max_trials is not None:
        own = replace(own, max_trials=max_trials)
    name = "QUEST+" if len(own.scales_db) == 1 else "psi-marginal"
    out = [(name, own)]
    if psi and len(own.scales_db) == 1:
        out.append(("psi-marginal", replace(own, scales_db=PSI_SCALES_DB)))
    return out


def compare_procedures(
    protocol: ThresholdProtocol,
    staircase: PlanResult | None,
    settings: PlanSettings,
    thresholds_db: NDArray[np.float64],
    *,
    quest_replicates: int = 400,
    sd_ladder_db: Sequence[float] = SD_LADDER_DB,
    psi: bool = False,
    progress: Progress | None = None,
    quest_max_trials: int | None = None,
    outcomes: Sequence[QuestPart] | None = None,
    scheduler: str | None = "synchronous",
) -> ProcedureComparison:
    """Simulate QUEST+ beside the staircase plan and rate every setting against the bound.

    Parameters
    ----------
    protocol : ThresholdProtocol
        Sets, QUEST+ settings (or the staircase's bounds for a default QUEST+), timing.
    staircase : PlanResult or None
        The staircase plan of the same protocol and observers (its rows join the comparison).
    settings : PlanSettings
        Observer, response time, precision question, seed.
    thresholds_db : array, shape (n_sets, ≥ quest_replicates)
        True thresholds, protocol's level unit (the staircase plan's; the first
        ``quest_replicates`` of each set are used).
    quest_replicates : int
        QUEST+ tracks per set.
    sd_ladder_db : sequence of float
        Posterior-SD targets read off each run, dB (the protocol's own is added).
    psi : bool
        Add the psi-marginal (slope unknown) beside a slope-known QUEST+ (slow).
    progress : callable, optional
        One line per step.
    quest_max_trials : int, optional
        Trial cap of the capped QUEST+ rows (default: the protocol's QUEST+ ``max_trials``, or
        for a staircase protocol its staircase's cap).
    outcomes : sequence of QuestPart, optional
        The results of :func:`quest_tasks` of the same arguments, in order, run elsewhere
        (``plan`` runs them beside the staircase plan's chunks); simulated here when None.
    scheduler : str or None
        Where the QUEST+ chunks run when simulated here
        (:func:`masking_lab.planning.parallel.run_chunks`); the same rows on any.

    Examples
    --------
    >>> from masking_lab.formats.resources import shipped
    >>> from masking_lab.formats.protocol import load_protocol
    >>> from masking_lab.planning.settings import StopRule, Schedule
    >>> p = load_protocol(shipped("protocols", "experiment1_questplus.yaml"))
    >>> s = PlanSettings((StopRule(11, 8),), (Schedule((4.0, 2.0)),), replicates=20)
    >>> c = compare_procedures(p, None, s, np.full((15, 20), 5.0), quest_replicates=20,
    ...                        sd_ladder_db=(1.5,))
    >>> sorted({r["setting"] for r in c.rows})
    ['SD ≤ 1.5 dB', 'SD ≤ 1.6 dB']
    """
    say = progress or (lambda _msg: None)
    obs = settings.observer
    trial_s = trial_duration_s(protocol.timing, settings.response_s)
    info, p_peak, _ = max_information(scale_db=obs.scale_db, guess=obs.guess, lapse=obs.lapse)
    bound = {
        "information": info,
        "p_correct": p_peak,
        "scale_db": obs.scale_db,
        "lapse": obs.lapse,
        "guess": obs.guess,
    }
    reps = min(quest_replicates, thresholds_db.shape[1])
    thr = thresholds_db[:, :reps].reshape(-1)
    set_of_row = np.repeat(np.arange(len(protocol.sets)), reps)
    rows: list[dict] = []
    per_set: list[dict] = []
    if staircase is not None:
        own_staircase = any(s.staircase is not None for s in protocol.sets)
        for r in staircase.table:
            rows.append({**_staircase_row(r, obs), "own": bool(r.get("own")) and own_staircase})
        for r in staircase.ladder:
            rows.append({**_staircase_row(r, obs), "capped": False, "own": False})
    # Only a protocol that runs QUEST+ has a QUEST+ row of its own ("this protocol").
    quest_is_protocol = protocol_quest_plus(protocol) is not None
    variants = _variants(protocol, obs, psi, quest_max_trials)
    tasks = quest_tasks(
        protocol,
        settings,
        thresholds_db,
        quest_replicates=quest_replicates,
        sd_ladder_db=sd_ladder_db,
        psi=psi,
        quest_max_trials=quest_max_trials,
    )
    verb = "simulating" if outcomes is None else "simulated"
    for name, own in variants:
        target = min(_targets(own, sd_ladder_db))
        say(f"{name}: {verb} {thr.size} tracks to posterior SD {target:g} dB")
    if outcomes is None:
        outcomes = run_tasks(tasks, scheduler=scheduler)
    if len(outcomes) != len(tasks):
        raise ValueError(f"expected {len(tasks)} QUEST+ chunk results, got {len(outcomes)}")
    n_sets = len(protocol.sets)
    # A chunk's parts are consecutive tasks; each chunk's first part starts at set 0.
    starts = [i for i, (_fn, a) in enumerate(tasks) if a[-1] is None or a[-1][0] == 0]
    starts.append(len(tasks))
    per_variant = (len(starts) - 1) // len(variants)
    for k, (name, own) in enumerate(variants):
        targets = _targets(own, sd_ladder_db)
        bounds = starts[k * per_variant : (k + 1) * per_variant + 1]
        chunks = [
            out
            if isinstance(out := outcomes[a], dict)
            else chunk_outcome(own, targets, outcomes[a:b])
            for a, b in pairwise(bounds)
        ]
        for target in targets:
            for capped in (True, False):
                status, n, est = (
                    np.concatenate(
                        [c[(target, capped)][i].reshape(n_sets, -1) for c in chunks], axis=1
                    ).reshape(-1)
                    for i in range(3)
                )
                sets_rows = []
                for j, spec in enumerate(protocol.sets):
                    mine = set_of_row == j
                    row = summarize(n[mine], status[mine], est[mine], thr[mine], trial_s)
                    row["trials_mean"] = float(np.mean(n[mine]))
                    sets_rows.append(row)
                    if capped:
                        head = _head(name, target, own, capped, quest_is_protocol and k == 0)
                        per_set.append({"set": spec.id, **head, **row})
                pooled = pool(sets_rows, n, trial_s)
                pooled["trials_mean"] = float(np.mean(n))
                pooled |= efficiency_fields(pooled["sd_db"], pooled["trials_mean"], obs)
                head = _head(name, target, own, capped, quest_is_protocol and k == 0)
                rows.append({**head, **pooled})
    fewest = _fewest(rows, settings.precision_db, settings.z)
    return ProcedureComparison(rows, per_set, bound, fewest, settings.precision_db, settings.z)


def _targets(own: QuestPlusSettings, sd_ladder_db: Sequence[float]) -> list[float]:
    return sorted({*sd_ladder_db, *([own.target_sd_db] if own.target_sd_db else [])})


#: QUEST+ tracks per set in one chunk: a worker holds its (tracks × 300) posterior arrays
#: (peak ~30 MB for the 15 sets of experiment I).
QUEST_CHUNK_REPLICATES = 100

#: A QUEST+ chunk's outcomes: per (posterior-SD target, capped), each track's status code,
#: trials and estimate (rows set-major), as :func:`_outcome` gives them.
QuestChunk = dict[tuple[float, bool], tuple[NDArray[np.int8], NDArray[np.int64], NDArray]]


def quest_tasks(
    protocol: ThresholdProtocol,
    settings: PlanSettings,
    thresholds_db: NDArray[np.float64],
    *,
    quest_replicates: int = 400,
    sd_ladder_db: Sequence[float] = SD_LADDER_DB,
    psi: bool = False,
    quest_max_trials: int | None = None,
) -> list[Task]:
    """The chunks of QUEST+ tracks :func:`compare_procedures` reads its rows from: per variant
    (QUEST+, and with ``psi`` the psi-marginal), chunks of :data:`QUEST_CHUNK_REPLICATES` tracks
    per set, each with its own seed, and a variant of fewer than :data:`QUEST_SPLIT_BELOW`
    chunks split into parts of :data:`QUEST_PART_SETS` sets; run them anywhere, in order
    (:func:`masking_lab.planning.parallel.run_tasks`).

    Arguments as for :func:`compare_procedures`; a chunk's result depends on nothing else.

    Examples
    --------
    >>> from masking_lab.formats.resources import shipped
    >>> from masking_lab.formats.protocol import load_protocol
    >>> from masking_lab.planning.settings import StopRule, Schedule
    >>> p = load_protocol(shipped("protocols", "experiment1_questplus.yaml"))
    >>> s = PlanSettings((StopRule(11, 8),), (Schedule((4.0, 2.0)),), replicates=5)
    >>> tasks = quest_tasks(p, s, np.full((15, 5), 5.0), quest_replicates=5)
    >>> fn, args = tasks[0]
    >>> len(tasks), fn(*args).sd_db.shape[0]  # one chunk in 15 parts of 1 set × 5 tracks
    (15, 5)
    >>> len(quest_tasks(p, s, np.full((15, 500), 5.0), quest_replicates=400))  # 4 chunks
    4
    """
    reps = min(quest_replicates, thresholds_db.shape[1])
    tasks: list[Task] = []
    n_sets = thresholds_db.shape[0]
    for k, (_name, own) in enumerate(_variants(protocol, settings.observer, psi, quest_max_trials)):
        targets = tuple(_targets(own, sd_ladder_db))
        plan = chunk_plan([settings.seed, 0x9E57, k], reps, QUEST_CHUNK_REPLICATES)
        # Enough chunks already keep the cores busy; fewer are split into parts by sets.
        parts: list[tuple[int, int] | None] = [None]
        if len(plan) < QUEST_SPLIT_BELOW:
            parts = [*_set_parts(n_sets)]
        first = 0
        for n, seq in plan:
            thr = thresholds_db[:, first : first + n]
            for part in parts:
                tasks.append((quest_chunk, (own, targets, settings.observer, thr, seq, part)))
            first += n
    return tasks


#: Sets per task of a QUEST+ chunk when a variant has fewer than :data:`QUEST_SPLIT_BELOW`
#: chunks (the psi-marginal's 40 tracks per set are one chunk): its tracks are split by sets
#: into parts that run anywhere (each draws the chunk's random numbers and keeps its own
#: tracks', so the parts are the chunk's tracks), which spreads a long chunk over the cores.
#: One set per part: the parts come last on the workers, and 15 short ones leave less of a
#: tail on one core than 5 long ones (the same tables either way).
QUEST_PART_SETS = 1
QUEST_SPLIT_BELOW = 4


def _set_parts(n_sets: int) -> list[tuple[int, int]]:
    """(first set, stop) of each part of a QUEST+ chunk: :data:`QUEST_PART_SETS` sets each."""
    return [(a, min(a + QUEST_PART_SETS, n_sets)) for a in range(0, n_sets, QUEST_PART_SETS)]


class QuestPart(NamedTuple):
    """A part of a QUEST+ chunk (:func:`quest_chunk`): its tracks' posterior mean and SD after
    each trial, dB, shape (tracks, trials), NaN past a track's end; rows set-major."""

    mean_db: NDArray[np.float64]
    sd_db: NDArray[np.float64]


def chunk_outcome(
    own: QuestPlusSettings, targets: Sequence[float], parts: Sequence[QuestPart]
) -> QuestChunk:
    """How each track of a chunk (its parts, in order) ends under every posterior-SD target,
    capped at ``own.max_trials`` and uncapped: status codes, trials, estimates (dB).

    The parts' traces are joined (padded with NaN to the longest track) into the whole chunk's
    before reading them, so every part's tracks are read as the whole chunk's are.

    Examples
    --------
    >>> own = QuestPlusSettings(0.0, 20.0, target_sd_db=1.0, max_trials=3)
    >>> a = QuestPart(np.array([[9.0, 9.5]]), np.array([[2.0, 0.9]]))
    >>> b = QuestPart(np.array([[8.0, 8.2, 8.1]]), np.array([[3.0, 1.8, 1.2]]))
    >>> status, n, est = chunk_outcome(own, [1.0], [a, b])[(1.0, False)]
    >>> n.tolist(), est[:1].tolist()
    ([2, 3], [9.5])
    """
    width = max(p.sd_db.shape[1] for p in parts)

    def joined(name: str) -> NDArray[np.float64]:
        arrays = [getattr(p, name) for p in parts]
        pad = [np.pad(a, ((0, 0), (0, width - a.shape[1])), constant_values=np.nan) for a in arrays]
        return np.concatenate(pad)

    mean, sd = joined("mean_db"), joined("sd_db")
    return {
        (target, capped): _outcome_of(
            mean, sd, replace(own, target_sd_db=target), own.max_trials if capped else None
        )
        for target in targets
        for capped in (True, False)
    }


def quest_chunk(
    own: QuestPlusSettings,
    targets: Sequence[float],
    observer: Observer,
    thresholds_db: NDArray[np.float64],
    seed: np.random.SeedSequence,
    sets: tuple[int, int] | None = None,
) -> QuestChunk | QuestPart:
    """One chunk of QUEST+ tracks (``thresholds_db``: sets × tracks), run to the strictest
    posterior-SD target, and how each would have ended under every target, capped at
    ``own.max_trials`` and uncapped (:func:`chunk_outcome`). The tracks themselves stay here.

    With ``sets`` = (first, stop), only those sets' tracks (rows) of the chunk, exactly as the
    whole chunk runs them (the same random numbers), and their posterior mean and SD after
    every trial (:class:`QuestPart`): the parts' traces, joined by :func:`chunk_outcome`, are
    the whole chunk's (to an ulp: tests/test_plan_parts.py)."""
    longest = replace(
        own, target_sd_db=min(targets), max_trials=max(QUEST_TRIAL_LIMIT, own.max_trials or 0)
    )
    n_sets, n = thresholds_db.shape
    first, stop = (0, n_sets) if sets is None else sets
    sim = simulate_quest_plus(
        longest,
        thresholds_db[first:stop].reshape(-1),
        scale_db=observer.scale_db,
        lapse=observer.lapse,
        guess=observer.guess,
        rng=np.random.default_rng(seed),
        part_of=(first * n, n_sets * n),
    )
    if sets is not None:
        return QuestPart(sim.mean_db, sim.sd_db)
    return chunk_outcome(own, targets, [QuestPart(sim.mean_db, sim.sd_db)])


def _head(
    name: str, target: float, own: QuestPlusSettings, capped: bool, mine: bool
) -> dict[str, Any]:
    return {
        "procedure": name,
        "setting": f"SD ≤ {target:g} dB",
        "estimator": "posterior_mean",
        "target_sd_db": target,
        "max_trials": own.max_trials if capped else None,
        "own": bool(mine and capped and target == own.target_sd_db),
        "capped": capped,
    }


def _staircase_row(r: dict, obs: Observer) -> dict:
    sched = r["schedule"] + ("" if r["down_up_ratio"] == 1.0 else f" d/u {r['down_up_ratio']:g}")
    out = {
        "procedure": f"staircase {sched}",
        "setting": r["rule"],
        "estimator": r["estimator"],
        "own": bool(r.get("own", False)),
        "capped": True,
        **{k: v for k, v in r.items() if k not in ("own",)},
    }
    if "efficiency" not in out:
        out |= efficiency_fields(out.get("sd_db", math.nan), out.get("trials_mean", math.nan), obs)
    return out


def _outcome(
    sim: SimulatedQuestPlus, rule: QuestPlusSettings, cap: int | None
) -> tuple[NDArray[np.int8], NDArray[np.int64], NDArray[np.float64]]:
    """Status codes, trials and estimates had every track stopped under ``rule`` and ``cap``."""
    return _outcome_of(sim.mean_db, sim.sd_db, rule, cap)


def _outcome_of(
    mean_db: NDArray[np.float64],
    sd_db: NDArray[np.float64],
    rule: QuestPlusSettings,
    cap: int | None,
) -> tuple[NDArray[np.int8], NDArray[np.int64], NDArray[np.float64]]:
    """:func:`_outcome` from the tracks' posterior traces (tracks × trials, NaN past the end)."""
    limit = sd_db.shape[1]
    n = trials_to_sd(sd_db, rule.target_sd_db or 0.0, rule.min_trials)
    reached = np.isfinite(n)
    stop = np.where(reached, n, limit)
    if cap is not None:
        stop = np.minimum(stop, cap)
    stop_i = stop.astype(np.int64)
    col = np.maximum(stop_i - 1, 0)
    rows = np.arange(stop_i.size)
    mean, sd = mean_db[rows, col], sd_db[rows, col]
    capped_rule = replace(rule, max_trials=int(cap) if cap is not None else limit)
    names = stop_status(capped_rule, stop_i, mean, sd)
    # A track that never reached the target within the simulation counts as trial_cap.
    codes = np.array([_CODES.get(str(s), RUNNING) for s in names], dtype=np.int8)
    est = np.where(codes == COMPLETED, mean, np.nan)
    return codes, stop_i, est


def _fewest(rows: Sequence[dict], precision_db: float, z: float) -> list[dict]:
    """Per procedure family, the cheapest uncapped setting meeting ±precision (worst set)."""
    families: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        if not r.get("capped", True):  # the staircase's uncapped ladder, QUEST+'s uncapped rows
            families.setdefault((r["procedure"], r["estimator"]), []).append(r)
    out = []
    for group in families.values():
        ok = [
            r
            for r in group
            if math.isfinite(r.get("worst_sd_db", math.nan))
            and z * r["worst_sd_db"] <= precision_db
        ]
        if ok:
            best = min(ok, key=lambda r: (r["trials_median"], r["trials_mean"]))
            out.append({**best, "met": True, "half_width_db": z * best["worst_sd_db"]})
        else:
            finite = [r for r in group if math.isfinite(r.get("worst_sd_db", math.nan))]
            if finite:
                best = min(finite, key=lambda r: r["worst_sd_db"])
                out.append({**best, "met": False, "half_width_db": z * best["worst_sd_db"]})
    return sorted(out, key=lambda r: (not r["met"], r["trials_median"]))
