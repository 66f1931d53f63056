"""Threshold (AL) estimators for one staircase track (pure).

* :func:`reversal_mean_al` — the paper's estimator: mean level of the last ``k`` reversals.
* :func:`ml_threshold` — maximum-likelihood fit of a 3IFC psychometric function
  ``p = γ + (1 − γ − λ)·logistic((x − α)/s)`` to every trial of the track, reporting the level
  at which p(correct) equals the p the staircase converges on (0.5^(1/3) ≈ 0.794 for 1-up
  3-down; :func:`masking_lab.procedures.staircase.implied_target_p`). Both estimators thus estimate
  the
  same quantity, and :class:`masking_lab.core.psychometric.Psychometric` uses the same definition.

The lapse rate λ is fixed by default (0.02): a single 50–80-trial staircase spends few trials
high enough on the function to pin λ down, and a free λ trades off against the slope (Wichmann
& Hill 2001). ``lapse=None`` fits it within [0, ``max_lapse``].
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from masking_lab.core.errors import AnalysisError
from masking_lab.core.psychometric import GUESS_3IFC, LEVITT_1U3D

ESTIMATORS = ("reversals", "ml")

#: Local maxima of the scale profile polished at most (the best few; rarely more than 3).
_MAX_STARTS = 4


def reversal_mean_al(reversal_levels_db: Sequence[float], k: int) -> float:
    """Mean of the last ``k`` reversal levels, dB (same unit as the levels).

    Raises
    ------
    AnalysisError
        If ``k`` < 1 or fewer than ``k`` reversals were logged.
    """
    if k < 1:
        raise AnalysisError(f"reversals averaged must be ≥ 1, got {k}")
    levels = list(map(float, reversal_levels_db))
    if len(levels) < k:
        raise AnalysisError(
            f"only {len(levels)} reversals logged, cannot average the last {k}; "
            "lower --reversals or use --estimator ml"
        )
    if not all(map(math.isfinite, levels[-k:])):
        raise AnalysisError("a reversal level is not a finite number of dB")
    return math.fsum(levels[-k:]) / k


@dataclass(frozen=True)
class MLThreshold:
    """A maximum-likelihood psychometric fit to one track.

    Attributes
    ----------
    threshold_db : float or None
        Level (the track's unit, dB) at which fitted p(correct) = ``p_target``; None if the fit
        failed.
    scale_db : float or None
        Logistic scale s, dB.
    lapse : float
        Lapse rate used (fixed or fitted).
    p_target : float
        p(correct) defining the threshold.
    n_trials : int
        Trials fitted.
    log_likelihood : float or None
        Maximised log-likelihood.
    message : str or None
        Why the fit failed, if it did.
    """

    threshold_db: float | None
    scale_db: float | None
    lapse: float
    p_target: float
    n_trials: int
    log_likelihood: float | None
    message: str | None = None

    @property
    def ok(self) -> bool:
        """True if the fit gave a threshold."""
        return self.threshold_db is not None


def ml_threshold(
    levels_db: ArrayLike,
    correct: ArrayLike,
    *,
    guess: float = GUESS_3IFC,
    lapse: float | None = 0.02,
    p_target: float = LEVITT_1U3D,
    max_lapse: float = 0.1,
    scale_bounds_db: tuple[float, float] = (0.1, 20.0),
    min_trials: int = 10,
) -> MLThreshold:
    """Fit a psychometric function to every trial by maximum likelihood.

    Parameters
    ----------
    levels_db : array_like
        Level of each trial, dB (dB SL or dB re 1 V; the result is in the same unit).
    correct : array_like of bool
        Whether each trial was answered correctly.
    guess : float
        Guess rate γ (1/3 for 3IFC).
    lapse : float or None
        Fixed lapse rate λ, or None to fit it in [0, ``max_lapse``].
    p_target : float
        p(correct) at which the threshold is read off (default Levitt's 1-up-3-down 0.794).
    max_lapse : float
        Upper bound on a fitted lapse rate.
    scale_bounds_db : (float, float)
        Search range for the logistic scale s, dB.
    min_trials : int
        Fewer trials than this give a failed fit.

    Returns
    -------
    MLThreshold
        With ``threshold_db`` None and a ``message`` when the likelihood has no interior maximum
        (all answers correct or all wrong, a threshold at the edge of the search range, too few
        trials): such a track is not a threshold.

    Raises
    ------
    AnalysisError
        For invalid arguments (lengths differ, non-finite levels, p_target outside (γ, 1 − λ)).
    """
    x = np.asarray(levels_db, dtype=float).ravel()
    r = np.asarray(correct, dtype=bool).ravel()
    if x.size != r.size:
        raise AnalysisError(f"{x.size} levels but {r.size} responses; give one per trial")
    if not np.isfinite(x).all():
        raise AnalysisError("trial levels must be finite numbers of dB")
    lam_max = max_lapse if lapse is None else lapse
    if not 0.0 <= lam_max < 1.0 - guess:
        raise AnalysisError(f"lapse must lie in [0, {1 - guess:.3f}), got {lam_max}")
    if not guess < p_target < 1.0 - lam_max:
        raise AnalysisError(
            f"p_target={p_target} must lie between guess={guess} and 1 − lapse={1 - lam_max}"
        )
    lapse0 = 0.02 if lapse is None else lapse

    def failed(msg: str) -> MLThreshold:
        return MLThreshold(None, None, lapse0, p_target, int(x.size), None, msg)

    if x.size < min_trials:
        return failed(f"only {x.size} trials; the ML fit needs at least {min_trials}")
    if r.all() or not r.any():
        which = "correct" if r.all() else "wrong"
        return failed(f"every answer was {which}: the likelihood has no maximum")

    lo, hi = float(x.min()), float(x.max())
    span = max(hi - lo, 1.0)
    t_bounds = (lo - span, hi + span)
    ls_bounds = (math.log(scale_bounds_db[0]), math.log(scale_bounds_db[1]))

    def nll(params: NDArray[np.float64]) -> float:
        # (threshold, log scale[, lapse]); the grid search passes two and uses the start lapse.
        t, log_s = params[0], params[1]
        lam = float(params[2]) if params.size == 3 else lapse0
        return _neg_log_lik(x, r, t, math.exp(log_s), guess, lam, p_target)

    # Profile first (vectorised): the best threshold on a grid for each of a dense set of
    # scales. The likelihood of a short track can have several local maxima along the scale (a
    # near-step function between two visited levels, a moderate slope, a shallow one), and a
    # single quasi-Newton climb from the best grid point can stop on the wrong one (issue 13:
    # a track stopped at scale 0.15 dB while the maximum was at 0.43 dB). So every local
    # maximum of the profile is polished and the best polished point is kept.
    # Thresholds close to each visited level join the regular grid: for a near-step function
    # the likelihood is a narrow peak (a few tenths of the scale wide) next to a visited level,
    # which a regular grid steps over.
    near = np.unique(x)[:, None] + scale_bounds_db[0] * np.linspace(-4.0, 4.0, 17)[None, :]
    grid_t = np.union1d(
        np.linspace(t_bounds[0], t_bounds[1], 81),
        np.clip(near.ravel(), t_bounds[0], t_bounds[1]),
    )
    grid_s = np.geomspace(scale_bounds_db[0], scale_bounds_db[1], 25)[:-1]
    tt, ss = np.meshgrid(grid_t, grid_s, indexing="ij")
    # On counts per distinct level (the likelihood's sufficient statistics): a staircase visits
    # a dozen levels however many trials it runs.
    xu, inv = np.unique(x, return_inverse=True)
    n_at = np.bincount(inv).astype(float)
    k_at = np.asarray(np.bincount(inv, weights=r.astype(float)), dtype=np.float64)  # no copy
    grid_nll = _neg_log_lik_grid(xu, n_at, k_at, tt.ravel(), ss.ravel(), guess, lapse0, p_target)
    grid_nll = grid_nll.reshape(tt.shape)
    best_t = np.argmin(grid_nll, axis=0)
    profile = grid_nll[best_t, np.arange(grid_s.size)]
    padded = np.concatenate([[np.inf], profile, [np.inf]])
    local = np.flatnonzero((profile <= padded[:-2]) & (profile <= padded[2:]))
    from scipy.optimize import minimize  # here, not at import: sessions and plan never fit

    res = None
    for j in local[np.argsort(profile[local])][:_MAX_STARTS]:
        start = (float(grid_t[best_t[j]]), float(np.log(grid_s[j])))
        if lapse is None:
            x0 = np.array([start[0], start[1], 0.02])
            bounds = [t_bounds, ls_bounds, (0.0, max_lapse)]
            cand = minimize(nll, x0, method="L-BFGS-B", bounds=bounds)
        else:
            cand = minimize(
                _nll_and_grad,
                np.array(start),
                args=(x, r, guess, lapse0, p_target),
                jac=True,
                method="L-BFGS-B",
                bounds=[t_bounds, ls_bounds],
            )
        if res is None or cand.fun < res.fun:
            res = cand
    assert res is not None  # the profile always has a minimum
    t_hat, log_s_hat = float(res.x[0]), float(res.x[1])
    lam_hat = float(res.x[2]) if lapse is None else lapse0
    tol = 1e-3 * span
    if t_hat <= t_bounds[0] + tol or t_hat >= t_bounds[1] - tol:
        return failed(
            f"the ML threshold runs to the edge of the search range ({t_hat:.1f} dB): the "
            "track does not bracket a threshold"
        )
    if log_s_hat >= ls_bounds[1] - 1e-6:
        return failed(
            f"the fitted psychometric function is flat (scale ≥ {scale_bounds_db[1]} dB): "
            "answers do not depend on level"
        )
    return MLThreshold(
        t_hat, math.exp(log_s_hat), lam_hat, p_target, int(x.size), -float(res.fun), None
    )


def _neg_log_lik(
    x: NDArray[np.float64],
    r: NDArray[np.bool_],
    threshold: float,
    scale: float,
    guess: float,
    lapse: float,
    p_target: float,
) -> float:
    q = (p_target - guess) / (1.0 - guess - lapse)
    location = threshold - scale * math.log(q / (1.0 - q))
    z = (x - location) / scale
    e = np.exp(-np.abs(z))
    f = np.where(z >= 0, 1.0 / (1.0 + e), e / (1.0 + e))
    p = guess + (1.0 - guess - lapse) * f
    p = np.clip(p, 1e-12, 1.0 - 1e-12)
    return -float(np.log(np.where(r, p, 1.0 - p)).sum())


def _neg_log_lik_grid(
    x: NDArray[np.float64],
    n: NDArray[np.float64],
    k: NDArray[np.float64],
    thresholds: NDArray[np.float64],
    scales: NDArray[np.float64],
    guess: float,
    lapse: float,
    p_target: float,
) -> NDArray[np.float64]:
    """:func:`_neg_log_lik` for many (threshold, scale) pairs at once, from ``n`` trials and
    ``k`` correct answers at each distinct level ``x``."""
    q = (p_target - guess) / (1.0 - guess - lapse)
    location = thresholds - scales * math.log(q / (1.0 - q))
    z = (x[None, :] - location[:, None]) / scales[:, None]
    e = np.exp(-np.abs(z))
    f = np.where(z >= 0, 1.0 / (1.0 + e), e / (1.0 + e))
    p = np.clip(guess + (1.0 - guess - lapse) * f, 1e-12, 1.0 - 1e-12)
    return -(k[None, :] * np.log(p) + (n - k)[None, :] * np.log(1.0 - p)).sum(axis=1)


def _nll_and_grad(
    params: NDArray[np.float64],
    x: NDArray[np.float64],
    r: NDArray[np.bool_],
    guess: float,
    lapse: float,
    p_target: float,
) -> tuple[float, NDArray[np.float64]]:
    """Negative log-likelihood and its gradient in (threshold, log scale) at a fixed lapse."""
    t, s = float(params[0]), math.exp(float(params[1]))
    q = (p_target - guess) / (1.0 - guess - lapse)
    c = math.log(q / (1.0 - q))  # z at the threshold
    z = (x - t) / s + c
    e = np.exp(-np.abs(z))
    f = np.where(z >= 0, 1.0 / (1.0 + e), e / (1.0 + e))
    span = 1.0 - guess - lapse
    p = np.clip(guess + span * f, 1e-12, 1.0 - 1e-12)
    nll = -float(np.log(np.where(r, p, 1.0 - p)).sum())
    # d(−log L)/dz per trial, then the chain rule: dz/dt = −1/s, dz/d(log s) = −(z − c).
    dldz = -np.where(r, 1.0 / p, -1.0 / (1.0 - p)) * span * f * (1.0 - f)
    grad = np.array([float((dldz * (-1.0 / s)).sum()), float((dldz * -(z - c)).sum())])
    return nll, grad
