"""Least-squares fits of the masking ramp ``shift = max(0, a + b·x)`` (paper §2.4, Eq. 1–2).

``x`` is the masker level in dB SL and ``shift`` the AL shift in dB. The fit is exact, not
iterative: with the slope constrained to b ≥ 0 the least-squares problem splits, by where the
knee −a/b falls between the sorted masker levels, into convex pieces whose minima are one of a
small set of candidates, each a *linear* map of the shifts:

* ordinary least squares on the points at or above each masker level (knee between two levels);
* a line through ``(u, 0)`` for each masker level ``u`` (knee exactly on a level);
* a constant ``max(0, mean)`` (b = 0) and zero (no masking at all).

Evaluating the true ramp loss of every candidate and keeping the smallest is the global optimum.
Because every candidate is linear in the shifts, thousands of bootstrap replicates are fitted at
once with one matrix product (:func:`ramp_least_squares_batch`).

Degenerate inputs never produce NaN: they give a :class:`RampFit` whose ``status`` is
``"insufficient_data"`` (fewer than two masker levels) or ``"no_masking"`` (every point lies in
the ramp's flat region), with a ``message`` saying what happened.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from masking_lab.analysis.distributions import t_ppf
from masking_lab.core.errors import AnalysisError

FitStatus = Literal["fitted", "no_masking", "insufficient_data"]
Uncertainty = Literal["asymptotic", "bootstrap", "none"]

# Shifts and levels are in dB with ~0.01 dB resolution; anything below this is numerical noise.
_TINY = 1e-9


@dataclass(frozen=True)
class RampFit:
    """A least-squares ramp fit and its diagnostics.

    Attributes
    ----------
    intercept_db : float or None
        Ramp intercept a in dB (AL shift at a 0 dB SL masker before the max with 0). 0.0 when
        ``status`` is ``"no_masking"``; None when ``"insufficient_data"``.
    slope : float or None
        Ramp slope b, dB of shift per dB SL of masker (≥ 0). Same conventions as the intercept.
    intercept_se_db, slope_se : float or None
        Standard errors (dB; dB/dB SL): asymptotic, or the SD of bootstrap replicates.
    intercept_ci_db, slope_ci : tuple[float, float] or None
        Confidence intervals at ``ci_level`` (t-based asymptotic or bootstrap percentile).
    ci_level : float
        Coverage of the intervals, e.g. 0.95.
    uncertainty : {"asymptotic", "bootstrap", "none"}
        How the SEs and intervals were obtained.
    r2, adj_r2 : float or None
        (Adjusted) coefficient of determination over all fitted points, with the ramp's two
        parameters; None with fewer than three points or zero variance in the shifts.
    adj_r2_active : float or None
        Adjusted R² of the straight line over the points above the knee only (how the paper
        appears to report it); None with fewer than three such points.
    knee_db_sl : float or None
        Masker level −a/b in dB SL below which the ramp is flat (no masking); None for b = 0.
    fitted_range_db_sl : tuple[float, float]
        Lowest and highest masker level fitted, dB SL.
    n_points : int
        Points fitted.
    n_active_levels : int
        Distinct masker levels above the knee (the points that carry the slope).
    sse_db2 : float
        Residual sum of squares, dB².
    status : {"fitted", "no_masking", "insufficient_data"}
        Outcome; only ``"fitted"`` carries a usable slope.
    message : str or None
        Why the status is what it is, or a caution about a fitted ramp.
    n_boot_failed : int
        Bootstrap replicates that could not be fitted (0 unless ``uncertainty == "bootstrap"``).
    intercept_slope_cov : float or None
        Covariance of intercept and slope (dB · dB/dB SL): asymptotic, or over the bootstrap
        replicates; None without standard errors.
    draws : tuple of (intercept_db, slope) tuples
        Up to :data:`MAX_KEPT_DRAWS` joint bootstrap replicates, in the order drawn (empty
        unless ``uncertainty == "bootstrap"``): the export carries them to the rendering.
    """

    intercept_db: float | None
    slope: float | None
    intercept_se_db: float | None
    slope_se: float | None
    intercept_ci_db: tuple[float, float] | None
    slope_ci: tuple[float, float] | None
    ci_level: float
    uncertainty: Uncertainty
    r2: float | None
    adj_r2: float | None
    adj_r2_active: float | None
    knee_db_sl: float | None
    fitted_range_db_sl: tuple[float, float]
    n_points: int
    n_active_levels: int
    sse_db2: float
    status: FitStatus
    message: str | None
    n_boot_failed: int = 0
    intercept_slope_cov: float | None = None
    draws: tuple[tuple[float, float], ...] = ()


#: Joint bootstrap replicates a fit keeps for the export (the rest only shape its SEs and CIs).
MAX_KEPT_DRAWS = 200


def ramp_least_squares_batch(
    x: ArrayLike, shifts: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Exact least-squares ramp for many replicates sharing one design.

    Parameters
    ----------
    x : array_like, shape (n,)
        Masker levels in dB SL (at least two distinct values, all finite).
    shifts : array_like, shape (n,) or (B, n)
        AL shifts in dB; each row is one replicate (finite).

    Returns
    -------
    intercept_db, slope : ndarray, shape (B,)
        Best ramp per replicate, slope ≥ 0. A replicate with no masking at all gets (0, 0).

    Raises
    ------
    AnalysisError
        If the inputs are not finite or there are fewer than two distinct masker levels.

    Examples
    --------
    Three replicates at 0, 10 and 20 dB SL: a ramp with its knee at 5 dB SL, no masking at
    all, and a constant 3 dB shift:

    >>> a, b = ramp_least_squares_batch([0, 10, 20], [[0, 4, 12], [0, 0, 0], [3, 3, 3]])
    >>> np.round(a, 6).tolist(), np.round(b, 6).tolist()
    ([-4.0, 0.0, 3.0], [0.8, 0.0, 0.0])
    """
    xv = _finite_vector(x, "masker level (dB SL)")
    y = np.atleast_2d(np.asarray(shifts, dtype=float))
    if y.shape[1] != xv.size:
        raise AnalysisError(
            f"got {xv.size} masker levels but {y.shape[1]} shifts per replicate; "
            "give one shift per masker level"
        )
    if not np.isfinite(y).all():
        raise AnalysisError("shifts contain NaN or ±inf; drop or fix those points before fitting")
    if np.unique(xv).size < 2:
        raise AnalysisError(
            f"a ramp needs shifts at two or more masker levels; got only {_levels_text(xv)} dB SL"
        )
    maps = _candidate_maps(xv)  # (K, 2, n)
    coef = np.einsum("kpn,bn->bkp", maps, y)  # (B, K, 2)
    a, b = coef[..., 0], coef[..., 1]
    pred = np.maximum(0.0, a[..., None] + b[..., None] * xv)  # (B, K, n)
    loss = ((pred - y[:, None, :]) ** 2).sum(axis=2)
    loss[b < -_TINY] = np.inf  # masking never decreases with masker level
    best = np.argmin(loss, axis=1)  # first minimum: candidate order breaks ties
    rows = np.arange(y.shape[0])
    a_best, b_best = a[rows, best], np.maximum(b[rows, best], 0.0)
    # Normalise "no masking anywhere in range" to the canonical zero ramp.
    flat = np.all(np.maximum(0.0, a_best[:, None] + b_best[:, None] * xv) <= _TINY, axis=1)
    a_best[flat], b_best[flat] = 0.0, 0.0
    # A flat ramp at a positive level: the slope is exactly 0.
    b_best[np.abs(b_best) <= _TINY] = 0.0
    return a_best, b_best


def ramp_least_squares(x: ArrayLike, shifts: ArrayLike) -> tuple[float, float]:
    """Exact least-squares ramp ``(intercept_db, slope)`` for one set of points (see batch).

    Parameters
    ----------
    x : array_like, shape (n,)
        Masker levels, dB SL.
    shifts : array_like, shape (n,)
        AL shifts, dB.

    Returns
    -------
    intercept_db : float
        Ramp intercept a, dB.
    slope : float
        Ramp slope b ≥ 0, dB of shift per dB SL of masker.

    Examples
    --------
    >>> a, b = ramp_least_squares([0, 5, 10, 15, 20, 25], [0.0, 0.1, 2.1, 5.9, 10.2, 13.8])
    >>> round(a, 2), round(b, 3)
    (-5.79, 0.788)
    """
    a, b = ramp_least_squares_batch(x, np.asarray(shifts, dtype=float)[None, :])
    return float(a[0]), float(b[0])


def fit_ramp(x: ArrayLike, shifts: ArrayLike, *, ci_level: float = 0.95) -> RampFit:
    """Fit ``max(0, a + b·x)`` by least squares, with asymptotic uncertainty.

    Parameters
    ----------
    x : array_like
        Masker levels in dB SL, one per point.
    shifts : array_like
        AL shifts in dB, one per point.
    ci_level : float
        Coverage of the confidence intervals (0 < ci_level < 1).

    Returns
    -------
    RampFit
        Degenerate data give ``status`` ``"insufficient_data"`` or ``"no_masking"`` and a
        ``message``; no field is ever NaN.

    Notes
    -----
    The asymptotic covariance is the Gauss–Newton one, ``σ²(JᵀJ)⁻¹`` with ``σ² = SSE/(n − 2)``
    and ``J`` the Jacobian ``[1, x]`` on points above the knee (0 on the flat ones); intervals use
    Student's t with n − 2 degrees of freedom.

    Examples
    --------
    >>> fit = fit_ramp([0, 5, 10, 15, 20, 25], [0.0, 0.1, 2.1, 5.9, 10.2, 13.8])
    >>> fit.status, round(fit.slope, 3), round(fit.knee_db_sl, 2), fit.n_active_levels
    ('fitted', 0.788, 7.35, 4)
    >>> [round(v, 3) for v in fit.slope_ci]
    [0.75, 0.826]
    >>> fit_ramp([10, 10], [1.0, 2.0]).status  # one masker level cannot fix a slope
    'insufficient_data'
    >>> fit_ramp([0, 10, 20], [0.0, 0.0, 0.0]).status
    'no_masking'
    """
    if not 0.0 < ci_level < 1.0:
        raise AnalysisError(f"ci_level must lie between 0 and 1, got {ci_level}")
    xv = _finite_vector(x, "masker level (dB SL)")
    y = _finite_vector(shifts, "AL shift (dB)")
    if xv.size != y.size:
        raise AnalysisError(f"got {xv.size} masker levels but {y.size} shifts")
    fitted_range = (float(xv.min()), float(xv.max())) if xv.size else (0.0, 0.0)
    base: dict[str, Any] = dict(  # the fields every outcome shares; RampFit checks the rest
        intercept_se_db=None,
        slope_se=None,
        intercept_ci_db=None,
        slope_ci=None,
        ci_level=ci_level,
        uncertainty="none",
        r2=None,
        adj_r2=None,
        adj_r2_active=None,
        knee_db_sl=None,
        fitted_range_db_sl=fitted_range,
        n_points=int(xv.size),
        n_active_levels=0,
    )
    if np.unique(xv).size < 2:
        return RampFit(
            intercept_db=None,
            slope=None,
            sse_db2=0.0,
            status="insufficient_data",
            message=(
                "a ramp needs shifts at two or more masker levels; got "
                f"{_levels_text(xv) or 'none'} dB SL — measure more levels or pool this pair "
                "with another"
            ),
            **base,
        )
    a, b = ramp_least_squares(xv, y)
    pred = np.maximum(0.0, a + b * xv)
    resid = y - pred
    sse = float(resid @ resid)
    n = xv.size
    sst = float(((y - y.mean()) ** 2).sum())
    r2 = adj = None
    if sst > _TINY and n >= 3:
        r2 = 1.0 - sse / sst
        adj = 1.0 - (1.0 - r2) * (n - 1) / (n - 2)
    if a == 0.0 and b == 0.0:
        return RampFit(
            intercept_db=0.0,
            slope=0.0,
            sse_db2=sse,
            status="no_masking",
            message=(
                f"every point lies in the ramp's flat region (largest shift {y.max():.3g} dB): "
                f"no masking between {fitted_range[0]:g} and {fitted_range[1]:g} dB SL; the "
                "exported ramp is 0 there and says nothing about higher masker levels"
            ),
            **{**base, "r2": r2, "adj_r2": adj},
        )
    active = (a + b * xv) > _TINY
    active_levels = np.unique(xv[active])
    knee = -a / b if b > 0 else None
    messages = []
    if b == 0.0:
        messages.append(
            f"the shift does not change with masker level (constant {a:.3g} dB, slope 0)"
        )
    elif active_levels.size == 1:
        messages.append(
            f"only one masker level ({active_levels[0]:g} dB SL) lies above the knee; the "
            "slope rests on that level alone"
        )
    elif knee is not None and knee < fitted_range[0]:
        messages.append(
            f"the knee ({knee:.3g} dB SL) lies below the lowest fitted level; the flat region "
            "is an extrapolation"
        )
    adj_active = _adj_r2_line(xv[active], y[active])
    fit = RampFit(
        intercept_db=float(a),
        slope=float(b),
        sse_db2=sse,
        status="fitted",
        message="; ".join(messages) or None,
        **{
            **base,
            "r2": r2,
            "adj_r2": adj,
            "adj_r2_active": adj_active,
            "knee_db_sl": None if knee is None else float(knee),
            "n_active_levels": int(active_levels.size),
        },
    )
    return _with_asymptotic(fit, xv[active], sse, n)


def _with_asymptotic(fit: RampFit, x_active: NDArray[np.float64], sse: float, n: int) -> RampFit:
    dof = n - 2
    if dof < 1 or np.unique(x_active).size < 2:
        why = (
            "no degrees of freedom left for uncertainty (two points fit exactly)"
            if dof < 1
            else "no standard errors: fewer than two masker levels above the knee"
        )
        msg = f"{fit.message}; {why}" if fit.message else why
        return replace(fit, message=msg)
    J = np.column_stack([np.ones_like(x_active), x_active])
    cov = (sse / dof) * np.linalg.inv(J.T @ J)
    se_a, se_b = math.sqrt(max(cov[0, 0], 0.0)), math.sqrt(max(cov[1, 1], 0.0))
    t = float(t_ppf(0.5 + fit.ci_level / 2.0, dof))
    a, b = float(fit.intercept_db), float(fit.slope)  # type: ignore[arg-type]  # fitted: set
    return replace(
        fit,
        intercept_se_db=se_a,
        slope_se=se_b,
        intercept_ci_db=(a - t * se_a, a + t * se_a),
        slope_ci=(b - t * se_b, b + t * se_b),
        uncertainty="asymptotic",
        intercept_slope_cov=float(cov[0, 1]),
    )


def with_bootstrap(
    fit: RampFit, boot_intercept_db: ArrayLike, boot_slope: ArrayLike, *, n_failed: int = 0
) -> RampFit:
    """Replace a fit's SEs and intervals by bootstrap ones.

    Parameters
    ----------
    fit : RampFit
        The point estimate (status ``"fitted"``; other statuses are returned unchanged).
    boot_intercept_db, boot_slope : array_like
        Replicate estimates (dB; dB/dB SL).
    n_failed : int
        Replicates that could not be fitted (reported, not hidden).

    Returns
    -------
    RampFit
        SE = SD of the replicates, intervals = percentile intervals at ``fit.ci_level``,
        their covariance, and the first :data:`MAX_KEPT_DRAWS` replicates as joint draws
        (replicates are independent, so the first ones are a random subset).

    Examples
    --------
    >>> fit = fit_ramp([0, 10, 20], [0.0, 4.0, 12.0])
    >>> boot = with_bootstrap(fit, [-4.2, -3.8, -4.0], [0.78, 0.82, 0.80])
    >>> boot.uncertainty, round(boot.slope_se, 3), len(boot.draws)
    ('bootstrap', 0.02, 3)
    """
    if fit.status != "fitted":
        return fit
    ab = np.asarray(boot_intercept_db, dtype=float)
    bb = np.asarray(boot_slope, dtype=float)
    if ab.size < 2:
        msg = "bootstrap gave fewer than two usable replicates; kept asymptotic uncertainty"
        return replace(fit, message=f"{fit.message}; {msg}" if fit.message else msg)
    q = [50.0 * (1.0 - fit.ci_level), 50.0 * (1.0 + fit.ci_level)]
    a_lo, a_hi = np.percentile(ab, q)
    b_lo, b_hi = np.percentile(bb, q)
    message = fit.message
    if n_failed:
        note = f"{n_failed} of {ab.size + n_failed} bootstrap replicates could not be fitted"
        message = f"{message}; {note}" if message else note
    return replace(
        fit,
        intercept_se_db=float(ab.std(ddof=1)),
        slope_se=float(bb.std(ddof=1)),
        intercept_ci_db=(float(a_lo), float(a_hi)),
        slope_ci=(float(b_lo), float(b_hi)),
        uncertainty="bootstrap",
        message=message,
        n_boot_failed=int(n_failed),
        intercept_slope_cov=float(np.cov(ab, bb, ddof=1)[0, 1]),
        draws=tuple(zip(ab[:MAX_KEPT_DRAWS].tolist(), bb[:MAX_KEPT_DRAWS].tolist(), strict=True)),
    )


def participant_bootstrap(
    x: ArrayLike,
    shifts_by_participant: ArrayLike,
    *,
    n_boot: int,
    rng: np.random.Generator,
) -> tuple[NDArray[np.float64], NDArray[np.float64], int]:
    """Bootstrap the ramp by resampling participants (cases), refitting cell means each time.

    Parameters
    ----------
    x : array_like, shape (C,)
        Masker level in dB SL of each cell (point) of the fit.
    shifts_by_participant : array_like, shape (P, C)
        AL shift in dB of each participant in each cell; NaN where a participant has no
        threshold for that cell.
    n_boot : int
        Replicates (≥ 2).
    rng : numpy.random.Generator
        Source of the resampling (seeded by the caller for reproducibility).

    Returns
    -------
    intercept_db, slope : ndarray
        Estimates of the replicates that could be fitted.
    n_failed : int
        Replicates with fewer than two masker levels left (every participant drawn lacked them).

    Raises
    ------
    AnalysisError
        For non-finite levels, a shape mismatch or ``n_boot`` < 2.

    Examples
    --------
    AL shifts (dB) of four participants at 0, 10 and 20 dB SL; a 95 % interval of the slope:

    >>> shifts = [[0, 2, 10], [0, 5, 14], [0, 4, 12], [1, 6, 11]]
    >>> a, b, failed = participant_bootstrap(
    ...     [0, 10, 20], shifts, n_boot=500, rng=np.random.default_rng(0))
    >>> len(b), failed, [round(float(v), 2) for v in np.percentile(b, [2.5, 97.5])]
    (500, 0, [0.55, 0.87])
    """
    xv = _finite_vector(x, "masker level (dB SL)")
    data = np.asarray(shifts_by_participant, dtype=float)
    if data.ndim != 2 or data.shape[1] != xv.size:
        raise AnalysisError("shifts_by_participant must be participants × cells")
    if n_boot < 2:
        raise AnalysisError(f"n_boot must be at least 2, got {n_boot}")
    n_part = data.shape[0]
    present = np.isfinite(data)
    filled = np.where(present, data, 0.0)
    # Each replicate as weights (how often each participant was drawn) times the data, not as
    # a materialised B x P x C copy. Drawn in blocks of replicates, which consume the generator
    # exactly as one (B, P) draw does; only a block's weights exist at a time, so the memory is
    # B x C plus ~2e6 weights (16 MB), whatever the number of participants.
    present_f = present.astype(float)
    counts = np.empty((n_boot, present.shape[1]))  # participants drawn with data, per cell
    sums = np.empty_like(counts)
    block = max(1, 2_000_000 // max(1, n_part))
    # One weights buffer for every block. The draws are int32 (the same 32-bit stream as
    # int64, in half the memory) and counted a replicate at a time: only a block's draws and
    # the weights exist at once (at 10,000 sessions 24 MB; a flat count held 48 MB).
    buffer = np.empty((min(block, n_boot), n_part))
    for lo in range(0, n_boot, block):
        rows = min(block, n_boot - lo)
        draws = rng.integers(0, n_part, size=(rows, n_part), dtype=np.int32)
        weights = buffer[:rows]
        for r in range(rows):
            weights[r] = np.bincount(draws[r], minlength=n_part)
        del draws
        counts[lo : lo + rows] = weights @ present_f
        sums[lo : lo + rows] = weights @ filled
    del buffer, weights
    with np.errstate(invalid="ignore", divide="ignore"):
        means = sums / counts
    complete = (counts > 0).all(axis=1)
    a_out: list[NDArray[np.float64]] = []
    b_out: list[NDArray[np.float64]] = []
    if complete.any():
        a, b = ramp_least_squares_batch(xv, means[complete])
        a_out.append(a)
        b_out.append(b)
    failed = 0
    for row in np.flatnonzero(~complete):  # rare: some cell drew nobody with data
        keep = counts[row] > 0
        if np.unique(xv[keep]).size < 2:
            failed += 1
            continue
        a1, b1 = ramp_least_squares(xv[keep], means[row, keep])
        a_out.append(np.array([a1]))
        b_out.append(np.array([b1]))
    if not a_out:
        return np.empty(0), np.empty(0), failed
    return np.concatenate(a_out), np.concatenate(b_out), failed


# --------------------------------------------------------------------------------------------


def _candidate_maps(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Linear maps y ↦ (a, b) of every candidate optimum, shape (K, 2, n). Order breaks ties."""
    n = x.size
    levels = np.unique(x)
    maps: list[NDArray[np.float64]] = [np.zeros((2, n))]  # no masking
    const = np.zeros((2, n))
    const[0, :] = 1.0 / n  # a = mean(y), b = 0
    maps.append(const)
    for u in levels[:-1]:
        # OLS on the points at or above level u (knee between the level below u and u).
        sel = x >= u
        X = np.column_stack([np.ones(int(sel.sum())), x[sel]])
        m = np.zeros((2, n))
        m[:, sel] = np.linalg.pinv(X)
        maps.append(m)
        # Line through (u, 0) fitted to the points above u (knee exactly at u).
        above = x > u
        d = x[above] - u
        m = np.zeros((2, n))
        m[1, above] = d / float(d @ d)
        m[0, above] = -u * d / float(d @ d)
        maps.append(m)
    return np.stack(maps)


def _adj_r2_line(x: NDArray[np.float64], y: NDArray[np.float64]) -> float | None:
    n = x.size
    if n < 3 or np.unique(x).size < 2:
        return None
    sst = float(((y - y.mean()) ** 2).sum())
    if sst <= _TINY:
        return None
    coef = np.polynomial.polynomial.polyfit(x, y, 1)
    resid = y - (coef[0] + coef[1] * x)
    r2 = 1.0 - float(resid @ resid) / sst
    return 1.0 - (1.0 - r2) * (n - 1) / (n - 2)


def _finite_vector(values: ArrayLike, what: str) -> NDArray[np.float64]:
    v = np.asarray(values, dtype=float).ravel()
    if not np.isfinite(v).all():
        bad = int(np.flatnonzero(~np.isfinite(v))[0])
        raise AnalysisError(f"{what} at position {bad} is {v[bad]!r}; give finite numbers")
    return v


def _levels_text(x: NDArray[np.float64]) -> str:
    return ", ".join(f"{u:g}" for u in np.unique(x))
