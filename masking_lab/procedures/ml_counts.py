"""Sufficient statistics of staircase tracks, and the likelihood of a forced-choice logistic.

A staircase visits a dozen or two distinct levels, so the binomial likelihood of a track depends
only on its trials and correct answers per distinct level (:class:`LevelCounts`).
:func:`index_levels` sorts each track's trials once (:class:`LevelIndex`) so that counts for any
prefix of every track — a shorter stop rule, a trial cap — come without sorting again.
:class:`LogisticModel` and :func:`log_likelihood` evaluate the model
``p(x) = γ + (1 − γ − λ)·F((x − α)/s)`` (levels and scale in dB) on those counts, with the
derivatives the batch fitter (:mod:`masking_lab.procedures.ml_batch`) climbs. Pure numpy.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from types import ModuleType

import numpy as np
from numpy.typing import ArrayLike, NDArray

from masking_lab.core.errors import AnalysisError
from masking_lab.core.psychometric import GUESS_3IFC, LEVITT_1U3D
from masking_lab.procedures.fused import compiled_loops

__all__ = [
    "LevelCounts",
    "LevelIndex",
    "LogisticModel",
    "index_levels",
    "level_counts",
    "log_likelihood",
    "logistic_model",
]


@dataclass(frozen=True)
class LevelCounts:
    """Trials per distinct level of each track (zero-padded to the longest row).

    Attributes
    ----------
    level_db : ndarray, shape (R, U)
        Distinct levels visited by each track, dB (ascending; padding repeats the last level).
    n_trials : ndarray, shape (R, U)
        Trials at each level.
    n_correct : ndarray, shape (R, U)
        Correct answers at each level.
    """

    level_db: NDArray[np.float64]
    n_trials: NDArray[np.float64]
    n_correct: NDArray[np.float64]

    @functools.cached_property
    def n_wrong(self) -> NDArray[np.float64]:
        """Wrong answers at each level (n_trials − n_correct), computed once per counts."""
        return self.n_trials - self.n_correct

    @functools.cached_property
    def any_correct(self) -> NDArray[np.bool_]:
        """Levels with at least one correct answer (where ln p(correct) is weighed)."""
        return self.n_correct > 0

    @functools.cached_property
    def any_wrong(self) -> NDArray[np.bool_]:
        """Levels with at least one wrong answer (where ln p(wrong) is weighed)."""
        return self.n_wrong > 0

    @functools.cached_property
    def floor_correct(self) -> NDArray[np.float64]:
        """Least p(correct) per level: the smallest normal float where a correct answer is
        weighed, 1 where none is (ln 1 = +0, so the term vanishes without a masked logarithm)."""
        return np.maximum(self.n_correct == 0, np.finfo(float).tiny)

    @functools.cached_property
    def floor_wrong(self) -> NDArray[np.float64]:
        """Least p(wrong) per level, as :attr:`floor_correct` for the wrong answers."""
        return np.maximum(self.n_wrong == 0, np.finfo(float).tiny)

    @functools.cached_property
    def no_correct(self) -> NDArray[np.bool_]:
        """Levels without a correct answer (the complement of :attr:`any_correct`)."""
        return ~self.any_correct

    @functools.cached_property
    def no_wrong(self) -> NDArray[np.bool_]:
        """Levels without a wrong answer (the complement of :attr:`any_wrong`)."""
        return ~self.any_wrong


@dataclass(frozen=True)
class LevelIndex:
    """Each trial's place among its track's distinct levels, computed once per set of tracks.

    :meth:`counts` then gives the counts for any prefix of every track (a shorter stop rule, a
    trial cap) without sorting again.

    Attributes
    ----------
    level_db : ndarray, shape (R, U)
        Distinct levels of each track, ascending, dB (padding repeats the row's last level).
    trial_level : ndarray of int, shape (R, T)
        Column of ``level_db`` holding each trial's level (−1: no trial).
    correct : ndarray of bool, shape (R, T)
        Answers.
    """

    level_db: NDArray[np.float64]
    trial_level: NDArray[np.int64]
    correct: NDArray[np.bool_]

    def counts(
        self, n_trials: ArrayLike | None = None, rows: ArrayLike | None = None
    ) -> LevelCounts:
        """Counts over the first ``n_trials[i]`` trials of each track (all trials if None).

        Parameters
        ----------
        n_trials : array of int, shape (R,), optional
            Trials of each track to count.
        rows : array of int, optional
            Only these tracks (the result has one row per entry).
        """
        group = self.trial_level
        correct = self.correct
        level = self.level_db
        use = group >= 0
        if n_trials is not None:
            use = use & (np.arange(group.shape[1])[None, :] < np.asarray(n_trials)[:, None])
        if rows is not None:
            idx = np.asarray(rows, dtype=np.intp)
            group, correct, level, use = group[idx], correct[idx], level[idx], use[idx]
        n_rows, n_groups = level.shape
        flat = (np.arange(n_rows)[:, None] * n_groups + group)[use]
        size = n_rows * n_groups
        n = np.bincount(flat, minlength=size).astype(float).reshape(n_rows, n_groups)
        # weighted bincount is float64 already (its stubs say int): asarray only retypes, no copy
        k_flat = np.bincount(flat, weights=correct[use], minlength=size)
        k = np.asarray(k_flat, dtype=np.float64).reshape(n_rows, n_groups)
        return LevelCounts(level, n, k)


def index_levels(levels_db: ArrayLike, correct: ArrayLike) -> LevelIndex:
    """Find each track's distinct levels (see :class:`LevelIndex`).

    Parameters
    ----------
    levels_db : array, shape (R, T)
        Trial levels in dB; NaN marks no trial (past a track's end).
    correct : array of bool, shape (R, T)
        Answers.

    Raises
    ------
    AnalysisError
        If the arrays are not matching 2-D arrays.
    """
    lv = np.asarray(levels_db, dtype=float)
    ok = np.asarray(correct, dtype=bool)
    if lv.ndim != 2 or lv.shape != ok.shape:
        raise AnalysisError(
            f"levels and answers must be matching 2-D (tracks × trials) arrays, got "
            f"{lv.shape} and {ok.shape}"
        )
    n_rows = lv.shape[0]
    keyed = np.where(np.isnan(lv), np.inf, lv)
    order = np.argsort(keyed, axis=1, kind="stable")
    x = np.take_along_axis(keyed, order, axis=1)
    valid = np.isfinite(x)
    new = np.ones_like(valid)
    new[:, 1:] = x[:, 1:] != x[:, :-1]
    group = np.cumsum(new, axis=1) - 1
    n_groups = int(group[valid].max()) + 1 if valid.any() else 1
    level = np.full((n_rows, n_groups), np.nan)
    rows = np.broadcast_to(np.arange(n_rows)[:, None], x.shape)
    level[rows[valid], group[valid]] = x[valid]
    # Padding repeats each row's last level so that it is a harmless finite number.
    seen = np.where(np.isnan(level), 0, np.arange(n_groups))
    level = np.take_along_axis(level, np.maximum.accumulate(seen, axis=1), axis=1)
    level = np.where(np.isnan(level), 0.0, level)  # rows without any trial
    trial_level = np.full(lv.shape, -1, dtype=np.int64)
    np.put_along_axis(trial_level, order, np.where(valid, group, -1), axis=1)
    return LevelIndex(level, trial_level, ok)


def level_counts(levels_db: ArrayLike, correct: ArrayLike) -> LevelCounts:
    """Reduce tracks to counts per distinct level (the likelihood's sufficient statistics).

    Takes the arrays of :func:`index_levels` (levels in dB, NaN past a track's end).

    Examples
    --------
    >>> c = level_counts([[-20.0, -20.0, -22.0, float("nan")]], [[True, True, False, False]])
    >>> c.level_db.tolist(), c.n_trials.tolist(), c.n_correct.tolist()
    ([[-22.0, -20.0]], [[1.0, 2.0]], [[0.0, 2.0]])
    """
    return index_levels(levels_db, correct).counts()


# --------------------------------------------------------------------------------------------
# The likelihood


def _logistic_parts(
    counts: LevelCounts, threshold_db: NDArray[np.float64], scale_db: NDArray[np.float64], c: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """y = (x − t)/s, F(y + c) and 1 − F(y + c) without cancellation or overflow (one exp).

    ``c`` = logit of the rise fraction at ``p_target``, so that p(t) = p_target.
    """
    y = (counts.level_db - threshold_db[:, None]) / scale_db[:, None]
    z = y + c
    e = np.exp(-np.abs(z))
    d = 1.0 + e
    # F = 1/d where z ≥ 0, else e/d; 1 − F the other one. Picked by maxima (0 ≤ e ≤ 1; with
    # h = 1 where z ≥ 0, max(e, h) is the numerator of F): a masked select costs more.
    h = np.heaviside(z, 1.0, out=z)
    f = np.maximum(e, h)
    np.subtract(1.0, h, out=h)
    g = np.maximum(e, h, out=h)
    f /= d
    g /= d
    return y, f, g


@dataclass(frozen=True)
class LogisticModel:
    """The forced-choice logistic with γ and λ fixed, parametrised by its threshold.

    Attributes
    ----------
    guess : float
        γ, p(correct) far below threshold.
    lapse : float
        λ, p(wrong) far above threshold.
    c : float
        logit((p_target − γ)/(1 − γ − λ)): threshold = α + s·c (dimensionless).
    compiled : bool
        Evaluate with the compiled loops of :mod:`masking_lab.procedures.ml_loops` when numba
        loads (the same numbers; worth numba's load only for many tracks).
    """

    guess: float
    lapse: float
    c: float
    compiled: bool = False

    @property
    def rise(self) -> float:
        """1 − γ − λ: the part of p(correct) the psychometric function spans."""
        return 1.0 - self.guess - self.lapse

    def log_likelihood(
        self, counts: LevelCounts, threshold_db: NDArray[np.float64], scale_db: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """Log-likelihood (natural log) per track at threshold ``threshold_db`` and scale
        ``scale_db`` (both dB, shape (R,))."""
        fused = self._fused_args(counts, threshold_db, scale_db)
        if fused is not None:
            loops, step, e = fused
            k, m = counts.n_correct, counts.n_wrong
            p, q = np.empty_like(e), np.empty_like(e)
            loops.answer_probabilities(step, e, k, m, self.rise, self.guess, self.lapse, p, q)
            np.log(p, out=p)
            np.log(q, out=q)
            ll = np.empty(e.shape[0])
            loops.weighed_sums(p, q, k, m, ll)
            return ll
        # The arithmetic of _logistic_parts, then p and q, in a few work arrays updated in
        # place (the fits call this ~10⁴ times: fresh temporaries cost more than the maths).
        # Every rounded operation and its order are those of _logistic_parts and derivatives,
        # so the sums are the same numbers bit for bit (tests/test_ml_likelihood_terms.py).
        z = self._z(counts, threshold_db, scale_db)
        # Selections by maxima, not masks (numpy's masked loops cost ~10× a plain pass): with
        # h = 1 where z ≥ 0 and 0 elsewhere, max(e, h) is 1 or e and max(e, 1 − h) is e or 1
        # (0 ≤ e ≤ 1), the numerators of F(z) and 1 − F(z); the quotients are those of
        # _logistic_parts exactly.
        e = np.abs(z)
        np.negative(e, out=e)
        np.exp(e, out=e)
        d = e + 1.0
        h = np.heaviside(z, 1.0, out=z)
        p = np.maximum(e, h)
        np.subtract(1.0, h, out=h)
        q = np.maximum(e, h, out=h)
        p /= d
        q /= d
        p *= self.rise
        p += self.guess
        q *= self.rise
        q += self.lapse  # 1 − p without cancellation
        # k·ln p + (n − k)·ln q. Where a weight is 0 the floor is 1 instead of the smallest
        # normal float: ln 1 = +0 and +0·0 = +0, the number the masked form puts there (p and
        # q never exceed 1, so the floor changes no weighed term and no other).
        np.maximum(p, counts.floor_correct, out=p)
        np.maximum(q, counts.floor_wrong, out=q)
        np.log(p, out=p)
        np.log(q, out=q)
        p *= counts.n_correct
        q *= counts.n_wrong
        p += q
        ll = p.sum(axis=1)
        # A row sums to NaN here exactly when its z holds a NaN (p and q lie in [tiny, 1]
        # otherwise); NaN must then count only where a term is weighed, as the masked form has
        # it. Checking the sums, not z, saves two passes over the array.
        if np.isnan(ll).any():
            return self._log_likelihood_masked(counts, self._z(counts, threshold_db, scale_db))
        return ll

    def _fused_args(
        self, counts: LevelCounts, threshold_db: NDArray[np.float64], scale_db: NDArray[np.float64]
    ) -> tuple[ModuleType, NDArray[np.float64], NDArray[np.float64]] | None:
        """For the compiled route: its loops, heaviside(z, 1) and exp(−|z|) at every level; None
        for the numpy route (not :attr:`compiled`, numba missing, or a NaN in z, whose terms
        only the numpy route weighs as it should)."""
        if not self.compiled:
            return None
        loops = compiled_loops("ml_loops")
        if loops is None:
            return None
        step, e = np.empty(counts.level_db.shape), np.empty(counts.level_db.shape)
        if loops.logistic_args(counts.level_db, threshold_db, scale_db, self.c, step, e):
            return None
        np.exp(e, out=e)
        return loops, step, e

    def _z(
        self, counts: LevelCounts, threshold_db: NDArray[np.float64], scale_db: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """(x − t)/s + c, the logistic's argument at every level (a fresh array)."""
        z = counts.level_db - threshold_db[:, None]
        z /= scale_db[:, None]
        z += self.c
        return z

    def _log_likelihood_masked(
        self, counts: LevelCounts, z: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """:meth:`log_likelihood` from z = (x − t)/s + c, skipping the logarithms whose
        weight is 0, so that a NaN in z leaves such a term 0."""
        pos = z >= 0
        e = np.abs(z)
        np.negative(e, out=e)
        np.exp(e, out=e)
        d = e + 1.0
        p = np.divide(1.0, d)  # 1/(1 + e): F(z) where z ≥ 0
        np.divide(e, d, out=e)  # e/(1 + e): F(z) where z < 0
        q = np.where(pos, e, p)  # 1 − F(z) without cancellation
        np.copyto(p, e, where=~pos)  # F(z)
        tiny = np.finfo(float).tiny
        p *= self.rise
        p += self.guess
        np.maximum(p, tiny, out=p)
        q *= self.rise
        q += self.lapse
        np.maximum(q, tiny, out=q)
        np.log(p, out=p, where=counts.any_correct)
        np.log(q, out=q, where=counts.any_wrong)
        np.copyto(p, 0.0, where=counts.no_correct)
        np.copyto(q, 0.0, where=counts.no_wrong)
        p *= counts.n_correct
        q *= counts.n_wrong
        p += q
        return p.sum(axis=1)

    def derivatives(
        self, counts: LevelCounts, threshold_db: NDArray[np.float64], scale_db: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], ...]:
        """Gradient and Hessian of the log-likelihood in (t, u = ln s), per track.

        Returns (g_t, g_u, H_tt, H_tu, H_uu, I_tt, I_tu, I_uu): gradient, observed Hessian and
        expected (Fisher) information, each of shape (R,).
        """
        fused = self._fused_args(counts, threshold_db, scale_db)
        if fused is not None:
            loops, step, e = fused
            out = np.empty((8, e.shape[0]))
            loops.slope_sums(
                counts.level_db, threshold_db, scale_db, step, e, counts.n_trials,
                counts.n_correct, counts.n_wrong, self.rise, self.guess, self.lapse, out,
            )  # fmt: skip
            return tuple(out)
        y, p, q, h, h2, w, curv = self._slopes(counts, threshold_db, scale_db)
        # The products of the formulas (−h/s, −h·y, h″/s², (h″·y + h)/s, h″·y² + h·y, then
        # w·a + curv·b·c), in order, into few arrays: fresh ones cost more than the maths.
        s = scale_db[:, None]
        info = np.multiply(p, q, out=p)
        np.divide(counts.n_trials, info, out=info)
        dt = np.negative(h)
        dt /= s
        du = np.negative(h)
        du *= y
        dtt = h2 / s**2
        dtu = h2 * y
        dtu += h
        dtu /= s
        duu = np.multiply(y, y, out=q)  # y² as y**2 computes it
        duu *= h2
        np.multiply(h, y, out=h)
        duu += h
        a, b = h2, y  # free now: work arrays for the sums

        def weighed(x: NDArray[np.float64]) -> NDArray[np.float64]:
            """Σ w·x per track."""
            return np.multiply(w, x, out=a).sum(axis=1)

        def curved(
            x: NDArray[np.float64], u: NDArray[np.float64], v: NDArray[np.float64]
        ) -> NDArray[np.float64]:
            """Σ (w·x + curv·u·v) per track."""
            np.multiply(w, x, out=a)
            np.multiply(curv, u, out=b)
            np.multiply(b, v, out=b)
            return np.add(a, b, out=a).sum(axis=1)

        def informed(u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
            """Σ info·u·v per track."""
            np.multiply(info, u, out=a)
            return np.multiply(a, v, out=a).sum(axis=1)

        return (
            weighed(dt),
            weighed(du),
            curved(dtt, dt, dt),
            curved(dtu, dt, du),
            curved(duu, du, du),
            informed(dt, dt),
            informed(dt, du),
            informed(du, du),
        )

    def threshold_derivatives(
        self, counts: LevelCounts, threshold_db: NDArray[np.float64], scale_db: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Score and observed curvature in t alone (g_t, H_tt of :meth:`derivatives`, the same
        numbers), for the fixed-scale fits that need no more."""
        fused = self._fused_args(counts, threshold_db, scale_db)
        if fused is not None:
            loops, step, e = fused
            out = np.empty((2, e.shape[0]))
            loops.threshold_slope_sums(
                scale_db, step, e, counts.n_correct, counts.n_wrong, self.rise, self.guess,
                self.lapse, out,
            )  # fmt: skip
            return out[0], out[1]
        _, _, _, h, h2, w, curv = self._slopes(counts, threshold_db, scale_db)
        s = scale_db[:, None]
        dt = -h / s
        dtt = h2 / s**2
        return (w * dt).sum(axis=1), (w * dtt + curv * dt * dt).sum(axis=1)

    def _slopes(
        self, counts: LevelCounts, threshold_db: NDArray[np.float64], scale_db: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], ...]:
        """y, p, q, dp/dz, d²p/dz², the score weight w and the curvature weight per level."""
        y, f, g = _logistic_parts(counts, threshold_db, scale_db, self.c)
        tiny = np.finfo(float).tiny
        # γ + (1 − γ − λ)·F, λ + (1 − γ − λ)·(1 − F), (1 − γ − λ)·F·(1 − F), that·(G − F),
        # k/p − m/q and −(k/p² + m/q²), in place where an operand is not needed again.
        p = self.rise * f
        p += self.guess
        np.maximum(p, tiny, out=p)
        q = self.rise * g
        q += self.lapse
        np.maximum(q, tiny, out=q)
        h = self.rise * f  # dp/dz
        h *= g
        h2 = np.subtract(g, f, out=f)  # d²p/dz²
        h2 *= h
        k, m = counts.n_correct, counts.n_wrong
        w = k / p
        w -= m / q
        curv = np.multiply(p, p, out=g)  # p² as p**2 computes it
        np.divide(k, curv, out=curv)
        q2 = q * q
        np.divide(m, q2, out=q2)
        curv += q2
        np.negative(curv, out=curv)
        return y, p, q, h, h2, w, curv


def log_likelihood(
    counts: LevelCounts,
    threshold_db: ArrayLike,
    scale_db: float,
    *,
    guess: float = GUESS_3IFC,
    lapse: float = 0.02,
    p_target: float = LEVITT_1U3D,
) -> NDArray[np.float64]:
    """Binomial log-likelihood (natural log) of each track for a threshold and scale.

    Parameters
    ----------
    counts : LevelCounts
        From :func:`level_counts`.
    threshold_db : array, shape (R,)
        Level where p(correct) = ``p_target``, per track, dB.
    scale_db : float
        Logistic scale s, dB.
    guess, lapse, p_target : float
        γ, λ and the p defining the threshold.
    """
    model = logistic_model(guess, lapse, p_target)
    t = np.asarray(threshold_db, dtype=float).reshape(-1)
    return model.log_likelihood(counts, t, np.full(t.shape, float(scale_db)))


def logistic_model(guess: float, lapse: float, p_target: float) -> LogisticModel:
    """Check γ, λ and p_target (probabilities) and build the model.

    Raises
    ------
    AnalysisError
        Unless 0 ≤ γ < 1, 0 ≤ λ < 1 − γ and γ < p_target < 1 − λ.
    """
    if not (0 <= guess < 1 and 0 <= lapse < 1 - guess):
        raise AnalysisError(f"need 0 ≤ guess < 1 and 0 ≤ lapse < 1 − guess, got {guess}, {lapse}")
    if not guess < p_target < 1 - lapse:
        raise AnalysisError(
            f"p_target={p_target} must lie between guess={guess} and 1 − lapse={1 - lapse}"
        )
    q = (p_target - guess) / (1.0 - guess - lapse)
    return LogisticModel(guess, lapse, float(np.log(q / (1.0 - q))))
