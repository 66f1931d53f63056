"""The inverse-rendering solver: Table 4 cases, uniqueness, folds, extremes, parameter files."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest

from masking_lab.core.errors import SolverError
from masking_lab.core.masking import MaskingFunction
from masking_lab.rendering.ramp_inverse import REPRODUCE_TOL_DB
from masking_lab.rendering.solver import (
    MissingMaskingError,
    MutualMasking,
    Reason,
    Status,
    forward,
    pair_from_params,
    solve,
)

# Paper §3.4: MV masked by EV a ≈ 1.39, b ≈ 1.09; EV masked by MV c ≈ −6.22, d ≈ 0.66.
PAPER = MutualMasking(1.39, 1.09, -6.22, 0.66, mv="MV180", ev="EV270")
INF = math.inf


def table4(mm: MutualMasking, case: int, m_p: float, e_p: float) -> tuple[float, float]:
    """The paper's Table 4 'Solution' column, written out independently of the solver."""
    a, b, c, d = mm.a_db, mm.b, mm.c_db, mm.d
    if case == 1:
        return m_p, e_p
    if case == 2:
        return m_p, d * m_p + e_p + c
    if case == 3:
        return m_p + b * e_p + a, e_p
    return (m_p + b * e_p + a + b * c) / (1 - b * d), (d * m_p + e_p + c + a * d) / (1 - b * d)


def residual(mm: MutualMasking, m_i: float, e_i: float, m_p: float, e_p: float) -> float:
    """Largest |perceived − target| in dB, from the paper's Eq. (1)–(4) directly."""
    f = max(0.0, mm.a_db + mm.b * e_i)
    g = max(0.0, mm.c_db + mm.d * m_i)
    return max(abs(m_i - f - m_p), abs(e_i - g - e_p))


@pytest.mark.parametrize(
    "m_p, e_p, case",
    [
        (-20.0, -10.0, 1),  # both below their knees: no masking at all
        (15.0, -10.0, 2),  # loud MV, faint EV: only EV is masked
        (0.0, 0.0, 3),  # EV at 0 dB SL already masks MV (a > 0); MV too faint to mask EV
        (12.0, 5.0, 4),  # the paper's operating point: both masked
    ],
)
def test_each_table4_case_matches_the_paper_formula(m_p, e_p, case):
    got = PAPER.solve_point(m_p, e_p)
    assert got.status == Status.UNIQUE and got.case == case
    want = table4(PAPER, case, m_p, e_p)
    assert got.mv_input_db_sl == pytest.approx(want[0], abs=1e-12)
    assert got.ev_input_db_sl == pytest.approx(want[1], abs=1e-12)
    assert residual(PAPER, got.mv_input_db_sl, got.ev_input_db_sl, m_p, e_p) < 1e-12


def test_vector_and_scalar_paths_agree_and_invert_the_forward_model():
    rng = np.random.default_rng(7)
    m_p = rng.uniform(-40, 40, 4000)
    e_p = rng.uniform(-40, 40, 4000)
    sol = solve(PAPER, m_p, e_p)
    assert np.all(sol.status == Status.UNIQUE)
    assert set(np.unique(sol.case)) == {1, 2, 3, 4}
    back_m, back_e = forward(PAPER, sol.mv_input_db_sl, sol.ev_input_db_sl)
    assert np.max(np.abs(back_m - m_p)) < 1e-9 and np.max(np.abs(back_e - e_p)) < 1e-9
    for i in range(0, 4000, 37):
        p = PAPER.solve_point(m_p[i], e_p[i])
        assert (p.mv_input_db_sl, p.ev_input_db_sl, p.case) == (
            sol.mv_input_db_sl[i],
            sol.ev_input_db_sl[i],
            sol.case[i],
        )
        assert PAPER.forward_point(p.mv_input_db_sl, p.ev_input_db_sl) == pytest.approx(
            (back_m[i], back_e[i]), abs=0
        )


def test_shape_is_kept_and_scalars_broadcast():
    sol = solve(PAPER, 12.0, np.linspace(0, 10, 6).reshape(2, 3))
    assert sol.shape == (2, 3)
    assert sol.mv_input_db_sl.shape == (2, 3)
    assert sol.solutions((1, 2))[0][:2] == (sol.mv_input_db_sl[1, 2], sol.ev_input_db_sl[1, 2])
    assert sol.counts() == {"none": 0, "unique": 6, "multiple": 0}


def test_bd_above_one_reports_two_answers_or_none_never_a_silent_pair():
    mm = MutualMasking(1.0, 2.0, -1.0, 1.0)  # b·d = 2
    # Third quadrant: both answers worked out by hand from Eq. (3)-(4).
    p = mm.solve_point(-20.0, -5.0)
    assert p.status == Status.MULTIPLE and math.isnan(p.mv_input_db_sl)
    assert [s[:2] for s in p.solutions] == [(-20.0, -5.0), (31.0, 25.0)]
    for m_i, e_i, _ in p.solutions:
        assert residual(mm, m_i, e_i, -20.0, -5.0) < 1e-12
    # U = 1 > 0 and V = 2 > 0 here: the uncovered wedge.
    none = mm.solve_point(3.0, 0.0)
    assert none.status == Status.NONE and none.reason == Reason.UNREACHABLE
    sol = solve(mm, [-20.0, 3.0], [-5.0, 0.0])
    assert list(sol.status) == [Status.MULTIPLE, Status.NONE]
    assert np.isnan(sol.mv_input_db_sl).all() and list(sol.case) == [0, 0]
    assert sol.solutions(0) == p.solutions and sol.solutions(1) == ()
    assert sol.status_names() == ["multiple", "none"]


def test_on_the_fold_with_bd_above_one_the_two_answers_merge():
    mm = MutualMasking(1.0, 2.0, -1.0, 1.0)
    # m_p = 1.5 → V = −1 + 1.5 = 0.5 > 0; e_p = −1 → U = 1 − 2 = −1; U + b·V = 0: on the fold,
    # where case 2 and case 4 give the same input pair.
    m_p, e_p = 1.5, -1.0
    p = mm.solve_point(m_p, e_p)
    assert p.status == Status.UNIQUE
    assert residual(mm, p.mv_input_db_sl, p.ev_input_db_sl, m_p, e_p) < 1e-12
    assert solve(mm, m_p, e_p).status[()] == Status.UNIQUE


def test_bd_exactly_one_gives_a_continuum_on_its_line_and_is_flagged():
    mm = MutualMasking(1.0, 2.0, -1.0, 0.5)  # b·d = 1 exactly
    # U + b·V = (1 + 2·5) + 2·(−1 + 0.5·m_p) = 9 + m_p = 0 on the line m_p = −9.
    p = mm.solve_point(-9.0, 5.0)
    assert p.status == Status.MULTIPLE and p.continuum
    start = next(s for s in p.solutions if s[2] == 4)
    for t in (0.0, 0.5, 10.0, 1e3):
        m_i, e_i = start[0] + t, start[1] + mm.d * t
        assert residual(mm, m_i, e_i, -9.0, 5.0) < 1e-9
    sol = solve(mm, [-9.0, -8.0, -20.0], [5.0, 5.0, -5.0])
    assert list(sol.continuum) == [True, False, False]
    assert sol.status[0] == Status.MULTIPLE
    assert sol.solutions(0) == p.solutions
    # Off the line case 4 has no answer; the edge cases answer or nothing does.
    assert sol.status[1] == Status.NONE and sol.reason[1] == Reason.UNREACHABLE
    assert sol.status[2] == Status.UNIQUE and sol.case[2] == 1


@pytest.mark.parametrize("eps", [1e-6, 1e-8])
def test_bd_just_below_one_matches_exact_rational_arithmetic(eps):
    b, d = 1.0, 1.0 - eps
    mm = MutualMasking(1.0, b, -2.0, d)
    assert mm.bd_side < 0
    m_p, e_p = 12.0, 5.0
    p = mm.solve_point(m_p, e_p)
    assert p.status == Status.UNIQUE and p.case == 4
    # Exact reference: Table 4 case 4 in rationals, rounded once.
    A, B, C, D = (Fraction(x) for x in (mm.a_db, b, mm.c_db, d))
    den = 1 - B * D
    m_ref = (Fraction(m_p) + B * Fraction(e_p) + A + B * C) / den
    e_ref = (D * Fraction(m_p) + Fraction(e_p) + C + A * D) / den
    assert p.mv_input_db_sl == pytest.approx(float(m_ref), rel=1e-12)
    assert p.ev_input_db_sl == pytest.approx(float(e_ref), rel=1e-12)
    assert residual(mm, p.mv_input_db_sl, p.ev_input_db_sl, m_p, e_p) <= REPRODUCE_TOL_DB
    sol = solve(mm, m_p, e_p)
    assert sol.mv_input_db_sl[()] == p.mv_input_db_sl


def test_bd_one_ulp_below_one_is_ill_conditioned_not_unique():
    # Was (issue 21): b·d one ulp below 1 gave "unique" answers of ~1e17 dB SL that the model
    # turned into targets 52 dB off, exit 0. The closed form is right in exact arithmetic, but
    # float64 cannot carry it back through the model, so no number is offered.
    mm = MutualMasking(1.39, 1.0, -6.22, 1.0 - 2.0**-53)
    assert mm.bd_side < 0 and mm.one_minus_bd == 2.0**-53
    for e_p in (0.0, 5.0, 10.0):
        p = mm.solve_point(12.0, e_p)
        assert p.status == Status.NONE and p.reason == Reason.ILL_CONDITIONED
        assert math.isnan(p.mv_input_db_sl) and p.solutions == ()
    sol = solve(mm, [12.0, 12.0, -20.0], [5.0, 10.0, -20.0])
    assert list(sol.status) == [Status.NONE, Status.NONE, Status.UNIQUE]  # ramps off: exact
    assert list(sol.reason[:2]) == [Reason.ILL_CONDITIONED] * 2
    assert np.isnan(sol.mv_input_db_sl[:2]).all()


@pytest.mark.parametrize("eps", [1e-10, 1e-12, 1e-13, 3e-15, 2.0**-52])
@pytest.mark.parametrize("side", [-1.0, 1.0])
def test_near_bd_one_every_answer_given_reproduces_its_target(eps, side):
    mm = MutualMasking(1.0, 1.0 + side * eps, -2.0, 1.0)
    targets = [(12.0, 5.0), (-20.0, -20.0), (3.0, 30.0), (40.0, 0.0), (0.0, 0.0)]
    vec = solve(mm, [t[0] for t in targets], [t[1] for t in targets])
    ill = 0
    for i, (m_p, e_p) in enumerate(targets):
        p = mm.solve_point(m_p, e_p)
        assert vec.status[i] == p.status and vec.reason[i] == p.reason
        for m_i, e_i, _ in p.solutions:
            assert residual(mm, m_i, e_i, m_p, e_p) <= REPRODUCE_TOL_DB
        ill += p.reason == Reason.ILL_CONDITIONED
    if eps < 1e-14:
        assert ill  # answers of ~1/eps dB SL: some cannot be carried in float64


def test_slopes_near_zero_and_flat_ramps():
    tiny = MutualMasking(2.0, 1e-300, -1.0, 0.0)
    p = tiny.solve_point(5.0, 5.0)
    assert p.status == Status.UNIQUE and p.mv_input_db_sl == 7.0 and p.ev_input_db_sl == 5.0
    flat = MutualMasking(3.0, 0.0, 4.0, 0.0)  # constant masking whatever the masker does
    sol = solve(flat, [0.0, -INF, 10.0], [0.0, 2.0, -INF])
    assert list(sol.mv_input_db_sl) == [3.0, -INF, 13.0]
    assert list(sol.ev_input_db_sl) == [4.0, 6.0, -INF]
    assert flat.forward_point(-INF, -INF) == (-INF, -INF)


def test_knees_at_the_edge_are_continuous():
    # Targets exactly on each region boundary, and just beside it.
    mm = PAPER
    a, b, c, d = mm.a_db, mm.b, mm.c_db, mm.d
    e_knee = -a / b  # U = 0
    m_knee = -c / d  # V = 0
    points = [
        (m_knee, -10.0),  # V = 0, U < 0: cases 1|2
        (-10.0, e_knee),  # U = 0, V < 0: cases 1|3
        (m_knee, e_knee),  # both knees: all four meet
        (20.0, -(a + b * (c + d * 20.0))),  # U + b·V = 0 with V > 0: cases 2|4
    ]
    for m_p, e_p in points:
        at = mm.solve_point(m_p, e_p)
        assert residual(mm, at.mv_input_db_sl, at.ev_input_db_sl, m_p, e_p) < 1e-12
        for dm, de in ((1e-9, 0), (-1e-9, 0), (0, 1e-9), (0, -1e-9)):
            near = mm.solve_point(m_p + dm, e_p + de)
            assert abs(near.mv_input_db_sl - at.mv_input_db_sl) < 1e-8
            assert abs(near.ev_input_db_sl - at.ev_input_db_sl) < 1e-8


def test_huge_targets_keep_relative_accuracy():
    t = np.array([-1e6, 1e6])
    m_p, e_p = np.meshgrid(t, t)
    sol = solve(PAPER, m_p, e_p)
    assert np.all(sol.status == Status.UNIQUE)
    back_m, back_e = forward(PAPER, sol.mv_input_db_sl, sol.ev_input_db_sl)
    scale = np.abs(sol.mv_input_db_sl) + np.abs(sol.ev_input_db_sl)
    assert np.all(np.abs(back_m - m_p) <= 1e-14 * scale)
    assert np.all(np.abs(back_e - e_p) <= 1e-14 * scale)


def test_nan_and_inf_targets():
    sol = solve(PAPER, [math.nan, 1.0, INF, -INF, -INF, 5.0], [1.0, math.nan, 0.0, 5.0, -INF, INF])
    assert list(sol.status) == [Status.NONE, Status.NONE, Status.NONE, 1, 1, Status.NONE]
    assert list(sol.reason) == [
        Reason.NAN_TARGET,
        Reason.NAN_TARGET,
        Reason.INFINITE_TARGET,
        Reason.OK,
        Reason.OK,
        Reason.INFINITE_TARGET,
    ]
    # MV off: its input is off and it masks nothing; EV plays at its target.
    assert (sol.mv_input_db_sl[3], sol.ev_input_db_sl[3]) == (-INF, 5.0)
    assert (sol.mv_input_db_sl[4], sol.ev_input_db_sl[4]) == (-INF, -INF)
    assert np.isnan(sol.mv_input_db_sl[[0, 1, 2, 5]]).all()
    for m_p, e_p, reason in (
        (math.nan, 0.0, Reason.NAN_TARGET),
        (INF, 0.0, Reason.INFINITE_TARGET),
    ):
        p = PAPER.solve_point(m_p, e_p)
        assert p.status == Status.NONE and p.reason == reason and p.solutions == ()
    p = PAPER.solve_point(12.0, -INF)
    assert (p.mv_input_db_sl, p.ev_input_db_sl) == (12.0, -INF)
    folded = MutualMasking(1.0, 2.0, -1.0, 1.0)
    s = solve(folded, [math.nan, INF, -INF], [0.0, 0.0, -INF])
    assert list(s.reason[:2]) == [Reason.NAN_TARGET, Reason.INFINITE_TARGET]
    assert s.solutions(0) == () and s.solutions(1) == ()
    assert s.status[2] == Status.UNIQUE and (s.mv_input_db_sl[2], s.ev_input_db_sl[2]) == (
        -INF,
        -INF,
    )


def test_overflowing_answers_are_reported_not_returned():
    mm = MutualMasking(1.0, 1.0, 1.0, 1.0 - 2.0**-52)
    p = mm.solve_point(1e300, 1e300)
    assert p.status == Status.NONE and p.reason == Reason.OVERFLOW
    sol = solve(mm, 1e300, 1e300)
    assert sol.status[()] == Status.NONE and sol.reason[()] == Reason.OVERFLOW


def test_inputs_beyond_the_rating_are_flagged_not_clipped():
    targets = (np.full(3, 12.0), np.array([0.0, 5.0, 10.0]))
    free = solve(PAPER, *targets)
    rated = solve(PAPER, *targets, max_mv_db_sl=30.0, max_ev_db_sl=30.0)
    np.testing.assert_array_equal(free.mv_input_db_sl, rated.mv_input_db_sl)
    np.testing.assert_array_equal(free.ev_input_db_sl, rated.ev_input_db_sl)
    assert list(rated.mv_exceeds_rating) == list(free.mv_input_db_sl > 30.0) == [False, True, True]
    assert list(rated.ev_exceeds_rating) == list(free.ev_input_db_sl > 30.0)
    assert not free.mv_exceeds_rating.any()
    with pytest.raises(SolverError, match="max_mv_db_sl is NaN"):
        solve(PAPER, 1.0, 1.0, max_mv_db_sl=math.nan)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"b": -0.1}, "slopes must be ≥ 0"),
        ({"d": -1.0}, "slopes must be ≥ 0"),
        ({"a_db": math.nan}, "must be finite"),
        ({"c_db": INF}, "must be finite"),
        ({"b": True}, "must be a number"),
        ({"d": "0.5"}, "must be a number"),
    ],
)
def test_bad_parameters_are_refused(kwargs, match):
    base = {"a_db": 1.0, "b": 1.0, "c_db": -1.0, "d": 0.5}
    with pytest.raises(SolverError, match=match):
        MutualMasking(**{**base, **kwargs})


def test_from_functions_pairs_the_right_directions():
    mv = MaskingFunction("MV180", "EV270", 1.304, 1.062)
    ev = MaskingFunction("EV270", "MV180", -5.927, 0.658)
    mm = MutualMasking.from_functions(mv, ev)
    assert (mm.mv, mm.ev) == ("MV180", "EV270")
    assert (mm.a_db, mm.b, mm.c_db, mm.d) == (1.304, 1.062, -5.927, 0.658)
    with pytest.raises(SolverError, match="do not form a pair"):
        MutualMasking.from_functions(mv, MaskingFunction("EV270", "MV120", -7.4, 0.7))


def _params(*entries):
    return {"schema_version": 1, "functions": list(entries)}


def _fn(target, masker, a, b, status="fitted"):
    return {"target": target, "masker": masker, "intercept_db": a, "slope": b, "status": status}


def test_pair_from_params_takes_only_the_named_pair():
    params = _params(
        _fn("EV270", "MV120", -7.44, 0.711),
        _fn("MV120", "EV270", -0.387, 0.939),
        _fn("EV270", "MV180", -5.93, 0.658),
        _fn("MV180", "EV270", 1.30, 1.06),
    )
    mm = pair_from_params(params, mv="MV180", ev="EV270")
    assert (mm.a_db, mm.b, mm.c_db, mm.d) == (1.30, 1.06, -5.93, 0.658)


def test_pair_from_params_reports_missing_and_unfitted_directions():
    params = _params(_fn("MV180", "EV270", None, None, status="insufficient_data"))
    with pytest.raises(MissingMaskingError) as info:
        pair_from_params(params, mv="MV180", ev="EV270", source="p.json")
    msg = str(info.value)
    assert (
        "p.json" in msg
        and "'insufficient_data'" in msg
        and "EV270 masked by MV180: no entry" in msg
    )
    assert [(p.target, p.masker, p.status) for p in info.value.problems] == [
        ("MV180", "EV270", "insufficient_data"),
        ("EV270", "MV180", "missing"),
    ]


def test_pair_from_params_refuses_malformed_files():
    with pytest.raises(SolverError, match="no 'functions' list"):
        pair_from_params({"fits": []}, mv="MV180")
    bad = _params(_fn("MV180", "EV270", "x", 1.0), _fn("EV270", "MV180", -6.0, 0.6))
    with pytest.raises(SolverError, match="no numeric intercept_db/slope"):
        pair_from_params(bad, mv="MV180")
    negative = _params(_fn("MV180", "EV270", 1.0, -0.2), _fn("EV270", "MV180", -6.0, 0.6))
    with pytest.raises(SolverError, match="slopes must be ≥ 0"):
        pair_from_params(negative, mv="MV180", source="neg.json")


def test_solve_leaves_the_callers_arrays_alone():
    for mm in (PAPER, MutualMasking(1.0, 2.0, -1.0, 1.0)):
        m_p = np.array([12.0, -INF, math.nan, 3.0])
        e_p = np.array([5.0, 1.0, 0.0, 0.0])
        before = (m_p.copy(), e_p.copy())
        solve(mm, m_p, e_p, max_mv_db_sl=10.0)
        np.testing.assert_array_equal(m_p, before[0])
        np.testing.assert_array_equal(e_p, before[1])
