"""What a vectorised batch of adaptive tracks returns, whatever the procedure (pure).

The batch simulators (:mod:`~masking_lab.procedures.staircase_batch`,
:mod:`~masking_lab.procedures.quest_plus_batch`) run, or replay, R tracks in lockstep and give
their trials as arrays: one row per track (replicate), one column per trial. Every procedure's
batch has the arrays of :class:`TrackBatch`; each adds what its own rule keeps (reversals for
the staircase, the posterior's mean and SD for QUEST+).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np
from numpy.typing import NDArray

__all__ = ["TrackBatch"]

SettingsT = TypeVar("SettingsT")


@dataclass(frozen=True, kw_only=True)
class TrackBatch(Generic[SettingsT]):
    """R tracks of one adaptive procedure, trial by trial.

    Past a track's end, levels are NaN and answers False.

    Attributes
    ----------
    settings : procedure settings
        The rules every track followed.
    levels_db : ndarray, shape (R, T)
        Level of every trial, dB.
    correct : ndarray of bool, shape (R, T)
        Whether each trial was answered correctly.
    n_trials : ndarray of int, shape (R,)
        Trials each track ran.
    true_threshold_db : ndarray or None, shape (R,)
        The simulated observers' thresholds, dB; None for replays of logged answers.

    Examples
    --------
    >>> batch = TrackBatch(
    ...     settings=None,
    ...     levels_db=np.array([[10.0, 8.0, np.nan], [10.0, 12.0, 10.0]]),
    ...     correct=np.array([[True, False, False], [False, True, True]]),
    ...     n_trials=np.array([2, 3]),
    ... )
    >>> batch.n_replicates, int(batch.n_trials.sum())
    (2, 5)
    """

    settings: SettingsT
    levels_db: NDArray[np.float64]
    correct: NDArray[np.bool_]
    n_trials: NDArray[np.int64]
    true_threshold_db: NDArray[np.float64] | None = None

    @property
    def n_replicates(self) -> int:
        """Number of tracks R."""
        return int(self.n_trials.shape[0])
