"""Simulated functional (ramp) tracks for ``plan`` and the study simulations (pure).

R simulated observers, each with its own ramp (intercept a dB, slope b dB/dB), answer their
own track; the answers come from one uniform per replicate per trial (streams stay aligned
whatever the stop rule). The tracks run one after another through the scalar
:class:`~masking_lab.procedures.functional.FunctionalRamp` (its placement is already one
batched product over the whole table), so the batch equals the scalar track by construction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from masking_lab.core.errors import ProcedureError
from masking_lab.core.masking import ramp
from masking_lab.core.psychometric import Psychometric
from masking_lab.procedures.batch import TrackBatch
from masking_lab.procedures.functional import FunctionalRampSettings

__all__ = ["SimulatedRamps", "simulate_ramps"]


@dataclass(frozen=True, kw_only=True)
class SimulatedRamps(TrackBatch[FunctionalRampSettings]):
    """R simulated ramp tracks.

    Attributes
    ----------
    maskers_db_sl : ndarray, shape (R, T)
        Masker level of every trial, dB SL (NaN past a track's end).
    intercept_db, intercept_sd_db, slope, slope_sd : ndarray, shape (R,)
        Each track's final posterior means and SDs.
    true_intercept_db, true_slope : ndarray, shape (R,)
        The observers' ramps.
    status : ndarray of str, shape (R,)
    """

    maskers_db_sl: NDArray[np.float64]
    intercept_db: NDArray[np.float64]
    intercept_sd_db: NDArray[np.float64]
    slope: NDArray[np.float64]
    slope_sd: NDArray[np.float64]
    true_intercept_db: NDArray[np.float64]
    true_slope: NDArray[np.float64]
    status: NDArray[np.str_]


def simulate_ramps(
    settings: FunctionalRampSettings,
    intercept_db: ArrayLike,
    slope: ArrayLike,
    *,
    scale_db: float = 1.5,
    lapse: float = 0.02,
    unmasked_offset_db: ArrayLike = 0.0,
    rng: np.random.Generator,
) -> SimulatedRamps:
    """Run one track per simulated observer with ramp (a, b).

    Parameters
    ----------
    settings : FunctionalRampSettings
    intercept_db, slope : array of shape (R,)
        The observers' ramps (a dB, b dB/dB).
    scale_db, lapse : float
        The observers' logistic scale (dB) and lapse (need not be on the settings' grids).
    unmasked_offset_db : float or array of shape (R,)
        Error of each observer's calibrated unmasked AL, dB.
    rng : numpy.random.Generator

    Examples
    --------
    >>> s = FunctionalRampSettings(max_trials=5)
    >>> sim = simulate_ramps(s, [-7.4], [0.71], rng=np.random.default_rng(0))
    >>> sim.n_trials.tolist(), sim.status.tolist()
    ([5], ['completed'])
    """
    a = np.asarray(intercept_db, dtype=float).reshape(-1)
    b = np.asarray(slope, dtype=float).reshape(-1)
    if a.shape != b.shape or not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise ProcedureError("intercepts and slopes must be finite arrays of one length")
    u = np.broadcast_to(np.asarray(unmasked_offset_db, dtype=float), a.shape)
    r, width = a.size, settings.max_trials
    psy = Psychometric(0.0, scale_db, settings.guess, lapse, settings.p_at_threshold)
    draws = rng.random((width, r))  # one per replicate per trial, drawn up front
    levels = np.full((r, width), np.nan)
    maskers = np.full((r, width), np.nan)
    correct = np.zeros((r, width), dtype=bool)
    n = np.zeros(r, dtype=np.int64)
    out = {k: np.zeros(r) for k in ("intercept_db", "intercept_sd_db", "slope", "slope_sd")}
    status = np.empty(r, dtype="<U9")
    for i in range(r):
        state = settings.start()
        while not state.finished:
            x, y = state.next_masker_level_db_sl(), state.next_level()
            theta = u[i] + float(ramp(x, float(a[i]), float(b[i])))
            state = state.update(bool(draws[state.n_trials, i] < psy.p_correct(y - theta)))
        k = state.n_trials
        levels[i, :k], maskers[i, :k], correct[i, :k] = (
            state.levels_db,
            state.maskers_db_sl,
            state.responses,
        )
        n[i] = k
        m = state.moments()
        for key in out:
            out[key][i] = m[key]
        status[i] = state.status
    return SimulatedRamps(
        settings=settings,
        levels_db=levels,
        correct=correct,
        n_trials=n,
        maskers_db_sl=maskers,
        true_intercept_db=a,
        true_slope=b,
        status=status,
        **out,
    )
