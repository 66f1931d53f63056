"""Solver hardening (issue 11, item 4): inside the documented range every unique answer checks
against the forward model; outside it the parameters are refused or the point has no answer;
nothing is a traceback. Extreme magnitudes (1e-300 … 1e6) are drawn on purpose."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from masking_lab.core.errors import SolverError
from masking_lab.rendering.ramp_inverse import (
    MAX_INTERCEPT_DB,
    MAX_SLOPE,
    MAX_TARGET_DB_SL,
    Reason,
    Status,
)
from masking_lab.rendering.solver import MutualMasking, solve

slopes = st.one_of(
    st.just(0.0),
    st.floats(1e-300, MAX_SLOPE),
    st.sampled_from([1e-300, 1e-12, 1.0, MAX_SLOPE]),
    st.floats(0.0, 3.0),
)
intercepts = st.one_of(st.floats(-MAX_INTERCEPT_DB, MAX_INTERCEPT_DB), st.floats(-30.0, 30.0))
targets = st.one_of(
    st.floats(-MAX_TARGET_DB_SL, MAX_TARGET_DB_SL),
    st.floats(-100.0, 100.0),
    st.just(-math.inf),
)


def residual_ok(mm: MutualMasking, mi: float, ei: float, mp: float, ep: float) -> bool:
    fm, fe = mm.forward_point(mi, ei)
    # Rounding of the terms of each equation is all the error there may be.
    scale_m = abs(mi) + abs(mm.a_db) + (abs(mm.b * ei) if math.isfinite(ei) else 0.0) + abs(mp)
    scale_e = abs(ei) + abs(mm.c_db) + (abs(mm.d * mi) if math.isfinite(mi) else 0.0) + abs(ep)
    return all(
        want == got or abs(want - got) <= 1e-12 * scale
        for want, got, scale in ((mp, fm, scale_m), (ep, fe, scale_e))
    )


@settings(derandomize=True, max_examples=1500, deadline=None)
@given(intercepts, slopes, intercepts, slopes, targets, targets)
def test_every_unique_answer_in_range_checks_against_the_forward_model(a, b, c, d, mp, ep):
    mm = MutualMasking(a, b, c, d)
    point = mm.solve_point(mp, ep)
    vector = solve(mm, [mp], [ep])
    assert vector.status[0] == point.status
    if point.status == Status.UNIQUE:
        assert residual_ok(mm, point.mv_input_db_sl, point.ev_input_db_sl, mp, ep)
        assert residual_ok(mm, vector.mv_input_db_sl[0], vector.ev_input_db_sl[0], mp, ep)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ((0.0, 1e300, 0.0, 0.5), "slopes up to 100"),
        ((0.0, 1e300, 0.0, 1e300), "slopes up to 100"),  # was: OverflowError
        ((0.0, 0.0, 0.0, 1e300), "slopes up to 100"),  # was: a wrong "unique" answer
        ((1e300, 0.5, 0.0, 0.5), "intercepts within ±1000 dB"),
        ((0.0, 0.5, -2e3, 0.5), "intercepts within ±1000 dB"),
    ],
)
def test_parameters_outside_the_range_are_refused(args, message):
    with pytest.raises(SolverError, match=message):
        MutualMasking(*args)


def test_a_slope_of_1e300_no_longer_gives_a_wrong_unique_answer():
    # Was: MutualMasking(4.74, 0, 0, 1e300).solve_point(0, 6.02) → "unique" (4.74, 4.74e300),
    # perceived as (0, 0): the 6.02 dB target was absorbed by 4.74e300.
    with pytest.raises(SolverError):
        MutualMasking(4.742091741068343, 0.0, 0.0, 1e300)


@pytest.mark.parametrize("target", [1e7, -1e300, 1e300, 2 * MAX_TARGET_DB_SL])
def test_targets_beyond_the_range_have_no_answer(target):
    mm = MutualMasking(-7.4, 0.7, -0.4, 0.94)
    point = mm.solve_point(target, 5.0)
    assert point.status == Status.NONE and point.reason == Reason.OVERFLOW
    sol = solve(mm, np.array([target, 5.0]), np.array([5.0, 5.0]))
    assert list(sol.status) == [Status.NONE, Status.UNIQUE]
    assert sol.reason[0] == Reason.OVERFLOW and np.isnan(sol.mv_input_db_sl[0])


def test_tiny_slopes_are_fine():
    mm = MutualMasking(2.0, 1e-300, -1.0, 1e-300)
    point = mm.solve_point(5.0, 5.0)
    assert point.status == Status.UNIQUE
    assert (point.mv_input_db_sl, point.ev_input_db_sl) == (7.0, 5.0)
