"""QUEST+ and psi-marginal threshold tracks on a dB grid (pure: no I/O, no clock, no RNG).

QUEST+ (Watson 2017) keeps a posterior over a grid of psychometric-function parameters and
plays, on every trial, the level of a stimulus grid whose answer is expected to leave the least
posterior entropy. Here the parameters are the threshold (dB; the level where p(correct) equals
``p_at_threshold``, 0.794 by default, as in :class:`masking_lab.core.psychometric.Psychometric`
and the ML estimator) and, optionally, the logistic scale and the lapse rate as nuisance
parameters. With more than one scale or lapse value, ``entropy_over="threshold"`` (the default)
is the psi-marginal method (Prins 2013): the expected entropy is that of the *marginal*
posterior of the threshold, so no trials are spent pinning down the slope for its own sake;
``entropy_over="all"`` is Watson's joint entropy. With one scale and one lapse both are the same.

Model: p(correct | x) = γ + (1 − γ − λ)·F((x − α)/s), F the logistic CDF, γ = 1/``n_intervals``
(1/3 for 3IFC), α = threshold − s·logit((p_at_threshold − γ)/(1 − γ − λ)).

A :class:`QuestPlus` is an immutable snapshot; :meth:`QuestPlus.update` returns the next one.
The posterior after a list of answers does not depend on anything else, so
:func:`masking_lab.procedures.base.replay` rebuilds a track exactly. The likelihood table and
the first level depend on the settings only and are computed once per settings object
(:func:`tables`, an LRU cache keyed by the frozen, hashable settings).

References: Watson A.B. (2017) QUEST+: a general multidimensional Bayesian adaptive
psychometric method. J Vis 17(3):10. Prins N. (2013) The psi-marginal adaptive method: how to
give nuisance parameters the attention they deserve (no more, no less). J Vis 13(7):3.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from typing import Any, Literal, TypeGuard

import numpy as np
from numpy.typing import NDArray

from masking_lab.core.errors import ProcedureError
from masking_lab.core.psychometric import LEVITT_1U3D
from masking_lab.procedures.base import ThresholdEstimate, settings_from_mapping
from masking_lab.procedures.base import replay as _replay
from masking_lab.procedures.limits import grid_memory_problem, grid_points, normal_prior_problem
from masking_lab.procedures.psi_screen import best_levels
from masking_lab.procedures.quest_plus_model import (
    EntropyOver,
    PosteriorTrack,
    expected_entropy,
    grid_db,
    psychometric_table,
)

__all__ = [
    "DEFAULT_LAPSES",
    "DEFAULT_SCALES_DB",
    "QuestPlus",
    "QuestPlusSettings",
    "Tables",
    "best_levels",
    "expected_entropy",
    "replay",
    "stop_status",
    "tables",
    "threshold_moments",
]

Status = Literal["running", "completed", "ceiling", "floor", "trial_cap"]

#: Default grid of the logistic scale, dB: a third to three times the simulated observer's
#: 1.5 dB. Marginalised (psi-marginal), so intervals hold when the slope is not known.
DEFAULT_SCALES_DB = (0.5, 0.75, 1.1, 1.5, 2.2, 3.0, 4.5)
#: Default grid of the lapse rate. It reaches past 0.08 because a flat prior whose edge is the
#: observer's lapse pulls the estimate inward and the intervals undercover there
#: (docs/procedures.md, "Intervals when the observer is not the model").
DEFAULT_LAPSES = (0.0, 0.04, 0.08, 0.12)


@dataclass(frozen=True)
class QuestPlusSettings:
    """Settings of a QUEST+ / psi-marginal track. All levels in dB (the session's unit).

    Attributes
    ----------
    min_level_db, max_level_db : float
        The stimulus range, dB (the runner passes the device limit as ``max_level_db``).
    level_step_db : float
        Spacing of the stimulus grid, dB (0.5 by default).
    threshold_min_db, threshold_max_db : float or None
        Range of the threshold grid, dB; None takes the stimulus range.
    threshold_step_db : float or None
        Spacing of the threshold grid, dB; None takes ``level_step_db``.
    scales_db : tuple of float
        Logistic scale(s) s, dB. Several (the default, :data:`DEFAULT_SCALES_DB`): a nuisance
        parameter with a flat prior over these values, marginalised out of the estimate. One
        value: the slope is known, and the intervals hold only for an observer with that slope.
    lapses : tuple of float
        Lapse rate(s) λ, likewise (default :data:`DEFAULT_LAPSES`).
    n_intervals : int
        Intervals per trial; the guess rate is 1/``n_intervals`` (3 → 1/3).
    p_at_threshold : float
        p(correct) that defines the threshold (Levitt's 1-up-3-down 0.794 by default, so that a
        staircase and this track estimate the same level).
    prior : {"flat", "normal"}
        Prior over the threshold grid: flat, or normal with ``prior_mean_db`` and
        ``prior_sd_db`` (truncated to the grid). Scales and lapses always have flat priors.
    prior_mean_db, prior_sd_db : float or None
        Parameters of the normal prior, dB.
    entropy_over : {"threshold", "all"}
        Which posterior's expected entropy the placement minimises: the threshold's marginal
        (psi-marginal, Prins 2013) or the joint one (QUEST+, Watson 2017).
    max_trials : int or None
        Trial count stop rule. Alone, reaching it completes the track; together with
        ``target_sd_db`` it is a cap (status ``trial_cap``).
    target_sd_db : float or None
        Precision stop rule: stop once the posterior SD of the threshold is ≤ this, dB.
    min_trials : int
        Trials run at least before the precision rule may stop the track.
    bound_margin_db : float
        A track that stops with its posterior mean within this distance of the top (bottom) of
        the threshold grid ends as ``ceiling`` (``floor``): the grid did not bracket the
        threshold, and the estimate is not a threshold.
    """

    min_level_db: float
    max_level_db: float
    level_step_db: float = 0.5
    threshold_min_db: float | None = None
    threshold_max_db: float | None = None
    threshold_step_db: float | None = None
    scales_db: tuple[float, ...] = DEFAULT_SCALES_DB
    lapses: tuple[float, ...] = DEFAULT_LAPSES
    n_intervals: int = 3
    p_at_threshold: float = LEVITT_1U3D
    prior: Literal["flat", "normal"] = "flat"
    prior_mean_db: float | None = None
    prior_sd_db: float | None = None
    entropy_over: EntropyOver = "threshold"
    max_trials: int | None = 64
    target_sd_db: float | None = None
    min_trials: int = 0
    bound_margin_db: float = 1.0

    def __post_init__(self) -> None:
        for name in ("scales_db", "lapses"):
            value = getattr(self, name)
            items = (value,) if isinstance(value, int | float) else value
            object.__setattr__(self, name, tuple(float(v) for v in items))
        for name, problem in self._problems():
            raise ProcedureError(f"quest_plus setting {name}: {problem}")

    def _problems(self) -> Iterable[tuple[str, str]]:
        def finite(v: object) -> TypeGuard[float]:  # narrows the optional settings for mypy
            return isinstance(v, int | float) and math.isfinite(v)

        for name in ("min_level_db", "max_level_db", "bound_margin_db"):
            if not finite(getattr(self, name)):
                yield name, f"must be a finite number, got {getattr(self, name)!r}"
        ordered = finite(self.min_level_db) and finite(self.max_level_db)
        if ordered and not self.min_level_db < self.max_level_db:
            yield (
                "min_level_db",
                f"must be below max_level_db ({self.min_level_db} ≥ {self.max_level_db})",
            )
        for name in ("level_step_db", "threshold_step_db"):
            v = getattr(self, name)
            if v is not None and not (finite(v) and v > 0):
                yield name, f"must be a positive number of dB, got {v!r}"
        t_lo, t_hi = self.threshold_range_db
        if not (finite(t_lo) and finite(t_hi) and t_lo < t_hi):
            yield (
                "threshold_min_db",
                f"the threshold range must be finite and increasing, got {t_lo}..{t_hi} dB",
            )
        if not self.scales_db:
            yield "scales_db", "needs at least one scale"
        for s in self.scales_db:
            if not (math.isfinite(s) and s > 0):
                yield "scales_db", f"every scale must be a positive number of dB, got {s}"
        if not (isinstance(self.n_intervals, int) and self.n_intervals >= 2):
            yield "n_intervals", f"must be an integer ≥ 2, got {self.n_intervals!r}"
            return
        if not self.lapses:
            yield "lapses", "needs at least one lapse rate"
        for lam in self.lapses:
            if not 0.0 <= lam < 1.0 - self.guess:
                yield "lapses", f"every lapse rate must lie in [0, {1 - self.guess:.3f}), got {lam}"
        top = 1.0 - max(self.lapses, default=0.0)
        if not (finite(self.p_at_threshold) and self.guess < self.p_at_threshold < top):
            yield (
                "p_at_threshold",
                f"must lie between the guess rate {self.guess:.3f} and 1 − the largest lapse "
                f"({top:.3f}), got {self.p_at_threshold!r}",
            )
        if self.prior not in ("flat", "normal"):
            yield "prior", f"must be 'flat' or 'normal', got {self.prior!r}"
        if self.prior == "normal":
            if not finite(self.prior_mean_db):
                yield "prior_mean_db", "a normal prior needs a finite prior_mean_db (dB)"
            if not (finite(self.prior_sd_db) and self.prior_sd_db > 0):
                yield "prior_sd_db", "a normal prior needs a positive prior_sd_db (dB)"
        yield from self._size_problems()
        if self.entropy_over not in ("threshold", "all"):
            yield "entropy_over", f"must be 'threshold' or 'all', got {self.entropy_over!r}"
        if self.max_trials is None and self.target_sd_db is None:
            yield "max_trials", "give max_trials, target_sd_db or both: the track needs a stop rule"
        if self.max_trials is not None and not (
            isinstance(self.max_trials, int) and self.max_trials >= 1
        ):
            yield "max_trials", f"must be an integer ≥ 1 or null, got {self.max_trials!r}"
        if self.target_sd_db is not None and not (
            finite(self.target_sd_db) and self.target_sd_db > 0
        ):
            yield (
                "target_sd_db",
                f"must be a positive number of dB or null, got {self.target_sd_db!r}",
            )
        if not (isinstance(self.min_trials, int) and self.min_trials >= 0):
            yield "min_trials", f"must be an integer ≥ 0, got {self.min_trials!r}"
        elif isinstance(self.max_trials, int) and self.min_trials > self.max_trials:
            yield "min_trials", f"{self.min_trials} exceeds max_trials={self.max_trials}"
        if finite(self.bound_margin_db) and self.bound_margin_db < 0:
            yield "bound_margin_db", f"must be ≥ 0 dB, got {self.bound_margin_db}"

    def _size_problems(self) -> Iterable[tuple[str, str]]:
        """Grids that would not fit in memory, priors the grid cannot hold (checked before any
        table is built, so ``validate`` refuses what ``run`` could not run)."""
        lo, hi = self.min_level_db, self.max_level_db
        t_lo, t_hi = self.threshold_range_db
        step = self.level_step_db
        t_step = self.threshold_step_db or step
        if not all(
            isinstance(v, int | float) and math.isfinite(v) for v in (lo, hi, t_lo, t_hi)
        ) or not (step > 0 and t_step > 0):
            return
        cells = self.table_cells
        problem = grid_memory_problem(cells, "QUEST+ grid (stimuli × thresholds × nuisance)")
        if problem is not None:
            yield "level_step_db", problem
            return
        if self.prior == "normal" and isinstance(self.prior_mean_db, int | float):
            sd = self.prior_sd_db if isinstance(self.prior_sd_db, int | float) else math.nan
            bad = normal_prior_problem(self.prior_mean_db, sd, t_lo, t_hi, t_step)
            if bad is not None and math.isfinite(self.prior_mean_db) and sd > 0:
                yield bad

    @property
    def guess(self) -> float:
        """Guess rate γ = 1/``n_intervals``."""
        return 1.0 / self.n_intervals

    @property
    def threshold_range_db(self) -> tuple[float, float]:
        """(lowest, highest) threshold on the grid, dB."""
        lo = self.min_level_db if self.threshold_min_db is None else self.threshold_min_db
        hi = self.max_level_db if self.threshold_max_db is None else self.threshold_max_db
        return lo, hi

    @property
    def table_cells(self) -> int:
        """Cells of one likelihood table (stimuli × thresholds × nuisance), without building
        it (0 for settings whose grid is invalid: those are refused for that)."""
        lo, hi = self.min_level_db, self.max_level_db
        t_lo, t_hi = self.threshold_range_db
        step = self.level_step_db
        t_step = self.threshold_step_db or step
        if not all(
            isinstance(v, int | float) and math.isfinite(v) for v in (lo, hi, t_lo, t_hi, step)
        ) or not (step > 0 and isinstance(t_step, int | float) and t_step > 0):
            return 0
        cells = grid_points(lo, hi, step) * grid_points(t_lo, t_hi, t_step)
        return cells * max(1, len(self.scales_db) * len(self.lapses))

    @property
    def kind(self) -> str:
        """The protocol's name for this procedure: ``"quest_plus"``."""
        return "quest_plus"

    def start(self) -> QuestPlus:
        """A fresh track: the prior, and the level it places first.

        Examples
        --------
        >>> track = QuestPlusSettings(-20.0, 45.0, target_sd_db=1.08).start()
        >>> track.n_trials, track.finished, track.next_level() in tables(track.settings).levels_db
        (0, False, True)
        """
        t = tables(self)
        return QuestPlus(self, t.prior, t.first_level_db)

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any]) -> QuestPlusSettings:
        """Build settings from a protocol's ``quest_plus:`` mapping (keys = attribute names).

        ``scales_db`` and ``lapses`` take a number or a list; an optional ``kind`` must be
        ``quest_plus``. See docs/procedures.md for the keys and their defaults.

        Raises
        ------
        ProcedureError
            On an unknown key (the message lists the valid ones) or an invalid value.

        Examples
        --------
        >>> s = QuestPlusSettings.from_mapping(
        ...     {"min_level_db": -20, "max_level_db": 45, "scales_db": [1, 1.5, 2],
        ...      "target_sd_db": 1.08, "max_trials": 80})
        >>> s.scales_db, s.lapses   # lapses not stated: the default grid, marginalised
        ((1.0, 1.5, 2.0), (0.0, 0.04, 0.08, 0.12))
        """
        return settings_from_mapping(
            cls,
            mapping,
            "quest_plus",
            tuples=("scales_db", "lapses"),
            required=("min_level_db", "max_level_db"),
        )


@dataclass(frozen=True, eq=False)
class Tables:
    """Everything about a :class:`QuestPlusSettings` that does not depend on the answers.

    Attributes
    ----------
    levels_db : ndarray, shape (S,)
        The stimulus grid, dB.
    thresholds_db : ndarray, shape (T,)
        The threshold grid, dB.
    nuisance : ndarray, shape (N, 2)
        Every (scale dB, lapse) pair.
    p_correct, p_wrong : ndarray, shape (S, T, N)
        Likelihood of each answer at each level for each parameter point (p_wrong computed
        without cancellation, so it stays > 0 where p_correct rounds to 1).
    prior : ndarray, shape (T, N)
        The prior, summing to 1.
    first_level_db : float
        The level the prior places first.
    """

    levels_db: NDArray[np.float64]
    thresholds_db: NDArray[np.float64]
    nuisance: NDArray[np.float64]
    p_correct: NDArray[np.float64]
    p_wrong: NDArray[np.float64]
    prior: NDArray[np.float64]
    first_level_db: float

    @functools.cached_property
    def xlogx_tables(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """L·ln L of ``p_correct`` and ``p_wrong``, flattened to shape (S, T·N), nats.

        The answer-independent term of the joint expected entropy: computed on first use and
        kept with the tables, so a trial costs two matrix products instead of a logarithm of
        every table cell (only the joint path needs it, so psi-marginal grids never pay its
        memory).

        Examples
        --------
        >>> t = tables(QuestPlusSettings(0.0, 5.0, max_trials=5))
        >>> c, w = t.xlogx_tables
        >>> c.shape, bool((c <= 0).all()), t.xlogx_tables[0] is c
        ((11, 308), True, True)
        """
        out = []
        for like in (self.p_correct, self.p_wrong):
            lf = like.reshape(like.shape[0], -1)
            xlogx = lf * np.log(lf)
            xlogx.flags.writeable = False
            out.append(xlogx)
        return out[0], out[1]


@functools.lru_cache(maxsize=16)
def tables(settings: QuestPlusSettings) -> Tables:
    """The grids, likelihood table and prior of ``settings`` (cached per settings object).

    Examples
    --------
    >>> t = tables(QuestPlusSettings(0.0, 10.0, max_trials=10))
    >>> t.levels_db.size, t.thresholds_db.size, t.p_correct.shape
    (21, 21, (21, 21, 28))
    """
    s = settings
    levels = grid_db(s.min_level_db, s.max_level_db, s.level_step_db)
    t_lo, t_hi = s.threshold_range_db
    thresholds = grid_db(t_lo, t_hi, s.threshold_step_db or s.level_step_db)
    nuisance = np.array([(sc, lam) for sc in s.scales_db for lam in s.lapses], dtype=float)
    p_c, p_w = psychometric_table(levels, thresholds, nuisance, s.guess, s.p_at_threshold)
    if s.prior == "normal":
        assert s.prior_mean_db is not None and s.prior_sd_db is not None
        w = np.exp(-0.5 * ((thresholds - s.prior_mean_db) / s.prior_sd_db) ** 2)
    else:
        w = np.ones(thresholds.size)
    prior = np.repeat(w[:, None], nuisance.shape[0], axis=1)
    prior /= prior.sum()
    partial = Tables(levels, thresholds, nuisance, p_c, p_w, prior, math.nan)
    first = float(levels[int(np.argmin(expected_entropy(partial, prior[None], s.entropy_over)))])
    out = replace(partial, first_level_db=first)
    for a in (levels, thresholds, nuisance, p_c, p_w, prior):
        a.flags.writeable = False
    return out


def threshold_moments(
    t: Tables, posterior: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Posterior mean and SD of the threshold (dB) of each of R posteriors (R, T, N)."""
    marginal = posterior.sum(axis=2)
    mean = marginal @ t.thresholds_db
    var = np.einsum("rt,rt->r", marginal, (t.thresholds_db[None, :] - mean[:, None]) ** 2)
    return mean, np.sqrt(np.maximum(var, 0.0))


def stop_status(
    settings: QuestPlusSettings,
    n_trials: NDArray[np.int64],
    mean_db: NDArray[np.float64],
    sd_db: NDArray[np.float64],
) -> NDArray[np.str_]:
    """Status of R tracks after ``n_trials`` answers with these posterior moments.

    ``running`` until a stop rule holds; then ``ceiling``/``floor`` if the posterior mean lies
    within ``bound_margin_db`` of the threshold grid's top/bottom, else ``completed`` (precision
    reached, or the trial count when that is the only rule) or ``trial_cap``.
    """
    s = settings
    precise = np.zeros(n_trials.shape, dtype=bool)
    if s.target_sd_db is not None:
        precise = (n_trials >= s.min_trials) & (sd_db <= s.target_sd_db)
    capped = n_trials >= s.max_trials if s.max_trials is not None else np.zeros_like(precise)
    status = np.full(n_trials.shape, "running", dtype="<U9")
    cap_name = "completed" if s.target_sd_db is None else "trial_cap"
    status[capped] = cap_name
    status[precise] = "completed"
    lo, hi = s.threshold_range_db
    stopped = precise | capped
    status[stopped & (mean_db >= hi - s.bound_margin_db)] = "ceiling"
    status[stopped & (mean_db <= lo + s.bound_margin_db)] = "floor"
    return status


@dataclass(frozen=True, eq=False)
class QuestPlus(PosteriorTrack):
    """Immutable state of one QUEST+ / psi-marginal track.

    Attributes
    ----------
    settings : QuestPlusSettings
        The rules.
    posterior : ndarray, shape (T, N)
        Posterior over (threshold, nuisance) grid points, summing to 1 (read-only).
    level_db : float
        Level of the next trial, dB (on the stimulus grid).
    levels_db : tuple of float
        Level of every trial so far, dB.
    responses : tuple of bool
        Whether each trial was answered correctly.
    status : {"running", "completed", "ceiling", "floor", "trial_cap"}
        ``running`` until a stop rule holds.
    """

    settings: QuestPlusSettings
    posterior: NDArray[np.float64]
    level_db: float
    levels_db: tuple[float, ...] = ()
    responses: tuple[bool, ...] = ()
    status: Status = "running"

    def next_level(self) -> float:
        """The level of the next trial, dB (the grid level of least expected entropy)."""
        return self.level_db

    @property
    def threshold_posterior(self) -> NDArray[np.float64]:
        """Marginal posterior over :attr:`Tables.thresholds_db` (sums to 1)."""
        return self.posterior.sum(axis=1)

    @property
    def posterior_mean_db(self) -> float:
        """Posterior mean of the threshold, dB."""
        return float(threshold_moments(tables(self.settings), self.posterior[None])[0][0])

    @property
    def posterior_sd_db(self) -> float:
        """Posterior SD of the threshold, dB."""
        return float(threshold_moments(tables(self.settings), self.posterior[None])[1][0])

    def update(self, correct: bool) -> QuestPlus:
        """The track after one trial at :meth:`next_level` answered ``correct``.

        Raises
        ------
        ProcedureError
            If the track has finished.

        Examples
        --------
        >>> track = QuestPlusSettings(-20.0, 45.0, max_trials=2).start()
        >>> track.update(True).update(False).status
        'completed'
        """
        if self.finished:
            raise ProcedureError(
                f"the QUEST+ track has finished ({self.status}); it takes no more responses"
            )
        t = tables(self.settings)
        correct = bool(correct)
        i = int(np.searchsorted(t.levels_db, self.level_db))
        like = (t.p_correct if correct else t.p_wrong)[i]
        post = self.posterior * like
        post /= post.sum()
        post.flags.writeable = False
        n = self.n_trials + 1
        mean, sd = threshold_moments(t, post[None])
        status = str(stop_status(self.settings, np.array([n]), mean, sd)[0])
        level = self.level_db
        if status == "running":
            level = float(
                t.levels_db[int(best_levels(t, post[None], self.settings.entropy_over)[0])]
            )
        return QuestPlus(
            self.settings,
            post,
            level,
            (*self.levels_db, self.level_db),
            (*self.responses, correct),
            status,  # type: ignore[arg-type]  # stop_status yields only the Status names
        )

    def estimate(self) -> ThresholdEstimate:
        """Posterior mean and SD of the threshold; ``level_db`` None unless ``completed``.

        Examples
        --------
        >>> QuestPlusSettings(-20.0, 45.0, max_trials=3).start().estimate().method
        'posterior_mean'
        """
        level = self.posterior_mean_db if self.status == "completed" else None
        return ThresholdEstimate(
            level_db=level, sd_db=self.posterior_sd_db, method="posterior_mean", status=self.status
        )

    def trial_summary(self) -> dict[str, float]:
        """Finite numbers for the per-trial log: posterior mean and SD (dB), next level (dB).

        Examples
        --------
        >>> sorted(QuestPlusSettings(-20.0, 45.0, max_trials=3).start().trial_summary())
        ['next_level_db', 'posterior_mean_db', 'posterior_sd_db']
        """
        mean, sd = threshold_moments(tables(self.settings), self.posterior[None])
        return {
            "posterior_mean_db": float(mean[0]),
            "posterior_sd_db": float(sd[0]),
            "next_level_db": float(self.level_db),
        }


def replay(settings: QuestPlusSettings, responses: Iterable[bool]) -> QuestPlus:
    """Rebuild a track from its answers (see :func:`masking_lab.procedures.base.replay`).

    Examples
    --------
    >>> s = QuestPlusSettings(-20.0, 45.0, max_trials=10)
    >>> replay(s, [True, False]) == s.start().update(True).update(False)
    True
    """
    state = _replay(settings, responses)
    assert isinstance(state, QuestPlus)
    return state
