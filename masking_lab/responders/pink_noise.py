"""Pink (1/f) masking noise for the participant's headphones.

The paper masks the actuators' sounds with pink noise at about 80 dB SPL in headphones. Pink
noise has equal power per octave: its power spectral density falls as 1/f, i.e. by
10·log10(2) ≈ 3.01 dB per octave.

The noise is synthesised in the frequency domain: every FFT bin of an ``n``-sample buffer gets a
complex Gaussian coefficient scaled by f^(-1/2), and the inverse real FFT returns the buffer. A
signal built from the FFT bins of length ``n`` is exactly periodic with period ``n``, so the buffer
loops seamlessly: the step from its last sample back to its first is just another step of the
noise, with no click. Bins below ``f_min_hz`` (default 20 Hz, below what headphones reproduce
and where 1/f power would grow without bound) and the DC bin are zero, so the mean is zero.

Levels are digital: ``level_db_fs`` is the RMS in dB re a digital amplitude of 1.0 (full scale).
What that becomes in dB SPL depends on the sound card, amplifier and headphones: set the volume
once with a sound level meter (docs/participant-window.md). Pure: the randomness is a
:class:`numpy.random.Generator` passed in.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from masking_lab.core.errors import LevelError

PINK_SLOPE_DB_PER_OCTAVE = -10.0 * math.log10(2.0)
"""Slope of the power spectral density of pink noise, dB/octave (≈ −3.01)."""


def pink_noise(
    n_samples: int,
    rng: np.random.Generator,
    sample_rate_hz: float = 44100.0,
    f_min_hz: float = 20.0,
) -> NDArray[np.float64]:
    """Zero-mean, unit-RMS pink noise that loops seamlessly with period ``n_samples``.

    Parameters
    ----------
    n_samples : int
        Buffer length, samples (≥ 2).
    rng : numpy.random.Generator
        Source of randomness.
    sample_rate_hz : float
        Sample rate, Hz.
    f_min_hz : float
        Lowest frequency present, Hz; bins below it are zero (≥ 0).

    Returns
    -------
    ndarray of float64, shape (n_samples,)
        Noise with RMS 1.0 (digital units) and a power spectral density ∝ 1/f above
        ``f_min_hz``.

    Raises
    ------
    ValueError
        If the buffer is too short, the sample rate not positive, or no FFT bin lies between
        ``f_min_hz`` and the Nyquist frequency.

    Examples
    --------
    One second at 44.1 kHz: unit RMS, and the power spectral density falls about 3 dB per
    octave (measured from the 100–200 Hz octave to the 1.6–3.2 kHz one, four octaves up):

    >>> x = pink_noise(44100, np.random.default_rng(0))
    >>> round(float(np.sqrt(np.mean(x**2))), 6)
    1.0
    >>> power = np.abs(np.fft.rfft(x)) ** 2
    >>> f_hz = np.fft.rfftfreq(x.size, d=1 / 44100)
    >>> def psd(lo_hz):
    ...     return power[(f_hz >= lo_hz) & (f_hz < 2 * lo_hz)].mean()
    >>> round(float(10 * np.log10(psd(1600) / psd(100)) / 4))
    -3
    """
    n = int(n_samples)
    if n < 2:
        raise ValueError(f"n_samples must be ≥ 2, got {n_samples!r}")
    if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
        raise ValueError(f"sample_rate_hz must be > 0 Hz, got {sample_rate_hz!r}")
    if not (math.isfinite(f_min_hz) and f_min_hz >= 0):
        raise ValueError(f"f_min_hz must be ≥ 0 Hz, got {f_min_hz!r}")
    freqs_hz = np.fft.rfftfreq(n, d=1.0 / sample_rate_hz)
    keep = (freqs_hz > 0) & (freqs_hz >= f_min_hz)
    if not keep.any():
        raise ValueError(
            f"no frequency between f_min_hz={f_min_hz} Hz and Nyquist "
            f"({sample_rate_hz / 2} Hz) for a {n}-sample buffer: make the buffer longer"
        )
    coeffs = rng.standard_normal(freqs_hz.size) + 1j * rng.standard_normal(freqs_hz.size)
    if n % 2 == 0:
        # The Nyquist bin of an even-length real signal is real; a complex value there would be
        # silently dropped by irfft and bias the level.
        coeffs[-1] = coeffs[-1].real * math.sqrt(2.0)
    amplitude = np.zeros_like(freqs_hz)
    amplitude[keep] = 1.0 / np.sqrt(freqs_hz[keep])  # power ∝ 1/f
    noise = np.fft.irfft(coeffs * amplitude, n=n)
    rms = math.sqrt(float(np.mean(noise**2)))
    return noise / rms


def rms_db_fs(signal: NDArray[np.floating]) -> float:
    """RMS level of ``signal`` in dB re digital full scale (RMS 1.0 = 0 dB); silence is −inf.

    Parameters
    ----------
    signal : ndarray
        Samples, digital units.

    Returns
    -------
    float
        RMS level, dB FS.

    Examples
    --------
    >>> round(rms_db_fs(np.full(4, 0.1)), 6), rms_db_fs(np.zeros(3))
    (-20.0, -inf)
    """
    rms = math.sqrt(float(np.mean(np.square(signal, dtype=np.float64))))
    return -math.inf if rms == 0 else 20.0 * math.log10(rms)


def normalize_rms(
    signal: NDArray[np.floating], target_rms_db_fs: float, max_peak: float = 1.0
) -> NDArray[np.float64]:
    """Scale ``signal`` to an RMS of ``target_rms_db_fs`` dB re full scale.

    Parameters
    ----------
    signal : ndarray
        Samples, digital units.
    target_rms_db_fs : float
        Wanted RMS level, dB re full scale (RMS 1.0 = 0 dB), finite.
    max_peak : float
        Largest absolute sample value allowed after scaling (1.0: full scale).

    Raises
    ------
    LevelError
        If the target is not finite, the signal is silent or not finite, or the scaled signal
        would exceed ``max_peak`` (it would clip: lower the level).

    Returns
    -------
    ndarray of float64
        The scaled samples, digital units.

    Examples
    --------
    >>> noise = pink_noise(44100, np.random.default_rng(0))
    >>> round(rms_db_fs(normalize_rms(noise, -20.0)), 6)
    -20.0
    >>> normalize_rms(noise, 0.0)
    Traceback (most recent call last):
    ...
    masking_lab.core.errors.LevelError: pink noise at 0 dB FS RMS would clip (peak 4.16 > 1); ...
    """
    if not math.isfinite(target_rms_db_fs):
        raise LevelError(f"noise level must be a finite dB FS value, got {target_rms_db_fs!r}")
    x = np.asarray(signal, dtype=np.float64)
    if not np.all(np.isfinite(x)):
        raise LevelError("noise buffer contains NaN or infinite samples")
    current_db = rms_db_fs(x)
    if current_db == -math.inf:
        raise LevelError("cannot set the level of a silent buffer")
    scaled = x * 10.0 ** ((target_rms_db_fs - current_db) / 20.0)
    peak = float(np.max(np.abs(scaled)))
    if peak > max_peak:
        headroom_db = 20.0 * math.log10(peak / max_peak)
        raise LevelError(
            f"pink noise at {target_rms_db_fs:g} dB FS RMS would clip (peak {peak:.2f} > "
            f"{max_peak:g}); use a level at most {target_rms_db_fs - headroom_db:.1f} dB FS and "
            "turn up the headphone amplifier instead"
        )
    return scaled


def loop_buffer(
    duration_s: float,
    rng: np.random.Generator,
    sample_rate_hz: float = 44100.0,
    level_db_fs: float = -20.0,
    f_min_hz: float = 20.0,
) -> NDArray[np.float32]:
    """A seamless pink-noise loop ready for a sound card.

    Parameters
    ----------
    duration_s : float
        Loop length, s (long enough that the repetition is not heard: 10–30 s).
    rng : numpy.random.Generator
        Source of randomness.
    sample_rate_hz : float
        Sample rate, Hz.
    level_db_fs : float
        RMS level, dB re full scale; −20 dB FS leaves room for the noise's peaks.
    f_min_hz : float
        Lowest frequency present, Hz.

    Returns
    -------
    ndarray of float32, shape (round(duration_s · sample_rate_hz),)
        Samples in [−1, 1].

    Raises
    ------
    ValueError
        For a duration or sample rate that gives fewer than 2 samples.
    LevelError
        For a level that is not finite or would clip.

    Examples
    --------
    >>> loop = loop_buffer(0.5, np.random.default_rng(1), level_db_fs=-20.0)
    >>> loop.dtype, loop.shape, round(rms_db_fs(loop), 2)
    (dtype('float32'), (22050,), -20.0)
    """
    if not (math.isfinite(duration_s) and duration_s > 0):
        raise ValueError(f"duration_s must be > 0 s, got {duration_s!r}")
    n = round(duration_s * sample_rate_hz)
    noise = pink_noise(n, rng, sample_rate_hz=sample_rate_hz, f_min_hz=f_min_hz)
    return normalize_rms(noise, level_db_fs).astype(np.float32)
