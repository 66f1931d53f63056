"""Many QUEST+ / psi-marginal tracks at once: :mod:`masking_lab.procedures.quest_plus`,
vectorised over replicates.

All tracks advance one trial per iteration: one posterior update and one placement
(:func:`~masking_lab.procedures.quest_plus.best_levels`, the function the scalar track uses)
for every track still running, with the same stop rules
(:func:`~masking_lab.procedures.quest_plus.stop_status`). Fed the same answers it yields the
levels, posteriors and statuses of :class:`~masking_lab.procedures.quest_plus.QuestPlus`
(tests/test_quest_plus_batch.py).

The posterior mean and SD are recorded after every trial. A track's levels do not depend on
its stop rule until it stops, so one run with a strict precision target (or a long trial count)
answers "how many trials to reach SD ≤ x" for every looser x (:meth:`SimulatedQuestPlus.
trials_to_sd`). As in :mod:`~masking_lab.procedures.staircase_batch`, the simulated observer
draws one uniform per replicate per trial, finished replicates included, so that settings
compared on the same seed share their random numbers.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from masking_lab.core.errors import ProcedureError
from masking_lab.core.psychometric import Psychometric
from masking_lab.procedures.batch import TrackBatch
from masking_lab.procedures.fused import COMPILED_FROM, compiled_loops
from masking_lab.procedures.quest_plus import (
    QuestPlusSettings,
    best_levels,
    stop_status,
    tables,
    threshold_moments,
)

#: Trials simulated at most when the settings have no ``max_trials``.
DEFAULT_TRIAL_LIMIT = 400

#: ``respond(trial_index, rows, levels_db) -> correct`` for the tracks ``rows`` still running.
Respond = Callable[[int, NDArray[np.intp], NDArray[np.float64]], ArrayLike]


@dataclass(frozen=True, kw_only=True)
class SimulatedQuestPlus(TrackBatch[QuestPlusSettings]):
    """The outcome of R tracks run under one :class:`QuestPlusSettings`.

    The arrays of :class:`~masking_lab.procedures.batch.TrackBatch`, and the posterior after
    each trial (NaN past a track's end).

    Attributes
    ----------
    mean_db, sd_db : ndarray, shape (R, T)
        Posterior mean and SD of the threshold after each trial, dB.
    status : ndarray of str, shape (R,)
        ``running`` (stopped by the simulation's trial limit), ``completed``, ``ceiling``,
        ``floor`` or ``trial_cap``.
    """

    mean_db: NDArray[np.float64]
    sd_db: NDArray[np.float64]
    status: NDArray[np.str_]

    @property
    def estimate_db(self) -> NDArray[np.float64]:
        """Final posterior mean of completed tracks, dB; NaN for the others."""
        last = self.mean_db[np.arange(self.n_trials.size), np.maximum(self.n_trials - 1, 0)]
        return np.where(self.status == "completed", last, np.nan)

    def trials_to_sd(self, target_sd_db: float, min_trials: int = 0) -> NDArray[np.float64]:
        """Trials each track needs before its posterior SD is ≤ ``target_sd_db`` (dB).

        Exactly what a run with ``target_sd_db`` as its precision rule would have used (the
        levels before a stop do not depend on the stop rule). NaN where the SD never got there.

        Examples
        --------
        >>> s = QuestPlusSettings(-20.0, 45.0, target_sd_db=1.5, max_trials=60)
        >>> sim = simulate_quest_plus(s, [5.0, 10.0], rng=np.random.default_rng(0))
        >>> bool(np.all(sim.trials_to_sd(2.0) <= sim.n_trials))
        True
        """
        return trials_to_sd(self.sd_db, target_sd_db, min_trials)

    def mean_at(self, n_trials: ArrayLike) -> NDArray[np.float64]:
        """Posterior mean of each track after ``n_trials[i]`` trials (NaN if never run), dB."""
        n = np.broadcast_to(np.asarray(n_trials, dtype=float), self.n_trials.shape)
        ok = np.isfinite(n) & (n >= 1) & (n <= self.n_trials)
        col = np.where(ok, n, 1).astype(np.intp) - 1
        return np.where(ok, self.mean_db[np.arange(n.size), col], np.nan)


def trials_to_sd(
    sd_db: NDArray[np.float64], target_sd_db: float, min_trials: int = 0
) -> NDArray[np.float64]:
    """Trials each track needs before its posterior SD is ≤ ``target_sd_db`` (dB), from the
    (tracks × trials) posterior SDs (dB; NaN past a track's end); NaN where it never got there.

    Examples
    --------
    >>> trials_to_sd(np.array([[3.0, 1.5, 0.9], [3.0, 2.5, np.nan]]), 2.0).tolist()
    [2.0, nan]
    """
    n = np.arange(1, sd_db.shape[1] + 1)
    ok = (sd_db <= target_sd_db) & (n[None, :] >= min_trials)
    first = np.argmax(ok, axis=1) + 1.0
    return np.where(ok.any(axis=1), first, np.nan)


def run_quest_plus(
    settings: QuestPlusSettings,
    respond: Respond,
    n_replicates: int,
    *,
    trial_limit: int | None = None,
    true_threshold_db: NDArray[np.float64] | None = None,
) -> SimulatedQuestPlus:
    """Run ``n_replicates`` tracks in lock step.

    Parameters
    ----------
    settings : QuestPlusSettings
        The rules.
    respond : callable
        ``respond(t, rows, levels_db)`` → one bool per row, for trial ``t`` of the running tracks.
    n_replicates : int
        Number of tracks R.
    trial_limit : int, optional
        Trials simulated at most (default ``settings.max_trials``, or
        :data:`DEFAULT_TRIAL_LIMIT`); tracks still going then stay ``running``.
    true_threshold_db : ndarray, optional
        Stored in the result, dB.

    Returns
    -------
    SimulatedQuestPlus

    Raises
    ------
    ProcedureError
        If ``n_replicates`` < 1 or ``respond`` answers the wrong number of tracks.

    Examples
    --------
    >>> s = QuestPlusSettings(0.0, 20.0, max_trials=5)
    >>> run_quest_plus(s, lambda t, rows, lv: lv > 8.0, 3).n_trials.tolist()
    [5, 5, 5]
    """
    s = settings
    n = int(n_replicates)
    if n < 1:
        raise ProcedureError(f"n_replicates must be ≥ 1, got {n}")
    tb = tables(s)
    limit = trial_limit if trial_limit is not None else (s.max_trials or DEFAULT_TRIAL_LIMIT)
    first = int(np.searchsorted(tb.levels_db, tb.first_level_db))
    # The running tracks' posteriors, in track order (rows leave as their tracks stop), and
    # both answers' likelihoods in one table: a trial gathers each track's row once.
    post = np.repeat(tb.prior[None], n, axis=0)
    answer_tables = np.stack((tb.p_wrong, tb.p_correct))
    idx = np.full(n, first, dtype=np.intp)
    shape = (n, limit)
    levels = np.full(shape, np.nan)
    correct = np.zeros(shape, dtype=bool)
    mean = np.full(shape, np.nan)
    sd = np.full(shape, np.nan)
    n_trials = np.zeros(n, dtype=np.int64)
    status = np.full(n, "running", dtype="<U9")
    active = np.arange(n)
    # One compiled pass per track (numpy's numbers) where the placement is compiled too (the
    # screened psi-marginal, many tracks); elsewhere loading numba would cost what it saves.
    screened = s.entropy_over == "threshold" and tb.prior.shape[1] > 1
    loops = compiled_loops("update_loops") if screened and n >= COMPILED_FROM else None
    for t in range(limit):
        if active.size == 0:
            break
        a = active
        lv = tb.levels_db[idx[a]]
        c = np.asarray(respond(t, a, lv), dtype=bool)
        if c.shape != a.shape:
            raise ProcedureError(f"respond() gave {c.shape} answers for {a.size} running tracks")
        # Normalised one track at a time, as QuestPlus.update does, so replays agree bit for bit.
        if loops is not None:
            loops.update_posteriors(post, answer_tables, c.astype(np.intp), idx[a])
        else:
            post *= answer_tables[c.astype(np.intp), idx[a]]
            post /= post.reshape(a.size, -1).sum(axis=1)[:, None, None]
        m, d = threshold_moments(tb, post)
        levels[a, t], correct[a, t], mean[a, t], sd[a, t] = lv, c, m, d
        n_trials[a] = t + 1
        st = stop_status(s, n_trials[a], m, d)
        status[a] = st
        going = st == "running"
        if not going.all():
            active, post = a[going], post[going]
        if active.size:
            idx[active] = best_levels(tb, post, s.entropy_over)
    width = int(n_trials.max()) if n else 0
    return SimulatedQuestPlus(
        settings=s,
        levels_db=levels[:, :width],
        correct=correct[:, :width],
        mean_db=mean[:, :width],
        sd_db=sd[:, :width],
        n_trials=n_trials,
        status=status,
        true_threshold_db=true_threshold_db,
    )


def simulate_quest_plus(
    settings: QuestPlusSettings,
    true_threshold_db: ArrayLike,
    *,
    scale_db: float = 1.5,
    lapse: float = 0.02,
    guess: float | None = None,
    rng: np.random.Generator,
    n_trials: int | None = None,
    part_of: tuple[int, int] | None = None,
) -> SimulatedQuestPlus:
    """Run one track per simulated observer.

    Parameters
    ----------
    settings : QuestPlusSettings
        The rules, levels in the unit of ``true_threshold_db``.
    true_threshold_db : array of shape (R,)
        Each observer's threshold (the level where p(correct) = ``settings.p_at_threshold``), dB.
    scale_db, lapse : float
        The observers' logistic scale (dB) and lapse rate (they need not be on the settings'
        grids: a misspecified model is a legitimate simulation).
    guess : float, optional
        The observers' guess rate (default the settings', 1/``n_intervals``).
    rng : numpy.random.Generator
        Source of the answers; one uniform per replicate per trial.
    n_trials : int, optional
        Trial limit of the simulation (default ``settings.max_trials``).
    part_of : (first, total), optional
        These observers are rows ``first``… of a run of ``total`` observers with the same
        ``rng``: each trial draws the ``total`` uniforms of that run and uses these rows'
        ones, so the part's tracks answer as in the whole run (a run split across
        processes; BLAS may sum a product's row in another order for fewer rows, which moves
        a posterior mean by an ulp at most). Default: the run is these observers alone.

    Returns
    -------
    SimulatedQuestPlus

    Raises
    ------
    ProcedureError
        If a threshold is not finite or ``part_of`` does not hold these observers.

    Examples
    --------
    >>> s = QuestPlusSettings(-20.0, 45.0, scales_db=1.5, lapses=0.02,  # slope, lapse known
    ...                       target_sd_db=1.08, max_trials=100)
    >>> sim = simulate_quest_plus(s, np.full(20, 10.0), rng=np.random.default_rng(1))
    >>> bool(np.all(sim.status == "completed")), bool(np.median(sim.n_trials) < 40)
    (True, True)
    """
    thr = np.asarray(true_threshold_db, dtype=float).reshape(-1)
    if not np.all(np.isfinite(thr)):
        raise ProcedureError("true_threshold_db must be finite dB values (no NaN or ±inf)")
    g = settings.guess if guess is None else float(guess)
    psy = Psychometric(0.0, scale_db, g, lapse, settings.p_at_threshold)
    first, size = (0, thr.size) if part_of is None else (int(part_of[0]), int(part_of[1]))
    if first < 0 or first + thr.size > size:
        raise ProcedureError(
            f"part_of={part_of}: {thr.size} observers from row {first} do not fit in a run "
            f"of {size}"
        )

    def respond(_t: int, rows: NDArray[np.intp], lv: NDArray[np.float64]) -> NDArray[np.bool_]:
        u = rng.random(size)  # one draw per replicate per trial keeps streams aligned
        return u[first + rows] < psy.p_correct(lv - thr[rows])

    return run_quest_plus(settings, respond, thr.size, trial_limit=n_trials, true_threshold_db=thr)


def replay_many(settings: QuestPlusSettings, correct: ArrayLike) -> SimulatedQuestPlus:
    """One track per row of an answer matrix (the vectorised
    :func:`masking_lab.procedures.quest_plus.replay`); answers after a track stops are ignored.

    Examples
    --------
    >>> s = QuestPlusSettings(0.0, 20.0, max_trials=3)
    >>> replay_many(s, [[True, True, True, True]]).n_trials.tolist()
    [3]
    """
    m = np.asarray(correct, dtype=bool)
    if m.ndim != 2:
        raise ProcedureError(f"answers must be a 2-D matrix (tracks × trials), got {m.shape}")
    limit = m.shape[1] if settings.max_trials is None else min(m.shape[1], settings.max_trials)
    return run_quest_plus(settings, lambda t, rows, _lv: m[rows, t], m.shape[0], trial_limit=limit)
