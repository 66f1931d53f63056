"""Maximum-likelihood thresholds for thousands of staircase tracks at once.

The model and its conventions are those of :func:`masking_lab.procedures.estimators.ml_threshold`
(the
analysis's estimator): the forced-choice logistic ``p(x) = γ + (1 − γ − λ)·F((x − α)/s)`` fitted
to every trial of a track, with γ and λ fixed, the scale ``s`` fitted within bounds (or fixed
with ``fit_scale=False``), the threshold searched within one level-span beyond the levels visited,
and the threshold reported at p(correct) = ``p_target`` (0.794 by default). A fit fails (NaN) on
the same grounds: too few trials, all answers correct or all wrong, a threshold on the edge of the
search range, a flat function (scale at its upper bound).

:mod:`masking_lab.procedures.staircase_batch` produces tracks by the thousand; fitting them one at
a time with a
scalar optimiser would dominate ``masking-lab plan``'s run time. Here each track is first reduced
to its distinct levels with trial and correct counts (:mod:`masking_lab.procedures.ml_counts`),
and all tracks are fitted together: for a fixed scale, a coarse grid over the threshold followed
by safeguarded Newton steps in the bracket around the best grid point; with a fitted scale,
three starts (that fit, a shallower one, and a near-step function), each climbed by projected
Newton steps on (threshold, log scale), the best kept. Pure numpy; for many tracks the
likelihood and its derivatives take the compiled loops of :mod:`masking_lab.procedures.ml_loops`
when numba loads (the same numbers, bit for bit).

Agreement with the scalar estimator (tests/test_simulate_ml.py): the same maximum wherever the
likelihood has a well-defined peak. When a track fits best with a near-step function (about one
track in eight of a 50-trial staircase), the likelihood is almost flat between two visited levels
and the two optimisers may stop at different points of that plateau (differences up to a few
tenths of a dB, at likelihoods equal to 1e-6); the threshold is then only known to that precision.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from masking_lab.core.errors import AnalysisError
from masking_lab.core.psychometric import GUESS_3IFC, LEVITT_1U3D
from masking_lab.procedures.fused import COMPILED_FROM
from masking_lab.procedures.ml_counts import (
    LevelCounts,
    LevelIndex,
    LogisticModel,
    index_levels,
    level_counts,
    log_likelihood,
    logistic_model,
)

__all__ = [
    "LevelCounts",
    "LevelIndex",
    "MLFit",
    "index_levels",
    "level_counts",
    "log_likelihood",
    "ml_threshold_from_counts",
]

_GRID_POINTS = 25
_NEWTON_ITERATIONS = 16  # the bisection fallback alone would shrink the bracket 65536-fold
_SCORING_ITERATIONS = 40
_STEP_TOLERANCE = 1e-8  # dB in t and nepers in ln s: far below any threshold's precision
_GAIN_TOLERANCE = 1e-7  # log-likelihood units; a step gaining less ends the climb
_HALVINGS = 12
_SHALLOW_FACTOR = 4.0  # the shallow start's scale, × the given scale
_GOLDEN_ITERATIONS = 30  # shrinks a gap between levels 0.618^30 ≈ 5e-7-fold


@dataclass(frozen=True)
class MLFit:
    """Per-track maximum-likelihood fits.

    Attributes
    ----------
    threshold_db : ndarray, shape (R,)
        Level where the fitted p(correct) = ``p_target``, dB; NaN where the fit fails (too few
        trials, all answers correct or all wrong, threshold on the edge of the search range,
        flat function).
    location_db : ndarray, shape (R,)
        Fitted logistic midpoint α, dB.
    scale_db : ndarray, shape (R,)
        Logistic scale used (fixed) or fitted, dB.
    log_likelihood : ndarray, shape (R,)
        Log-likelihood at the fit (natural log).
    """

    threshold_db: NDArray[np.float64]
    location_db: NDArray[np.float64]
    scale_db: NDArray[np.float64]
    log_likelihood: NDArray[np.float64]


def ml_threshold_from_counts(
    counts: LevelCounts,
    *,
    scale_db: float = 1.5,
    lapse: float = 0.02,
    guess: float = GUESS_3IFC,
    p_target: float = LEVITT_1U3D,
    fit_scale: bool = True,
    scale_bounds_db: tuple[float, float] = (0.1, 20.0),
    min_trials: int = 10,
) -> MLFit:
    """Maximum-likelihood threshold of every track (see the module docstring), from its counts:
    :func:`level_counts` of a (tracks × trials) level and answer matrix, or
    :meth:`LevelIndex.counts`.

    Parameters
    ----------
    counts : LevelCounts
        Trials and correct answers per distinct level of every track.
    scale_db : float
        Logistic scale s in dB: fixed (``fit_scale=False``) or where the search starts.
    lapse : float
        Lapse rate λ (fixed).
    guess : float
        Guess rate γ (1/3 for 3IFC).
    p_target : float
        p(correct) at which the threshold is read off the fitted function.
    fit_scale : bool
        Fit the scale within ``scale_bounds_db`` (as the analysis does) or keep ``scale_db``.
    scale_bounds_db : (float, float)
        Range of a fitted scale, dB; a fit at the upper bound is a flat function and fails.
    min_trials : int
        Tracks with fewer trials fail.

    Raises
    ------
    AnalysisError
        If the model parameters are impossible.
    """
    # Many tracks (plan's simulations) take the compiled loops: the same numbers, ~40 % sooner.
    n_rows = counts.level_db.shape[0]
    model = replace(logistic_model(guess, lapse, p_target), compiled=n_rows >= COMPILED_FROM)
    s_lo, s_hi = (float(v) for v in scale_bounds_db)
    if not (0 < s_lo < s_hi and np.isfinite(s_hi)):
        raise AnalysisError(f"scale_bounds_db must be 0 < low < high dB, got {scale_bounds_db}")
    if not (np.isfinite(scale_db) and s_lo <= scale_db <= s_hi):
        raise AnalysisError(f"scale_db must lie within {scale_bounds_db} dB, got {scale_db}")

    has = counts.n_trials > 0
    n_total = counts.n_trials.sum(axis=1)
    k_total = counts.n_correct.sum(axis=1)
    lo = np.where(has, counts.level_db, np.inf).min(axis=1)
    hi = np.where(has, counts.level_db, -np.inf).max(axis=1)
    usable = (n_total >= min_trials) & (k_total > 0) & (k_total < n_total)
    rows = np.flatnonzero(usable)
    out = MLFit(
        threshold_db=np.full(n_rows, np.nan),
        location_db=np.full(n_rows, np.nan),
        scale_db=np.full(n_rows, np.nan),
        log_likelihood=np.full(n_rows, np.nan),
    )
    if rows.size == 0:
        return out
    span = np.maximum(hi[rows] - lo[rows], 1.0)
    t_lo, t_hi = lo[rows] - span, hi[rows] + span
    t = np.empty(rows.size)
    s = np.empty(rows.size)
    ll = np.empty(rows.size)
    # Rows are padded to the longest track's number of levels; most visit half as many. Fitting
    # rows in groups of similar width, trimmed, halves the arithmetic.
    width = has[rows].shape[1] - np.argmax(has[rows][:, ::-1], axis=1)
    edges = np.unique(np.percentile(width, [33, 66, 100], method="higher").astype(int))
    lower = 0
    for edge in edges:
        group = np.flatnonzero((width > lower) & (width <= edge))
        lower = edge
        if group.size == 0:
            continue
        r = rows[group]
        part = LevelCounts(
            counts.level_db[r, :edge], counts.n_trials[r, :edge], counts.n_correct[r, :edge]
        )
        t[group], s[group], ll[group] = _fit_rows(
            part, model, t_lo[group], t_hi[group], float(scale_db), fit_scale, s_lo, s_hi
        )

    tol = 1e-3 * span
    ok = (t > t_lo + tol) & (t < t_hi - tol)
    if fit_scale:
        ok &= np.log(s) < np.log(s_hi) - 1e-6
    out.threshold_db[rows] = np.where(ok, t, np.nan)
    out.location_db[rows] = t - s * model.c
    out.scale_db[rows] = s
    out.log_likelihood[rows] = ll
    return out


def _fit_rows(
    sub: LevelCounts,
    model: LogisticModel,
    t_lo: NDArray[np.float64],
    t_hi: NDArray[np.float64],
    scale_db: float,
    fit_scale: bool,
    s_lo: float,
    s_hi: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Threshold, scale and log-likelihood of each (usable) track."""
    n = t_lo.size
    t, ll = _fit_threshold(sub, np.full(n, scale_db), model, t_lo, t_hi)
    s = np.full(n, scale_db)
    if not fit_scale:
        return t, s, ll
    # Three starts, each climbed in (t, ln s), the best kept: the fit above, a shallow one, and
    # a near-step function (staircase data often fit best with one; its likelihood in t is then
    # a row of plateaus between visited levels that a smooth start does not reach).
    shallow = min(_SHALLOW_FACTOR * scale_db, 0.5 * (scale_db + s_hi))
    t_c, ll_c = _fit_threshold(sub, np.full(n, shallow), model, t_lo, t_hi)
    t_b, ll_b = _steep_start(sub, s_lo, model)
    # The three climbs run as one stacked problem (one pass of numpy calls, not three).
    stacked = LevelCounts(
        np.tile(sub.level_db, (3, 1)), np.tile(sub.n_trials, (3, 1)), np.tile(sub.n_correct, (3, 1))
    )
    t3, s3, ll3 = _maximise_2d(
        stacked,
        np.concatenate([t, t_c, t_b]),
        np.concatenate([s, np.full(n, shallow), np.full(n, s_lo)]),
        np.concatenate([ll, ll_c, ll_b]),
        model,
        np.tile(t_lo, 3),
        np.tile(t_hi, 3),
        s_lo,
        s_hi,
    )
    pick = np.argmax(np.where(np.isfinite(ll3), ll3, -np.inf).reshape(3, n), axis=0)
    take = pick * n + np.arange(n)
    return t3[take], s3[take], ll3[take]


def _fit_threshold(
    counts: LevelCounts,
    scale_db: NDArray[np.float64],
    model: LogisticModel,
    t_lo: NDArray[np.float64],
    t_hi: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Best threshold per track for fixed scales: a grid, then safeguarded Newton steps.

    The grid's best point and its neighbours bracket the maximum; Newton steps that would leave
    the bracket (or climb a convex stretch) are replaced by bisection, and the score's sign
    shrinks the bracket every iteration.
    """
    spacing = (t_hi - t_lo) / (_GRID_POINTS - 1)
    grid_ll = np.empty((t_lo.size, _GRID_POINTS))
    for j in range(_GRID_POINTS):
        grid_ll[:, j] = model.log_likelihood(counts, t_lo + j * spacing, scale_db)
    j_best = np.argmax(grid_ll, axis=1)
    a = t_lo + np.maximum(j_best - 1, 0) * spacing
    b = t_lo + np.minimum(j_best + 1, _GRID_POINTS - 1) * spacing
    t = t_lo + j_best * spacing
    active = np.arange(t.size)
    for _ in range(_NEWTON_ITERATIONS):
        if active.size == 0:
            break
        part = _rows(counts, active)
        ta = t[active]
        score, curvature = model.threshold_derivatives(part, ta, scale_db[active])
        a[active] = np.where(score > 0, ta, a[active])
        b[active] = np.where(score < 0, ta, b[active])
        with np.errstate(divide="ignore", invalid="ignore"):
            newton = ta - score / curvature
        ok = (curvature < 0) & (newton >= a[active]) & (newton <= b[active])
        new_t = np.where(score == 0, ta, np.where(ok, newton, 0.5 * (a[active] + b[active])))
        t[active] = new_t
        active = active[np.abs(new_t - ta) > 1e-10 * np.maximum(1.0, np.abs(new_t))]
    ll = model.log_likelihood(counts, t, scale_db)
    grid_best = grid_ll[np.arange(j_best.size), j_best]
    worse = ll < grid_best  # never return less than the grid found (guards odd likelihoods)
    t = np.where(worse, t_lo + j_best * spacing, t)
    return t, np.where(worse, grid_best, ll)


def _rows(counts: LevelCounts, rows: NDArray[np.intp]) -> LevelCounts:
    """The counts of some tracks (``rows``: ascending, distinct); all of them are the counts
    themselves, not a copy, so that their cached terms are computed once."""
    if rows.size == counts.level_db.shape[0]:
        return counts
    return LevelCounts(counts.level_db[rows], counts.n_trials[rows], counts.n_correct[rows])


def _steep_start(
    counts: LevelCounts, scale_db: float, model: LogisticModel
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Best threshold for a near-step function (scale ``scale_db``).

    The likelihood is then nearly flat between consecutive visited levels and changes steeply
    near each: take the best gap (tried at its midpoint), then golden-section search inside it.
    """
    level = np.where(counts.n_trials > 0, counts.level_db, np.nan)
    n_rows = level.shape[0]
    s = np.full(n_rows, scale_db)
    best_j = np.zeros(n_rows, dtype=np.intp)
    best_ll = np.full(n_rows, -np.inf)
    for j in range(level.shape[1] - 1):
        mid = 0.5 * (level[:, j] + level[:, j + 1])
        has = ~np.isnan(mid)
        if not has.any():
            break
        ll = np.where(has, model.log_likelihood(counts, np.where(has, mid, 0.0), s), -np.inf)
        better = ll > best_ll
        best_j[better], best_ll[better] = j, ll[better]
    found = np.isfinite(best_ll)
    rows = np.arange(n_rows)
    a = np.where(found, level[rows, best_j], 0.0)
    b = np.where(found, level[rows, np.minimum(best_j + 1, level.shape[1] - 1)], 0.0)
    ratio = (np.sqrt(5.0) - 1.0) / 2.0
    x1, x2 = b - ratio * (b - a), a + ratio * (b - a)
    f1, f2 = model.log_likelihood(counts, x1, s), model.log_likelihood(counts, x2, s)
    for _ in range(_GOLDEN_ITERATIONS):
        left = f1 >= f2  # the maximum lies in [a, x2]
        a, b = np.where(left, a, x1), np.where(left, x2, b)
        new_x = np.where(left, b - ratio * (b - a), a + ratio * (b - a))
        f_new = model.log_likelihood(counts, new_x, s)
        x1, x2, f1, f2 = (
            np.where(left, new_x, x2),
            np.where(left, x1, new_x),
            np.where(left, f_new, f2),
            np.where(left, f1, f_new),
        )
    t = np.where(f1 >= f2, x1, x2)
    ll = np.maximum(f1, f2)
    return np.where(found, t, np.nan), np.where(found, ll, -np.inf)


def _maximise_2d(
    counts: LevelCounts,
    t: NDArray[np.float64],
    s: NDArray[np.float64],
    ll: NDArray[np.float64],
    model: LogisticModel,
    t_lo: NDArray[np.float64],
    t_hi: NDArray[np.float64],
    s_lo: float,
    s_hi: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Maximise over (threshold, ln scale) within the bounds: projected Newton, step halving.

    Newton steps where the observed Hessian is negative definite, Fisher-scoring steps
    elsewhere (the expected information is positive semi-definite, so they point uphill). When
    the scale sits on a bound and the step pushes outward, only the threshold moves. Halving
    keeps the likelihood from ever decreasing.
    """
    t, u, ll = t.copy(), np.log(s), ll.copy()
    u_lo, u_hi = float(np.log(s_lo)), float(np.log(s_hi))
    active = np.flatnonzero(np.isfinite(t))
    for _ in range(_SCORING_ITERATIONS):
        if active.size == 0:
            break
        sub = _rows(counts, active)
        ta, ua, la = t[active], u[active], ll[active]
        g_t, g_u, h_tt, h_tu, h_uu, i_tt, i_tu, i_uu = model.derivatives(sub, ta, np.exp(ua))
        newton_ok = (h_tt < 0) & (h_tt * h_uu - h_tu**2 > 0)
        a_tt = np.where(newton_ok, -h_tt, i_tt)
        a_tu = np.where(newton_ok, -h_tu, i_tu)
        a_uu = np.where(newton_ok, -h_uu, i_uu)
        ridge = 1e-12 * (a_tt + a_uu) + 1e-300
        det = (a_tt + ridge) * (a_uu + ridge) - a_tu**2
        step_t = ((a_uu + ridge) * g_t - a_tu * g_u) / det
        step_u = ((a_tt + ridge) * g_u - a_tu * g_t) / det
        # Active set: a scale on its bound with the step pushing outward stays there.
        pinned = ((ua <= u_lo) & (step_u < 0)) | ((ua >= u_hi) & (step_u > 0))
        t_only = np.where(h_tt < 0, -h_tt, i_tt) + 1e-300
        step_t = np.where(pinned, g_t / t_only, step_t)
        step_u = np.where(pinned, 0.0, np.clip(step_u, -1.0, 1.0))  # ≤ a factor e per step
        factor = np.ones(active.size)
        accepted = np.zeros(active.size, dtype=bool)
        new_t, new_u, new_l = ta.copy(), ua.copy(), la.copy()
        t_lo_a, t_hi_a = t_lo[active], t_hi[active]
        for _ in range(_HALVINGS):
            todo = np.flatnonzero(~accepted)
            if todo.size == 0:
                break
            cand_t = np.clip(ta[todo] + factor[todo] * step_t[todo], t_lo_a[todo], t_hi_a[todo])
            cand_u = np.clip(ua[todo] + factor[todo] * step_u[todo], u_lo, u_hi)
            part = _rows(sub, todo)
            cand_l = model.log_likelihood(part, cand_t, np.exp(cand_u))
            good = cand_l >= la[todo]
            hit = todo[good]
            new_t[hit], new_u[hit], new_l[hit] = cand_t[good], cand_u[good], cand_l[good]
            accepted[hit] = True
            factor[todo[~good]] *= 0.5
        moved = np.maximum(np.abs(new_t - ta), np.abs(new_u - ua))
        t[active], u[active], ll[active] = new_t, new_u, new_l
        gained = new_l - la
        active = active[accepted & (moved > _STEP_TOLERANCE) & (gained > _GAIN_TOLERANCE)]
    return t, np.exp(u), ll
