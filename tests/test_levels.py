"""Level conversions and their guards."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from masking_lab.core import levels as L
from masking_lab.core.errors import LevelError


def test_volts_and_db_re_1v():
    assert L.volts_to_db_v(1.0) == 0.0
    assert L.volts_to_db_v(10.0) == pytest.approx(20.0)
    assert L.db_v_to_volts(-6.0206) == pytest.approx(0.5, rel=1e-4)


def test_zero_volts_is_minus_inf_only_when_asked():
    with pytest.raises(LevelError, match="allow_zero"):
        L.volts_to_db_v(0.0)
    assert L.volts_to_db_v(0.0, allow_zero=True) == -math.inf
    assert L.db_v_to_volts(-math.inf) == 0.0


@pytest.mark.parametrize("bad", [math.nan, math.inf, -1.0])
def test_bad_volts_are_refused(bad):
    with pytest.raises(LevelError):
        L.volts_to_db_v(bad, allow_zero=True)


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_bad_db_are_refused(bad):
    with pytest.raises(LevelError):
        L.db_v_to_volts(bad)


def test_sensation_level_round_trip_and_guards():
    assert L.db_sl_to_db_v(10.0, -14.0) == -4.0
    assert L.db_v_to_db_sl(-4.0, -14.0) == 10.0
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(LevelError, match="finite"):
            L.db_sl_to_db_v(bad, -14.0)
        with pytest.raises(LevelError, match="finite"):
            L.db_v_to_db_sl(0.0, bad)


def test_rating_check_names_the_limit():
    assert L.check_within_rating(13.0, 5.0) == 13.0  # 5 V = 13.98 dB re 1 V
    with pytest.raises(LevelError, match=r"exceeds the device limit of 5 V"):
        L.check_within_rating(14.5, 5.0, what="masker EV270 at 25 dB SL")


def test_array_versions_never_produce_nan():
    out = L.volts_to_db_v_array([0.0, 1.0, 10.0])
    assert out[0] == -np.inf and out[1] == 0.0 and out[2] == pytest.approx(20.0)
    assert not np.isnan(out).any()
    with pytest.raises(LevelError, match="index"):
        L.volts_to_db_v_array([1.0, np.nan])
    with pytest.raises(LevelError, match="index"):
        L.db_v_to_volts_array([0.0, np.inf])
    assert L.db_v_to_volts_array([-np.inf, 0.0]).tolist() == [0.0, 1.0]


@given(st.floats(min_value=1e-12, max_value=1e6, allow_nan=False))
def test_round_trip(volts):
    assert L.db_v_to_volts(L.volts_to_db_v(volts)) == pytest.approx(volts, rel=1e-12)
