"""Brent's root finder (masking_lab.core.roots) against scipy.optimize.brentq, bit for bit."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import brentq as scipy_brentq

from masking_lab.core.roots import RTOL_MIN, brentq
from masking_lab.procedures.downup_ratio import downup_ratio_for
from masking_lab.procedures.staircase import _step_rates, implied_target_p_for

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)


def families():
    """Smooth functions with one sign change somewhere: (name, f of x and parameters)."""
    return st.sampled_from(
        [
            ("cubic", lambda x, r, s: s * (x - r) ** 3 + (x - r)),
            ("exp", lambda x, r, s: math.exp(max(-50.0, min(50.0, s * 1e-2 * (x - r)))) - 1.0),
            ("tanh", lambda x, r, s: math.tanh(s * (x - r))),
            ("atan+wiggle", lambda x, r, s: math.atan(x - r) + 0.1 * math.sin(s * (x - r))),
            ("steep", lambda x, r, s: math.copysign(abs(x - r) ** 0.2, x - r) * (1 + s * s)),
            ("tiny", lambda x, r, s: 1e-200 * (x - r)),
        ]
    )


def both(f, a, b, **kw):
    """Each implementation's root, or its exception type and None."""
    out = []
    for solve in (brentq, scipy_brentq):
        try:
            out.append(solve(f, a, b, **kw))
        except (ValueError, RuntimeError) as exc:
            out.append(type(exc))
    return out


@settings(max_examples=1500, deadline=None)
@given(
    families(),
    finite,
    st.floats(0.1, 20.0),
    st.floats(1e-3, 500.0),
    st.floats(1e-3, 500.0),
    st.floats(1e-15, 1e-2),
    st.floats(RTOL_MIN, 1e-3),
    st.integers(1, 120),
)
def test_the_same_root_bit_for_bit_as_scipy(fam, r, s, left, right, xtol, rtol, maxiter):
    _, g = fam

    def f(x):
        return g(x, r, s)

    a, b = r - left, r + right
    ours, theirs = both(f, a, b, xtol=xtol, rtol=rtol, maxiter=maxiter)
    if isinstance(ours, float):
        assert isinstance(theirs, float)
        assert ours == theirs or (math.isnan(ours) and math.isnan(theirs))
        assert math.copysign(1, ours) == math.copysign(1, theirs)
    else:
        assert ours is theirs  # the same failure: too few iterations


@pytest.mark.parametrize(
    ("n_up", "n_down", "ratio"),
    [(1, 1, 1.0), (1, 2, 1.0), (1, 3, 1.0), (1, 4, 1.0), (2, 1, 1.0), (1, 3, 0.7393), (1, 2, 0.5)],
)
def test_a_staircase_rules_target_p_is_scipys(n_up, n_down, ratio):
    def drift(p):
        p_up, p_down = _step_rates(n_up, n_down, p)
        return p_up * 1.0 - p_down * ratio

    expected = float(scipy_brentq(drift, 1e-9, 1 - 1e-9, xtol=1e-13))
    assert implied_target_p_for(n_up, n_down, ratio) == expected
    if ratio == 1.0 and n_up == 1:
        assert expected == pytest.approx(0.5 ** (1 / n_down), abs=1e-12)  # Levitt's target


@pytest.mark.parametrize(("target", "n_up", "n_down"), [(0.6, 2, 1), (0.75, 2, 3), (0.9, 2, 4)])
def test_a_down_up_ratio_is_the_one_scipy_finds(target, n_up, n_down):
    # The oracle solves both levels with SciPy: the rule's target p, then the ratio.
    def scipy_target_p(ratio):
        def drift(p):
            p_up, p_down = _step_rates(n_up, n_down, p)
            return p_up * 1.0 - p_down * ratio

        return float(scipy_brentq(drift, 1e-9, 1 - 1e-9, xtol=1e-13))

    log_r = scipy_brentq(
        lambda v: scipy_target_p(float(np.exp(v))) - target, -12.0, 12.0, xtol=1e-13
    )
    ratio = downup_ratio_for(target, n_down=n_down, n_up=n_up)
    assert ratio == float(np.exp(log_r))
    assert implied_target_p_for(n_up, n_down, ratio) == pytest.approx(target, abs=1e-9)


def test_an_end_that_is_a_root_is_returned():
    assert brentq(lambda x: x - 1.0, 1.0, 3.0) == 1.0
    assert brentq(lambda x: x - 3.0, 1.0, 3.0) == 3.0


def test_a_bracket_without_a_sign_change_is_refused():
    with pytest.raises(ValueError, match="different signs"):
        brentq(lambda x: x * x + 1.0, -1.0, 1.0)


def test_nan_is_refused_with_where_it_happened():
    with pytest.raises(ValueError, match=r"NaN at x = 1\.0"):
        brentq(lambda x: math.nan if x > 0.6 else x - 0.25, 0.0, 1.0)
    with pytest.raises(ValueError, match="NaN at x = "):  # met on the way, not at an end
        brentq(lambda x: math.nan if 0.3 < x < 0.7 else x - 0.5, 0.0, 1.0)


def test_too_few_iterations_is_an_error():
    with pytest.raises(RuntimeError, match="no root found in 2 iterations"):
        brentq(math.tanh, -1.0, 3.0, xtol=1e-15, maxiter=2)
    assert both(math.tanh, -1.0, 3.0, xtol=1e-15, maxiter=2) == [RuntimeError, RuntimeError]


@pytest.mark.parametrize(("xtol", "rtol"), [(0.0, RTOL_MIN), (-1.0, RTOL_MIN), (1e-12, 1e-17)])
def test_tolerances_out_of_range_are_refused(xtol, rtol):
    with pytest.raises(ValueError, match="tol must be"):
        brentq(math.tanh, -1.0, 1.0, xtol=xtol, rtol=rtol)
