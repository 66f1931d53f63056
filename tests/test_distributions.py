"""masking_lab.analysis.distributions gives scipy.stats' numbers to the bit, edges included."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from masking_lab.analysis.distributions import chi2_sf, f_sf, t_ppf, t_sf

XS = [-math.inf, -50.0, -3.0, -1e-300, -0.0, 0.0, 1e-300, 1e-12, 0.3, 1.0, 2.0, 3.84, 7.7, 40.0,
      1e6, math.inf, math.nan]  # fmt: skip
DFS = [-1.0, 0.0, 1e-3, 0.37, 1.0, 2.0, 2.5, 7.0, 29.0, 1e3, 1e7, math.inf, math.nan]


def _same(a: float, b: float) -> bool:
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return a == b and math.copysign(1, a) == math.copysign(1, b)


def _grid(rng: np.random.Generator) -> list[float]:
    return XS + list(rng.normal(0, 5, 40)) + list(np.abs(rng.standard_cauchy(20)))


def test_t_sf_is_scipy_bit_for_bit() -> None:
    xs = _grid(np.random.default_rng(1))
    for df in DFS:
        for x in xs:
            assert _same(t_sf(x, df), float(stats.t.sf(x, df))), (x, df)


def test_t_ppf_is_scipy_bit_for_bit() -> None:
    qs = [-0.1, 0.0, 1e-300, 1e-9, 0.025, 0.5, 0.8, 0.975, 0.995, 1 - 1e-16, 1.0, 1.5, math.nan]
    qs += list(np.random.default_rng(2).uniform(0, 1, 40))
    for df in DFS:
        for q in qs:
            assert _same(t_ppf(q, df), float(stats.t.ppf(q, df))), (q, df)


def test_f_sf_is_scipy_bit_for_bit() -> None:
    xs = _grid(np.random.default_rng(3))
    for dfn in DFS:
        for dfd in DFS[::2]:
            for x in xs:
                assert _same(f_sf(x, dfn, dfd), float(stats.f.sf(x, dfn, dfd))), (x, dfn, dfd)


def test_chi2_sf_is_scipy_bit_for_bit() -> None:
    xs = _grid(np.random.default_rng(4))
    for df in DFS:
        for x in xs:
            assert _same(chi2_sf(x, df), float(stats.chi2.sf(x, df))), (x, df)


@pytest.mark.parametrize("fn", [t_sf, chi2_sf])
def test_tails_fall_with_x(fn) -> None:
    assert fn(1.0, 3.0) > fn(2.0, 3.0) > fn(4.0, 3.0) > 0.0
