"""t-tests of AL shifts (paper §2.4) and of user-test correct rates: pure functions on arrays.

* :func:`paired_comparisons` — Bonferroni-corrected paired t-tests between the levels of one
  factor, on each participant's mean over the other factor (marginal means).
* :func:`one_sample_t` — two-tailed one-sample t-test of shifts against 0.
* :func:`paired_t` — the project's one paired t-test (the one-sample test of the differences),
  also used by the user-test analysis.

Undefined cases (one value, zero variance) give ``t`` and ``p`` None with a note, never NaN;
non-finite input raises :class:`~masking_lab.core.errors.AnalysisError`.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from masking_lab.analysis.distributions import t_sf
from masking_lab.core.errors import AnalysisError


@dataclass(frozen=True)
class PairedTest:
    """A paired t-test between two levels of a factor.

    Attributes
    ----------
    a, b : object
        The two levels compared (difference is a − b).
    n : int
        Participants.
    mean_diff : float
        Mean of the paired differences (dB).
    t : float or None
        t statistic (None when the differences have zero variance).
    df : int
        n − 1.
    p : float or None
        Two-tailed uncorrected p.
    p_bonf : float or None
        Bonferroni-corrected p: min(1, p × number of comparisons).
    dz : float or None
        Cohen's d_z = mean_diff / SD of differences.
    note : str or None
        Why t is missing, if it is.
    """

    a: object
    b: object
    n: int
    mean_diff: float
    t: float | None
    df: int
    p: float | None
    p_bonf: float | None
    dz: float | None
    note: str | None = None


@dataclass(frozen=True)
class OneSampleT:
    """Two-tailed one-sample t-test of values against ``popmean``.

    Attributes
    ----------
    n : int
        Values.
    mean, sd, se : float or None
        Mean, SD (ddof 1) and standard error, in the values' unit (dB); sd/se None for n < 2.
    t : float or None
        t statistic; None when it is undefined (n < 2 or zero variance).
    df : int
        n − 1.
    p : float or None
        Two-tailed p.
    note : str or None
        Why the test could not be run, if it could not.
    """

    n: int
    mean: float
    sd: float | None
    se: float | None
    t: float | None
    df: int
    p: float | None
    note: str | None = None


def paired_comparisons(marginal: ArrayLike, labels: Sequence[object]) -> list[PairedTest]:
    """Bonferroni-corrected paired t-tests between every pair of levels.

    Parameters
    ----------
    marginal : array_like, shape (n, k)
        Each participant's mean (dB) at each of the k levels (averaged over the other factor).
    labels : sequence
        The k level labels, in column order.

    Returns
    -------
    list[PairedTest]
        One per pair (i < j in column order); p_bonf = min(1, p × k(k−1)/2).

    Raises
    ------
    AnalysisError
        With fewer than two participants or two levels.

    Examples
    --------
    Marginal mean shifts (dB) of 4 participants under three maskers:

    >>> m = [[8.0, 4.0, 5.0], [8.2, 4.5, 5.5], [7.9, 4.7, 5.1], [7.0, 4.6, 4.9]]
    >>> for r in paired_comparisons(m, ["MV120", "EV270", "MV120am40"]):
    ...     print(f"{r.a} - {r.b}: {r.mean_diff:+.2f} dB, p_bonf = {r.p_bonf:.4f}")
    MV120 - EV270: +3.32 dB, p_bonf = 0.0074
    MV120 - MV120am40: +2.65 dB, p_bonf = 0.0025
    EV270 - MV120am40: -0.68 dB, p_bonf = 0.1122
    """
    m = np.asarray(marginal, dtype=float)
    if m.ndim != 2 or m.shape[1] != len(labels):
        raise AnalysisError("marginal must be participants × levels, one column per label")
    n, k = m.shape
    if n < 2:
        raise AnalysisError(f"paired comparisons need at least two participants; got {n}")
    if k < 2:
        raise AnalysisError("paired comparisons need at least two levels to compare")
    n_tests = k * (k - 1) // 2
    out = []
    for i, j in itertools.combinations(range(k), 2):
        diff = m[:, i] - m[:, j]
        res = one_sample_t(diff)
        p_bonf = None if res.p is None else min(1.0, res.p * n_tests)
        dz = None if not res.sd else res.mean / res.sd
        note = None if res.note is None else f"differences {labels[i]} − {labels[j]}: {res.note}"
        out.append(
            PairedTest(labels[i], labels[j], n, res.mean, res.t, res.df, res.p, p_bonf, dz, note)
        )
    return out


def paired_t(a: ArrayLike, b: ArrayLike) -> OneSampleT:
    """Two-tailed paired t-test of ``a`` against ``b``: the one-sample test of ``a − b`` against 0.

    The project's one paired t-test (R's ``t.test(a, b, paired = TRUE)``); undefined cases
    (fewer than two pairs, every difference the same) return ``t`` and ``p`` None with a
    ``note``, as :func:`one_sample_t` does.

    Parameters
    ----------
    a, b : array_like
        Finite values in one unit (dB, or a correct rate 0–1), one per participant, paired by
        position.

    Returns
    -------
    OneSampleT
        Of the differences ``a − b`` (``mean`` is the mean difference, in the values' unit).

    Raises
    ------
    AnalysisError
        If ``a`` and ``b`` differ in length, are empty, or hold NaN or ±inf.

    Examples
    --------
    R's ``sleep`` data (extra hours of sleep of ten patients under two drugs):

    >>> drug1 = [0.7, -1.6, -0.2, -1.2, -0.1, 3.4, 3.7, 0.8, 0.0, 2.0]
    >>> drug2 = [1.9, 0.8, 1.1, 0.1, -0.1, 4.4, 5.5, 1.6, 4.6, 3.4]
    >>> r = paired_t(drug1, drug2)
    >>> print(f"{r.mean:+.2f} h, t({r.df}) = {r.t:.4f}, p = {r.p:.6f}")
    -1.58 h, t(9) = -4.0621, p = 0.002833
    """
    x = np.asarray(a, dtype=float).ravel()
    y = np.asarray(b, dtype=float).ravel()
    if x.shape != y.shape:
        raise AnalysisError(
            f"paired t-test: {x.size} values against {y.size}; give one pair per participant"
        )
    return one_sample_t(x - y)


def one_sample_t(values: ArrayLike, popmean: float = 0.0) -> OneSampleT:
    """Two-tailed one-sample t-test of ``values`` (dB) against ``popmean`` (dB).

    Undefined cases (fewer than two values, zero variance) return a result with ``t`` and ``p``
    None and a ``note``; they never raise or return NaN.

    Parameters
    ----------
    values : array_like
        Finite values, dB (e.g. one AL shift per participant).
    popmean : float
        Hypothesised mean, dB.

    Returns
    -------
    OneSampleT

    Raises
    ------
    AnalysisError
        If there are no values or some are NaN or ±inf.

    Examples
    --------
    Is the AL shift of four participants different from 0 dB?

    >>> r = one_sample_t([2.1, 3.4, 1.8, 2.9])
    >>> print(f"mean {r.mean:.2f} dB, t({r.df}) = {r.t:.2f}, p = {r.p:.4f}")
    mean 2.55 dB, t(3) = 6.96, p = 0.0061
    >>> one_sample_t([2.0]).note
    'one value only: no test'
    """
    v = np.asarray(values, dtype=float).ravel()
    if not np.isfinite(v).all():
        raise AnalysisError("one-sample t-test: values contain NaN or ±inf")
    n = v.size
    if n == 0:
        raise AnalysisError("one-sample t-test: no values")
    mean = float(v.mean())
    if n < 2:
        return OneSampleT(n, mean, None, None, None, 0, None, "one value only: no test")
    sd = float(v.std(ddof=1))
    se = sd / math.sqrt(n)
    if sd <= 1e-12 * max(1.0, abs(mean)):
        return OneSampleT(
            n,
            mean,
            0.0,
            0.0,
            None,
            n - 1,
            None,
            f"all {n} values equal ({mean:.4g}): zero variance, t undefined",
        )
    t = (mean - popmean) / se
    p = float(2.0 * t_sf(abs(t), n - 1))
    return OneSampleT(n, mean, sd, se, float(t), n - 1, p)
