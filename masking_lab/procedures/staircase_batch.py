"""Many staircases at once: the rules of :mod:`masking_lab.procedures.staircase`, vectorized over
replicates.

:func:`run_staircases` advances every replicate one trial at a time with boolean masks over
numpy arrays (no Python loop per session). It implements exactly the rules of
:class:`masking_lab.procedures.staircase.Staircase` — run counter, reversals, step schedule by
reversal
count, down/up ratio, optional initial 1-down-1-up phase, bounds with clamp/stop and hit counting,
trial cap, stop after ``n_reversals`` — so that, fed the same responses, it yields the same level
tracks, reversal levels, statuses and ALs (tests/test_simulate.py checks this with hypothesis).
From :data:`COMPILED_TRACKS` tracks on, each trial's bookkeeping is one compiled pass instead
(:mod:`masking_lab.procedures.staircase_loops`, the same numbers bit for bit).

Responses come either from a matrix (:func:`replay_many`, used to check conformance) or from a
simulated observer (:func:`simulate`): p(correct) from :class:`~masking_lab.core.psychometric.
Psychometric` at the trial level minus the replicate's true threshold, decided by a uniform draw
from the numpy ``Generator`` passed in. One uniform is drawn per replicate per trial (finished
replicates included), so trial ``t`` of replicate ``i`` always sees the same draw whatever the
stop rule: settings compared on the same seed share their random numbers, and
:func:`outcome_under` / :func:`truncate` derive a shorter stop rule or a trial cap from one long
run exactly.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from masking_lab.core.errors import StaircaseError
from masking_lab.core.psychometric import GUESS_3IFC, Psychometric
from masking_lab.procedures.batch import TrackBatch
from masking_lab.procedures.fused import compiled_loops
from masking_lab.procedures.staircase import StaircaseSettings

#: Status names indexed by the integer codes in :attr:`SimulatedTracks.status_code`.
STATUSES = ("running", "completed", "ceiling", "floor", "trial_cap")
RUNNING, COMPLETED, CEILING, FLOOR, TRIAL_CAP = range(5)

#: Trials simulated at most when the settings have no ``max_trials`` (tracks still going then
#: are reported as ``running``: the simulator never invents a stop the staircase would not make).
DEFAULT_TRIAL_LIMIT = 1000
#: From this many tracks on, each trial's bookkeeping runs compiled
#: (:mod:`masking_lab.procedures.staircase_loops`) when numba loads: numba's ~0.3 s load pays off
#: only for a simulation's thousands of tracks.
COMPILED_TRACKS = 256

#: ``respond(trial_index, rows, levels_db) -> correct``: answers trial ``trial_index`` of the
#: replicates ``rows`` (int array) presented at ``levels_db`` (dB), one bool per row.
Respond = Callable[[int, NDArray[np.intp], NDArray[np.float64]], ArrayLike]


@dataclass(frozen=True)
class Observer:
    """A simulated 3IFC observer: a logistic psychometric function around a true threshold.

    Attributes
    ----------
    scale_db : float
        Logistic scale in dB (the slope setting; 10–90 % of the rise spans ≈ 4.4·scale dB).
    lapse : float
        Lapse rate λ (0 ≤ λ < 1 − guess).
    guess : float
        Guess rate γ (1/3 for 3IFC).
    """

    scale_db: float = 1.5
    lapse: float = 0.02
    guess: float = GUESS_3IFC

    @property
    def psychometric(self) -> Psychometric:
        """ψ with its threshold (p = 0.794) at 0 dB: evaluate it at level − true threshold."""
        return Psychometric(0.0, self.scale_db, self.guess, self.lapse)


@dataclass(frozen=True, kw_only=True)
class SimulatedTracks(TrackBatch[StaircaseSettings]):
    """The outcome of ``R`` staircase tracks run under one :class:`StaircaseSettings`.

    The arrays of :class:`~masking_lab.procedures.batch.TrackBatch` (``levels_db`` and
    ``correct`` have shape (R, 0) when run with ``store_levels=False``; each row may start at
    its own level; the true thresholds are the levels where p = 0.794), and the reversals.

    Attributes
    ----------
    start_level_db : ndarray, shape (R,)
        First level of each track, dB.
    reversal_levels_db : ndarray, shape (R, settings.n_reversals)
        Level of each reversal, dB (NaN beyond the reversals a track made).
    reversal_trials : ndarray of int, shape (R, settings.n_reversals)
        0-based trial index of each reversal (−1 beyond the reversals a track made).
    reversal_count : ndarray of int, shape (R,)
        Reversals each track made.
    status_code : ndarray of int8, shape (R,)
        Index into :data:`STATUSES`.
    al_db : ndarray, shape (R,)
        Mean of the last ``n_reversals_averaged`` reversal levels, dB, for completed tracks
        (``math.fsum`` per row, exactly as :attr:`Staircase.al_db`); NaN otherwise.
    """

    start_level_db: NDArray[np.float64]
    reversal_levels_db: NDArray[np.float64]
    reversal_trials: NDArray[np.int64]
    reversal_count: NDArray[np.int64]
    status_code: NDArray[np.int8]
    al_db: NDArray[np.float64]

    @property
    def status(self) -> NDArray[np.str_]:
        """Status name of each track (``running``, ``completed``, ``ceiling``, …)."""
        return np.asarray(STATUSES)[self.status_code]

    @property
    def completed(self) -> NDArray[np.bool_]:
        """True for tracks that made all their reversals (the only ones with an AL)."""
        return self.status_code == COMPLETED

    def fraction(self, status: str) -> float:
        """Fraction of tracks that ended with ``status`` (a name from :data:`STATUSES`)."""
        return float(np.mean(self.status_code == STATUSES.index(status)))


def run_staircases(
    settings: StaircaseSettings,
    respond: Respond,
    n_replicates: int,
    *,
    start_level_db: ArrayLike | None = None,
    trial_limit: int | None = None,
    true_threshold_db: NDArray[np.float64] | None = None,
    store_levels: bool = True,
) -> SimulatedTracks:
    """Run ``n_replicates`` staircases in lock step, one trial per iteration over all of them.

    Parameters
    ----------
    settings : StaircaseSettings
        The rules (as :class:`masking_lab.procedures.staircase.Staircase`).
    respond : callable
        ``respond(t, rows, levels_db)`` → correct (bool per row) for trial ``t`` of the tracks
        still running.
    n_replicates : int
        Number of tracks R.
    start_level_db : float or array of shape (R,), optional
        Start level per track in dB (default ``settings.start_level_db``); must respect the bounds.
    trial_limit : int, optional
        Trials simulated at most (default ``settings.max_trials``, or
        :data:`DEFAULT_TRIAL_LIMIT` without a cap). Tracks still going then stay ``running``.
    true_threshold_db : array of shape (R,), optional
        Stored in the result for the caller's bias computations, dB.
    store_levels : bool
        Keep every trial's level and answer (``levels_db``, ``correct``); False keeps only the
        reversals, trial counts and statuses, which is all a reversal-mean study needs, in a
        fraction of the memory.

    Returns
    -------
    SimulatedTracks

    Raises
    ------
    StaircaseError
        If a start level is not finite or lies outside the bounds, or the sizes disagree.
    """
    s = settings
    n = int(n_replicates)
    level = _start_levels(s, n, start_level_db)
    start = level.copy()
    limit = trial_limit if trial_limit is not None else (s.max_trials or DEFAULT_TRIAL_LIMIT)
    steps = np.asarray(s.step_sizes_db, dtype=float)
    last_step = len(steps) - 1
    hi = math.inf if s.max_level_db is None else float(s.max_level_db)
    lo = -math.inf if s.min_level_db is None else float(s.min_level_db)
    clamp = s.bound_policy == "clamp"

    # run counter: +k after k correct in a row, −k after k wrong in a row, 0 after a step
    run = np.zeros(n, dtype=np.int64)
    direction = np.zeros(n, dtype=np.int8)  # 0 start, +1 up, −1 down
    n_rev = np.zeros(n, dtype=np.int64)
    hits = np.zeros(n, dtype=np.int64)
    status = np.zeros(n, dtype=np.int8)
    last_correct = np.zeros(n, dtype=bool)
    n_trials = np.zeros(n, dtype=np.int64)
    rev_levels = np.full((n, s.n_reversals), np.nan)
    rev_trials = np.full((n, s.n_reversals), -1, dtype=np.int64)
    level_cols: list[NDArray[np.float64]] = []
    correct_cols: list[NDArray[np.bool_]] = []

    # Many tracks take one compiled pass per trial (the same numbers; numba's load pays off).
    loops = compiled_loops("staircase_loops") if n >= COMPILED_TRACKS else None
    rules = np.array(
        [s.n_up, s.n_down, s.down_up_ratio, s.initial_one_down_one_up, s.n_reversals, clamp,
         s.max_bound_hits], dtype=float,
    )  # fmt: skip

    active = np.arange(n)
    for t in range(limit):
        if active.size == 0:
            break
        a = active
        lv = level[a]
        c = np.asarray(respond(t, a, lv), dtype=bool)
        if c.shape != a.shape:
            raise StaircaseError(f"respond() gave {c.shape} answers for {a.size} running tracks")
        n_trials[a] += 1
        if store_levels:
            col = np.full(n, np.nan)
            col[a] = lv
            level_cols.append(col)
            ccol = np.zeros(n, dtype=bool)
            ccol[a] = c
            correct_cols.append(ccol)
        if loops is not None:
            capped = s.max_trials is not None and t + 1 >= s.max_trials
            active = loops.staircase_trial(
                t, a, lv, c, level, run, direction, n_rev, hits, status, last_correct,
                rev_levels, rev_trials, steps, rules, hi, lo, capped,
            )  # fmt: skip
            continue

        # Run counter, as Staircase.update: continue a run of equal answers, else restart it.
        same = (last_correct[a] == c) if t > 0 else np.zeros(a.size, dtype=bool)
        r = run[a]
        r = np.where(c, np.where(same, r + 1, 1), np.where(same, r - 1, -1))
        k = n_rev[a]
        initial = (k == 0) if s.initial_one_down_one_up else np.zeros(a.size, dtype=bool)
        wants_down = r >= s.n_down
        wants_up = r <= -s.n_up
        want = np.where(
            initial, np.where(c, -1, 1), np.where(wants_down, -1, np.where(wants_up, 1, 0))
        )
        d = direction[a]
        rev = (want != 0) & (d != 0) & (d != want)
        direction[a] = np.where(want != 0, want, d)
        if rev.any():
            rows = a[rev]
            rev_levels[rows, k[rev]] = lv[rev]
            rev_trials[rows, k[rev]] = t
        k = k + rev
        n_rev[a] = k
        done = k >= s.n_reversals

        # The step uses the schedule entry for the reversal count *after* this trial.
        up = steps[np.minimum(k, last_step)]
        down = -up * s.down_up_ratio
        step = np.where(
            initial, np.where(c, down, up), np.where(wants_down, down, np.where(wants_up, up, 0.0))
        )
        step[done] = 0.0  # a completed track takes no step
        moving = step != 0.0
        target = lv + step
        rising = step > 0
        beyond = moving & np.where(rising, target > hi, target < lo)
        free = moving & ~beyond
        new_level = np.where(free, target, lv)
        h = hits[a]
        new_hits = np.where(free, 0, h)
        new_status = np.where(done, COMPLETED, RUNNING).astype(np.int8)
        ended = np.where(rising, CEILING, FLOOR).astype(np.int8)
        if clamp:
            bound = np.where(rising, hi, lo)
            clamped_hits = np.where(lv == bound, h + 1, 0)
            new_hits = np.where(beyond, clamped_hits, new_hits)
            new_level = np.where(beyond, bound, new_level)
            new_status = np.where(beyond & (clamped_hits >= s.max_bound_hits), ended, new_status)
        else:
            new_status = np.where(beyond, ended, new_status)  # level stays at the trial level
        if s.max_trials is not None and t + 1 >= s.max_trials:
            new_status = np.where(new_status == RUNNING, TRIAL_CAP, new_status).astype(np.int8)

        run[a] = np.where(moving, 0, r)
        level[a] = new_level
        hits[a] = new_hits
        status[a] = new_status
        last_correct[a] = c
        active = a[new_status == RUNNING]

    levels = np.column_stack(level_cols) if level_cols else np.empty((n, 0))
    correct = np.column_stack(correct_cols) if correct_cols else np.empty((n, 0), dtype=bool)
    return SimulatedTracks(
        settings=s,
        start_level_db=start,
        levels_db=levels,
        correct=correct,
        n_trials=n_trials,
        reversal_levels_db=rev_levels,
        reversal_trials=rev_trials,
        reversal_count=n_rev,
        status_code=status,
        al_db=_reversal_mean_al(rev_levels, status, s.n_reversals, s.n_reversals_averaged),
        true_threshold_db=true_threshold_db,
    )


def replay_many(
    settings: StaircaseSettings,
    correct: ArrayLike,
    *,
    start_level_db: ArrayLike | None = None,
) -> SimulatedTracks:
    """Run one track per row of a response matrix (the vectorized :func:`staircase.replay`).

    Parameters
    ----------
    settings : StaircaseSettings
        The rules.
    correct : array of bool, shape (R, W)
        Row ``i`` holds the answers track ``i`` gets, in order; answers after the track finishes
        are ignored, and a track that runs out of answers stays ``running``.
    start_level_db : float or array of shape (R,), optional
        Start level per track in dB.
    """
    m = np.asarray(correct, dtype=bool)
    if m.ndim != 2:
        raise StaircaseError(f"responses must be a 2-D matrix (tracks × trials), got {m.shape}")
    width = m.shape[1]
    limit = width if settings.max_trials is None else min(width, settings.max_trials)
    return run_staircases(
        settings,
        lambda t, rows, _levels: m[rows, t],
        m.shape[0],
        start_level_db=start_level_db,
        trial_limit=limit,
    )


def simulate(
    settings: StaircaseSettings,
    true_threshold_db: ArrayLike,
    observer: Observer,
    rng: np.random.Generator,
    *,
    start_level_db: ArrayLike | None = None,
    trial_limit: int | None = None,
    store_levels: bool = True,
) -> SimulatedTracks:
    """Run one staircase per simulated observer.

    Parameters
    ----------
    settings : StaircaseSettings
        The rules, levels in the unit of ``true_threshold_db``.
    true_threshold_db : array of shape (R,)
        Each observer's true threshold (the level where p(correct) = 0.794), dB.
    observer : Observer
        Psychometric scale, lapse and guess rate shared by all replicates.
    rng : numpy.random.Generator
        Source of the answers; one uniform per replicate per trial.
    start_level_db, trial_limit, store_levels
        As :func:`run_staircases`.
    """
    thr = np.asarray(true_threshold_db, dtype=float).reshape(-1)
    if not np.all(np.isfinite(thr)):
        raise StaircaseError("true_threshold_db must be finite dB values (no NaN or ±inf)")
    psy = observer.psychometric
    n = thr.size

    def respond(_t: int, rows: NDArray[np.intp], levels: NDArray[np.float64]) -> NDArray:
        u = rng.random(n)  # drawn for every replicate so streams stay aligned across stop rules
        return u[rows] < psy.p_correct(levels - thr[rows])

    return run_staircases(
        settings,
        respond,
        n,
        start_level_db=start_level_db,
        trial_limit=trial_limit,
        true_threshold_db=thr,
        store_levels=store_levels,
    )


@dataclass(frozen=True)
class StopOutcome:
    """How each track ends under a shorter stop rule or a trial cap (see :func:`outcome_under`).

    Attributes
    ----------
    n_trials : ndarray of int, shape (R,)
        Trials the track runs.
    status_code : ndarray of int8, shape (R,)
        Index into :data:`STATUSES`.
    al_db : ndarray, shape (R,)
        Mean of the last ``n_reversals_averaged`` reversal levels for completed tracks, dB; NaN
        otherwise.
    """

    n_trials: NDArray[np.int64]
    status_code: NDArray[np.int8]
    al_db: NDArray[np.float64]

    @property
    def completed(self) -> NDArray[np.bool_]:
        """True for tracks that made all their reversals."""
        return self.status_code == COMPLETED


def outcome_under(
    tracks: SimulatedTracks,
    n_reversals: int,
    n_reversals_averaged: int,
    max_trials: int | None = None,
    *,
    exact: bool = True,
) -> StopOutcome:
    """Trials, status and AL of each track had it stopped after ``n_reversals`` reversals or at
    ``max_trials`` trials.

    A track's first trials do not depend on how many reversals it is set to run nor on its cap,
    and :func:`simulate` gives trial ``t`` the same random draw whatever the stop rule, so this
    equals re-simulating with the shorter rule on the same seed — at the cost of one long run.

    Parameters
    ----------
    tracks : SimulatedTracks
        Tracks run for at least ``n_reversals`` reversals, without a cap or with one ≥
        ``max_trials``.
    n_reversals, n_reversals_averaged : int
        The stop rule.
    max_trials : int, optional
        Trial cap (None keeps the tracks' own).
    exact : bool
        Average reversals with ``math.fsum`` (bit-identical to :attr:`Staircase.al_db`) rather
        than numpy's faster pairwise sum (differences ~1e-15 dB).

    Raises
    ------
    StaircaseError
        If the rule is invalid or cannot be derived from these tracks.
    """
    s = tracks.settings
    replace(s, n_reversals=n_reversals, n_reversals_averaged=n_reversals_averaged)  # validates
    if n_reversals > s.n_reversals:
        raise StaircaseError(
            f"cannot derive a {n_reversals}-reversal rule from tracks run for {s.n_reversals}; "
            "simulate with the longest stop rule first"
        )
    if max_trials is not None:
        if not (isinstance(max_trials, int | np.integer) and max_trials >= 1):
            raise StaircaseError(f"max_trials must be an integer ≥ 1, got {max_trials!r}")
        if s.max_trials is not None and max_trials > s.max_trials:
            raise StaircaseError(
                f"cannot derive a cap of {max_trials} trials from tracks capped at "
                f"{s.max_trials}; simulate without a cap first"
            )
    reached = tracks.reversal_count >= n_reversals
    end = np.where(reached, tracks.reversal_trials[:, n_reversals - 1] + 1, tracks.n_trials)
    status = np.where(reached, COMPLETED, tracks.status_code).astype(np.int8)
    if max_trials is not None:
        # A track still going at its max_trials-th trial is capped; one that ends on that very
        # trial (completed, ceiling, floor) keeps its status, as in Staircase.update.
        capped = (end > max_trials) | ((end == max_trials) & (status == RUNNING))
        status = np.where(capped, TRIAL_CAP, status).astype(np.int8)
        end = np.minimum(end, max_trials)
    rev = tracks.reversal_levels_db[:, :n_reversals]
    if exact:
        al = _reversal_mean_al(rev, status, n_reversals, n_reversals_averaged)
    else:
        done = status == COMPLETED
        al = np.full(status.shape, np.nan)
        al[done] = rev[done, n_reversals - n_reversals_averaged :].mean(axis=1)
    return StopOutcome(end.astype(np.int64), status, al)


def truncate(
    tracks: SimulatedTracks,
    n_reversals: int,
    n_reversals_averaged: int,
    max_trials: int | None = None,
) -> SimulatedTracks:
    """The tracks as they would have been under a shorter stop rule or a trial cap.

    Equals re-simulating with ``replace(settings, n_reversals=…, n_reversals_averaged=…,
    max_trials=…)`` on the same seed (see :func:`outcome_under`).

    Raises
    ------
    StaircaseError
        If the rule is invalid or cannot be derived from these tracks.
    """
    out = outcome_under(tracks, n_reversals, n_reversals_averaged, max_trials)
    s = tracks.settings
    new = replace(
        s,
        n_reversals=n_reversals,
        n_reversals_averaged=n_reversals_averaged,
        max_trials=s.max_trials if max_trials is None else max_trials,
    )
    end = out.n_trials
    width = min(int(end.max()) if end.size else 0, tracks.levels_db.shape[1])
    keep = np.arange(width)[None, :] < end[:, None]
    rev_trials = tracks.reversal_trials[:, :n_reversals]
    made = (rev_trials >= 0) & (rev_trials < end[:, None])  # a cap can cut late reversals
    return SimulatedTracks(
        settings=new,
        start_level_db=tracks.start_level_db,
        levels_db=np.where(keep, tracks.levels_db[:, :width], np.nan),
        correct=keep & tracks.correct[:, :width],
        n_trials=end,
        reversal_levels_db=np.where(made, tracks.reversal_levels_db[:, :n_reversals], np.nan),
        reversal_trials=np.where(made, rev_trials, -1),
        reversal_count=made.sum(axis=1).astype(np.int64),
        status_code=out.status_code,
        al_db=out.al_db,
        true_threshold_db=tracks.true_threshold_db,
    )


def _start_levels(
    s: StaircaseSettings, n: int, start_level_db: ArrayLike | None
) -> NDArray[np.float64]:
    if n < 1:
        raise StaircaseError(f"n_replicates must be ≥ 1, got {n}")
    if start_level_db is None:
        return np.full(n, float(s.start_level_db))
    level = np.broadcast_to(np.asarray(start_level_db, dtype=float), (n,)).copy()
    if not np.all(np.isfinite(level)):
        raise StaircaseError("start_level_db must be finite dB values (no NaN or ±inf)")
    if s.min_level_db is not None and np.any(level < s.min_level_db):
        raise StaircaseError(f"a start level is below min_level_db={s.min_level_db} dB")
    if s.max_level_db is not None and np.any(level > s.max_level_db):
        raise StaircaseError(f"a start level is above max_level_db={s.max_level_db} dB")
    return level


def _reversal_mean_al(
    rev_levels: NDArray[np.float64], status: NDArray[np.int8], n_reversals: int, k: int
) -> NDArray[np.float64]:
    """Mean of the last ``k`` reversal levels per completed row; fsum so it equals the scalar AL."""
    al = np.full(rev_levels.shape[0], np.nan)
    rows = np.flatnonzero(status == COMPLETED)
    if rows.size:
        block = rev_levels[rows, n_reversals - k : n_reversals]
        al[rows] = np.fromiter((math.fsum(r) / k for r in block.tolist()), float, rows.size)
    return al
