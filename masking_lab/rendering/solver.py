"""Inverse rendering under mutual masking: the perceived pair wanted → the input pair to play.

Paper §3.2, Eq. (1)–(4) and Table 4, on arrays. The entry points of the solver:

- :class:`MutualMasking` (from :mod:`masking_lab.rendering.pair`): the two masking ramps of one
  MV/EV pair, with a scalar :meth:`~MutualMasking.solve_point` for a 1 kHz haptic loop;
  :func:`pair_from_params` builds one from ``masking_params.json``.
- :func:`solve`: the vectorised inverse, one :class:`Solution` for arrays of targets.
- :func:`forward`, :func:`mv_masked_al_db_sl`, :func:`ev_masked_al_db_sl`: the forward model.

The four cases of the closed form, and when a target has none, one or several answers, are
derived in :mod:`masking_lab.rendering.ramp_inverse`. All levels are dB SL; ``-inf`` is a silent
channel. Pure: no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from masking_lab.core.errors import SolverError
from masking_lab.rendering.pair import (
    MissingMaskingError,
    MutualMasking,
    PairProblem,
    pair_from_params,
)
from masking_lab.rendering.ramp_inverse import (
    MAX_TARGET_DB_SL,
    REASON_TEXT,
    STATUS_NAMES,
    PointSolution,
    Reason,
    Status,
    folded_cases,
    reproduces_array,
    tiled_cases,
)

__all__ = [
    "REASON_TEXT",
    "STATUS_NAMES",
    "MissingMaskingError",
    "MutualMasking",
    "PairProblem",
    "PointSolution",
    "Reason",
    "Solution",
    "Status",
    "ev_masked_al_db_sl",
    "forward",
    "mv_masked_al_db_sl",
    "pair_from_params",
    "solve",
]


@dataclass(frozen=True)
class Solution:
    """Answers for an array of targets (from :func:`solve`); every array has the targets' shape.

    Attributes
    ----------
    mv_target_db_sl, ev_target_db_sl : ndarray of float
        The targets m_p, e_p in dB SL (broadcast).
    mv_input_db_sl, ev_input_db_sl : ndarray of float
        Required inputs m_i, e_i in dB SL where ``status`` is unique; NaN elsewhere (never a
        guess: see :meth:`solutions` for points with several answers).
    case : ndarray of int8
        1–4 where unique, 0 elsewhere.
    status : ndarray of int8
        :class:`Status` codes.
    reason : ndarray of int8
        :class:`Reason` codes (``OK`` where unique or multiple).
    continuum : ndarray of bool
        b·d == 1 and a half-line of answers (see :class:`PointSolution`).
    mv_exceeds_rating, ev_exceeds_rating : ndarray of bool
        The unique answer needs more than the device's rated level on that channel.
    candidates_mv_input_db_sl, candidates_ev_input_db_sl : ndarray or None
        Shape ``(..., 4)``: the answer each case would give (b·d ≥ 1 only).
    candidate_valid : ndarray of bool or None
        Shape ``(..., 4)``: which of those are distinct answers (b·d ≥ 1 only).
    max_mv_db_sl, max_ev_db_sl : float or None
        The device's rated maximum input per channel, dB SL, if given.
    """

    mv_target_db_sl: NDArray[np.float64]
    ev_target_db_sl: NDArray[np.float64]
    mv_input_db_sl: NDArray[np.float64]
    ev_input_db_sl: NDArray[np.float64]
    case: NDArray[np.int8]
    status: NDArray[np.int8]
    reason: NDArray[np.int8]
    continuum: NDArray[np.bool_]
    mv_exceeds_rating: NDArray[np.bool_]
    ev_exceeds_rating: NDArray[np.bool_]
    candidates_mv_input_db_sl: NDArray[np.float64] | None = None
    candidates_ev_input_db_sl: NDArray[np.float64] | None = None
    candidate_valid: NDArray[np.bool_] | None = None
    max_mv_db_sl: float | None = None
    max_ev_db_sl: float | None = None

    @property
    def shape(self) -> tuple[int, ...]:
        """Shape of the target arrays."""
        return self.status.shape

    def status_names(self) -> list[str]:
        """Status per point as ``"unique"``, ``"none"`` or ``"multiple"`` (flattened)."""
        return [STATUS_NAMES[Status(int(s))] for s in self.status.ravel()]

    def solutions(self, index: int | tuple[int, ...]) -> tuple[tuple[float, float, int], ...]:
        """Every answer ``(mv_input_db_sl, ev_input_db_sl, case)`` at one point, by case."""
        st = Status(int(self.status[index]))
        if st == Status.UNIQUE:
            m_i = float(self.mv_input_db_sl[index])
            return ((m_i, float(self.ev_input_db_sl[index]), int(self.case[index])),)
        if st == Status.NONE or self.candidate_valid is None:
            return ()
        assert self.candidates_mv_input_db_sl is not None
        assert self.candidates_ev_input_db_sl is not None
        valid = self.candidate_valid[index]
        mv = self.candidates_mv_input_db_sl[index]
        ev = self.candidates_ev_input_db_sl[index]
        return tuple((float(mv[k]), float(ev[k]), k + 1) for k in range(4) if valid[k])

    def counts(self) -> dict[str, int]:
        """Number of points per status name."""
        return {
            name: int(np.count_nonzero(self.status == code)) for code, name in STATUS_NAMES.items()
        }


def solve(
    mm: MutualMasking,
    mv_target_db_sl: ArrayLike,
    ev_target_db_sl: ArrayLike,
    *,
    max_mv_db_sl: float | None = None,
    max_ev_db_sl: float | None = None,
) -> Solution:
    """Vectorised inverse: inputs (m_i, e_i) in dB SL perceived as (m_p, e_p) in dB SL.

    Parameters
    ----------
    mm : MutualMasking
        The pair's masking ramps.
    mv_target_db_sl, ev_target_db_sl : array_like
        Wanted perceived intensities m_p and e_p, dB SL; broadcast together. ``-inf`` turns a
        channel off.
    max_mv_db_sl, max_ev_db_sl : float, optional
        The device's rated maximum input per channel, dB SL; points whose answer needs more are
        flagged in ``mv_exceeds_rating`` / ``ev_exceeds_rating`` (never clipped).

    Returns
    -------
    Solution
        Per point: inputs, case, status and reason.
    """
    m_p, e_p = np.broadcast_arrays(
        np.asarray(mv_target_db_sl, dtype=float), np.asarray(ev_target_db_sl, dtype=float)
    )
    for name, lim in (("max_mv_db_sl", max_mv_db_sl), ("max_ev_db_sl", max_ev_db_sl)):
        if lim is not None and math.isnan(lim):
            raise SolverError(f"{name} is NaN; give the device's rated maximum in dB SL")
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        u = _lin(mm.a_db, mm.b, e_p)
        v = _lin(mm.c_db, mm.d, m_p)
        # n1 = U + b·V and n2 = V + d·U, with the same rounding as the scalar path.
        # (asarray: arithmetic on 0-d arrays gives scalars, which cannot be updated in place.)
        n1 = np.asarray(mm.b * v if mm.b else np.zeros_like(v))
        n1 += u
        n2 = np.asarray(mm.d * u if mm.d else np.zeros_like(u))
        n2 += v
        if mm.bd_side < 0:
            out = tiled_cases(mm, m_p, e_p, u, v, n1, n2)
        else:
            out = folded_cases(mm, m_p, e_p, u, v, n1, n2)
        m_i, e_i, case, status, reason, continuum, cand_m, cand_e, cand_ok = out
        fine = m_i < np.inf
        fine &= e_i < np.inf
        # Finite targets beyond the documented range get no answer (see ramp_inverse).
        far = (np.abs(m_p) > MAX_TARGET_DB_SL) & (m_p > -np.inf)
        far |= (np.abs(e_p) > MAX_TARGET_DB_SL) & (e_p > -np.inf)
        if cand_ok is not None or not fine.all() or far.any():
            # Slow path, only when something needs reporting: NaN/+inf targets, overflow,
            # or b·d ≥ 1.
            nan_t = np.isnan(m_p) | np.isnan(e_p)
            inf_t = (m_p == np.inf) | (e_p == np.inf)
            bad = nan_t | inf_t
            overflow = (status == Status.UNIQUE) & ~fine & ~bad
            overflow |= far & ~bad
            if cand_ok is not None:
                assert cand_m is not None and cand_e is not None
                cand_over = cand_ok & ~((cand_m < np.inf) & (cand_e < np.inf))
                overflow |= cand_over.any(axis=-1) & ~bad
                cand_ok[overflow | bad] = False
                cand_m[~cand_ok] = np.nan
                cand_e[~cand_ok] = np.nan
            status[overflow | bad] = Status.NONE
            reason[overflow] = Reason.OVERFLOW
            reason[inf_t] = Reason.INFINITE_TARGET
            reason[nan_t] = Reason.NAN_TARGET
            continuum[bad | overflow] = False
            not_unique = status != Status.UNIQUE
            m_i[not_unique] = np.nan
            e_i[not_unique] = np.nan
            case[not_unique] = 0
        _refuse_irreproducible(mm, m_p, e_p, out=(m_i, e_i, case, status, reason, continuum))
        if cand_ok is not None:
            assert cand_m is not None and cand_e is not None
            _refuse_irreproducible_candidates(
                mm, m_p, e_p, cand_m, cand_e, cand_ok, (m_i, e_i, case, status, reason, continuum)
            )
        mv_over = _exceeds(m_i, max_mv_db_sl)
        ev_over = _exceeds(e_i, max_ev_db_sl)
    return Solution(
        mv_target_db_sl=m_p,
        ev_target_db_sl=e_p,
        mv_input_db_sl=m_i,
        ev_input_db_sl=e_i,
        case=case,
        status=status,
        reason=reason,
        continuum=continuum,
        mv_exceeds_rating=mv_over,
        ev_exceeds_rating=ev_over,
        candidates_mv_input_db_sl=cand_m,
        candidates_ev_input_db_sl=cand_e,
        candidate_valid=cand_ok,
        max_mv_db_sl=max_mv_db_sl,
        max_ev_db_sl=max_ev_db_sl,
    )


def _refuse_irreproducible(mm: MutualMasking, m_p, e_p, out) -> None:
    """A unique answer that the forward model does not turn back into its target is refused.

    Near b·d = 1 the closed form divides by 1 − b·d and float64 cannot carry the result; such a
    point gets status none, reason ILL_CONDITIONED (in place on ``out``).
    """
    m_i, e_i, status = out[0], out[1], out[3]
    unique = status == Status.UNIQUE
    if not unique.any():
        return
    bad = unique & ~reproduces_array(mm, m_p, e_p, m_i, e_i)
    if bad.any():
        _mark_ill(bad, out)


def _refuse_irreproducible_candidates(
    mm: MutualMasking, m_p, e_p, cand_m, cand_e, cand_ok, out
) -> None:
    """b·d ≥ 1: a point any of whose listed answers fails the forward check is ill-conditioned."""
    if not cand_ok.any():
        return
    good = reproduces_array(mm, m_p[..., None], e_p[..., None], cand_m, cand_e)
    bad = (cand_ok & ~good).any(axis=-1)
    if bad.any():
        cand_ok[bad] = False
        cand_m[bad] = np.nan
        cand_e[bad] = np.nan
        _mark_ill(bad, out)


def _mark_ill(bad, out) -> None:
    m_i, e_i, case, status, reason, continuum = out
    status[bad] = Status.NONE
    reason[bad] = Reason.ILL_CONDITIONED
    continuum[bad] = False
    m_i[bad] = np.nan
    e_i[bad] = np.nan
    case[bad] = 0


def _lin(intercept: float, slope: float, x: NDArray[np.float64]) -> NDArray[np.float64]:
    if slope == 0:
        return np.full(x.shape, intercept)
    return intercept + slope * x


def _exceeds(x: NDArray[np.float64], limit: float | None) -> NDArray[np.bool_]:
    if limit is None:
        return np.zeros(x.shape, dtype=bool)
    return x > limit


def forward(
    mm: MutualMasking, mv_input_db_sl: ArrayLike, ev_input_db_sl: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Perceived (m_p, e_p) in dB SL for inputs (m_i, e_i) in dB SL, vectorised (Eq. 3–4).

    ``-inf`` inputs (channel off) mask nothing and are perceived as ``-inf``.
    """
    m_i, e_i = np.broadcast_arrays(
        np.asarray(mv_input_db_sl, dtype=float), np.asarray(ev_input_db_sl, dtype=float)
    )
    return m_i - mv_masked_al_db_sl(mm, e_i), e_i - ev_masked_al_db_sl(mm, m_i)


def mv_masked_al_db_sl(mm: MutualMasking, ev_input_db_sl: ArrayLike) -> NDArray[np.float64]:
    """f(e_i): the MV stimulus's masked AL in dB SL (= its AL shift, dB) with EV at e_i dB SL."""
    x = np.asarray(ev_input_db_sl, dtype=float)
    with np.errstate(invalid="ignore"):
        return np.maximum(0.0, _lin(mm.a_db, mm.b, x))


def ev_masked_al_db_sl(mm: MutualMasking, mv_input_db_sl: ArrayLike) -> NDArray[np.float64]:
    """g(m_i): EV's masked AL in dB SL (= its AL shift, dB) with MV at m_i dB SL."""
    x = np.asarray(mv_input_db_sl, dtype=float)
    with np.errstate(invalid="ignore"):
        return np.maximum(0.0, _lin(mm.c_db, mm.d, x))
