"""Property tests of the solver (hypothesis), checked against the forward model and brute force."""

from __future__ import annotations

import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.optimize import brentq

from masking_lab.rendering.ramp_inverse import REPRODUCE_TOL_DB
from masking_lab.rendering.solver import MutualMasking, Reason, Status, forward, solve

intercepts = st.floats(-30.0, 30.0, allow_nan=False)
slopes = st.floats(0.0, 3.0, allow_nan=False)
targets = st.floats(-100.0, 100.0, allow_nan=False)

EPS = float(np.finfo(float).eps)


def forward_error(mm, m_i, e_i, m_p, e_p):
    """|perceived − target| in dB, by Eq. (1)–(4) in plain floats (not the solver's forward)."""
    f = max(0.0, mm.a_db + mm.b * e_i)
    g = max(0.0, mm.c_db + mm.d * m_i)
    return max(abs(m_i - f - m_p), abs(e_i - g - e_p))


def brute_force_roots(mm, m_p, e_p, half_width=1e5, n=40_001):
    """Every e_i (up to grid resolution) with forward(m_p + f(e_i), e_i) = (m_p, e_p).

    Eq. (3) fixes m_i = m_p + f(e_i) for any e_i, so the problem is the 1-D equation
    h(e_i) = e_i − g(m_p + f(e_i)) − e_p = 0: scan a grid for sign changes and refine each.
    """

    def h(e):
        f = np.maximum(0.0, mm.a_db + mm.b * e)
        return e - np.maximum(0.0, mm.c_db + mm.d * (m_p + f)) - e_p

    grid = np.linspace(-half_width, half_width, n)
    values = h(grid)
    roots = list(grid[values == 0.0])
    for i in np.flatnonzero(np.sign(values[:-1]) * np.sign(values[1:]) < 0):
        roots.append(brentq(lambda e: float(h(np.array(e))), grid[i], grid[i + 1], xtol=1e-12))
    out = []
    for e_i in roots:
        m_i = m_p + max(0.0, mm.a_db + mm.b * e_i)
        out.append((float(m_i), float(e_i)))
    return out


@settings(max_examples=300, deadline=None)
@given(intercepts, slopes, intercepts, slopes, targets, targets)
def test_bd_below_one_forward_of_solve_is_the_target(a, b, c, d, m_p, e_p):
    assume(b * d <= 0.99)
    mm = MutualMasking(a, b, c, d)
    p = mm.solve_point(m_p, e_p)
    assert p.status == Status.UNIQUE and p.case in (1, 2, 3, 4)
    assert forward_error(mm, p.mv_input_db_sl, p.ev_input_db_sl, m_p, e_p) <= 1e-9
    sol = solve(mm, np.array([m_p]), np.array([e_p]))
    assert sol.status[0] == Status.UNIQUE
    assert (sol.mv_input_db_sl[0], sol.ev_input_db_sl[0], sol.case[0]) == (
        p.mv_input_db_sl,
        p.ev_input_db_sl,
        p.case,
    )


@settings(max_examples=200, deadline=None)
@given(
    intercepts,
    st.floats(0.5, 2.0),
    intercepts,
    st.floats(-12.0, -2.0),
    targets,
    targets,
)
def test_bd_just_below_one_is_accurate_relative_to_the_answer(a, b, c, log_gap, m_p, e_p):
    # b·d = 1 − 10^log_gap, down to 1e-12: the answers grow like 1/(1 − b·d), and float64
    # resolves them only to rounding of their size: the rounded answer pair, times slopes up to
    # 2 and 1/d up to 4 in the forward model, reaches ~70 ulps of the size (seen: 1.5e-14).
    d = (1.0 - 10.0**log_gap) / b
    mm = MutualMasking(a, b, c, d)
    assume(mm.bd_side < 0)
    p = mm.solve_point(m_p, e_p)
    # Unique only when the answer gives the target back (issue 21); else ill-conditioned.
    if p.status != Status.UNIQUE:
        assert p.reason == Reason.ILL_CONDITIONED
        return
    size = abs(p.mv_input_db_sl) + abs(p.ev_input_db_sl) + abs(m_p) + abs(e_p) + abs(a) + abs(c)
    error = forward_error(mm, p.mv_input_db_sl, p.ev_input_db_sl, m_p, e_p)
    assert error <= min(REPRODUCE_TOL_DB, 1e-9 + 256 * EPS * size)


@settings(max_examples=150, deadline=None)
@given(
    st.floats(-20.0, 20.0),
    st.floats(0.5, 4.0),
    st.floats(-20.0, 20.0),
    st.floats(0.5, 4.0),
    st.floats(-50.0, 50.0),
    st.floats(-50.0, 50.0),
)
def test_bd_at_least_one_reports_every_answer_and_only_answers(a, b, c, d, m_p, e_p):
    assume(b * d >= 1.05)
    mm = MutualMasking(a, b, c, d)
    p = mm.solve_point(m_p, e_p)
    assert p.status in (Status.NONE, Status.UNIQUE, Status.MULTIPLE)
    assert len(p.solutions) == {Status.NONE: 0, Status.UNIQUE: 1}.get(p.status, len(p.solutions))
    if p.status == Status.MULTIPLE:
        assert len(p.solutions) >= 2
    # Only answers: each one satisfies the forward model.
    for m_i, e_i, case in p.solutions:
        assert case in (1, 2, 3, 4)
        assert forward_error(mm, m_i, e_i, m_p, e_p) <= 1e-9 * (1 + abs(m_i) + abs(e_i))
    # None missed: every root the brute-force search finds is one of them.
    for m_b, e_b in brute_force_roots(mm, m_p, e_p):
        assert any(
            abs(m_b - m_i) <= 1e-6 * (1 + abs(m_i)) and abs(e_b - e_i) <= 1e-6 * (1 + abs(e_i))
            for m_i, e_i, _ in p.solutions
        ), (m_b, e_b, p.solutions)
    # The vector path says the same.
    sol = solve(mm, m_p, e_p)
    assert sol.status[()] == p.status
    assert sol.solutions(()) == p.solutions


@settings(max_examples=100, deadline=None)
@given(intercepts, slopes, intercepts, slopes, targets, targets)
def test_brute_force_finds_exactly_one_root_when_bd_below_one(a, b, c, d, m_p, e_p):
    assume(b * d <= 0.95)
    mm = MutualMasking(a, b, c, d)
    p = mm.solve_point(m_p, e_p)
    roots = brute_force_roots(mm, m_p, e_p)
    assert len(roots) >= 1
    for m_b, e_b in roots:
        assert abs(m_b - p.mv_input_db_sl) <= 1e-6 * (1 + abs(m_b))
        assert abs(e_b - p.ev_input_db_sl) <= 1e-6 * (1 + abs(e_b))


@settings(max_examples=100, deadline=None)
@given(
    intercepts,
    slopes,
    intercepts,
    slopes,
    st.lists(st.tuples(targets, targets), min_size=1, max_size=20),
)
def test_vector_forward_inverts_vector_solve(a, b, c, d, pts):
    assume(b * d <= 0.99)
    mm = MutualMasking(a, b, c, d)
    m_p = np.array([p[0] for p in pts])
    e_p = np.array([p[1] for p in pts])
    sol = solve(mm, m_p, e_p)
    back_m, back_e = forward(mm, sol.mv_input_db_sl, sol.ev_input_db_sl)
    assert np.all(np.abs(back_m - m_p) <= 1e-9)
    assert np.all(np.abs(back_e - e_p) <= 1e-9)
