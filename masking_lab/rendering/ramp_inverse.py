"""The four-case closed form of the inverse, and how many answers a target has.

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

This module only classifies and solves; the pair of ramps lives in
:mod:`masking_lab.rendering.pair` and the public entry points in
:mod:`masking_lab.rendering.solver`. :func:`point_answer` uses plain float arithmetic so one call
costs a few µs inside a 1 kHz haptic loop; :func:`tiled_cases` and :func:`folded_cases` do the
same on arrays with numpy. Pure: no I/O.

Silence is ``-inf`` dB SL: a target of ``-inf`` for a channel means that channel is off and is
answered with an input of ``-inf``. NaN and ``+inf`` targets have no answer (status ``none``).

Documented range. Floats carry about 16 significant digits, so where a target, an intercept and
a slope-times-level differ by many orders of magnitude the small one is absorbed and no float
pair is perceived as the target (a slope of 1e300 once gave such a wrong "unique" answer). The
solver therefore works on slopes 0 ≤ b, d ≤ :data:`MAX_SLOPE` dB/dB, intercepts
``|a|, |c| ≤`` :data:`MAX_INTERCEPT_DB` dB (refused in :class:`~masking_lab.rendering.pair.
MutualMasking`) and finite targets ``|m_p|, |e_p| ≤`` :data:`MAX_TARGET_DB_SL` dB SL (answered
``none``, reason ``OVERFLOW``): a thousand times the paper's ranges, and inside it every answer
checks against the forward model to rounding (``tests/test_hardening_solver.py``).
"""

from __future__ import annotations

import math
from enum import IntEnum
from typing import NamedTuple, Protocol

import numpy as np

__all__ = [
    "REASON_TEXT",
    "STATUS_NAMES",
    "PointSolution",
    "RampPair",
    "Reason",
    "Status",
    "folded_cases",
    "point_answer",
    "reproduces",
    "reproduces_array",
    "tiled_cases",
]

#: Largest masking slope b or d the solver accepts, dB of AL shift per dB SL (paper: 0.6–1.1).
MAX_SLOPE = 100.0
#: Largest intercept magnitude |a| or |c| the solver accepts, dB (paper: within ±8 dB).
MAX_INTERCEPT_DB = 1000.0
#: Largest finite target magnitude solved, dB SL (a touch screen presents at most ~40 dB SL).
MAX_TARGET_DB_SL = 1e6
#: An answer counts only if the forward model, in float64, gives back each target within this
#: many dB (a millionth of the ~1 dB a participant can tell apart).
REPRODUCE_TOL_DB = 1e-6


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
    ILL_CONDITIONED = 5


STATUS_NAMES = {Status.NONE: "none", Status.UNIQUE: "unique", Status.MULTIPLE: "multiple"}
REASON_TEXT = {
    Reason.OK: "",
    Reason.NAN_TARGET: "target is NaN",
    Reason.INFINITE_TARGET: "a +inf dB SL target needs an infinite input",
    Reason.UNREACHABLE: "no input pair is perceived this way (b·d ≥ 1: outside the reachable "
    "region)",
    Reason.OVERFLOW: "outside the solver's range: a target beyond ±1e6 dB SL, or a required "
    "input beyond the float range",
    Reason.ILL_CONDITIONED: "ill-conditioned: the float64 answer does not give the target back "
    f"through the masking model within {REPRODUCE_TOL_DB:g} dB (b·d too close to 1, or levels "
    "too far apart in magnitude)",
}

_EPS = float(np.finfo(float).eps)


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


class RampPair(Protocol):
    """What the case analysis reads of a pair of ramps (a :class:`~.pair.MutualMasking`).

    Attributes
    ----------
    a_db, c_db : float
        Intercepts of f and g, dB.
    b, d : float
        Slopes of f and g, dB per dB SL (≥ 0).
    one_minus_bd : float
        1 − b·d, rounded once from its exact value.
    bd_side : int
        Sign of b·d − 1 (−1, 0 or 1), exact.
    """

    # read-only, so that a frozen dataclass such as MutualMasking satisfies the protocol
    @property
    def a_db(self) -> float: ...
    @property
    def b(self) -> float: ...
    @property
    def c_db(self) -> float: ...
    @property
    def d(self) -> float: ...
    @property
    def one_minus_bd(self) -> float: ...
    @property
    def bd_side(self) -> int: ...


# --------------------------------------------------------------------------------------------
# One point


def point_answer(mm: RampPair, m_p: float, e_p: float) -> PointSolution:
    """Every input pair (m_i, e_i) in dB SL perceived as (m_p, e_p) in dB SL; plain floats.

    Parameters
    ----------
    mm : RampPair
        The two ramps.
    m_p, e_p : float
        Wanted perceived MV and EV intensities, dB SL (``-inf``: that channel off).
    """
    if m_p != m_p or e_p != e_p:
        return _NO_NAN
    if m_p == math.inf or e_p == math.inf:
        return _NO_INF
    if max(abs(m_p) if m_p > -math.inf else 0.0, abs(e_p) if e_p > -math.inf else 0.0) > (
        MAX_TARGET_DB_SL
    ):
        return _NO_OVERFLOW
    b, d = mm.b, mm.d
    u = mm.a_db + b * e_p if b else mm.a_db
    v = mm.c_db + d * m_p if d else mm.c_db
    if mm.bd_side < 0:
        if u <= 0.0 and v <= 0.0:
            return _unique(mm, m_p, e_p, m_p, e_p, 1)
        if v > 0.0 and u + b * v <= 0.0:
            return _unique(mm, m_p, e_p, m_p, e_p + v, 2)
        if u > 0.0 and v + d * u <= 0.0:
            return _unique(mm, m_p, e_p, m_p + u, e_p, 3)
        den = mm.one_minus_bd
        return _unique(mm, m_p, e_p, m_p + (u + b * v) / den, e_p + (v + d * u) / den, 4)
    return _point_folded(mm, m_p, e_p, u, v)


def _point_folded(mm: RampPair, m_p: float, e_p: float, u: float, v: float) -> PointSolution:
    """Every answer when b·d ≥ 1 (none, one on the fold, two, or a half-line)."""
    b, d = mm.b, mm.d
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
    if mm.bd_side > 0:
        if n1 <= 0.0 and n2 <= 0.0:
            den = mm.one_minus_bd
            cands.append((n1 / den, n2 / den, 4))
    elif abs(n1) <= _fold_tolerance(mm, m_p, e_p):
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
    if not all(reproduces(mm, m_p, e_p, s[0], s[1]) for s in sols):
        return _NO_ILL
    if not sols:
        return PointSolution(math.nan, math.nan, 0, Status.NONE, (), False, Reason.UNREACHABLE)
    if len(sols) == 1 and not continuum:
        return PointSolution(sols[0][0], sols[0][1], sols[0][2], Status.UNIQUE, sols)
    return PointSolution(math.nan, math.nan, 0, Status.MULTIPLE, sols, continuum)


def _unique(
    mm: RampPair, m_p: float, e_p: float, m_i: float, e_i: float, case: int
) -> PointSolution:
    if not (m_i < math.inf and e_i < math.inf):
        return _NO_OVERFLOW
    if not reproduces(mm, m_p, e_p, m_i, e_i):
        return _NO_ILL
    return PointSolution(m_i, e_i, case, Status.UNIQUE, ((m_i, e_i, case),))


def reproduces(mm: RampPair, m_p: float, e_p: float, m_i: float, e_i: float) -> bool:
    """Whether inputs (m_i, e_i) are perceived as (m_p, e_p) within :data:`REPRODUCE_TOL_DB`.

    The forward model of paper Eq. (3)–(4) in float64, with the same operations as
    :func:`reproduces_array`, so the scalar and the vector solver agree bit for bit.

    Parameters
    ----------
    mm : RampPair
        The two ramps.
    m_p, e_p : float
        Targets, dB SL (``-inf``: channel off).
    m_i, e_i : float
        Candidate inputs, dB SL.

    Returns
    -------
    bool
        True when both targets come back within the tolerance (a ``-inf`` target exactly).

    Examples
    --------
    With b·d one ulp below 1 the closed form's answer is ~1e17 dB SL and gives a target back
    tens of dB off; a paper-like pair gives it back to rounding:

    >>> from masking_lab.rendering.pair import MutualMasking
    >>> mm = MutualMasking(1.39, 1.09, -6.22, 0.66)
    >>> p = mm.solve_point(12.0, 5.0)
    >>> reproduces(mm, 12.0, 5.0, p.mv_input_db_sl, p.ev_input_db_sl)
    True
    >>> reproduces(mm, 12.0, 5.0, p.mv_input_db_sl + 0.01, p.ev_input_db_sl)
    False
    """
    fm = m_i - _ramp_value(mm.a_db, mm.b, e_i)
    fe = e_i - _ramp_value(mm.c_db, mm.d, m_i)
    return (fm == m_p or abs(fm - m_p) <= REPRODUCE_TOL_DB) and (
        fe == e_p or abs(fe - e_p) <= REPRODUCE_TOL_DB
    )


def _ramp_value(intercept: float, slope: float, x: float) -> float:
    # max(0, intercept + slope·x); a flat ramp ignores its masker (0·±inf would be NaN).
    y = intercept + slope * x if slope else intercept
    return y if y > 0.0 else 0.0


def reproduces_array(
    mm: RampPair,
    m_p: np.ndarray,
    e_p: np.ndarray,
    m_i: np.ndarray,
    e_i: np.ndarray,
) -> np.ndarray:
    """:func:`reproduces` on arrays (broadcast); NaN inputs never reproduce.

    Parameters
    ----------
    mm : RampPair
        The two ramps.
    m_p, e_p, m_i, e_i : ndarray of float
        Targets and candidate inputs, dB SL.

    Returns
    -------
    ndarray of bool
        Per element, as :func:`reproduces`.

    Examples
    --------
    >>> from masking_lab.rendering.pair import MutualMasking
    >>> mm = MutualMasking(0.0, 0.5, 0.0, 0.5)
    >>> reproduces_array(mm, np.array([2.0]), np.array([2.0]), np.array([4.0, 5.0]),
    ...                  np.array([4.0, 4.0])).tolist()
    [True, False]
    """
    with np.errstate(invalid="ignore", over="ignore"):
        fm = m_i - _ramp_array(mm.a_db, mm.b, e_i)
        fe = e_i - _ramp_array(mm.c_db, mm.d, m_i)
        ok_m = (fm == m_p) | (np.abs(fm - m_p) <= REPRODUCE_TOL_DB)
        ok_e = (fe == e_p) | (np.abs(fe - e_p) <= REPRODUCE_TOL_DB)
    return ok_m & ok_e


def _ramp_array(intercept: float, slope: float, x: np.ndarray) -> np.ndarray:
    y = intercept + slope * x if slope else np.full(np.shape(x), intercept)
    return np.where(y > 0.0, y, 0.0)


def _fold_tolerance(mm: RampPair, m_p: float, e_p: float) -> float:
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
_NO_ILL = PointSolution(math.nan, math.nan, 0, Status.NONE, (), False, Reason.ILL_CONDITIONED)


# --------------------------------------------------------------------------------------------
# Arrays


def tiled_cases(mm, m_p, e_p, u, v, n1, n2):
    """b·d < 1: exactly one case holds at every finite target (see the module table).

    Parameters
    ----------
    mm : RampPair
        The ramps (slopes b, d ≥ 0, ``one_minus_bd`` > 0).
    m_p, e_p : ndarray of float
        Targets, dB SL (broadcast to one shape).
    u, v, n1, n2 : ndarray of float
        ``U``, ``V``, ``U + b·V`` and ``V + d·U``, dB (``n1`` and ``n2`` are overwritten).

    Returns
    -------
    tuple
        ``(m_i, e_i, case, status, reason, continuum, None, None, None)``: inputs in dB SL and
        per-point codes, in the layout :func:`folded_cases` returns.
    """
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


def folded_cases(mm, m_p, e_p, u, v, n1, n2):
    """b·d ≥ 1: test every case, keep the distinct answers.

    Parameters are those of :func:`tiled_cases`.

    Returns
    -------
    tuple
        ``(m_i, e_i, case, status, reason, continuum, cand_m, cand_e, ok)``: the unique answer
        (NaN elsewhere) in dB SL, per-point codes, and the ``(..., 4)`` arrays of each case's
        answer (dB SL) with which of them are distinct answers.
    """
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
        # asarray: for 0-d targets the comparison is a numpy scalar, which cannot be updated.
        continuum = np.asarray(np.abs(n1) <= 16.0 * _EPS * terms)
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
