"""Fisher information of a forced-choice trial and the Cramér-Rao bound on threshold precision.

One n-interval trial at level x is a Bernoulli draw with p = ψ(x). Its Fisher information about
the threshold θ (slope, guess and lapse known) is

    I(x) = (∂p/∂θ)² / (p·(1 − p)),    ∂p/∂θ = −(1 − γ − λ)·F(z)·(1 − F(z)) / s,

with F the logistic, z = (x − α)/s and α = θ − s·logit((p_θ − γ)/(1 − γ − λ)) (the model of
:class:`masking_lab.core.psychometric.Psychometric`). I(x) depends on x − θ only; its maximum
I* is what a trial placed at the best level yields. The Cramér-Rao bound: an unbiased estimate
from n trials has SD ≥ 1/√(n·I*), so a target SD σ needs at least n* = 1/(I*·σ²) trials, and a
procedure that reaches SD σ in n trials has *efficiency* n*/n (1 for an ideal procedure).

For the default simulated observer (3IFC, scale 1.5 dB, lapse 0.02) I* ≈ 0.0534 dB⁻² at
p(correct) ≈ 0.708, and n* ≈ 16 trials for σ = 1.08 dB.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from masking_lab.core.psychometric import GUESS_3IFC, LEVITT_1U3D, Psychometric


def fisher_information(
    level_db: ArrayLike,
    threshold_db: float = 0.0,
    *,
    scale_db: float = 1.5,
    guess: float = GUESS_3IFC,
    lapse: float = 0.02,
) -> NDArray[np.float64]:
    """Fisher information about the threshold of one trial at ``level_db``, dB⁻².

    Parameters
    ----------
    level_db : array_like
        Trial level(s), dB.
    threshold_db : float
        The observer's threshold, dB (only ``level_db − threshold_db`` matters).
    scale_db : float
        Logistic scale s, dB.
    guess, lapse : float
        γ (1/n for n intervals) and λ.

    Returns
    -------
    ndarray
        I(x) in dB⁻², same shape as ``level_db``.

    Examples
    --------
    >>> round(float(fisher_information(0.0)), 4)  # at the 0.794 point
    0.0477
    """
    psy = Psychometric(threshold_db, scale_db, guess, lapse, LEVITT_1U3D)
    x = np.asarray(level_db, dtype=float)
    z = (x - psy.location_db) / scale_db
    e = np.exp(-np.abs(z))
    f = np.where(z >= 0, 1.0 / (1.0 + e), e / (1.0 + e))
    g = np.where(z >= 0, e / (1.0 + e), 1.0 / (1.0 + e))  # 1 − F without cancellation
    rise = 1.0 - guess - lapse
    p = guess + rise * f
    q = lapse + rise * g  # 1 − p
    dp = rise * f * g / scale_db
    return dp**2 / (p * q)


def max_information(
    *, scale_db: float = 1.5, guess: float = GUESS_3IFC, lapse: float = 0.02
) -> tuple[float, float, float]:
    """The most informative trial: (I* in dB⁻², p(correct) there, its level re the 0.794 point, dB).

    Examples
    --------
    >>> info, p, offset = max_information()
    >>> round(info, 4), round(p, 3)
    (0.0534, 0.708)
    """
    # A plan asks for the same observer's bound a few hundred times (every row's efficiency),
    # ~3 ms each: computed once per observer (the numbers are those of the search below).
    return _max_information(float(scale_db), float(guess), float(lapse))


@functools.lru_cache(maxsize=64)
def _max_information(scale_db: float, guess: float, lapse: float) -> tuple[float, float, float]:
    """:func:`max_information` for one observer, searched once."""
    # I(x) is smooth and unimodal in x − θ; a dense grid over ±12 scales then golden-section
    # refinement in the winning cell gives the maximum to ~1e-12 dB without scipy.
    x = np.linspace(-12.0 * scale_db, 12.0 * scale_db, 4801)
    kw = {"scale_db": scale_db, "guess": guess, "lapse": lapse}
    j = int(np.argmax(fisher_information(x, **kw)))
    a, b = x[max(j - 1, 0)], x[min(j + 1, x.size - 1)]
    ratio = (math.sqrt(5.0) - 1.0) / 2.0
    for _ in range(60):
        c, d = b - ratio * (b - a), a + ratio * (b - a)
        if fisher_information(c, **kw) >= fisher_information(d, **kw):
            b = d
        else:
            a = c
    best = 0.5 * (a + b)
    p = float(Psychometric(0.0, scale_db, guess, lapse).p_correct(best))
    return float(fisher_information(best, **kw)), p, float(best)


def cramer_rao_trials(sd_db: ArrayLike, **model: float) -> NDArray[np.float64]:
    """Trials an ideal procedure needs for a threshold SD of ``sd_db`` (dB): 1/(I*·σ²).

    ``model`` takes ``scale_db``, ``guess`` and ``lapse`` as :func:`max_information`.

    Examples
    --------
    >>> round(float(cramer_rao_trials(1.08)), 1)
    16.1
    """
    info = max_information(**model)[0]
    sd = np.asarray(sd_db, dtype=float)
    return 1.0 / (info * sd**2)


def cramer_rao_sd(n_trials: ArrayLike, **model: float) -> NDArray[np.float64]:
    """The smallest threshold SD (dB) ``n_trials`` trials allow: 1/√(n·I*).

    Examples
    --------
    >>> round(float(cramer_rao_sd(16)), 2)
    1.08
    """
    info = max_information(**model)[0]
    return 1.0 / np.sqrt(np.asarray(n_trials, dtype=float) * info)


def efficiency(sd_db: ArrayLike, n_trials: ArrayLike, **model: float) -> NDArray[np.float64]:
    """Cramér-Rao trials for the SD achieved, divided by the trials used (1 = ideal).

    Parameters
    ----------
    sd_db : array_like
        SD of the threshold estimates a procedure achieved, dB.
    n_trials : array_like
        Trials it used (mean per track).
    **model : float
        ``scale_db``, ``guess``, ``lapse`` of the observer.

    Examples
    --------
    >>> round(float(efficiency(1.08, 52)), 2)
    0.31
    """
    return cramer_rao_trials(sd_db, **model) / np.asarray(n_trials, dtype=float)
