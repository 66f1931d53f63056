"""Many functional (ramp) tracks advanced together, trial by trial (pure: no I/O, no RNG).

``plan`` and the study simulations run tens of simulated participants through the functional
procedure. One scalar track (:class:`~masking_lab.procedures.functional.FunctionalRamp`)
reads the whole float32 likelihood table (stimuli × (a, b) × nuisance, 22 MB for the shipped
grids) on every placement; here one pass over the table serves several tracks at once
(:func:`expected_entropy_batch`, with the compiled loops of :mod:`masking_lab.procedures.fused`),
and the float64 likelihood of a stimulus is computed once per run instead of once per trial.

Every number is computed by the same elementwise operations, in the same order, on arrays of
the same shape as the scalar track's, so a track here places the same stimuli and ends with the
same posterior, bit for bit (tests/test_functional_lockstep.py pins it).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from masking_lab.procedures.functional import (
    FunctionalRampSettings,
    RampTables,
    _entropy_after,
    ramp_moments,
    ramp_tables,
    stimulus_likelihood,
    stop_status,
)
from masking_lab.procedures.fused import nuisance_sums

__all__ = ["LockstepTracks", "expected_entropy_batch", "run_lockstep"]

#: Tracks per pass over the table: the compiled loops read each (a, b) row's slice of the table
#: once for all of them; their products (0.8 MB per track) bound the memory.
_TRACKS_PER_PASS = 8


def expected_entropy_batch(t: RampTables, posteriors: NDArray[np.float64]) -> NDArray[np.float64]:
    """:func:`~masking_lab.procedures.functional.expected_entropy` of every track, nats.

    Parameters
    ----------
    t : RampTables
    posteriors : ndarray, shape (R, A, N)
        One posterior per track.

    Returns
    -------
    ndarray, shape (R, S)
        Row r equals ``expected_entropy(t, posteriors[r])`` bit for bit.

    Examples
    --------
    >>> from masking_lab.procedures.functional import expected_entropy
    >>> t = ramp_tables(FunctionalRampSettings(max_trials=5))
    >>> two = np.stack([t.prior, t.prior])
    >>> bool(np.array_equal(expected_entropy_batch(t, two)[1], expected_entropy(t, t.prior)))
    True
    """
    out = np.empty((posteriors.shape[0], t.p_correct.shape[2]))
    for r0 in range(0, posteriors.shape[0], _TRACKS_PER_PASS):
        post = posteriors[r0 : r0 + _TRACKS_PER_PASS].astype(np.float32)
        m_c = nuisance_sums(t.p_correct, post)
        for k in range(post.shape[0]):
            out[r0 + k] = _entropy_after(m_c[k], post[k].sum(axis=1))
    return out


@dataclass(frozen=True)
class LockstepTracks:
    """R functional tracks run to their stop rules.

    Attributes
    ----------
    levels_db, maskers_db_sl : ndarray, shape (R, T)
        Target and masker level of every trial, dB SL (NaN past a track's end).
    correct : ndarray of bool, shape (R, T)
    n_trials : ndarray of int, shape (R,)
    posterior : ndarray, shape (R, A, N)
        Final posteriors.
    status : ndarray of str, shape (R,)
    at_trials : dict of int to list of dict
        Posterior moments of every track still running at each requested trial count (the
        moments of :func:`~masking_lab.procedures.functional.ramp_moments`), in track order.
    """

    levels_db: NDArray[np.float64]
    maskers_db_sl: NDArray[np.float64]
    correct: NDArray[np.bool_]
    n_trials: NDArray[np.int64]
    posterior: NDArray[np.float64]
    status: NDArray[np.str_]
    at_trials: dict[int, list[dict[str, float]]]


def run_lockstep(
    settings: FunctionalRampSettings,
    answer: Callable[[int, int, float, float], bool],
    n_tracks: int,
    *,
    checkpoints: Sequence[int] = (),
) -> LockstepTracks:
    """Run ``n_tracks`` tracks together; ``answer(track, trial, masker_db_sl, target_db)``
    gives each trial's answer (True = correct).

    Examples
    --------
    >>> s = FunctionalRampSettings(max_trials=4)
    >>> run = run_lockstep(s, lambda i, k, x, y: y > 10.0, 2, checkpoints=(2,))
    >>> run.n_trials.tolist(), len(run.at_trials[2])
    ([4, 4], 2)
    """
    t = ramp_tables(settings)
    width = settings.max_trials
    post = np.repeat(t.prior[None], n_tracks, axis=0)
    stim = np.full(n_tracks, t.first_stimulus, dtype=np.intp)
    levels = np.full((n_tracks, width), np.nan)
    maskers = np.full((n_tracks, width), np.nan)
    correct = np.zeros((n_tracks, width), dtype=bool)
    n = np.zeros(n_tracks, dtype=np.int64)
    status = np.full(n_tracks, "running", dtype="<U9")
    at: dict[int, list[dict[str, float]]] = {c: [] for c in checkpoints}
    likes: dict[int, NDArray[np.float64]] = {}
    active = np.arange(n_tracks)
    while active.size:
        placing = []
        for i in active:
            s_i = int(stim[i])
            x, y = float(t.maskers_db_sl[s_i]), float(t.targets_db[s_i])
            ok = bool(answer(int(i), int(n[i]), x, y))
            if s_i not in likes:
                likes[s_i] = stimulus_likelihood(t, settings, s_i)
            like = likes[s_i]
            p = post[i] * (like if ok else 1.0 - like)
            p /= p.sum()
            post[i] = p
            k = int(n[i])
            levels[i, k], maskers[i, k], correct[i, k] = y, x, ok
            n[i] = k + 1
            m = ramp_moments(t, p)
            if k + 1 in at:
                at[k + 1].append(m)
            status[i] = stop_status(settings, k + 1, m)
            if status[i] == "running":
                placing.append(i)
        active = np.array(placing, dtype=np.intp)
        if active.size:
            stim[active] = np.argmin(expected_entropy_batch(t, post[active]), axis=1)
    return LockstepTracks(levels, maskers, correct, n, post, status, at)
