"""Inverse rendering under mutual masking: the perceived pair wanted → the input pair to play.

Paper §3.2, Eq. (1)–(4) and Table 4. With all levels in dB SL,

    f(e_i) = max(0, a + b·e_i)      AL shift of the MV stimulus caused by EV at e_i
    g(m_i) = max(0, c + d·m_i)      AL shift of EV caused by the MV stimulus at m_i
    m_p = m_i − f(e_i)              perceived MV
    e_p = e_i − g(m_i)              perceived EV

Given a target (m_p, e_p), find (m_i, e_i). Write ``F = f(e_i)`` and ``G = g(m_i)`` for the
masking the answer will suffer, so ``m_i = m_p + F`` and ``e_i = e_p + G``, and let

    U = a + b·e_p      (what EV would do to MV if EV played exactly at its target)
    V = c + d·m_p      (what MV would do to EV if MV played exactly at its target)

Then only ``U``, ``V``, ``b`` and ``d`` matter: ``F = max(0, U + b·G)``, ``G = max(0, V + d·F)``.
The four cases are which of the two ramps is on its rising part at the answer:

=====  =================  =================================  ==========================
case   ramps rising        masking F, G                         holds when
=====  =================  =================================  ==========================
1      neither             F = 0, G = 0                         U ≤ 0, V ≤ 0
2      g (EV is masked)    F = 0, G = V                         V ≥ 0, U + b·V ≤ 0
3      f (MV is masked)    F = U, G = 0                         U ≥ 0, V + d·U ≤ 0
4      both                F = (U + b·V)/(1 − b·d),             F ≥ 0 and G ≥ 0
                           G = (V + d·U)/(1 − b·d)
=====  =================  =================================  ==========================

Case 2 in the paper is m_i = m_p, e_i = d·m_p + e_p + c and case 4 is
m_i = (m_p + b·e_p + a + b·c)/(1 − b·d); both are the rows above written out. The last column
is derived here; the paper's "condition (e_p, m_p)" column agrees with it except for a typo in
case 3, which writes e_i ≥ −a/b where the condition on the target is e_p ≥ −a/b (U ≥ 0).

With ``b·d < 1`` (and slopes ≥ 0) the four regions tile the (U, V) plane, so every real target
has exactly one answer. With ``b·d > 1`` case 4 overlaps cases 1–3 and leaves a wedge uncovered:
a target has two answers or none (one on the fold). With ``b·d == 1`` exactly, case 4 has no
answer unless ``U + b·V == 0``, where it has a half-line of them (reported as a *continuum*).

Scalar calls (:meth:`MutualMasking.solve_point`) use plain float arithmetic so one call costs a
few µs inside a 1 kHz haptic loop; :func:`solve` does the same on arrays with numpy.

Silence is ``-inf`` dB SL: a target of ``-inf`` for a channel means that channel is off and is
answered with an input of ``-inf``. NaN and ``+inf`` targets have no answer (status ``none``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import IntEnum
from fractions import Fraction
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from masking_lab.core.errors import SolverError
from masking_lab.core.masking import MaskingFunction


class Status(IntEnum):
    """How many input pairs produce a target."""

    NONE = 0
    UNIQUE = 1
    MULTIPLE = 2


class Reason(IntEnum):
    """Why a point has no unique answer (``OK`` when it has one, or several)."""

    OK = 0
    NAN_TARGET = 1
    INFINITE_TARGET = 2
    UNREACHABLE = 3
    OVERFLOW = 4


STATUS_NAMES = {Status.NONE: "none", Status.UNIQUE: "unique", Status.MULTIPLE: "multiple"}
REASON_TEXT = {
    Reason.OK: "",
    Reason.NAN_TARGET: "target is NaN",
    Reason.INFINITE_TARGET: "a +inf dB SL target needs an infinite input",
    Reason.UNREACHABLE: "no input pair is perceived this way (b·d ≥ 1: outside the reachable "
    "region)",
    Reason.OVERFLOW: "the required input is beyond the float range",
}

_EPS = np.finfo(float).eps


class PointSolution(NamedTuple):
    """The answer for one target (scalar path).

    Attributes
    ----------
    mv_input_db_sl, ev_input_db_sl : float
        Required inputs in dB SL when ``status`` is unique; NaN otherwise.
    case : int
        1–4 (see the module docstring) when unique; 0 otherwise.
    status : Status
        ``UNIQUE``, ``NONE`` or ``MULTIPLE``.
    solutions : tuple of (mv_input_db_sl, ev_input_db_sl, case)
        Every answer (one when unique, none when none). With ``continuum`` the case-4 entry is
        the start of a half-line of answers.
    continuum : bool
        ``b·d == 1`` and the target lies on the line where case 4 holds for a whole half-line:
        from the listed case-4 start, ``(m_i, e_i) + t·(1, d)`` for every t ≥ 0 dB.
    reason : Reason
        Why there is no answer (``OK`` otherwise).
    """

    mv_input_db_sl: float
    ev_input_db_sl: float
    case: int
    status: Status
    solutions: tuple[tuple[float, float, int], ...] = ()
    continuum: bool = False
    reason: Reason = Reason.OK


@dataclass(frozen=True)
class MutualMasking:
    """The two masking ramps of one MV stimulus and one EV stimulus (paper Eq. 1–2).

    Attributes
    ----------
    a_db : float
        Intercept of f, the AL shift of the MV stimulus caused by EV, dB.
    b : float
        Slope of f, dB of AL shift per dB SL of EV (≥ 0).
    c_db : float
        Intercept of g, the AL shift of EV caused by the MV stimulus, dB.
    d : float
        Slope of g, dB of AL shift per dB SL of MV (≥ 0).
    mv : str
        Name of the MV stimulus (e.g. ``"MV180"``); labels only.
    ev : str
        Name of the EV stimulus (``"EV270"``); labels only.
    f_fitted_range_db_sl, g_fitted_range_db_sl : tuple[float, float] or None
        EV (for f) and MV (for g) masker levels the ramps were fitted on, dB SL; beyond them a
        ramp is an extrapolation. None if unknown.
    notes : tuple[str, ...]
        Caveats from the parameter file (e.g. a direction with no masking found).
    """

    a_db: float
    b: float
    c_db: float
    d: float
    mv: str = "MV"
    ev: str = "EV270"
    f_fitted_range_db_sl: tuple[float, float] | None = field(default=None, compare=False)
    g_fitted_range_db_sl: tuple[float, float] | None = field(default=None, compare=False)
    notes: tuple[str, ...] = field(default=(), compare=False)
    one_minus_bd: float = field(init=False, repr=False)
    bd_side: int = field(init=False, repr=False)

    def __post_init__(self) -> None:
        for name in ("a_db", "b", "c_db", "d"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float | np.floating):
                raise SolverError(f"masking parameter {name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise SolverError(
                    f"masking parameter {name} must be finite, got {value!r}; check the fitted "
                    "masking functions"
                )
            object.__setattr__(self, name, float(value))
        for name, what in (("b", f"{self.mv} by {self.ev}"), ("d", f"{self.ev} by {self.mv}")):
            if getattr(self, name) < 0:
                raise SolverError(
                    f"masking slope {name} ({what}) is {getattr(self, name)!r}: a masking ramp "
                    "rises with the masker, so slopes must be ≥ 0. A negative fitted slope means "
                    "no masking was found; use slope 0 with intercept ≤ 0 for 'no masking'"
                )
        # 1 − b·d exactly, then rounded once: near b·d = 1 the plain float product loses it.
        exact = 1 - Fraction(self.b) * Fraction(self.d)
        object.__setattr__(self, "one_minus_bd", float(exact))
        object.__setattr__(self, "bd_side", (exact < 0) - (exact > 0))

    # ----------------------------------------------------------------------------- building

    @classmethod
    def from_functions(cls, mv_by_ev: MaskingFunction, ev_by_mv: MaskingFunction) -> MutualMasking:
        """Pair two :class:`~masking_lab.core.masking.MaskingFunction` objects.

        Parameters
        ----------
        mv_by_ev : MaskingFunction
            Target an MV stimulus, masker the EV stimulus (gives a, b).
        ev_by_mv : MaskingFunction
            Target the EV stimulus, masker the same MV stimulus (gives c, d).
        """
        if mv_by_ev.target != ev_by_mv.masker or mv_by_ev.masker != ev_by_mv.target:
            raise SolverError(
                f"the two masking functions do not form a pair: {mv_by_ev.target} by "
                f"{mv_by_ev.masker} and {ev_by_mv.target} by {ev_by_mv.masker}; pass the MV "
                "stimulus masked by EV and EV masked by the same MV stimulus"
            )
        return cls(
            mv_by_ev.intercept_db,
            mv_by_ev.slope,
            ev_by_mv.intercept_db,
            ev_by_mv.slope,
            mv=mv_by_ev.target,
            ev=mv_by_ev.masker,
        )

    @property
    def bd(self) -> float:
        """Product of the two slopes b·d (dimensionless); < 1 means every target is reachable."""
        return self.b * self.d

    # ----------------------------------------------------------------------------- forward

    def mv_masking_db(self, ev_input_db_sl: float) -> float:
        """f(e_i): the MV stimulus's masked AL in dB SL (its AL shift, dB) with EV at e_i."""
        return _ramp(self.a_db, self.b, ev_input_db_sl)

    def ev_masking_db(self, mv_input_db_sl: float) -> float:
        """g(m_i): EV's masked AL in dB SL (its AL shift, dB) with MV at m_i."""
        return _ramp(self.c_db, self.d, mv_input_db_sl)

    def forward_point(self, mv_input_db_sl: float, ev_input_db_sl: float) -> tuple[float, float]:
        """Perceived (m_p, e_p) in dB SL for inputs (m_i, e_i) in dB SL (paper Eq. 3–4)."""
        m_i = float(mv_input_db_sl)
        e_i = float(ev_input_db_sl)
        return m_i - _ramp(self.a_db, self.b, e_i), e_i - _ramp(self.c_db, self.d, m_i)

    # ----------------------------------------------------------------------------- inverse

    def solve_point(self, mv_target_db_sl: float, ev_target_db_sl: float) -> PointSolution:
        """Inputs (m_i, e_i) in dB SL that are perceived as (m_p, e_p) in dB SL; scalar path.

        Plain float arithmetic (no numpy) so that it fits a 1 kHz haptic loop.

        Parameters
        ----------
        mv_target_db_sl : float
            Wanted perceived MV intensity m_p, dB SL (``-inf``: MV off).
        ev_target_db_sl : float
            Wanted perceived EV intensity e_p, dB SL (``-inf``: EV off).
        """
        m_p = float(mv_target_db_sl)
        e_p = float(ev_target_db_sl)
        if m_p != m_p or e_p != e_p:
            return _NO_NAN
        if m_p == math.inf or e_p == math.inf:
            return _NO_INF
        b, d = self.b, self.d
        u = self.a_db + b * e_p if b else self.a_db
        v = self.c_db + d * m_p if d else self.c_db
        if self.bd_side < 0:
            if u <= 0.0 and v <= 0.0:
                return _unique(m_p, e_p, 1)
            if v > 0.0 and u + b * v <= 0.0:
                return _unique(m_p, e_p + v, 2)
            if u > 0.0 and v + d * u <= 0.0:
                return _unique(m_p + u, e_p, 3)
            den = self.one_minus_bd
            return _unique(m_p + (u + b * v) / den, e_p + (v + d * u) / den, 4)
        return self._solve_point_folded(m_p, e_p, u, v)

    def _solve_point_folded(self, m_p: float, e_p: float, u: float, v: float) -> PointSolution:
        """Every answer when b·d ≥ 1 (none, one on the fold, two, or a half-line)."""
        b, d = self.b, self.d
        n1 = u + b * v if b else u
        n2 = v + d * u if d else v
        cands: list[tuple[float, float, int]] = []
        if u <= 0.0 and v <= 0.0:
            cands.append((0.0, 0.0, 1))
        if v >= 0.0 and n1 <= 0.0:
            cands.append((0.0, v, 2))
        if u >= 0.0 and n2 <= 0.0:
            cands.append((u, 0.0, 3))
        continuum = False
        if self.bd_side > 0:
            if n1 <= 0.0 and n2 <= 0.0:
                den = self.one_minus_bd
                cands.append((n1 / den, n2 / den, 4))
        elif abs(n1) <= _fold_tolerance(self, m_p, e_p):
            f0 = max(0.0, -v / d)
            cands.append((f0, v + d * f0, 4))
            continuum = True
        if continuum:
            # Keep the half-line's start under case 4 when an edge case meets it there.
            cands.insert(0, cands.pop())
        distinct: list[tuple[float, float, int]] = []
        for f, g, case in cands:
            if not any(_same(f, g, f2, g2, u, v) for f2, g2, _ in distinct):
                distinct.append((f, g, case))
        distinct.sort(key=lambda s: s[2])
        sols = tuple((m_p + f, e_p + g, case) for f, g, case in distinct)
        if any(not (s[0] < math.inf and s[1] < math.inf) for s in sols):
            return _NO_OVERFLOW
        if not sols:
            return PointSolution(math.nan, math.nan, 0, Status.NONE, (), False, Reason.UNREACHABLE)
        if len(sols) == 1 and not continuum:
            return PointSolution(sols[0][0], sols[0][1], sols[0][2], Status.UNIQUE, sols)
        return PointSolution(math.nan, math.nan, 0, Status.MULTIPLE, sols, continuum)


def _ramp(intercept: float, slope: float, x: float) -> float:
    # slope 0 times ±inf would be NaN; a flat ramp ignores its masker.
    y = intercept + slope * x if slope else intercept
    return y if y > 0.0 else (0.0 if y == y else y)


def _unique(m_i: float, e_i: float, case: int) -> PointSolution:
    if m_i < math.inf and e_i < math.inf:
        return PointSolution(m_i, e_i, case, Status.UNIQUE, ((m_i, e_i, case),))
    return _NO_OVERFLOW


def _fold_tolerance(mm: MutualMasking, m_p: float, e_p: float) -> float:
    # Rounding in U + b·V = a + b·e_p + b·c + b·d·m_p: a few ulps of its largest term.
    b, d = mm.b, mm.d
    terms = abs(mm.a_db) + b * abs(mm.c_db)
    if b and math.isfinite(e_p):
        terms += b * abs(e_p)
    if b and d and math.isfinite(m_p):
        terms += b * d * abs(m_p)
    return 16.0 * _EPS * terms


def _same(f1: float, g1: float, f2: float, g2: float, u: float, v: float) -> bool:
    # Two case formulas meeting on a region boundary give one answer up to rounding.
    scale = 64.0 * _EPS * (abs(f1) + abs(g1) + abs(f2) + abs(g2) + abs(u) + abs(v))
    return abs(f1 - f2) <= scale and abs(g1 - g2) <= scale


_NO_NAN = PointSolution(math.nan, math.nan, 0, Status.NONE, (), False, Reason.NAN_TARGET)
_NO_INF = PointSolution(math.nan, math.nan, 0, Status.NONE, (), False, Reason.INFINITE_TARGET)
_NO_OVERFLOW = PointSolution(math.nan, math.nan, 0, Status.NONE, (), False, Reason.OVERFLOW)


# --------------------------------------------------------------------------------------------
# Arrays


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
            out = _solve_tiled(mm, m_p, e_p, u, v, n1, n2)
        else:
            out = _solve_folded(mm, m_p, e_p, u, v, n1, n2)
        m_i, e_i, case, status, reason, continuum, cand_m, cand_e, cand_ok = out
        fine = m_i < np.inf
        fine &= e_i < np.inf
        if cand_ok is not None or not fine.all():
            # Slow path, only when something needs reporting: NaN/+inf targets, overflow,
            # or b·d ≥ 1.
            nan_t = np.isnan(m_p) | np.isnan(e_p)
            inf_t = (m_p == np.inf) | (e_p == np.inf)
            bad = nan_t | inf_t
            overflow = (status == Status.UNIQUE) & ~fine & ~bad
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


def _lin(intercept: float, slope: float, x: NDArray[np.float64]) -> NDArray[np.float64]:
    if slope == 0:
        return np.full(x.shape, intercept)
    return intercept + slope * x


def _exceeds(x: NDArray[np.float64], limit: float | None) -> NDArray[np.bool_]:
    if limit is None:
        return np.zeros(x.shape, dtype=bool)
    return x > limit


def _solve_tiled(mm, m_p, e_p, u, v, n1, n2):  # type: ignore[no-untyped-def]
    """b·d < 1: exactly one case holds at every finite target (see the module table)."""
    u_on = u > 0
    v_on = v > 0
    c1 = ~(u_on | v_on)
    c2 = v_on & (n1 <= 0)  # implies u ≤ 0 when b ≥ 0
    c3 = u_on & (n2 <= 0)  # implies v ≤ 0 when d ≥ 0
    # Case 4 everywhere first (reusing n1, n2), then overwrite the other cases.
    f = np.divide(n1, mm.one_minus_bd, out=n1)
    g = np.divide(n2, mm.one_minus_bd, out=n2)
    np.copyto(f, u, where=c3)
    np.copyto(g, v, where=c2)
    off_f = c1 | c2
    off_g = c1 | c3
    np.copyto(f, 0.0, where=off_f)
    np.copyto(g, 0.0, where=off_g)
    case = np.full(m_p.shape, 4, dtype=np.int8)
    np.copyto(case, 3, where=c3)
    np.copyto(case, 2, where=c2)
    np.copyto(case, 1, where=c1)
    status = np.ones(m_p.shape, dtype=np.int8)  # Status.UNIQUE
    reason = np.zeros(m_p.shape, dtype=np.int8)
    continuum = np.zeros(m_p.shape, dtype=bool)
    f += m_p
    g += e_p
    return f, g, case, status, reason, continuum, None, None, None


def _solve_folded(mm, m_p, e_p, u, v, n1, n2):  # type: ignore[no-untyped-def]
    """b·d ≥ 1: test every case, keep the distinct answers."""
    shape = m_p.shape
    f = np.zeros((*shape, 4))
    g = np.zeros((*shape, 4))
    ok = np.zeros((*shape, 4), dtype=bool)
    ok[..., 0] = (u <= 0) & (v <= 0)
    ok[..., 1] = (v >= 0) & (n1 <= 0)
    g[..., 1] = v
    ok[..., 2] = (u >= 0) & (n2 <= 0)
    f[..., 2] = u
    continuum = np.zeros(shape, dtype=bool)
    if mm.bd_side > 0:
        den = mm.one_minus_bd
        ok[..., 3] = (n1 <= 0) & (n2 <= 0)
        f[..., 3] = n1 / den
        g[..., 3] = n2 / den
    else:
        terms = abs(mm.a_db) + mm.b * abs(mm.c_db)
        if mm.b:
            terms = terms + np.where(np.isfinite(e_p), mm.b * np.abs(e_p), 0.0)
            terms = terms + np.where(np.isfinite(m_p), mm.b * mm.d * np.abs(m_p), 0.0)
        continuum = np.abs(n1) <= 16.0 * _EPS * terms
        f0 = np.maximum(0.0, -v / mm.d)
        ok[..., 3] = continuum
        f[..., 3] = f0
        g[..., 3] = v + mm.d * f0
    f[~ok] = 0.0
    g[~ok] = 0.0
    scale = 64.0 * _EPS * (np.abs(u) + np.abs(v))[..., None]
    for k in range(1, 4):
        for j in range(k):
            tol = scale[..., 0] + 64.0 * _EPS * (
                np.abs(f[..., k]) + np.abs(g[..., k]) + np.abs(f[..., j]) + np.abs(g[..., j])
            )
            same = (
                ok[..., j]
                & ok[..., k]
                & (np.abs(f[..., k] - f[..., j]) <= tol)
                & (np.abs(g[..., k] - g[..., j]) <= tol)
            )
            if k == 3:
                # Keep the half-line's start under case 4 when an edge case meets it there.
                ok[..., j] &= ~(same & continuum)
                same &= ~continuum
            ok[..., k] &= ~same
    n_ok = ok.sum(axis=-1)
    unique = (n_ok == 1) & ~continuum
    first = np.argmax(ok, axis=-1)
    cand_m = m_p[..., None] + f
    cand_e = e_p[..., None] + g
    cand_m[~ok] = np.nan
    cand_e[~ok] = np.nan
    m_i = np.take_along_axis(cand_m, first[..., None], axis=-1)[..., 0].copy()
    e_i = np.take_along_axis(cand_e, first[..., None], axis=-1)[..., 0].copy()
    case = np.where(unique, first + 1, 0).astype(np.int8)
    status = np.where(n_ok == 0, Status.NONE, Status.MULTIPLE).astype(np.int8)
    status[unique] = Status.UNIQUE
    reason = np.where(n_ok == 0, Reason.UNREACHABLE, Reason.OK).astype(np.int8)
    return m_i, e_i, case, status, reason, continuum, cand_m, cand_e, ok


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


# --------------------------------------------------------------------------------------------
# masking_params.json → a pair


@dataclass(frozen=True)
class PairProblem:
    """Why one direction of a stimulus pair cannot be used.

    Attributes
    ----------
    target, masker : str
        Stimulus names of the missing masking function.
    status : str
        ``"missing"`` (no entry) or the entry's status (e.g. ``"insufficient_data"``).
    """

    target: str
    masker: str
    status: str


class MissingMaskingError(SolverError):
    """The parameters file lacks a fitted masking function the solver needs.

    Attributes
    ----------
    problems : list[PairProblem]
        Each unusable direction, with why.
    """

    def __init__(self, message: str, problems: list[PairProblem]) -> None:
        super().__init__(message)
        self.problems = problems


def pair_from_params(
    params: Mapping[str, Any], *, mv: str, ev: str = "EV270", source: str = "masking_params.json"
) -> MutualMasking:
    """Look up the two masking functions of one MV/EV stimulus pair in a parsed params file.

    Only that pair's two entries are read. A ``"no_masking"`` entry is used (its ramp is flat)
    and reported in ``notes``; an entry without a ramp (``"insufficient_data"``) is an error.

    Parameters
    ----------
    params : mapping
        Parsed ``masking_params.json`` (``{"functions": [{target, masker, intercept_db, slope,
        status, ...}, ...]}``).
    mv, ev : str
        Stimulus names, e.g. ``"MV180"`` and ``"EV270"``.
    source : str
        Name of the file, for messages.

    Raises
    ------
    MissingMaskingError
        If either direction is absent or has no ramp (e.g. ``"insufficient_data"``); lists both.
    """
    functions = params.get("functions") if isinstance(params, Mapping) else None
    if not isinstance(functions, list):
        raise SolverError(
            f"{source}: no 'functions' list; is this a masking_params.json written by "
            "`masking-lab fit`?"
        )
    found: dict[tuple[str, str], MaskingFunction] = {}
    ranges: dict[tuple[str, str], tuple[float, float] | None] = {}
    notes: list[str] = []
    problems: list[PairProblem] = []
    for target, masker in ((mv, ev), (ev, mv)):
        entry = next(
            (
                f
                for f in functions
                if isinstance(f, Mapping) and (f.get("target"), f.get("masker")) == (target, masker)
            ),
            None,
        )
        if entry is None:
            problems.append(PairProblem(target, masker, "missing"))
            continue
        status = entry.get("status", "fitted")
        if status not in ("fitted", "no_masking"):
            problems.append(PairProblem(target, masker, str(status)))
            continue
        try:
            found[(target, masker)] = MaskingFunction(
                target, masker, float(entry["intercept_db"]), float(entry["slope"])
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise SolverError(
                f"{source}: the entry for {target} masked by {masker} has no numeric "
                f"intercept_db/slope ({exc}); re-export it with `masking-lab fit`"
            ) from exc
        rng = entry.get("fitted_range_db_sl")
        ranges[(target, masker)] = (float(rng[0]), float(rng[1])) if rng else None
        if status == "no_masking":
            fn = found[(target, masker)]
            notes.append(
                f"{target} masked by {masker}: no masking was found (status 'no_masking'); "
                f"using the exported ramp max(0, {fn.intercept_db:g} + {fn.slope:g}·x)"
            )
    if problems:
        listed = "; ".join(
            f"{p.target} masked by {p.masker}: "
            + ("no entry" if p.status == "missing" else f"status {p.status!r}, not fitted")
            for p in problems
        )
        raise MissingMaskingError(
            f"{source}: cannot compensate {mv} with {ev}: {listed}. Measure the pair (masked "
            "sessions of each stimulus by the other), fit, and export again",
            problems,
        )
    f, g = found[(mv, ev)], found[(ev, mv)]
    try:
        return MutualMasking(
            f.intercept_db,
            f.slope,
            g.intercept_db,
            g.slope,
            mv=mv,
            ev=ev,
            f_fitted_range_db_sl=ranges[(mv, ev)],
            g_fitted_range_db_sl=ranges[(ev, mv)],
            notes=tuple(notes),
        )
    except SolverError as exc:
        raise SolverError(f"{source}: {exc}") from exc
