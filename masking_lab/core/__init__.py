"""The functional core: units, stimuli, masking functions, the psychometric function, trial
value types, seeded random streams, waveforms, clocks and the error types. Pure, no I/O; every
other package builds on it.

- ``levels``: dB re 1 V ↔ volts, sensation level, rating checks.
- ``stimulus``: the paper's stimuli (``EV270``, ``MV120am40``) and their names.
- ``masking``: the ramp masking function ``shift = max(0, a + b·x)``.
- ``psychometric``: the 3IFC logistic (guess rate 1/3, lapse).
- ``trial``: :class:`TrialPlan` and :class:`PlayResult`, what a device is asked and answers.
- ``seeding``: per-trial random streams, so a resumed session draws what an uninterrupted one would.
- ``waveforms``: DAC buffers with ramps; ``clock``: real and virtual clocks; ``errors``.
"""

from masking_lab.core.exports import lazy_exports

_HOME = {
    "Clock": "clock",
    "DeviceError": "errors",
    "LevelError": "errors",
    "LogError": "errors",
    "MaskingFunction": "masking",
    "MaskingLabError": "errors",
    "PlayResult": "trial",
    "ProtocolError": "errors",
    "Psychometric": "psychometric",
    "RealClock": "clock",
    "Stimulus": "stimulus",
    "TrialPlan": "trial",
    "VirtualClock": "clock",
    "db_sl_to_db_v": "levels",
    "db_v_to_db_sl": "levels",
    "db_v_to_volts": "levels",
    "parse_stimulus": "stimulus",
    "ramp": "masking",
    "trial_buffers": "waveforms",
    "trial_rng": "seeding",
    "volts_to_db_v": "levels",
}
__all__ = sorted(_HOME)
__getattr__, __dir__ = lazy_exports(__name__, _HOME)
