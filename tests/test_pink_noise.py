"""Pink masking noise: spectrum slope, level, seamless looping, and its refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import signal

from masking_lab.core.errors import LevelError
from masking_lab.responders.pink_noise import (
    PINK_SLOPE_DB_PER_OCTAVE,
    loop_buffer,
    normalize_rms,
    pink_noise,
    rms_db_fs,
)

FS = 44100.0


def psd_slope_db_per_octave(x, fs, f_lo, f_hi):
    """Least-squares slope of the Welch PSD (dB) against log2 frequency, dB/octave."""
    f, pxx = signal.welch(x, fs=fs, nperseg=8192)
    band = (f >= f_lo) & (f <= f_hi)
    slope, _ = np.polyfit(np.log2(f[band]), 10 * np.log10(pxx[band]), 1)
    return slope


def test_pink_slope_constant_is_minus_3_db_per_octave():
    # Halving the power per doubling of frequency: 10·log10(1/2).
    assert math.isclose(PINK_SLOPE_DB_PER_OCTAVE, -3.0103, abs_tol=1e-4)


def test_spectrum_falls_3_db_per_octave():
    x = pink_noise(int(20 * FS), np.random.default_rng(1), sample_rate_hz=FS)
    assert psd_slope_db_per_octave(x, FS, 50, 16000) == pytest.approx(-3.01, abs=0.25)


def test_equal_power_per_octave():
    x = pink_noise(int(20 * FS), np.random.default_rng(2), sample_rate_hz=FS)
    f, pxx = signal.welch(x, fs=FS, nperseg=16384)
    df = f[1] - f[0]
    octaves = [(100 * 2**k, 200 * 2**k) for k in range(6)]  # 100 Hz … 6.4 kHz
    powers = [pxx[(f >= lo) & (f < hi)].sum() * df for lo, hi in octaves]
    spread_db = 10 * np.log10(max(powers) / min(powers))
    assert spread_db < 1.0


def test_white_noise_would_fail_the_slope_check():
    # The slope estimator itself discriminates: white noise is flat (0 dB/octave).
    x = np.random.default_rng(3).standard_normal(int(20 * FS))
    assert abs(psd_slope_db_per_octave(x, FS, 50, 16000)) < 0.3


def test_nothing_below_f_min_and_zero_mean():
    x = pink_noise(2**16, np.random.default_rng(4), sample_rate_hz=FS, f_min_hz=40.0)
    spectrum = np.abs(np.fft.rfft(x))
    f = np.fft.rfftfreq(x.size, 1 / FS)
    assert np.all(spectrum[f < 40.0] < 1e-9 * spectrum.max())
    assert abs(x.mean()) < 1e-12


def test_same_generator_seed_same_noise_different_seed_different_noise():
    a = pink_noise(4096, np.random.default_rng(7))
    b = pink_noise(4096, np.random.default_rng(7))
    c = pink_noise(4096, np.random.default_rng(8))
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def wrap_to_interior_step_ratio(buffers):
    """Mean squared step across the loop point over mean squared step inside the buffers."""
    wrap = np.array([b[0] - b[-1] for b in buffers])
    interior = np.concatenate([np.diff(b) for b in buffers])
    return np.mean(wrap**2) / np.mean(interior**2)


def test_loop_point_is_seamless():
    # Over many buffers the jump from the last sample back to the first is distributed like any
    # other step of the noise: the mean squared wrap step matches the interior one.
    rng = np.random.default_rng(5)
    buffers = [pink_noise(2048, rng, sample_rate_hz=FS) for _ in range(400)]
    assert 0.75 < wrap_to_interior_step_ratio(buffers) < 1.3


def test_a_cut_out_segment_would_click_at_the_loop_point():
    # The same statistic on pink noise that is not periodic (a segment of a longer buffer) shows
    # the click a naive loop makes: pink noise varies slowly, so its ends differ by much more
    # than one step.
    rng = np.random.default_rng(6)
    buffers = [pink_noise(8192, rng, sample_rate_hz=FS)[1000:3048] for _ in range(400)]
    assert wrap_to_interior_step_ratio(buffers) > 2.5


def test_periodic_extension_keeps_the_spectrum():
    # Ten copies end to end are one long stretch of pink noise, slope intact.
    x = pink_noise(int(2 * FS), np.random.default_rng(9), sample_rate_hz=FS)
    tiled = np.tile(x, 10)
    assert psd_slope_db_per_octave(tiled, FS, 50, 16000) == pytest.approx(-3.01, abs=0.3)


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(64, 5000),
    seed=st.integers(0, 2**32 - 1),
    level=st.floats(-60.0, -15.0),
)
def test_level_is_exact_and_samples_are_bounded(n, seed, level):
    x = pink_noise(n, np.random.default_rng(seed), sample_rate_hz=FS)
    assert rms_db_fs(x) == pytest.approx(0.0, abs=1e-9)
    y = normalize_rms(x, level)
    assert rms_db_fs(y) == pytest.approx(level, abs=1e-9)
    assert np.all(np.isfinite(y))
    assert np.max(np.abs(y)) <= 1.0


def test_loop_buffer_is_float32_at_the_level_asked():
    buf = loop_buffer(1.5, np.random.default_rng(10), sample_rate_hz=48000.0, level_db_fs=-26.0)
    assert buf.dtype == np.float32
    assert buf.size == 72000
    assert rms_db_fs(buf) == pytest.approx(-26.0, abs=0.01)
    assert np.max(np.abs(buf)) <= 1.0


def test_rms_db_fs_of_known_signals():
    assert rms_db_fs(np.ones(10)) == 0.0
    assert rms_db_fs(np.full(10, 0.1)) == pytest.approx(-20.0)
    assert rms_db_fs(np.zeros(10)) == -math.inf


def test_level_that_would_clip_is_refused_with_the_highest_usable_level():
    x = pink_noise(44100, np.random.default_rng(11))
    with pytest.raises(LevelError, match=r"would clip.*at most -\d+\.\d dB FS"):
        normalize_rms(x, -3.0)


@pytest.mark.parametrize("level", [math.nan, math.inf, -math.inf])
def test_non_finite_level_is_refused(level):
    with pytest.raises(LevelError, match="finite"):
        normalize_rms(np.ones(4), level)


def test_silent_or_broken_buffers_are_refused():
    with pytest.raises(LevelError, match="silent"):
        normalize_rms(np.zeros(16), -20.0)
    with pytest.raises(LevelError, match="NaN"):
        normalize_rms(np.array([0.1, np.nan]), -20.0)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"n_samples": 1}, "n_samples"),
        ({"n_samples": 64, "sample_rate_hz": 0.0}, "sample_rate_hz"),
        ({"n_samples": 64, "f_min_hz": -1.0}, "f_min_hz"),
        ({"n_samples": 64, "f_min_hz": 30000.0}, "make the buffer longer"),
        ({"n_samples": 4, "sample_rate_hz": 100.0, "f_min_hz": 60.0}, "no frequency"),
    ],
)
def test_bad_generation_settings_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        pink_noise(rng=np.random.default_rng(0), **kwargs)


@pytest.mark.parametrize("duration", [0.0, -1.0, math.nan])
def test_bad_loop_duration_is_refused(duration):
    with pytest.raises(ValueError, match="duration_s"):
        loop_buffer(duration, np.random.default_rng(0))
