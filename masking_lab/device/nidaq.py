"""Optional NI-DAQmx back-end for rigs wired like the paper's (NI 9264 analog outputs).

Each trial is one hardware-timed finite output task writing the two buffers built by
:func:`masking_lab.core.waveforms.trial_buffers` (rows EV, MV); the buffers end on exactly 0 V, so
the outputs rest at 0 V when the task ends. The task's output range is the configured limit, so
the driver itself refuses anything beyond it. ``nidaqmx`` is imported only when this back-end is
opened. Not supported: streamed amplitudes (use the serial firmware for rendering).

The NI 9264 holds its last value when a task is aborted: on errors, STOP, close, normal exit
and SIGTERM the host writes 0 V to both lines; a SIGKILL mid-trial cannot be caught here (the
serial firmware's watchdog exists for that; see docs/devices.md).
"""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np
from numpy.typing import NDArray

from masking_lab import __version__
from masking_lab.core import waveforms
from masking_lab.core.clock import Clock, RealClock
from masking_lab.device import safety
from masking_lab.device.base import DeviceIdentity, PlayResult, TrialPlan
from masking_lab.device.config import DeviceConfig, default_device_config
from masking_lab.core.errors import DeviceError
from masking_lab.core.stimulus import CHANNELS, Channel, Stimulus

INSTALL_HINT = (
    "the nidaq back-end needs NI's `nidaqmx` Python package and the NI-DAQmx driver: "
    "pip install 'masking-lab[nidaq]' and install NI-DAQmx from ni.com, or choose another "
    "device (--device serial:PORT, emulator or sim)"
)


def build_output_buffer(plan: TrialPlan, config: DeviceConfig) -> NDArray[np.float64]:
    """The (2, n) array of volts a trial writes, rows EV then MV, after the limit check.

    Raises
    ------
    SafetyLimitError
        If an amplitude of ``plan`` exceeds ``config.limits``; no buffer is built.
    """
    safety.check_plan(plan, config.limits)
    bufs = waveforms.trial_buffers(
        plan, config.waveform.sample_rate_hz, ramp_s=config.waveform.ramp_s
    )
    return bufs.stacked()


def import_nidaqmx() -> Any:
    """Import ``nidaqmx`` or raise DeviceError saying how to install it."""
    try:
        import nidaqmx
        import nidaqmx.constants
    except ImportError as exc:
        raise DeviceError(INSTALL_HINT) from exc
    return nidaqmx


class NidaqDevice:
    """Two analog outputs of an NI-DAQmx device (EV and MV drive).

    Parameters
    ----------
    config : DeviceConfig, optional
        Limits, sample rate, ramp and ``nidaq`` wiring (reference rig if None).
    clock : Clock, optional
        Must be a real clock: hardware cannot run in virtual time.
    device_name : str, optional
        Overrides ``config.nidaq.device`` (``--device nidaq:cDAQ1Mod1``).
    """

    def __init__(
        self,
        config: DeviceConfig | None = None,
        clock: Clock | None = None,
        *,
        device_name: str | None = None,
    ) -> None:
        self.config = config or default_device_config()
        self.clock: Clock = clock or RealClock()
        if self.clock.virtual:
            raise DeviceError("the nidaq back-end drives hardware: it needs a real clock")
        self._nidaqmx = import_nidaqmx()
        self.device_name = device_name or self.config.nidaq.device
        self.lines = {
            ch: f"{self.device_name}/{self.config.nidaq.ao_channels[ch]}" for ch in CHANNELS
        }
        self.identity = DeviceIdentity(
            backend="nidaq",
            model=f"NI-DAQmx {self.device_name}",
            serial_number="n/a",
            firmware_version=f"masking-lab {__version__}",
            port=None,
            limits=self.config.limits,
        )
        self._closed = False
        self.stop()  # start from 0 V whatever the last program left behind
        safety.zero_on_exit(self)

    def play_trial(self, plan: TrialPlan, start_s: float) -> PlayResult:
        """Write the trial's buffers as one finite, hardware-timed task starting at ``start_s``."""
        data = build_output_buffer(plan, self.config)
        fs = self.config.waveform.sample_rate_hz
        onsets = waveforms.trial_buffers(plan, fs, ramp_s=self.config.waveform.ramp_s)
        constants = self._nidaqmx.constants
        try:
            with self._nidaqmx.Task() as task:
                self._add_channels(task)
                task.timing.cfg_samp_clk_timing(
                    rate=fs,
                    sample_mode=constants.AcquisitionType.FINITE,
                    samps_per_chan=data.shape[1],
                )
                task.write(data, auto_start=False)
                self.clock.sleep_until(start_s)
                t0 = self.clock.now()
                task.start()
                task.wait_until_done(timeout=plan.duration_s + 2.0)
                task.stop()
        except BaseException as exc:
            self._zero_quietly()
            if isinstance(exc, Exception) and type(exc).__module__.startswith("nidaqmx"):
                raise DeviceError(
                    f"NI-DAQmx {self.device_name} failed during a trial ({exc}); outputs set to "
                    "0 V. Check the chassis and cabling, then `masking-lab resume LOG`"
                ) from exc
            raise
        return PlayResult(
            planned_onsets_s=plan.planned_onsets_s(start_s),
            actual_onsets_s=[t0 + k / fs for k in onsets.onset_samples],
            played_target_v=plan.target_amplitude_v,
            played_masker_v=plan.masker_amplitude_v if plan.masker is not None else 0.0,
            extra={"backend": "nidaq", "start_s": t0},
        )

    def set_amplitude(self, channel: Channel, stimulus: Stimulus, amplitude_v: float) -> None:
        """Not supported: streamed rendering needs the serial firmware."""
        raise DeviceError(
            "the nidaq back-end plays timed trials only; streamed amplitudes need the serial "
            "firmware (--device serial:PORT or emulator)"
        )

    def stop(self) -> None:
        """Write 0 V to both outputs (on-demand task)."""
        with self._nidaqmx.Task() as task:
            self._add_channels(task)
            task.write([0.0, 0.0], auto_start=True)

    def close(self) -> None:
        """Write 0 V to both outputs. Idempotent."""
        if self._closed:
            return
        try:
            self.stop()
        finally:
            self._closed = True
            safety.forget(self)

    def _add_channels(self, task: Any) -> None:
        for ch in CHANNELS:
            limit = self.config.limits.max_drive_v[ch]
            task.ao_channels.add_ao_voltage_chan(self.lines[ch], min_val=-limit, max_val=limit)

    def _zero_quietly(self) -> None:
        # The driver is already failing; the error that got us here is what gets raised.
        with contextlib.suppress(Exception):
            self.stop()
