"""Simulated functional (ramp) tracks for ``plan`` and the study simulations (pure).

R simulated observers, each with its own ramp (intercept a dB, slope b dB/dB), answer their
own track; the answers come from one uniform per replicate per trial (streams stay aligned
whatever the stop rule). The tracks advance together
(:mod:`masking_lab.procedures.functional_lockstep`), each exactly as the scalar
:class:`~masking_lab.procedures.functional.FunctionalRamp` would run it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from masking_lab.core.errors import ProcedureError
from masking_lab.core.masking import ramp
from masking_lab.core.psychometric import Psychometric
from masking_lab.procedures.batch import TrackBatch
from masking_lab.procedures.functional import FunctionalRampSettings, ramp_moments, ramp_tables
from masking_lab.procedures.functional_lockstep import run_lockstep

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

    def answer(i: int, k: int, masker_db_sl: float, target_db: float) -> bool:
        theta = u[i] + float(ramp(masker_db_sl, float(a[i]), float(b[i])))
        return bool(draws[k, i] < psy.p_correct(target_db - theta))

    run = run_lockstep(settings, answer, r)
    t = ramp_tables(settings)
    out = {k: np.zeros(r) for k in ("intercept_db", "intercept_sd_db", "slope", "slope_sd")}
    for i in range(r):
        m = ramp_moments(t, run.posterior[i])
        for key in out:
            out[key][i] = m[key]
    return SimulatedRamps(
        settings=settings,
        levels_db=run.levels_db,
        correct=run.correct,
        n_trials=run.n_trials,
        maskers_db_sl=run.maskers_db_sl,
        true_intercept_db=a,
        true_slope=b,
        status=run.status,
        **out,
    )
