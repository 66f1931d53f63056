"""In-process simulated device: plays nothing, but behaves like one on the session clock.

:class:`SimDevice` checks limits exactly like a real back-end, quantises amplitudes like the
rig's converters (attenuator step per stimulus, whole LSBs; see
:mod:`masking_lab.device.levels_range`), reports onsets (planned plus an optional seeded
lateness) and advances the session clock to the end of each trial, so a
VirtualClock session runs as fast as the responder answers. The simulated *observer* that
answers trials is a responder (``masking_lab.responders.sim``), not part of the device.
"""

from __future__ import annotations

import numpy as np

from masking_lab import __version__
from masking_lab.core.clock import Clock, VirtualClock
from masking_lab.core.errors import DeviceError, SafetyLimitError
from masking_lab.core.stimulus import CHANNELS, Channel, Stimulus
from masking_lab.device import safety, serial_checks
from masking_lab.device.base import DeviceIdentity, PlayResult, TrialPlan
from masking_lab.device.config import DeviceConfig, default_device_config


class SimDevice:
    """A :class:`~masking_lab.device.base.Device` that lives in the host process.

    Parameters
    ----------
    config : DeviceConfig, optional
        Limits in force (reference rig if None).
    clock : Clock, optional
        Session clock (a VirtualClock starting at 0 s if None).
    seed : int
        Seed of the simulated onset lateness.
    onset_jitter_s : float
        SD of the simulated onset lateness, s (0: onsets exactly as planned).
    """

    def __init__(
        self,
        config: DeviceConfig | None = None,
        clock: Clock | None = None,
        *,
        seed: int = 0,
        onset_jitter_s: float = 0.0,
    ) -> None:
        self.config = config or default_device_config()
        self.clock: Clock = clock or VirtualClock()
        self.identity = DeviceIdentity(
            backend="sim",
            model="masking-lab simulated device",
            serial_number="n/a",
            firmware_version=__version__,
            port=None,
            limits=self.config.limits,
        )
        self.onset_jitter_s = float(onset_jitter_s)
        self._rng = np.random.default_rng(seed)
        self._amp: dict[str, float] = dict.fromkeys(CHANNELS, 0.0)
        self._closed = False
        self.trials_played = 0

    def play_trial(self, plan: TrialPlan, start_s: float) -> PlayResult:
        """Check limits, advance the clock to the end of the trial, report the onsets (s) and the
        amplitudes the converters play (V)."""
        safety.check_plan(plan, self.identity.limits)
        self._check_open()
        extra: dict[str, object] = {"backend": "sim"}
        played_t = plan.target_amplitude_v
        played_m = plan.masker_amplitude_v if plan.masker is not None else 0.0
        if set(self.config.converters) >= {"EV", "MV"}:
            steps = serial_checks.choose_steps(plan, self.config.converters, "simulated device")
            played_t, played_m = steps.target_v, steps.masker_v
            extra.update(
                requested_target_v=plan.target_amplitude_v,
                requested_masker_v=plan.masker_amplitude_v if plan.masker is not None else 0.0,
                target_att_db=steps.target_db,
                masker_att_db=steps.masker_db,
            )
        planned = plan.planned_onsets_s(start_s)
        late = (
            np.abs(self._rng.normal(0.0, self.onset_jitter_s, len(planned)))
            if self.onset_jitter_s > 0
            else np.zeros(len(planned))
        )
        self._amp = dict.fromkeys(CHANNELS, 0.0)  # a trial replaces any streamed output
        self.clock.sleep_until(start_s + plan.duration_s)
        self.trials_played += 1
        return PlayResult(
            planned_onsets_s=planned,
            actual_onsets_s=[t + float(d) for t, d in zip(planned, late, strict=True)],
            played_target_v=played_t,
            played_masker_v=played_m,
            extra=extra,
        )

    def set_amplitude(self, channel: Channel, stimulus: Stimulus, amplitude_v: float) -> None:
        """Record a streamed amplitude (V) after the same checks a real device makes."""
        if stimulus.channel != channel:
            raise SafetyLimitError(f"{stimulus} is a {stimulus.channel} stimulus, not {channel}")
        safety.check_amplitude(channel, amplitude_v, self.identity.limits, what=str(stimulus))
        self._check_open()
        self._amp[channel] = float(amplitude_v)

    def outputs(self) -> dict[str, float]:
        """Current streamed peak amplitude per channel, V."""
        return dict(self._amp)

    def stop(self) -> None:
        """Zero both outputs."""
        self._amp = dict.fromkeys(CHANNELS, 0.0)

    def close(self) -> None:
        """Zero both outputs; later calls to play raise. Idempotent."""
        self.stop()
        self._closed = True

    def _check_open(self) -> None:
        if self._closed:
            raise DeviceError("the simulated device is closed; open a new one")
