"""Waveforms: exact peaks, silent ends, click-free ramps, and the 3IFC trial layout."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from masking_lab.core import waveforms
from masking_lab.core.stimulus import parse_stimulus
from masking_lab.core.trial import TrialPlan

FS = 20000.0


@st.composite
def tones(draw):
    fs = draw(st.sampled_from([2000.0, 8000.0, 20000.0, 25000.0, 48000.0]))
    carrier = draw(st.floats(5.0, fs / 4))
    envelope = draw(st.one_of(st.none(), st.floats(1.0, fs / 8)))
    duration = draw(st.floats(5.0 / fs, 0.3))
    amplitude = draw(st.floats(0.0, 10.0))
    ramp = draw(st.floats(1.0 / fs, 0.05))
    return carrier, amplitude, duration, fs, envelope, ramp


@settings(max_examples=60, deadline=None)
@given(tones())
def test_tone_peak_is_the_amplitude_and_both_ends_are_zero(params):
    carrier, amplitude, duration, fs, envelope, ramp = params
    x = waveforms.tone(carrier, amplitude, duration, fs, envelope_hz=envelope, ramp_s=ramp)
    assert len(x) == round(duration * fs) + 1
    assert x[0] == 0.0 and x[-1] == 0.0
    assert np.all(np.isfinite(x))
    assert np.max(np.abs(x)) == amplitude  # exact, not approximate


def test_a_steady_sine_peaks_where_the_analogue_sine_does():
    # 250 Hz at 20 kHz: 80 samples per cycle, so the sampled sine hits ±1 exactly.
    x = waveforms.tone(250.0, 2.0, 0.2, FS, ramp_s=0.01)
    mid = x[len(x) // 2 - 200 : len(x) // 2 + 200]
    assert np.max(mid) == pytest.approx(2.0) and np.min(mid) == pytest.approx(-2.0)
    # and it is a 250 Hz sine: the spectrum peaks at 250 Hz
    spectrum = np.abs(np.fft.rfft(x * np.hanning(len(x))))
    freqs = np.fft.rfftfreq(len(x), 1 / FS)
    assert freqs[np.argmax(spectrum)] == pytest.approx(250.0, abs=FS / len(x))


def test_ramps_do_not_click():
    """With 10 ms raised-cosine ramps, the first and last ms stay below ~2.5 % of the peak."""
    amplitude = 5.0
    x = waveforms.tone(270.0, amplitude, 0.5, FS, ramp_s=0.01)
    one_ms = int(0.001 * FS)
    # 0.5·(1 − cos(π·0.1)) = 0.0245: the raised cosine 1 ms into a 10 ms ramp
    assert np.max(np.abs(x[:one_ms])) <= 0.0245 * amplitude * 1.001
    assert np.max(np.abs(x[-one_ms:])) <= 0.0245 * amplitude * 1.001
    # sample-to-sample steps at the edges are far smaller than an abrupt start would make
    assert np.max(np.abs(np.diff(x[:one_ms]))) < 0.01 * amplitude
    assert np.max(np.abs(x[int(0.02 * FS) : int(0.03 * FS)])) > 0.99 * amplitude


def test_coarse_texture_is_am_at_40_hz():
    x = waveforms.stimulus_tone(parse_stimulus("MV120am40"), 1.0, 1.0, FS, ramp_s=0.01)
    spectrum = np.abs(np.fft.rfft(x))
    freqs = np.fft.rfftfreq(len(x), 1 / FS)

    def power_at(f):
        return spectrum[np.argmin(np.abs(freqs - f))]

    # full-depth AM of 120 Hz by 40 Hz: carrier plus sidebands at 80 and 160 Hz, half as tall
    assert power_at(80) == pytest.approx(power_at(120) / 2, rel=0.05)
    assert power_at(160) == pytest.approx(power_at(120) / 2, rel=0.05)
    assert power_at(200) < power_at(120) / 50


def test_zero_amplitude_is_silence():
    assert not np.any(waveforms.tone(270.0, 0.0, 0.1, FS))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"carrier_hz": 15000.0}, "half the sample rate"),
        ({"envelope_hz": 10000.0}, "half the sample rate"),
        ({"amplitude_v": -1.0}, "≥ 0 V"),
        ({"amplitude_v": float("nan")}, "finite"),
        ({"duration_s": 0.0}, "> 0"),
        ({"duration_s": 1e-5}, "at least 3 samples"),
        ({"ramp_s": 0.0}, "do not click"),
        ({"sample_rate_hz": 0.0}, "sample_rate_hz"),
    ],
)
def test_unplayable_tones_are_refused(kwargs, message):
    args = {"carrier_hz": 270.0, "amplitude_v": 1.0, "duration_s": 0.1, "sample_rate_hz": FS}
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        waveforms.tone(
            args.pop("carrier_hz"),
            args.pop("amplitude_v"),
            args.pop("duration_s"),
            args.pop("sample_rate_hz"),
            **args,
        )


def _plan(**kw):
    base = {
        "target": parse_stimulus("EV270"),
        "target_amplitude_v": 0.8,
        "target_interval": 2,
        "masker": parse_stimulus("MV120"),
        "masker_amplitude_v": 0.3,
        "stimulus_s": 0.1,
        "gap_s": 0.05,
        "lead_in_s": 0.04,
    }
    base.update(kw)
    return TrialPlan(**base)


def _segments(buf, onsets, n):
    return [buf[s : s + n] for s in onsets]


def test_trial_buffers_layout():
    plan = _plan()
    bufs = waveforms.trial_buffers(plan, FS, ramp_s=0.005)
    n_stim = round(plan.stimulus_s * FS) + 1
    assert len(bufs.ev_v) == len(bufs.mv_v) == round(plan.duration_s * FS) + 1
    assert bufs.duration_s == pytest.approx(plan.duration_s)
    assert bufs.onset_samples == tuple(round(t * FS) for t in (0.04, 0.19, 0.34))
    ev = _segments(bufs.ev_v, bufs.onset_samples, n_stim)
    mv = _segments(bufs.mv_v, bufs.onset_samples, n_stim)
    # target only in interval 2, at its exact peak; masker in all three at its exact peak
    assert [np.max(np.abs(s)) for s in ev] == [0.0, 0.8, 0.0]
    assert [np.max(np.abs(s)) for s in mv] == [0.3, 0.3, 0.3]
    # silence outside the intervals: lead-in, gaps and the end
    inside = np.zeros(len(bufs.ev_v), dtype=bool)
    for s in bufs.onset_samples:
        inside[s : s + n_stim] = True
    assert not np.any(bufs.ev_v[~inside]) and not np.any(bufs.mv_v[~inside])
    assert bufs.ev_v[-1] == 0.0 and bufs.mv_v[-1] == 0.0
    np.testing.assert_array_equal(bufs.stacked(), np.vstack([bufs.ev_v, bufs.mv_v]))
    assert bufs.channel("MV") is bufs.mv_v


def test_unmasked_trial_leaves_the_other_channel_silent():
    bufs = waveforms.trial_buffers(_plan(masker=None, masker_amplitude_v=0.0), FS)
    assert not np.any(bufs.mv_v)
    assert np.max(np.abs(bufs.ev_v)) == 0.8


def test_same_channel_target_and_masker_add():
    plan = _plan(target=parse_stimulus("MV250"), target_interval=1, gap_s=0.0)
    bufs = waveforms.trial_buffers(plan, FS)
    masker_only = waveforms.stimulus_tone(parse_stimulus("MV120"), 0.3, plan.stimulus_s, FS)
    target_only = waveforms.stimulus_tone(parse_stimulus("MV250"), 0.8, plan.stimulus_s, FS)
    start = bufs.onset_samples[0]
    np.testing.assert_allclose(
        bufs.mv_v[start : start + len(masker_only)], masker_only + target_only, atol=1e-12
    )
    assert bufs.mv_v[-1] == 0.0


@settings(max_examples=40, deadline=None)
@given(
    st.integers(1, 3),
    st.floats(0.0, 5.0),
    st.floats(0.0, 10.0),
    st.floats(0.01, 0.1),
    st.floats(0.0, 0.05),
    st.floats(0.0, 0.05),
)
def test_every_trial_buffer_ends_on_zero_and_peaks_as_asked(ti, tamp, mamp, stim, gap, lead):
    plan = _plan(
        target_interval=ti,
        target_amplitude_v=tamp,
        masker_amplitude_v=mamp,
        stimulus_s=stim,
        gap_s=gap,
        lead_in_s=lead,
    )
    bufs = waveforms.trial_buffers(plan, 10000.0, ramp_s=0.005)
    for buf, peak in ((bufs.ev_v, tamp), (bufs.mv_v, mamp)):
        assert buf[0] == 0.0 and buf[-1] == 0.0
        assert np.max(np.abs(buf)) == peak


def test_bad_target_interval_is_refused():
    with pytest.raises(ValueError, match="target_interval 4"):
        waveforms.trial_buffers(_plan(target_interval=4), FS)
