"""The down/up step ratio that makes a transformed up-down staircase converge on a chosen p.

Kaernbach (1991): a track with up step Δ↑ and down step Δ↓ = r·Δ↑ drifts by
Δ↑·P(up step) − Δ↓·P(down step) per trial, and settles where that expected step is zero. For
1-up N-down, every run from a step to the next ends either with N correct answers in a row
(probability p^N, a down step) or with a wrong answer first (1 − p^N, an up step), so

    r · p^N = 1 − p^N,   i.e.   p = (1 / (1 + r))^(1/N),   r = (1 − p^N) / p^N.

For other rules the per-trial step rates come from the run counter's Markov chain
(:func:`masking_lab.procedures.staircase.implied_target_p_for`), and the ratio is found by
inverting it. Either way the ratio is a property of p(correct), not of the number of
intervals: the guess rate only bounds which targets make sense (p must exceed it).

García-Pérez (1998) recommended r = 0.7393 for 1-up 3-down (target 0.8315 = its zero-drift
point above) from simulations of *two-alternative* tasks, where it held across step sizes.
That stability is a finite-step property of the psychometric function's shape and guess rate;
with three intervals (guess 1/3) it does not hold (docs/speed-accuracy.md), so
:func:`simulated_target_p` measures where a rule actually settles for the protocol's observer
and step size.
"""

from __future__ import annotations

import numpy as np

from masking_lab.core.errors import StaircaseError
from masking_lab.core.psychometric import GUESS_3IFC, Psychometric
from masking_lab.core.roots import brentq
from masking_lab.procedures.staircase import StaircaseSettings, implied_target_p_for
from masking_lab.procedures.staircase_batch import Observer, simulate

#: García-Pérez's (1998) down/up ratio for 1-up 3-down, derived for 2AFC (guess rate 1/2).
GARCIA_PEREZ_2AFC_RATIO = 0.7393


def downup_ratio_for(
    target_p: float, n_down: int, n_up: int = 1, guess_rate: float = GUESS_3IFC
) -> float:
    """Down step / up step at which an ``n_up``-up ``n_down``-down track converges on ``target_p``.

    Kaernbach's (1991) zero-drift condition, generalised to any rule (see the module
    docstring); the small-step limit, where the track's own spread is negligible. García-Pérez's
    0.7393 for 1-up 3-down is this ratio for p = 0.8315; he found it for two-alternative tasks
    (2AFC), and with three intervals the finite-step convergence differs
    (:func:`simulated_target_p`).

    Parameters
    ----------
    target_p : float
        p(correct) the track should converge on; must lie between ``guess_rate`` and 1.
    n_down, n_up : int
        Consecutive correct / wrong answers that lower / raise the level.
    guess_rate : float
        Chance performance (1/n for n intervals); a target at or below it cannot be tracked.

    Returns
    -------
    float
        The ratio r = Δ↓/Δ↑.

    Raises
    ------
    StaircaseError
        If the target is not between the guess rate and 1, or the rule is invalid.

    Examples
    --------
    >>> round(downup_ratio_for(0.8315, n_down=3), 4)  # García-Pérez's 2AFC value
    0.7395
    >>> round(downup_ratio_for(0.5 ** (1 / 3), n_down=3), 6)  # Levitt: equal steps
    1.0
    >>> round(downup_ratio_for(0.75, n_down=1), 4)  # Kaernbach: 1-up 1-down at 75 %
    0.3333
    """
    if not (isinstance(n_down, int) and n_down >= 1 and isinstance(n_up, int) and n_up >= 1):
        raise StaircaseError(f"n_down and n_up must be integers ≥ 1, got {n_down!r}, {n_up!r}")
    if not 0.0 <= guess_rate < 1.0:
        raise StaircaseError(f"guess_rate must be in [0, 1), got {guess_rate}")
    if not guess_rate < target_p < 1.0:
        raise StaircaseError(
            f"target_p={target_p} must lie between the guess rate {guess_rate:.3f} and 1: a "
            "track cannot converge on chance performance or on certainty"
        )
    if n_up == 1:
        pn = target_p**n_down
        return (1.0 - pn) / pn

    # The zero-drift p rises monotonically as the down step shrinks relative to the up step.
    def excess(log_r: float) -> float:
        return implied_target_p_for(n_up, n_down, float(np.exp(log_r))) - target_p

    return float(np.exp(brentq(excess, -12.0, 12.0, xtol=1e-13)))


def simulated_target_p(
    ratio: float,
    up_step_db: float,
    rng: np.random.Generator,
    *,
    n_down: int = 3,
    n_up: int = 1,
    observer: Observer | None = None,
    n_tracks: int = 1000,
    n_reversals: int = 40,
    n_discarded: int = 8,
) -> float:
    """p(correct) at the mean reversal-mean level of long fixed-step tracks (where they settle).

    Parameters
    ----------
    ratio : float
        Down step / up step.
    up_step_db : float
        The (fixed) up step, dB.
    rng : numpy.random.Generator
        Source of the simulated answers.
    n_down, n_up : int
        The rule.
    observer : Observer, optional
        The simulated observer (default 3IFC, scale 1.5 dB, lapse 0.02); its 0.794 point is at
        0 dB, where every track starts.
    n_tracks, n_reversals, n_discarded : int
        Tracks simulated, reversals each runs, and early reversals left out of its mean.

    Returns
    -------
    float
        The observer's p(correct) at the mean of the tracks' reversal means.

    Examples
    --------
    >>> p = simulated_target_p(1.0, 0.375, np.random.default_rng(0), n_tracks=200)
    >>> abs(p - 0.794) < 0.01
    True
    """
    obs = observer or Observer()
    s = StaircaseSettings(
        0.0,
        step_sizes_db=(up_step_db,),
        down_up_ratio=ratio,
        n_up=n_up,
        n_down=n_down,
        n_reversals=n_reversals,
        n_reversals_averaged=n_reversals - n_discarded,
    )
    tracks = simulate(s, np.zeros(n_tracks), obs, rng, trial_limit=100_000, store_levels=False)
    al = float(np.nanmean(tracks.al_db))
    psy = Psychometric(0.0, obs.scale_db, obs.guess, obs.lapse)
    return float(psy.p_correct(al))
