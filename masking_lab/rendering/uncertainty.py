"""Uncertainty carried to the finger: how sure the rendering is of what is felt (issue 19.3).

Each masking function's (intercept, slope) uncertainty is drawn jointly, by the best means its
``masking_params.json`` entry offers:

1. *bootstrap draws* / *posterior draws*: the joint (a, b) draws the export stores
   (``draws``: up to 200 participant-bootstrap replicates of the fit), used as they are,
   cycled and shuffled to the number of draws asked for;
2. *covariance*: a bivariate normal with the exported standard errors and the
   intercept–slope covariance (``intercept_slope_cov``);
3. *parametric fallback*: independent normals with the exported standard errors (or the
   interval's half-width over the normal quantile), as files written before the export kept
   draws or covariances. A fitted intercept and slope are negatively correlated, so this
   overstates the spread in the middle of the fitted range (conservative intervals).

Slopes are kept ≥ 0; the two functions of a pair are drawn independently of each other.
For every draw the played inputs are pushed through the drawn model (paper Eq. 3–4), with and
without compensation, giving per-point percentile intervals of the perceived intensities. Two
per-point flags:

- *compensation not better*: over the draws, the paired gain |error without| − |error with|
  (dB, both channels summed) is not above 0 at the interval's lower percentile;
- *beyond the fitted range*: a compensated input masks the other channel at a level above the
  top of the masker range its ramp was fitted on (an extrapolated ramp).

Pure: the random generator is seeded by the caller.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from statistics import NormalDist
from typing import Any

import numpy as np
from numpy.typing import NDArray

from masking_lab.core.errors import SolverError
from masking_lab.rendering.render import NO_MASKING, Rendering

__all__ = ["PairSpread", "RenderingUncertainty", "pair_spread", "perceived_intervals"]

METHOD = (
    "parametric fallback (independent normals with the exported standard errors; the file "
    "stores no joint draws and no intercept-slope covariance, so the intervals are conservative)"
)
#: Short names of how one function's (intercept, slope) draws are made.
BOOTSTRAP, POSTERIOR, COVARIANCE, FALLBACK = (
    "bootstrap draws",
    "posterior draws",
    "covariance",
    "parametric fallback",
)


@dataclass(frozen=True)
class PairSpread:
    """Standard errors of the four ramp parameters (a, c in dB; b, d in dB/dB).

    Attributes
    ----------
    a_sd_db, b_sd, c_sd_db, d_sd : float
        Standard error of each parameter (0: known exactly).
    source : str
        Where they came from (``"bootstrap"``/``"asymptotic"`` per direction).
    ab_cov, cd_cov : float or None
        Intercept–slope covariance of each function (dB · dB/dB), when the file stores it.
    ab_draws, cd_draws : tuple of (float, float)
        Stored joint (intercept dB, slope dB/dB) draws of each function (empty: none).
    draws_kind : (str, str)
        ``"bootstrap"``/``"posterior"`` of the two functions' stored draws (``""``: none).
    names : (str, str)
        ``"target by masker"`` of the two functions (MV masked by EV first).
    """

    a_sd_db: float
    b_sd: float
    c_sd_db: float
    d_sd: float
    source: str = ""
    ab_cov: float | None = None
    cd_cov: float | None = None
    ab_draws: tuple[tuple[float, float], ...] = ()
    cd_draws: tuple[tuple[float, float], ...] = ()
    draws_kind: tuple[str, str] = ("", "")
    names: tuple[str, str] = ("MV by EV", "EV by MV")

    def methods(self) -> tuple[str, str]:
        """How each function is drawn: bootstrap/posterior draws, covariance or the fallback."""
        out = []
        for draws, kind, cov in (
            (self.ab_draws, self.draws_kind[0], self.ab_cov),
            (self.cd_draws, self.draws_kind[1], self.cd_cov),
        ):
            if draws:
                out.append(POSTERIOR if kind == "posterior" else BOOTSTRAP)
            else:
                out.append(COVARIANCE if cov is not None else FALLBACK)
        return out[0], out[1]


def pair_spread(
    params: Mapping[str, Any], *, mv: str, ev: str, level_default: float = 0.95
) -> PairSpread:
    """Read the uncertainty of one pair's two masking functions from masking_params.json.

    The standard errors, and the joint draws and intercept–slope covariance where the file
    stores them. A missing standard error is taken from the interval (half-width / z of its
    level); with neither, the parameter counts as exact (0) and ``source`` says so.

    Examples
    --------
    >>> doc = {"functions": [
    ...     {"target": "MV180", "masker": "EV270", "intercept_se_db": 0.4, "slope_se": 0.02,
    ...      "uncertainty": "bootstrap"},
    ...     {"target": "EV270", "masker": "MV180", "intercept_se_db": None, "slope_se": None,
    ...      "intercept_ci_db": [-7.0, -5.04], "slope_ci": [0.6, 0.7], "ci_level": 0.95}]}
    >>> s = pair_spread(doc, mv="MV180", ev="EV270")
    >>> round(s.a_sd_db, 3), round(s.c_sd_db, 3), round(s.d_sd, 4)
    (0.4, 0.5, 0.0255)
    >>> s.methods()
    ('parametric fallback', 'parametric fallback')
    """
    out: list[float] = []
    sources = []
    covs: list[float | None] = []
    joint: list[tuple[tuple[float, float], ...]] = []
    kinds: list[str] = []
    for target, masker in ((mv, ev), (ev, mv)):
        entry = next(
            (
                f
                for f in params.get("functions", [])
                if isinstance(f, Mapping) and (f.get("target"), f.get("masker")) == (target, masker)
            ),
            None,
        )
        if entry is None:
            raise SolverError(f"no masking function for {target} masked by {masker}")
        z = NormalDist().inv_cdf(0.5 + float(entry.get("ci_level") or level_default) / 2)
        for se_key, ci_key in (("intercept_se_db", "intercept_ci_db"), ("slope_se", "slope_ci")):
            se, ci = entry.get(se_key), entry.get(ci_key)
            if isinstance(se, int | float) and np.isfinite(se) and se >= 0:
                out.append(float(se))
            elif ci and all(isinstance(v, int | float) for v in ci) and np.isfinite(ci).all():
                out.append(abs(float(ci[1]) - float(ci[0])) / (2 * z))
            else:
                out.append(0.0)
        sources.append(f"{target} by {masker}: {entry.get('uncertainty', 'unknown')}")
        cov = entry.get("intercept_slope_cov")
        covs.append(float(cov) if isinstance(cov, int | float) and np.isfinite(cov) else None)
        raw_draws = entry.get("draws")
        d = raw_draws if isinstance(raw_draws, Mapping) else {}
        pairs = tuple(
            (float(a), float(b))
            for a, b in zip(d.get("intercept_db") or (), d.get("slope") or (), strict=False)
            if np.isfinite(a) and np.isfinite(b)
        )
        joint.append(pairs if len(pairs) >= 2 else ())
        kinds.append(str(d.get("method", "")) if joint[-1] else "")
    return PairSpread(
        out[0],
        out[1],
        out[2],
        out[3],
        "; ".join(sources),
        ab_cov=covs[0],
        cd_cov=covs[1],
        ab_draws=joint[0],
        cd_draws=joint[1],
        draws_kind=(kinds[0], kinds[1]),
        names=(f"{mv} by {ev}", f"{ev} by {mv}"),
    )


@dataclass(frozen=True)
class RenderingUncertainty:
    """Per-point intervals of the perceived intensities (dB SL) and the two flags.

    Attributes
    ----------
    level : float
        Interval level (e.g. 0.95).
    n_draws : int
        Parameter draws.
    mv_lo, mv_hi, ev_lo, ev_hi : ndarray
        Interval of the perceived intensity with compensation, dB SL.
    mv_uncomp_lo, mv_uncomp_hi, ev_uncomp_lo, ev_uncomp_hi : ndarray
        The same without compensation, dB SL.
    not_better : ndarray of bool
        Compensation is not better than none within the interval.
    beyond_fitted : ndarray of bool
        The compensation relies on a ramp beyond its fitted masker range.
    method : str
        How the draws were made, in words.
    method_by_function : tuple of (str, str)
        ``("target by masker", method)`` per masking function: ``"bootstrap draws"``,
        ``"posterior draws"``, ``"covariance"`` or ``"parametric fallback"``.
    """

    level: float
    n_draws: int
    mv_lo: NDArray[np.float64]
    mv_hi: NDArray[np.float64]
    ev_lo: NDArray[np.float64]
    ev_hi: NDArray[np.float64]
    mv_uncomp_lo: NDArray[np.float64]
    mv_uncomp_hi: NDArray[np.float64]
    ev_uncomp_lo: NDArray[np.float64]
    ev_uncomp_hi: NDArray[np.float64]
    not_better: NDArray[np.bool_]
    beyond_fitted: NDArray[np.bool_]
    method: str = METHOD
    method_by_function: tuple[tuple[str, str], ...] = ()

    def columns(self) -> dict[str, NDArray[Any]]:
        """The per-point columns for points.csv (dB SL; flags as bool)."""
        return {
            "mv_perceived_lo_db_sl": self.mv_lo,
            "mv_perceived_hi_db_sl": self.mv_hi,
            "ev_perceived_lo_db_sl": self.ev_lo,
            "ev_perceived_hi_db_sl": self.ev_hi,
            "mv_perceived_uncomp_lo_db_sl": self.mv_uncomp_lo,
            "mv_perceived_uncomp_hi_db_sl": self.mv_uncomp_hi,
            "ev_perceived_uncomp_lo_db_sl": self.ev_uncomp_lo,
            "ev_perceived_uncomp_hi_db_sl": self.ev_uncomp_hi,
            "compensation_not_better": self.not_better,
            "beyond_fitted_range": self.beyond_fitted,
        }

    def summary(self) -> dict[str, Any]:
        """JSON-ready counts and band widths (dB)."""

        def width(lo: NDArray[np.float64], hi: NDArray[np.float64]) -> float | None:
            w = hi - lo
            w = w[np.isfinite(w)]
            return round(float(np.max(w)), 6) if w.size else None

        return {
            "method": self.method,
            "method_by_function": dict(self.method_by_function),
            "n_draws": self.n_draws,
            "level": self.level,
            "max_band_width_db": {
                "MV": width(self.mv_lo, self.mv_hi),
                "EV": width(self.ev_lo, self.ev_hi),
            },
            "points_compensation_not_better": int(np.count_nonzero(self.not_better)),
            "points_beyond_fitted_range": int(np.count_nonzero(self.beyond_fitted)),
        }


def perceived_intervals(
    r: Rendering,
    spread: PairSpread,
    *,
    n_draws: int = 200,
    level: float = 0.95,
    rng: np.random.Generator | None = None,
) -> RenderingUncertainty:
    """Per-point intervals of what is felt under the masking functions' uncertainty.

    Parameters
    ----------
    r : Rendering
        A rendered scene (its played inputs and targets, dB SL).
    spread : PairSpread
        Standard errors of a, b, c, d.
    n_draws : int
        Parameter draws (≥ 20).
    level : float
        Interval level, 0–1.
    rng : numpy.random.Generator, optional
        Seeded generator (default: seed 0, so a rendering is reproducible).

    Returns
    -------
    RenderingUncertainty

    Examples
    --------
    >>> from masking_lab.rendering.pair import MutualMasking
    >>> from masking_lab.rendering.render import render_scene
    >>> from masking_lab.rendering.scene import GeometrySpec, PathSpec, Scene, TextureSpec
    >>> scene = Scene("bump_rough", PathSpec(n_points=91), GeometrySpec("bump"),
    ...               TextureSpec("rough", "MV180", 6.0))
    >>> pair = MutualMasking(1.304, 1.062, -5.927, 0.658, mv="MV180", ev="EV270")
    >>> u = perceived_intervals(render_scene(scene, pair), PairSpread(0.4, 0.03, 0.5, 0.02))
    >>> bool((u.mv_lo <= 6.0 + 1e-9).all() and (u.mv_hi >= 6.0 - 1e-9).all())
    True
    """
    if n_draws < 20:
        raise SolverError(f"uncertainty: give at least 20 draws, got {n_draws}")
    if not 0 < level < 1:
        raise SolverError(f"uncertainty: the interval level must be in (0, 1), got {level}")
    rng = rng if rng is not None else np.random.default_rng(0)
    pair = r.pair if r.pair is not None else NO_MASKING
    base = np.array([pair.a_db, pair.b, pair.c_db, pair.d])
    draws, method, by_function = _draws(base, spread, n_draws, rng, single=r.pair is None)
    mi, ei = r.mv_input_db_sl, r.ev_input_db_sl
    mt, et = r.mv_target_db_sl, r.ev_target_db_sl
    comp = np.empty((2, n_draws, mi.size))
    unc = np.empty((2, n_draws, mi.size))
    q = [50 * (1 - level), 50 * (1 + level)]
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        # A point without inputs (no unique answer) has no interval: NaN, written empty.
        warnings.simplefilter("ignore", RuntimeWarning)
        for k, (a, b, c, d) in enumerate(draws):
            comp[0, k], comp[1, k] = _forward(a, b, c, d, mi, ei)
            unc[0, k], unc[1, k] = _forward(a, b, c, d, mt, et)
        lo_c, hi_c = _nan_percentile(comp, q, axis=1)
        lo_u, hi_u = _nan_percentile(unc, q, axis=1)
        # Both against the targets the rendering aims at (the mapped ones, if mapped).
        gain = _error(unc, mt, et) - _error(comp, mt, et)
        gain_lo = _nan_percentile(gain, [q[0]], axis=0)[0]
    not_better = ~(gain_lo > 0)
    beyond = np.zeros(mi.shape, dtype=bool)
    if r.pair is not None:
        g_rng, f_rng = r.pair.g_fitted_range_db_sl, r.pair.f_fitted_range_db_sl
        if g_rng:
            beyond |= mi > g_rng[1]
        if f_rng:
            beyond |= ei > f_rng[1]
    return RenderingUncertainty(
        level=level,
        n_draws=n_draws,
        mv_lo=lo_c[0],
        mv_hi=hi_c[0],
        ev_lo=lo_c[1],
        ev_hi=hi_c[1],
        mv_uncomp_lo=lo_u[0],
        mv_uncomp_hi=hi_u[0],
        ev_uncomp_lo=lo_u[1],
        ev_uncomp_hi=hi_u[1],
        not_better=np.asarray(not_better),
        beyond_fitted=beyond,
        method=method,
        method_by_function=by_function,
    )


def _nan_percentile(x: NDArray[np.float64], q: list[float], axis: int) -> NDArray[np.float64]:
    """``np.nanpercentile(x, q, axis)`` (linear method), vectorised over the other axes.

    numpy falls back to one Python call per column as soon as a NaN is present (a point without
    a unique input): ~50 s of CPU for a 100,000-point scene, a hang to the user. Here one sort
    puts the NaNs last and every column is interpolated at once; all-NaN columns give NaN.
    """
    s = np.moveaxis(np.sort(x, axis=axis), axis, 0)
    n = np.sum(~np.isnan(s), axis=0)
    out = np.full((len(q), *s.shape[1:]), np.nan)
    has = n > 0
    for j, pct in enumerate(q):
        pos = (n - 1) * (np.float64(pct) / 100.0)
        below = np.floor(pos).astype(np.intp).clip(0, None)
        above = np.minimum(below + 1, np.maximum(n - 1, 0))
        t = pos - below
        a = np.take_along_axis(s, below[None], axis=0)[0]
        b = np.take_along_axis(s, above[None], axis=0)[0]
        diff = b - a
        # numpy's _lerp: from the nearer end, so an exact percentile stays exact.
        val = np.where(t >= 0.5, b - diff * (1 - t), a + diff * t)
        out[j] = np.where(has, val, np.nan)
    return out


def _draws(
    base: NDArray[np.float64],
    spread: PairSpread,
    n_draws: int,
    rng: np.random.Generator,
    *,
    single: bool,
) -> tuple[NDArray[np.float64], str, tuple[tuple[str, str], ...]]:
    """(n_draws, 4) draws of a, b, c, d, the method in words and per function."""
    if single:  # nothing masks a single channel
        return np.tile(base, (n_draws, 1)), "none (a single-channel scene has no masking)", ()
    sd = np.array([spread.a_sd_db, spread.b_sd, spread.c_sd_db, spread.d_sd])
    with np.errstate(over="ignore", invalid="ignore"):
        z = rng.standard_normal((n_draws, 4))  # the fallback's draws, as before
        draws = base + z * sd
    methods = spread.methods()
    words = []
    for k, (stored, cov, method) in enumerate(
        (
            (spread.ab_draws, spread.ab_cov, methods[0]),
            (spread.cd_draws, spread.cd_cov, methods[1]),
        )
    ):
        cols = [2 * k, 2 * k + 1]
        if stored:
            # Every stored draw used alike (cycled), in an order independent of the other
            # function's, so the two functions stay independent.
            idx = rng.permutation(np.arange(n_draws) % len(stored))
            draws[:, cols] = np.asarray(stored, dtype=float)[idx]
            words.append(f"{spread.names[k]}: {method} ({len(stored)} stored, used jointly)")
        elif cov is not None and sd[cols[0]] > 0 and sd[cols[1]] > 0:
            with np.errstate(over="ignore", invalid="ignore"):
                rho = float(np.clip(cov / (sd[cols[0]] * sd[cols[1]]), -1.0, 1.0))
            rho = rho if np.isfinite(rho) else 0.0
            mixed = rho * z[:, cols[0]] + np.sqrt(1.0 - rho**2) * z[:, cols[1]]
            draws[:, cols[1]] = base[cols[1]] + mixed * sd[cols[1]]
            words.append(
                f"{spread.names[k]}: {method} (bivariate normal, exported SEs, "
                f"correlation {rho:.2f})"
            )
        else:
            words.append(
                f"{spread.names[k]}: {FALLBACK} (independent normals with the exported SEs; "
                "no joint draws or covariance stored, so conservative)"
            )
    draws[:, [1, 3]] = np.maximum(draws[:, [1, 3]], 0.0)
    by_function = tuple(zip(spread.names, methods, strict=True))
    if methods == (FALLBACK, FALLBACK):
        return draws, METHOD, by_function
    return draws, "; ".join(words), by_function


def _forward(
    a: float, b: float, c: float, d: float, mi: NDArray[np.float64], ei: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    f = np.maximum(0.0, a + b * np.where(np.isfinite(ei), ei, -np.inf)) if b else max(0.0, a)
    g = np.maximum(0.0, c + d * np.where(np.isfinite(mi), mi, -np.inf)) if d else max(0.0, c)
    return mi - f, ei - g


def _error(
    perceived: NDArray[np.float64], want_m: NDArray[np.float64], want_e: NDArray[np.float64]
) -> NDArray[np.float64]:
    """|perceived − wanted| summed over the channels that play, per draw and point (dB)."""
    total = np.zeros(perceived.shape[1:])
    for k, want in enumerate((want_m, want_e)):
        if np.all(want == -np.inf):
            continue
        total = total + np.abs(perceived[k] - want)
    return total
