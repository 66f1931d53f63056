"""Drive waveforms: sine carrier, optional AM envelope, raised-cosine ramps, 3IFC trial buffers.

Pure numpy; the sample rate is always a parameter. Shared by the firmware emulator and the
NI-DAQmx back-end, so what the emulator reports is what a rig would output.

Guarantees, for every buffer built here:

- every tone starts and ends with raised-cosine ramps, so nothing clicks;
- every buffer's first and last samples are exactly 0 V, so an output that stops at the end of a
  buffer rests at 0 V;
- a tone's peak ``max |x|`` equals the requested peak amplitude (the sampled waveform is scaled
  so that its largest sample, not the analogue sine, hits the amplitude).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from masking_lab.core.errors import InputError, LevelError
from masking_lab.core.stimulus import Channel, Stimulus

if TYPE_CHECKING:  # annotation only: the core does not import the device shell at run time
    from masking_lab.core.trial import TrialPlan

DEFAULT_RAMP_S = 0.01


def ramp_window(n_samples: int, ramp_samples: int) -> NDArray[np.float64]:
    """Raised-cosine onset/offset window, 0 at both ends and 1 in between.

    Parameters
    ----------
    n_samples : int
        Window length, samples (≥ 3).
    ramp_samples : int
        Samples from 0 to 1 (and back); shortened to fit when ``n_samples`` is small.

    Returns
    -------
    ndarray
        Gain in [0, 1] (dimensionless), length ``n_samples``.

    Raises
    ------
    ValueError
        If ``n_samples`` < 3.

    Examples
    --------
    >>> np.round(ramp_window(7, 2), 6).tolist()
    [0.0, 0.5, 1.0, 1.0, 1.0, 0.5, 0.0]
    """
    if n_samples < 3:
        raise ValueError(
            f"a tone needs at least 3 samples to start and end at 0 V, got {n_samples}"
        )
    r = max(1, min(int(ramp_samples), (n_samples - 1) // 2))
    w = np.ones(n_samples)
    rise = 0.5 * (1.0 - np.cos(np.pi * np.arange(r) / r))  # rise[0] == 0 exactly
    w[:r] = rise
    w[n_samples - r :] = rise[::-1]
    w[-1] = 0.0
    return w


def tone(
    carrier_hz: float,
    amplitude_v: float,
    duration_s: float,
    sample_rate_hz: float,
    *,
    envelope_hz: float | None = None,
    ramp_s: float = DEFAULT_RAMP_S,
) -> NDArray[np.float64]:
    """One ramped tone: ``amplitude_v · ramp · envelope · sin(2π f t)``, peak ``amplitude_v``.

    Parameters
    ----------
    carrier_hz : float
        Carrier frequency, Hz (below half the sample rate).
    amplitude_v : float
        Peak amplitude, V (≥ 0; 0 gives silence).
    duration_s : float
        Time from the first to the last sample, s (``round(duration_s·fs) + 1`` samples).
    sample_rate_hz : float
        Sample rate, Hz.
    envelope_hz : float or None
        Full-depth AM envelope ``(1 − cos 2π f_e t)/2``, Hz; None for a plain carrier.
    ramp_s : float
        Raised-cosine onset and offset duration, s (> 0).

    Returns
    -------
    ndarray
        Drive in V, ``round(duration_s·fs) + 1`` samples, first and last exactly 0 V.

    Raises
    ------
    LevelError
        For a non-finite or negative amplitude.
    InputError
        For frequencies at or above Nyquist, a non-positive ramp or duration.
    ValueError
        For a tone shorter than 3 samples.

    Examples
    --------
    100 ms of EV270 at 0.5 V peak, sampled at 10 kHz:

    >>> x = tone(270.0, 0.5, 0.1, 10_000.0)
    >>> len(x), float(np.max(np.abs(x))), abs(float(x[0])), abs(float(x[-1]))
    (1001, 0.5, 0.0, 0.0)
    """
    _check_rate(sample_rate_hz)
    if not (math.isfinite(amplitude_v) and amplitude_v >= 0):
        raise LevelError(f"amplitude must be a finite peak ≥ 0 V, got {amplitude_v!r}")
    for name, f in (("carrier_hz", carrier_hz), ("envelope_hz", envelope_hz)):
        if f is not None and not (0 < f < sample_rate_hz / 2):
            raise InputError(
                f"{name}={f!r} must be between 0 and half the sample rate "
                f"({sample_rate_hz / 2:g} Hz); raise waveform.sample_rate_hz"
            )
    if not ramp_s > 0:
        raise InputError(f"ramp_s must be > 0 s so tones do not click, got {ramp_s!r}")
    if not (math.isfinite(duration_s) and duration_s > 0):
        raise InputError(f"duration must be a finite number of s > 0, got {duration_s!r}")
    n = round(duration_s * sample_rate_hz) + 1
    t = np.arange(n) / sample_rate_hz
    unit = ramp_window(n, round(ramp_s * sample_rate_hz)) * np.sin(2 * np.pi * carrier_hz * t)
    if envelope_hz is not None:
        unit *= 0.5 * (1.0 - np.cos(2 * np.pi * envelope_hz * t))
    peak = float(np.max(np.abs(unit)))
    if amplitude_v == 0 or peak == 0:
        return np.zeros(n)
    # unit/peak is exactly ±1 at the largest sample (x/x == 1 in IEEE), so the peak is exact.
    return (unit / peak) * amplitude_v


def stimulus_tone(
    stimulus: Stimulus,
    amplitude_v: float,
    duration_s: float,
    sample_rate_hz: float,
    *,
    ramp_s: float = DEFAULT_RAMP_S,
) -> NDArray[np.float64]:
    """:func:`tone` for a :class:`~masking_lab.core.stimulus.Stimulus` (carrier and envelope).

    Parameters
    ----------
    stimulus : Stimulus
        Supplies the carrier and envelope frequencies, Hz.
    amplitude_v : float
        Peak amplitude, V.
    duration_s : float
        Time from the first to the last sample, s.
    sample_rate_hz : float
        Sample rate, Hz.
    ramp_s : float
        Raised-cosine onset and offset duration, s.

    Returns
    -------
    ndarray
        Drive in V whose largest sample is exactly ``amplitude_v``.

    Examples
    --------
    >>> from masking_lab.core.stimulus import parse_stimulus
    >>> x = stimulus_tone(parse_stimulus("MV120am40"), 0.2, 0.5, 5_000.0)
    >>> len(x), float(np.max(np.abs(x)))
    (2501, 0.2)
    """
    return tone(
        stimulus.carrier_hz,
        amplitude_v,
        duration_s,
        sample_rate_hz,
        envelope_hz=stimulus.envelope_hz,
        ramp_s=ramp_s,
    )


@dataclass(frozen=True)
class TrialBuffers:
    """The sample buffers of one 3IFC trial, one per channel, starting at the trial start.

    Attributes
    ----------
    sample_rate_hz : float
        Sample rate, Hz.
    ev_v, mv_v : ndarray
        Drive of the EV and MV channels, V, same length; both end on exactly 0 V.
    onset_samples : tuple[int, ...]
        Sample index of each interval onset.

    Examples
    --------
    >>> buffers = TrialBuffers(1000.0, np.zeros(5), np.ones(5), (0,))
    >>> buffers.stacked().shape, buffers.duration_s, float(buffers.channel("MV")[2])
    ((2, 5), 0.004, 1.0)
    """

    sample_rate_hz: float
    ev_v: NDArray[np.float64]
    mv_v: NDArray[np.float64]
    onset_samples: tuple[int, ...]

    def channel(self, channel: Channel) -> NDArray[np.float64]:
        """The buffer of ``channel`` (``"EV"`` or ``"MV"``)."""
        return self.ev_v if channel == "EV" else self.mv_v

    def stacked(self) -> NDArray[np.float64]:
        """Shape (2, n) array, rows EV then MV (the order the NI-DAQmx task writes)."""
        return np.vstack([self.ev_v, self.mv_v])

    @property
    def duration_s(self) -> float:
        """Time from the first to the last sample, s."""
        return (len(self.ev_v) - 1) / self.sample_rate_hz


def trial_buffers(
    plan: TrialPlan, sample_rate_hz: float, *, ramp_s: float = DEFAULT_RAMP_S
) -> TrialBuffers:
    """Build the buffers of a trial: the target in its interval, the masker in every interval.

    Silence (exactly 0 V) before the first interval (lead-in), between intervals (gaps) and at
    the end. When target and masker share a channel their drives add.

    Parameters
    ----------
    plan : TrialPlan
        Stimuli, peak amplitudes (V) and timing (s).
    sample_rate_hz : float
        Sample rate, Hz.
    ramp_s : float
        Raised-cosine ramp of every tone, s.

    Returns
    -------
    TrialBuffers
        EV and MV drive in V from the trial start, and the interval onsets in samples.

    Raises
    ------
    ValueError
        For a target interval outside 1..``n_intervals`` or a bad sample rate.

    Examples
    --------
    EV270 at 50 mV in interval 2 under an MV120 masker at 0.2 V, sampled at 1 kHz: the EV
    channel is silent in interval 1 and the masker plays in every interval.

    >>> from masking_lab.core.stimulus import parse_stimulus
    >>> from masking_lab.core.trial import TrialPlan
    >>> plan = TrialPlan(parse_stimulus("EV270"), 0.05, 2, parse_stimulus("MV120"), 0.2)
    >>> b = trial_buffers(plan, 1000.0)
    >>> b.onset_samples, b.duration_s
    ((600, 3000, 5400), 7.2)
    >>> first, second = slice(600, 2400), slice(3000, 4800)
    >>> float(np.max(np.abs(b.ev_v[first]))), float(np.max(np.abs(b.ev_v[second])))
    (0.0, 0.05)
    >>> float(np.max(np.abs(b.mv_v[first])))
    0.2
    """
    _check_rate(sample_rate_hz)
    if not 1 <= plan.target_interval <= plan.n_intervals:
        raise ValueError(f"target_interval {plan.target_interval} is not in 1..{plan.n_intervals}")
    fs = sample_rate_hz
    n_total = round(plan.duration_s * fs) + 1
    bufs: dict[str, NDArray[np.float64]] = {"EV": np.zeros(n_total), "MV": np.zeros(n_total)}
    onsets = tuple(round(t * fs) for t in plan.planned_onsets_s(0.0))
    target = stimulus_tone(plan.target, plan.target_amplitude_v, plan.stimulus_s, fs, ramp_s=ramp_s)
    masker = None
    if plan.masker is not None and plan.masker_amplitude_v > 0:
        masker = stimulus_tone(
            plan.masker, plan.masker_amplitude_v, plan.stimulus_s, fs, ramp_s=ramp_s
        )
    for k, start in enumerate(onsets):
        if k + 1 == plan.target_interval:
            _add(bufs[plan.target.channel], target, start)
        if masker is not None and plan.masker is not None:
            _add(bufs[plan.masker.channel], masker, start)
    for buf in bufs.values():
        buf[0] = 0.0
        buf[-1] = 0.0
    return TrialBuffers(fs, bufs["EV"], bufs["MV"], onsets)


def _add(buf: NDArray[np.float64], seg: NDArray[np.float64], start: int) -> None:
    end = min(len(buf), start + len(seg))
    buf[start:end] += seg[: end - start]


def _check_rate(sample_rate_hz: float) -> None:
    if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
        raise ValueError(
            f"sample_rate_hz must be a finite number of Hz > 0, got {sample_rate_hz!r}"
        )
