"""Pooling by model comparison: one ramp for several frequency levels against one ramp each.

The paper pools levels whose Bonferroni-corrected paired test is not significant
(:mod:`masking_lab.analysis.pooling`, the default decision). That treats absence of evidence as
equivalence; Palamedes' answer is to compare the models directly. For a candidate group of
levels this module fits the ramp ``max(0, a + b·x)`` (:func:`~masking_lab.analysis.ramp_fit.
ramp_least_squares`) to every participant's shifts of the group at once (pooled, 2 parameters)
and to each level separately (2 per level), with Gaussian errors of one common variance, and
reports:

- the likelihood ratio LR = n·ln(RSS_pooled / RSS_separate) against χ² with 2(k − 1) degrees
  of freedom (k levels), and the extra-sum-of-squares F test (better for small n);
- ΔAIC = AIC_pooled − AIC_separate = LR − 4(k − 1) and ΔBIC = LR − 2(k − 1)·ln n: negative
  values favour the pooled ramp.

The points are individual participants' shifts, which are correlated within a participant; the
tests treat them as independent, so their p-values are optimistic (a reason to keep the paper's
rule as the decision and report these beside it). Pure. Shifts and intercepts in dB, masker
levels in dB SL.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from masking_lab.analysis.distributions import chi2_sf, f_sf
from masking_lab.analysis.ramp_fit import ramp_least_squares

__all__ = ["PoolComparison", "compare_pooling", "comparison_lines", "pooled_vs_separate"]


@dataclass(frozen=True)
class PoolComparison:
    """One ramp for ``levels`` against one ramp per level.

    Attributes
    ----------
    levels : tuple of str
        The frequency levels compared (MV stimulus names).
    n_points : int
        Shifts fitted.
    rss_pooled_db2, rss_separate_db2 : float
        Residual sums of squares, dB².
    lr_chi2 : float
        Likelihood-ratio statistic.
    df : int
        Its degrees of freedom, 2(k − 1).
    p_lr : float
        χ² p-value of the LR (NaN when it cannot be formed).
    f_stat, p_f : float
        Extra-sum-of-squares F statistic and p-value.
    delta_aic, delta_bic : float
        Pooled minus separate; negative favours pooling.
    """

    levels: tuple[str, ...]
    n_points: int
    rss_pooled_db2: float
    rss_separate_db2: float
    lr_chi2: float
    df: int
    p_lr: float
    f_stat: float
    p_f: float
    delta_aic: float
    delta_bic: float

    def prefers(self, alpha: float = 0.05) -> str:
        """``"pooled"`` when the separate ramps do not fit significantly better (LR test at
        ``alpha``) and BIC does not favour them, else ``"separate"``."""
        if math.isfinite(self.p_lr) and self.p_lr < alpha:
            return "separate"
        if math.isfinite(self.delta_bic) and self.delta_bic > 0:
            return "separate"
        return "pooled"


def pooled_vs_separate(points: Mapping[str, tuple[ArrayLike, ArrayLike]]) -> PoolComparison:
    """Compare one ramp through all ``points`` with one ramp per level.

    Parameters
    ----------
    points : mapping of level → (masker levels dB SL, shifts dB)
        Every participant's shifts of each level (at least two masker levels each).

    Examples
    --------
    Two levels with the same ramp pool; two very different ramps do not:

    >>> x = np.repeat([5.0, 10.0, 15.0, 20.0, 25.0], 10)
    >>> noise = np.random.default_rng(1).normal(0, 1, (2, x.size))
    >>> same = pooled_vs_separate({"MV120": (x, 0.8 * x - 4 + noise[0]),
    ...                            "MV180": (x, 0.8 * x - 4 + noise[1])})
    >>> same.prefers(), same.df
    ('pooled', 2)
    >>> apart = pooled_vs_separate({"MV120": (x, 0.8 * x - 4 + noise[0]),
    ...                             "MV180": (x, 0.3 * x + noise[1])})
    >>> apart.prefers(), apart.p_lr < 1e-6
    ('separate', True)
    """
    levels = tuple(points)
    rss_sep = 0.0
    xs, ys = [], []
    for lv in levels:
        x = np.asarray(points[lv][0], dtype=float)
        y = np.asarray(points[lv][1], dtype=float)
        rss_sep += _rss(x, y)
        xs.append(x)
        ys.append(y)
    x_all, y_all = np.concatenate(xs), np.concatenate(ys)
    rss_pool = _rss(x_all, y_all)
    n, k = int(x_all.size), len(levels)
    df = 2 * (k - 1)
    tiny = 1e-12 * max(1.0, float(np.sum(y_all**2)))
    if rss_sep <= tiny or n <= 2 * k:
        lr = f_stat = p_lr = p_f = math.nan
    else:
        lr = n * math.log(max(rss_pool, rss_sep) / rss_sep)
        p_lr = float(chi2_sf(lr, df))
        f_stat = ((rss_pool - rss_sep) / df) / (rss_sep / (n - 2 * k))
        p_f = float(f_sf(f_stat, df, n - 2 * k))
    d_aic = lr - 2 * df if math.isfinite(lr) else math.nan
    d_bic = lr - df * math.log(n) if math.isfinite(lr) else math.nan
    return PoolComparison(levels, n, rss_pool, rss_sep, lr, df, p_lr, f_stat, p_f, d_aic, d_bic)


def compare_pooling(
    points: Mapping[str, tuple[ArrayLike, ArrayLike]], levels: Sequence[str]
) -> list[PoolComparison]:
    """Every pair of ``levels`` and, with three or more, all of them together.

    Examples
    --------
    >>> x = np.repeat([5.0, 15.0, 25.0], 4)
    >>> pts = {lv: (x, 0.5 * x + i) for i, lv in enumerate(["MV120", "MV180", "MV270"])}
    >>> [c.levels for c in compare_pooling(pts, ["MV120", "MV180", "MV270"])][-1]
    ('MV120', 'MV180', 'MV270')
    """
    usable = [lv for lv in levels if lv in points and np.unique(points[lv][0]).size >= 2]
    groups = [tuple(g) for g in itertools.combinations(usable, 2)]
    if len(usable) >= 3:
        groups.append(tuple(usable))
    return [pooled_vs_separate({lv: points[lv] for lv in g}) for g in groups]


def comparison_lines(comparisons: Sequence[PoolComparison], alpha: float = 0.05) -> list[str]:
    """One report line per comparison.

    Examples
    --------
    >>> x = np.repeat([5.0, 15.0, 25.0], 4)
    >>> pts = {"MV120": (x, 0.5 * x), "MV180": (x, 0.5 * x + np.tile([0.1, -0.1], 6))}
    >>> comparison_lines(compare_pooling(pts, ["MV120", "MV180"]))[0][:27]
    'MV120+MV180: one ramp vs 2:'
    """
    out = []
    for c in comparisons:
        p = "—" if not math.isfinite(c.p_lr) else f"{c.p_lr:.3g}"
        pf = "—" if not math.isfinite(c.p_f) else f"{c.p_f:.3g}"
        out.append(
            f"{'+'.join(c.levels)}: one ramp vs {len(c.levels)}: LR χ²({c.df}) = "
            f"{c.lr_chi2:.2f}, p = {p}; F p = {pf}; ΔAIC {c.delta_aic:+.1f}, "
            f"ΔBIC {c.delta_bic:+.1f} (n = {c.n_points}) → {c.prefers(alpha)}"
        )
    return out


def _rss(x: np.ndarray, y: np.ndarray) -> float:
    a, b = ramp_least_squares(x, y)
    return float(np.sum((np.maximum(0.0, a + b * x) - y) ** 2))
