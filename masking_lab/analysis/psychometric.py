"""A psychometric function per set, as Palamedes and psignifit report it (pure).

The model is the 3IFC logistic of :mod:`masking_lab.core.psychometric` written with Palamedes'
parameters::

    p(x) = γ + (1 − γ − λ) · F(x),   F(x) = 1 / (1 + exp(−β · (x − α)))

x the level in dB (the set's unit), γ the guess rate (1/3), α the **threshold** (dB, where F is
one half: psignifit's default threshold), β the **slope** (1/dB; the logistic scale is 1/β) and
λ the lapse rate. The AL a staircase converges on (p = its target, 0.794 for 1-up 3-down) is
reported too (``al_db``), so it compares with ``thresholds.csv``.

The point estimate is the maximum-likelihood fit, found as
:func:`masking_lab.procedures.estimators.ml_threshold` finds it (a profile search over the
scale, so a short track's several local maxima are all tried, then a climb from each).
Uncertainty and goodness of fit come from a **parametric bootstrap**, as Palamedes'
``PAL_PFML_BootstrapParametric`` and ``PAL_PFML_GoodnessOfFit`` do: ``n_boot`` data sets are
drawn from the fitted function at the levels and counts that were run, each is refitted (a
vectorised Fisher scoring from the fit, kept within the same bounds), and

* the 95 % intervals are the 2.5 and 97.5 percentiles of the refitted parameters,
* ``deviance`` is 2·Σ[k·ln(k/(n·p)) + (n − k)·ln((n − k)/(n·(1 − p)))] against the saturated
  model (one p per level), and ``deviance_p`` the share of simulated deviances at least as large.

Everything is seeded (``seed``): same trials, same numbers.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from masking_lab.analysis.pf_likelihood import nll as _nll
from masking_lab.analysis.pf_likelihood import refit as _refit
from masking_lab.analysis.pf_likelihood import set_nll as _set_nll
from masking_lab.core.errors import AnalysisError
from masking_lab.core.psychometric import GUESS_3IFC, LEVITT_1U3D

__all__ = [
    "PFFit",
    "PFJob",
    "batch_group",
    "binned",
    "deviance",
    "fit_pf",
    "fit_pf_many",
    "pf_curve",
]

MAX_LAPSE = 0.1
MIN_TRIALS = 10
SCALE_BOUNDS_DB = (0.1, 20.0)  # as ml_threshold: 1/β between 0.1 and 20 dB


@dataclass(frozen=True)
class PFFit:
    """One fitted psychometric function, or why there is none.

    Attributes
    ----------
    ok : bool
        False when the track has no interior likelihood maximum (``message`` says why).
    message : str or None
        Why the fit failed, or a note (e.g. few usable bootstrap refits).
    n_trials, n_levels : int
        Trials and distinct levels fitted.
    guess, p_target : float
        γ, and the p(correct) at which ``al_db`` is read.
    lapse_fixed : bool
        λ was given, not fitted (then its interval is empty).
    threshold_db, slope_per_db, lapse, al_db : float or None
        α (dB), β (1/dB), λ, and the level at ``p_target`` (dB).
    threshold_ci_db, slope_ci_per_db, lapse_ci, al_ci_db : tuple or None
        95 % parametric-bootstrap percentile intervals.
    al_sd_db : float or None
        Bootstrap SD of ``al_db``, dB.
    deviance, deviance_p : float or None
        Deviance against the saturated model and its bootstrap p-value.
    n_boot : int
        Bootstrap refits that converged within the bounds (of those asked for).
    """

    ok: bool
    message: str | None
    n_trials: int
    n_levels: int
    guess: float
    p_target: float
    lapse_fixed: bool
    threshold_db: float | None = None
    slope_per_db: float | None = None
    lapse: float | None = None
    al_db: float | None = None
    threshold_ci_db: tuple[float, float] | None = None
    slope_ci_per_db: tuple[float, float] | None = None
    lapse_ci: tuple[float, float] | None = None
    al_ci_db: tuple[float, float] | None = None
    al_sd_db: float | None = None
    deviance: float | None = None
    deviance_p: float | None = None
    n_boot: int = 0


def binned(
    levels_db: ArrayLike, correct: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Distinct levels, trials and correct answers at each (the likelihood's statistics).

    Parameters
    ----------
    levels_db : array_like
        Level of each trial, dB.
    correct : array_like of bool
        Each trial's answer.

    Returns
    -------
    (levels_db, n, k) : three arrays
        Sorted distinct levels (dB), trials at each and correct answers at each.

    Examples
    --------
    >>> x, n, k = binned([2.0, 1.0, 2.0], [True, False, False])
    >>> x.tolist(), n.tolist(), k.tolist()
    ([1.0, 2.0], [1.0, 2.0], [0.0, 1.0])
    """
    x = np.asarray(levels_db, dtype=float).ravel()
    r = np.asarray(correct, dtype=bool).ravel()
    if x.size != r.size:
        raise AnalysisError(f"{x.size} levels but {r.size} answers; give one per trial")
    xu, inv = np.unique(x, return_inverse=True)
    n = np.bincount(inv, minlength=xu.size).astype(float)
    k = np.asarray(np.bincount(inv, weights=r.astype(float), minlength=xu.size), dtype=np.float64)
    return xu, n, k


def pf_curve(
    level_db: ArrayLike,
    threshold_db: float | NDArray[np.float64],
    slope_per_db: float | NDArray[np.float64],
    lapse: float | NDArray[np.float64],
    guess: float,
) -> NDArray[np.float64]:
    """p(correct) of the fitted function at ``level_db`` (dB).

    Threshold (dB), slope (per dB) and lapse may be arrays; they broadcast against the levels.

    Examples
    --------
    >>> np.round(pf_curve([0.0, 100.0], 0.0, 1.0, 0.02, 1 / 3), 3).tolist()
    [0.657, 0.98]
    """
    x = np.asarray(level_db, dtype=float)
    f = 0.5 * (1.0 + np.tanh(0.5 * slope_per_db * (x - threshold_db)))  # logistic, no overflow
    return guess + (1.0 - guess - lapse) * f


def deviance(n: ArrayLike, k: ArrayLike, p: ArrayLike) -> NDArray[np.float64]:
    """Deviance of predicted p against the saturated model (one p per level), per row.

    Parameters
    ----------
    n, k : array_like
        Trials and correct answers per level (last axis: levels).
    p : array_like
        Predicted p(correct) per level, broadcast against ``k``.

    Examples
    --------
    >>> float(deviance([10], [5], [0.5]))
    0.0
    >>> round(float(deviance([10, 10], [2, 9], [0.5, 0.5])), 3)
    11.216
    """
    n_ = np.asarray(n, dtype=float)
    k_ = np.asarray(k, dtype=float)
    p_ = np.clip(np.asarray(p, dtype=float), 1e-12, 1 - 1e-12)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(k_ > 0, k_ * np.log(k_ / (n_ * p_)), 0.0)
        b = np.where(n_ - k_ > 0, (n_ - k_) * np.log((n_ - k_) / (n_ * (1 - p_))), 0.0)
    return 2.0 * np.sum(a + b, axis=-1)


def _al(alpha: NDArray, beta: NDArray, lam: NDArray, guess: float, p_target: float) -> NDArray:
    q = (p_target - guess) / (1.0 - guess - lam)
    return alpha + np.log(q / (1.0 - q)) / beta


def _interval(values: NDArray[np.float64]) -> tuple[float, float] | None:
    if values.size < 20:
        return None
    lo, hi = np.percentile(values, [2.5, 97.5])
    return float(lo), float(hi)


@dataclass(frozen=True)
class PFJob:
    """One set's trials and the model to fit them with: the arguments of :func:`fit_pf`.

    Attributes
    ----------
    levels_db : sequence of float
        Level of each trial, dB.
    correct : sequence of bool
        Each trial's answer.
    guess, p_target, lapse, n_boot, seed, estimate
        As :func:`fit_pf` takes them.
    """

    levels_db: ArrayLike
    correct: ArrayLike
    guess: float = GUESS_3IFC
    p_target: float = LEVITT_1U3D
    lapse: float | None = None
    n_boot: int = 200
    seed: int = 0
    estimate: tuple[float, float, float] | None = None


@dataclass
class _Fit:
    """One job on its way through :func:`fit_pf_many`."""

    job: PFJob
    xu: NDArray[np.float64]
    n: NDArray[np.float64]
    k: NDArray[np.float64]
    base: dict
    bounds: NDArray[np.float64]
    starts: NDArray[np.float64] | None = None  # profile minima to climb from
    start: NDArray[np.float64] | None = None  # the point estimate (α, log s, λ)
    sims: NDArray[np.int64] | None = None
    fields: dict | None = None  # the point estimate's fields of the result
    result: PFFit | None = None

    @property
    def group(self) -> tuple[int, float, bool]:
        """What data sets must share to climb together: levels, guess rate, λ fitted."""
        return _group(self.xu.size, self.job)


def batch_group(job: PFJob) -> tuple[int, float, bool]:
    """What a set's data sets share with those they climb beside in :func:`fit_pf_many`: the
    number of distinct levels, the guess rate and whether λ is fitted.

    Sets of one group fill a batch together; sorting sets by it before cutting them into
    chunks gives full batches. It never changes a fit.

    Examples
    --------
    >>> batch_group(PFJob([0.0, 2.0, 2.0, 4.0], [False, True, True, True]))
    (3, 0.3333333333333333, True)
    """
    levels = np.unique(np.asarray(job.levels_db, dtype=float).ravel())
    return _group(levels.size, job)


def _group(n_levels: int, job: PFJob) -> tuple[int, float, bool]:
    # one definition for the sort (batch_group) and the batches (_Fit.group)
    return (n_levels, job.guess, job.lapse is None)


_BATCH_ROWS = 8192  # data sets climbed together: large enough to amortise numpy's overhead


def fit_pf(
    levels_db: ArrayLike,
    correct: ArrayLike,
    *,
    guess: float = GUESS_3IFC,
    p_target: float = LEVITT_1U3D,
    lapse: float | None = None,
    n_boot: int = 200,
    seed: int = 0,
    estimate: tuple[float, float, float] | None = None,
) -> PFFit:
    """Fit the psychometric function to one set's trials, with bootstrap intervals and deviance.

    Parameters
    ----------
    levels_db : array_like
        Level of each trial, dB (the result is in the same unit).
    correct : array_like of bool
        Each trial's answer.
    guess : float
        Guess rate γ (1/3 for 3IFC).
    p_target : float
        p(correct) at which ``al_db`` is read (the set's staircase target).
    lapse : float or None
        A fixed λ, or None to fit it within [0, 0.1].
    n_boot : int
        Parametric-bootstrap data sets (0: no intervals, no deviance p-value).
    seed : int
        Seed of the bootstrap.
    estimate : (threshold_db, slope_per_db, lapse), optional
        A maximum-likelihood estimate found elsewhere (e.g. the ML AL estimator's), used as
        the point estimate the bootstrap draws from, instead of this function's own search.

    Returns
    -------
    PFFit
        ``ok`` False, with a message, for a track without an interior maximum (all correct,
        all wrong, fewer than 10 trials, a threshold at the edge of the levels run).

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> x = np.repeat(np.arange(-6.0, 7.0, 2.0), 30)
    >>> r = rng.random(x.size) < pf_curve(x, 0.0, 1.0, 0.02, 1 / 3)
    >>> fit = fit_pf(x, r, n_boot=100)
    >>> fit.ok, abs(fit.threshold_db) < 1.0, fit.threshold_ci_db[0] < 0.0 < fit.threshold_ci_db[1]
    (True, True, True)
    """
    job = PFJob(levels_db, correct, guess, p_target, lapse, n_boot, seed, estimate)
    return fit_pf_many([job])[0]


def fit_pf_many(jobs: Sequence[PFJob], *, compiled: bool = False) -> list[PFFit]:
    """:func:`fit_pf` of many sets at once: the same numbers, a fraction of the time.

    The climbs of all sets with the same number of distinct levels (the profile starts, then
    the bootstrap data sets) run as the rows of one :func:`_refit`, so numpy's per-call cost
    is paid once per batch instead of once per set; every step is computed per row, so each
    set's fit is bit for bit what :func:`fit_pf` gives it alone.

    Parameters
    ----------
    jobs : sequence of PFJob
        One per set (levels in dB; each job's own model, bootstrap size and seed).
    compiled : bool
        Climb with the compiled loops where numba is available (the same numbers,
        :func:`~masking_lab.analysis.pf_likelihood.refit`).

    Returns
    -------
    list of PFFit
        In the order of ``jobs``.

    Examples
    --------
    >>> x = np.repeat(np.arange(-6.0, 7.0, 2.0), 10)
    >>> r = pf_curve(x, 0.0, 1.0, 0.02, 1 / 3) > np.tile(np.linspace(0.05, 0.95, 10), 7)
    >>> fits = fit_pf_many([PFJob(x, r, n_boot=50, seed=s) for s in (1, 2)])
    >>> fits[1] == fit_pf(x, r, n_boot=50, seed=2)
    True
    """
    fits = [_prepare(job, compiled) for job in jobs]
    # The point estimates: every profile minimum of every set climbed together.
    search = [f for f in fits if f.result is None and f.start is None]
    starts = [(f, np.tile(f.k, (len(_got(f.starts)), 1)), _got(f.starts)) for f in search]
    climbed = _climb(starts, compiled)
    for f, (th, good) in zip(search, climbed, strict=True):
        _pick_start(f, th, good)
    # The parametric bootstraps: every simulated data set of every set climbed together.
    boot = [f for f in fits if f.result is None and _draw_sims(f)]
    climbed = _climb([(f, _got(f.sims).astype(float), _got(f.start)) for f in boot], compiled)
    for f, (theta, good) in zip(boot, climbed, strict=True):
        _finish(f, theta, good)
    return [f.result for f in fits]  # type: ignore[misc]


def _got(a: NDArray[Any] | None) -> NDArray[Any]:
    """A stage's array that the previous stage set (``_prepare`` the starts, ``_draw_sims`` the
    data sets and the start)."""
    if a is None:
        raise AssertionError("fit_pf_many: a stage ran before the one that sets its input")
    return a


def _prepare(job: PFJob, compiled: bool = False) -> _Fit:
    """Bin the trials, set the bounds, and either refuse the set or find where to climb from."""
    guess, lapse = job.guess, job.lapse
    x_all = np.asarray(job.levels_db, dtype=float).ravel()
    xu, n, k = binned(x_all, job.correct)
    base: dict[str, Any] = {
        "n_trials": int(x_all.size),
        "n_levels": int(xu.size),
        "guess": guess,
        "p_target": job.p_target,
        "lapse_fixed": lapse is not None,
    }
    lo, hi = (float(xu.min()), float(xu.max())) if xu.size else (0.0, 0.0)
    span = max(hi - lo, 1.0)
    bounds = np.array(
        [
            [lo - span, hi + span],
            [math.log(SCALE_BOUNDS_DB[0]), math.log(SCALE_BOUNDS_DB[1])],
            [0.0, MAX_LAPSE] if lapse is None else [lapse, lapse],
        ]
    )
    f = _Fit(job, xu, n, k, base, bounds)
    r = np.asarray(job.correct, dtype=bool).ravel()
    if x_all.size < MIN_TRIALS:
        msg = f"only {x_all.size} trials; the fit needs at least {MIN_TRIALS}"
        f.result = PFFit(False, msg, **base)
    elif not np.isfinite(x_all).all():
        f.result = PFFit(False, "trial levels must be finite numbers of dB", **base)
    elif r.all() or not r.any():
        which = "correct" if r.all() else "wrong"
        msg = f"every answer was {which}: the likelihood has no maximum"
        f.result = PFFit(False, msg, **base)
    elif job.estimate is not None:
        e = job.estimate
        f.start = np.array([e[0], math.log(1.0 / e[1]), e[2]])
    else:
        f.starts = _profile_starts(xu, n, k, bounds, guess, lapse, compiled)
    return f


def _profile_starts(
    xu: NDArray,
    n: NDArray,
    k: NDArray,
    bounds: NDArray,
    guess: float,
    lapse: float | None,
    compiled: bool = False,
) -> NDArray[np.float64]:
    """Where to climb from: the profile's local minima (rows of α, log s, λ).

    The profile is found on a grid (vectorised): the best α for each of a dense set of scales
    at λ = 0.02. A short track's likelihood can have several local maxima along the scale, so
    every local minimum of the profile is climbed (jointly in α, s and a fitted λ) and the
    best climb is kept (as procedures.estimators.ml_threshold does).
    """
    lam0 = 0.02 if lapse is None else lapse
    near = xu[:, None] + SCALE_BOUNDS_DB[0] * np.linspace(-4.0, 4.0, 9)[None, :]
    grid_a = np.union1d(
        np.linspace(bounds[0, 0], bounds[0, 1], 81), np.clip(near.ravel(), *bounds[0])
    )
    grid_ls = np.linspace(bounds[1, 0], bounds[1, 1], 25)[:-1]
    aa, ll = np.meshgrid(grid_a, grid_ls, indexing="ij")
    grid = np.column_stack([aa.ravel(), ll.ravel(), np.full(aa.size, lam0)])
    prof_all = _set_nll(xu, n, k, grid, guess, compiled=compiled).reshape(aa.shape)
    best = np.argmin(prof_all, axis=0)
    profile = prof_all[best, np.arange(grid_ls.size)]
    padded = np.concatenate([[np.inf], profile, [np.inf]])
    local = np.flatnonzero((profile <= padded[:-2]) & (profile <= padded[2:]))
    local = local[np.argsort(profile[local])][:4]
    starts = np.column_stack([grid_a[best[local]], grid_ls[local], np.full(local.size, lam0)])
    if lapse is None:  # each start also from the ends of the lapse range
        starts = np.vstack([starts, starts * [1, 1, 0], starts * [1, 1, 0] + [0, 0, MAX_LAPSE]])
    return starts


def _climb(
    items: Sequence[tuple[_Fit, NDArray[np.float64], NDArray[np.float64]]],
    compiled: bool = False,
) -> list[tuple[NDArray[np.float64], NDArray[np.bool_]]]:
    """:func:`_refit` of each item's data sets (rows of counts, from its start rows), the
    items with the same levels count, guess rate and lapse rule climbing as one batch."""
    out: list[tuple[NDArray[np.float64], NDArray[np.bool_]]] = [None] * len(items)  # type: ignore[list-item]
    groups: dict[tuple[int, float, bool], list[int]] = {}
    for i, (f, _, _) in enumerate(items):
        groups.setdefault(f.group, []).append(i)
    for (_, guess, fit_lapse), members in groups.items():
        batch: list[int] = []
        rows = 0
        for pos, i in enumerate(members):
            batch.append(i)
            rows += len(items[i][1])
            if rows >= _BATCH_ROWS or pos == len(members) - 1:
                _climb_batch(items, batch, guess, fit_lapse, out, compiled)
                batch, rows = [], 0
    return out


def _climb_batch(
    items: Sequence[tuple[_Fit, NDArray[np.float64], NDArray[np.float64]]],
    batch: list[int],
    guess: float,
    fit_lapse: bool,
    out: list[tuple[NDArray[np.float64], NDArray[np.bool_]]],
    compiled: bool = False,
) -> None:
    sizes = [len(items[i][1]) for i in batch]
    k = np.concatenate([items[i][1] for i in batch])
    x = np.concatenate([np.broadcast_to(items[i][0].xu, items[i][1].shape) for i in batch])
    n = np.concatenate([np.broadcast_to(items[i][0].n, items[i][1].shape) for i in batch])
    start = np.concatenate(
        [np.broadcast_to(items[i][2], (m, 3)) for i, m in zip(batch, sizes, strict=True)]
    )
    bounds = np.concatenate(
        [np.broadcast_to(items[i][0].bounds, (m, 3, 2)) for i, m in zip(batch, sizes, strict=True)]
    )
    theta, good = _refit(x, n, k, start, bounds, guess, fit_lapse, compiled=compiled)
    edges = np.cumsum([0, *sizes])
    for i, a, b in zip(batch, edges[:-1], edges[1:], strict=True):
        out[i] = (theta[a:b], good[a:b])


def _pick_start(f: _Fit, th: NDArray[np.float64], good: NDArray[np.bool_]) -> None:
    """The best climb from the profile starts is the point estimate, unless it ran off."""
    kk = np.tile(f.k, (len(th), 1))
    vals = _nll(f.xu, f.n, kk, th, f.job.guess)
    top = int(np.argmin(vals))
    if good[top]:
        f.start = th[top]
        return
    if th[top, 1] >= f.bounds[1, 1] - 1e-6:
        msg = (
            f"the fitted psychometric function is flat (scale ≥ {SCALE_BOUNDS_DB[1]} dB): "
            "answers do not depend on level"
        )
    else:
        msg = (
            f"the threshold runs to the edge of the search range ({th[top, 0]:.1f} dB): "
            "the track does not bracket a threshold"
        )
    f.result = PFFit(False, msg, **f.base)


def _point(f: _Fit) -> tuple[float, float, float, NDArray[np.float64], dict]:
    """α, s, λ, the fitted p at each level, and the point-estimate fields of the result."""
    job, start = f.job, f.start
    alpha, s, lam = float(start[0]), float(math.exp(start[1])), float(start[2])  # type: ignore[index]
    beta = 1.0 / s
    p_hat = pf_curve(f.xu, alpha, beta, lam, job.guess)
    fields = {
        "threshold_db": alpha,
        "slope_per_db": beta,
        "lapse": lam,
        "al_db": float(
            _al(np.array(alpha), np.array(beta), np.array(lam), job.guess, job.p_target)
        ),
        "deviance": float(deviance(f.n, f.k, p_hat)),
    }
    return alpha, s, lam, p_hat, fields


def _steep_note(scale_db: float) -> str | None:
    """A step in the answers drives the scale to its lower limit: β is then a lower bound only."""
    if scale_db > SCALE_BOUNDS_DB[0] * (1.0 + 1e-6):
        return None
    return (
        f"β at its limit ({1.0 / SCALE_BOUNDS_DB[0]:g}/dB): no level fell on the rising part, so "
        "the slope is only a lower bound"
    )


def _draw_sims(f: _Fit) -> bool:
    """Draw the bootstrap data sets (seeded), and say whether there are any to refit."""
    alpha, s, lam, p_hat, fields = _point(f)
    if f.job.n_boot <= 0:
        f.result = PFFit(True, _steep_note(s), **f.base, **fields)
        return False
    rng = np.random.default_rng(f.job.seed)
    f.sims = rng.binomial(f.n.astype(int)[None, :], p_hat[None, :], size=(f.job.n_boot, f.xu.size))
    f.start = np.array([alpha, math.log(s), lam])
    f.fields = fields
    return True


def _finish(f: _Fit, theta: NDArray[np.float64], good: NDArray[np.bool_]) -> None:
    """The intervals, SD and deviance p from the refitted bootstrap data sets."""
    job, xu, n, guess = f.job, f.xu, f.n, f.job.guess
    fields: dict = f.fields  # type: ignore[assignment]
    th = theta[good]
    a_b, beta_b, lam_b = th[:, 0], np.exp(-th[:, 1]), th[:, 2]
    al_b = _al(a_b, beta_b, lam_b, guess, job.p_target)
    p_b = pf_curve(xu[None, :], a_b[:, None], beta_b[:, None], lam_b[:, None], guess)
    dev_b = deviance(n[None, :], f.sims[good], p_b)  # type: ignore[index]
    n_good = int(good.sum())
    note = _steep_note(1.0 / fields["slope_per_db"])
    if n_good < 0.9 * job.n_boot:
        rough = (
            f"only {n_good} of {job.n_boot} bootstrap refits stayed inside the bounds: the "
            "intervals are rough"
        )
        note = rough if note is None else f"{note}; {rough}"
    f.result = PFFit(
        True,
        note,
        **f.base,
        **fields,
        threshold_ci_db=_interval(a_b),
        slope_ci_per_db=_interval(beta_b),
        lapse_ci=None if job.lapse is not None else _interval(lam_b),
        al_ci_db=_interval(al_b),
        al_sd_db=float(np.std(al_b, ddof=1)) if n_good >= 20 else None,
        deviance_p=float(np.mean(dev_b >= fields["deviance"] - 1e-9)) if n_good >= 20 else None,
        n_boot=n_good,
    )
