"""Repeated-measures statistics of AL shifts (paper §2.4): pure functions on arrays and tables.

* :func:`rm_anova` — two-way (or one-way) repeated-measures ANOVA on a participants × A × B
  array, with Mauchly's test of sphericity, the Greenhouse–Geisser ε and corrected p, and
  partial η², per effect (``frequency``, ``level``, ``frequency:level``).

The t-tests (post hoc paired comparisons, one-sample and paired t) are in
:mod:`masking_lab.analysis.t_tests`.

Every effect is computed from orthonormal contrasts: for an effect with ``d`` degrees of freedom
and contrast matrix ``C`` (cells × d), the scores ``Z = Y·C`` give ``SS_effect = n·|mean(Z)|²``
and ``SS_error = Σ|Z − mean(Z)|²``; the sample covariance ``S`` of ``Z`` gives
``ε_GG = tr(S)² / (d·tr(S²))`` and Mauchly's ``W = det(S) / (tr(S)/d)^d``. The χ² approximation
of W and its second-order correction follow R's ``car`` package (used by ``afex``), with ``k``
the number of conditions of the whole design, so p-values match R and ``pingouin.rm_anova``.

Degenerate inputs raise :class:`~masking_lab.core.errors.AnalysisError` with a message naming the
problem (one participant, zero variance, a missing cell) instead of returning NaN.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from masking_lab.analysis.distributions import chi2_sf, f_sf
from masking_lab.core.errors import AnalysisError

EFFECT_NAMES = ("frequency", "level", "frequency:level")
# Relative size under which a sum of squares counts as exactly zero (floating-point noise).
_ZERO_REL = 1e-12


@dataclass(frozen=True)
class Effect:
    """One row of a repeated-measures ANOVA table.

    Attributes
    ----------
    name : str
        ``"frequency"``, ``"level"`` or ``"frequency:level"`` (or the names passed in).
    F : float
        F ratio.
    df1, df2 : int
        Effect and error degrees of freedom (uncorrected).
    p : float
        Uncorrected p-value.
    eps_gg : float
        Greenhouse–Geisser ε (1 for an effect with one degree of freedom).
    p_gg : float
        p-value with both dfs multiplied by ``eps_gg``.
    np2 : float
        Partial η² = SS_effect / (SS_effect + SS_error).
    ss_effect, ss_error : float
        Sums of squares, dB².
    mauchly_w, mauchly_chi2, mauchly_p : float or None
        Mauchly's test; W = 1, p = 1 for one df; None if there are too few participants
        (n − 1 < df1) for the test to exist.
    mauchly_df : int
        Degrees of freedom of Mauchly's χ².
    note : str or None
        Why Mauchly's test is missing, if it is.
    """

    name: str
    F: float
    df1: int
    df2: int
    p: float
    eps_gg: float
    p_gg: float
    np2: float
    ss_effect: float
    ss_error: float
    mauchly_w: float | None
    mauchly_chi2: float | None
    mauchly_df: int
    mauchly_p: float | None
    note: str | None = None


@dataclass(frozen=True)
class RMDesign:
    """A complete participants × A × B array built from a long table.

    Attributes
    ----------
    data : ndarray, shape (n, a, b)
        The dependent variable (e.g. AL shift in dB) per participant and cell.
    subjects : tuple[str, ...]
        Participants kept (each has every cell).
    levels_a, levels_b : tuple
        Levels of the two factors, sorted.
    dropped : tuple[tuple[str, str], ...]
        ``(participant, reason)`` of participants left out for missing cells.
    """

    data: NDArray[np.float64]
    subjects: tuple[str, ...]
    levels_a: tuple
    levels_b: tuple
    dropped: tuple[tuple[str, str], ...]


# --------------------------------------------------------------------------------------------
# Building the design


def rm_design(
    table: pd.DataFrame, *, subject: str, factor_a: str, factor_b: str, dv: str
) -> RMDesign:
    """Pivot a long table to participants × A × B, dropping participants with missing cells.

    Parameters
    ----------
    table : DataFrame
        One row per participant and cell; ``dv`` in its unit (AL shift in dB).
    subject, factor_a, factor_b, dv : str
        Column names of the participant, the two factors and the dependent variable.

    Returns
    -------
    RMDesign

    Raises
    ------
    AnalysisError
        If a cell has no data from any participant, a participant has two values for one cell,
        or fewer than two participants have every cell.

    Examples
    --------
    AL shifts (dB) of three participants at two masker frequencies (Hz) × two levels (dB SL);
    P3 lacks the last cell and is left out:

    >>> shifts = {"P1": [6.3, 9.8, 3.3, 4.7], "P2": [6.9, 9.4, 2.6, 6.5], "P3": [5.5, 10.2, 3.9]}
    >>> cells = [(120, 10), (120, 20), (240, 10), (240, 20)]
    >>> table = pd.DataFrame(
    ...     [(p, f, x, s) for p, v in shifts.items() for (f, x), s in zip(cells, v)],
    ...     columns=["participant", "frequency_hz", "level_db_sl", "shift_db"],
    ... )
    >>> d = rm_design(table, subject="participant", factor_a="frequency_hz",
    ...               factor_b="level_db_sl", dv="shift_db")
    >>> d.data.shape, d.subjects, d.dropped
    ((2, 2, 2), ('P1', 'P2'), (('P3', 'no value for 240@20'),))
    """
    for col in (subject, factor_a, factor_b, dv):
        if col not in table.columns:
            raise AnalysisError(f"the table has no column {col!r}; columns are {list(table)}")
    t = table[[subject, factor_a, factor_b, dv]].copy()
    if not np.isfinite(t[dv].to_numpy(dtype=float)).all():
        raise AnalysisError(f"column {dv!r} has NaN or infinite values; drop those rows first")
    dup = t.duplicated([subject, factor_a, factor_b], keep=False)
    if dup.any():
        r = t[dup].iloc[0]
        raise AnalysisError(
            f"participant {r[subject]} has {int(dup.sum())} values for {factor_a}={r[factor_a]}, "
            f"{factor_b}={r[factor_b]}; keep one value per participant and cell"
        )
    levels_a = tuple(sorted(t[factor_a].unique()))
    levels_b = tuple(sorted(t[factor_b].unique()))
    counts = t.groupby([factor_a, factor_b]).size()
    empty = [
        f"{factor_a}={a}, {factor_b}={b}"
        for a, b in itertools.product(levels_a, levels_b)
        if (a, b) not in counts.index
    ]
    if empty:
        raise AnalysisError(
            f"no participant has a value for {'; '.join(empty)}: the design has a missing cell, "
            "so the repeated-measures ANOVA cannot be run; measure that cell or leave its "
            "factor level out"
        )
    wide = t.pivot(index=subject, columns=[factor_a, factor_b], values=dv)
    wide = wide.reindex(columns=pd.MultiIndex.from_product([levels_a, levels_b]))
    wide = wide.sort_index()
    missing = wide.isna().to_numpy()
    partial: NDArray[np.bool_] = np.asarray(missing.any(axis=1), dtype=bool)
    cells_ab = list(itertools.product(levels_a, levels_b))  # the columns, in order
    # Only the participants with a gap are visited (a row-by-row scan of thousands cost ~0.3 s).
    dropped = []
    for subj, row in zip(wide.index[partial], missing[partial], strict=True):
        cells = [f"{a}@{b}" for (a, b), m in zip(cells_ab, row, strict=True) if m]
        dropped.append((str(subj), f"no value for {', '.join(cells)}"))
    kept = wide[~partial]
    if len(kept) < 2:
        raise AnalysisError(
            f"a repeated-measures ANOVA needs at least two participants with every cell; "
            f"{len(kept)} of {len(wide)} have them"
            + (f" (left out: {'; '.join(f'{s}: {r}' for s, r in dropped[:5])})" if dropped else "")
        )
    data = kept.to_numpy(dtype=float).reshape(len(kept), len(levels_a), len(levels_b))
    return RMDesign(data, tuple(str(s) for s in kept.index), levels_a, levels_b, tuple(dropped))


# --------------------------------------------------------------------------------------------
# ANOVA


def rm_anova(data: ArrayLike, names: Sequence[str] = EFFECT_NAMES) -> list[Effect]:
    """Two-way repeated-measures ANOVA with sphericity tests and GG correction.

    Parameters
    ----------
    data : array_like, shape (n, a, b)
        Dependent variable per participant (n ≥ 2) and cell (factor A level, factor B level).
        A factor with one level drops out (its effects are not reported), giving a one-way ANOVA.
    names : sequence of 3 str
        Names of the A, B and A×B effects.

    Returns
    -------
    list[Effect]
        A, B, A×B in that order (effects with zero df omitted).

    Raises
    ------
    AnalysisError
        Fewer than two participants, non-finite data, no factor with two levels, or an effect
        whose error variance is zero (F undefined).

    Examples
    --------
    AL shifts (dB) of 3 participants × 2 masker frequencies × 2 masker levels:

    >>> data = np.array([[[6.3, 9.8], [3.3, 4.7]], [[6.9, 9.4], [2.6, 6.5]],
    ...                  [[5.5, 10.2], [3.9, 5.6]]])
    >>> for e in rm_anova(data):
    ...     print(f"{e.name:15} F({e.df1},{e.df2}) = {e.F:6.2f}  p = {e.p:.4f}")
    frequency       F(1,2) = 170.57  p = 0.0058
    level           F(1,2) = 139.24  p = 0.0071
    frequency:level F(1,2) =   0.84  p = 0.4551
    """
    y = np.asarray(data, dtype=float)
    if y.ndim != 3:
        raise AnalysisError(f"expected participants × A × B data, got shape {y.shape}")
    n, a, b = y.shape
    if n < 2:
        raise AnalysisError(f"a repeated-measures ANOVA needs at least two participants; got {n}")
    if not np.isfinite(y).all():
        raise AnalysisError("the data contain NaN or ±inf; every participant needs every cell")
    if a < 2 and b < 2:
        raise AnalysisError("no factor has two or more levels: there is no effect to test")
    flat = y.reshape(n, a * b)
    ha, hb = _orthonormal_contrasts(a), _orthonormal_contrasts(b)
    ua, ub = np.full((a, 1), 1 / math.sqrt(a)), np.full((b, 1), 1 / math.sqrt(b))
    designs = [
        (names[0], np.kron(ha, ub)),
        (names[1], np.kron(ua, hb)),
        (names[2], np.kron(ha, hb)),
    ]
    scale = float(((flat - flat.mean()) ** 2).sum())
    out = []
    for name, contrast in designs:
        d = contrast.shape[1]
        if d == 0:
            continue
        z = flat @ contrast
        zbar = z.mean(axis=0)
        ss_eff = float(n * zbar @ zbar)
        resid = z - zbar
        ss_err = float((resid**2).sum())
        if ss_err <= _ZERO_REL * max(scale, 1.0):
            raise AnalysisError(
                f"the error variance of the {name} effect is zero: every participant shows the "
                "same pattern across its levels, so F is undefined; check for copied or "
                "noise-free data"
            )
        df1, df2 = d, d * (n - 1)
        F = (ss_eff / df1) / (ss_err / df2)
        p = float(f_sf(F, df1, df2))
        cov = resid.T @ resid / (n - 1)
        eps = gg_epsilon(cov)
        p_gg = float(f_sf(F, df1 * eps, df2 * eps))
        # k = all a·b conditions in the second-order term, as car/afex in R and pingouin do.
        w, chi2, mdf, mp, note = mauchly(cov, n - 1, a * b)
        out.append(
            Effect(
                name=name,
                F=float(F),
                df1=int(df1),
                df2=int(df2),
                p=p,
                eps_gg=float(eps),
                p_gg=p_gg,
                np2=ss_eff / (ss_eff + ss_err),
                ss_effect=ss_eff,
                ss_error=ss_err,
                mauchly_w=w,
                mauchly_chi2=chi2,
                mauchly_df=mdf,
                mauchly_p=mp,
                note=note,
            )
        )
    return out


def gg_epsilon(cov: ArrayLike) -> float:
    """Greenhouse–Geisser ε from the d × d covariance of orthonormal contrasts (1/d ≤ ε ≤ 1).

    Parameters
    ----------
    cov : array_like, shape (d, d)
        Sample covariance of the contrast scores, dB².

    Returns
    -------
    float
        ε (dimensionless); 1 for spherical data or d ≤ 1.

    Examples
    --------
    >>> gg_epsilon(np.eye(3)), gg_epsilon(np.diag([1.0, 0.0]))
    (1.0, 0.5)
    """
    s = np.atleast_2d(np.asarray(cov, dtype=float))
    d = s.shape[0]
    if d <= 1:
        return 1.0
    tr = float(np.trace(s))
    tr2 = float(np.trace(s @ s))
    if tr2 <= 0:
        raise AnalysisError("the contrast covariance is zero; ε is undefined (zero variance)")
    return min(1.0, tr * tr / (d * tr2))


def mauchly(
    cov: ArrayLike, df_resid: int, k: int
) -> tuple[float | None, float | None, int, float | None, str | None]:
    """Mauchly's test of sphericity.

    Parameters
    ----------
    cov : array_like, shape (d, d)
        Sample covariance of the orthonormal contrast scores of one effect.
    df_resid : int
        Its degrees of freedom (n − 1 participants).
    k : int
        Number of repeated-measures conditions (used only in the second-order term; R's ``car``
        passes every condition of the design, a one-way test passes the factor's levels).

    Returns
    -------
    W, chi2, df, p, note
        W = det(S)/(tr(S)/d)^d; χ² = −(df_resid − (2d² + d + 2)/(6d))·ln W on d(d+1)/2 − 1 df,
        p with the second-order correction of Anderson (2003) as in R's ``mauchly.test``.
        For d = 1: W = 1, p = 1. When ``df_resid < d`` the covariance is singular and the test
        does not exist: W, χ², p are None and ``note`` says so.

    Examples
    --------
    >>> w, chi2, df, p, note = mauchly(np.eye(2), df_resid=5, k=4)
    >>> w, df, p, note
    (1.0, 2, 1.0, None)
    """
    s = np.atleast_2d(np.asarray(cov, dtype=float))
    d = s.shape[0]
    mdf = d * (d + 1) // 2 - 1
    if d <= 1:
        return 1.0, 0.0, 0, 1.0, None
    if df_resid < d:
        return (
            None,
            None,
            mdf,
            None,
            f"Mauchly's test needs more participants than the effect's {d} df "
            f"(have {df_resid + 1}); sphericity untested, use the GG-corrected p",
        )
    sign, logdet = np.linalg.slogdet(s)
    tr = float(np.trace(s))
    if sign <= 0 or tr <= 0:
        return (
            0.0,
            None,
            mdf,
            None,
            "the contrast covariance is singular (W = 0); sphericity cannot be tested, use the "
            "GG-corrected p",
        )
    log_w = float(logdet) - d * math.log(tr / d)
    rho = 1.0 - (2 * d * d + d + 2) / (6.0 * d * df_resid)
    chi2 = -df_resid * rho * log_w
    w2 = (
        (d + 2)
        * (d - 1)
        * (d - 2)
        * (2 * d**3 + 6 * d * d + 3 * k + 2)
        / (288.0 * (df_resid * d * rho) ** 2)
    )
    p1 = float(chi2_sf(chi2, mdf))
    p2 = float(chi2_sf(chi2, mdf + 4))
    p = min(1.0, max(0.0, p1 + w2 * (p2 - p1)))
    return math.exp(log_w), float(chi2), mdf, p, None


def _orthonormal_contrasts(k: int) -> NDArray[np.float64]:
    """k × (k − 1) orthonormal contrasts (normalised Helmert), orthogonal to the unit vector."""
    if k < 2:
        return np.zeros((k, 0))
    h = np.zeros((k, k - 1))
    for j in range(1, k):
        h[:j, j - 1] = 1.0
        h[j, j - 1] = -float(j)
        h[:, j - 1] /= math.sqrt(j * (j + 1))
    return h
