"""Optional NI-DAQmx back-end for rigs wired like the paper's (NI 9264 analog outputs).

Each trial is one hardware-timed finite output task writing the two buffers built by
:func:`masking_lab.core.waveforms.trial_buffers` (rows EV, MV); the buffers end on exactly 0 V, so
the outputs rest at 0 V when the task ends. The task's output range is the configured limit, so
the driver itself refuses anything beyond it. ``nidaqmx`` is imported only when this back-end is
opened. Not supported: streamed amplitudes (use the serial firmware for rendering).

The task is committed before its timed start and the sample rate the driver chose is read back
and used to synthesize the buffers. The running task is kept, so STOP, SIGTERM and Ctrl-C abort
it (stop, close) and then write 0 V: the NI 9264 holds its last value when a task is aborted.
Where the chassis has a watchdog, it is armed with 0 V expiration states, so the hardware zeroes
the outputs if the process dies (SIGKILL) and nothing resets the timer any more. A device without
an analog-output watchdog (X Series boards) is said at session start (:attr:`NidaqDevice.notices`):
a killed host leaves the last sample on the output, which is 0 V between trials (every buffer ends
on 0 V) but a stimulus value mid-trial. Where the device allows, each channel's idle output
behaviour is set to 0 V and the onsets come from the hardware start-trigger timestamp (else from
the host clock read at start). A watchdog found expired is cleared as NI documents
(``WatchdogTask.clear_expiration``), and a device left locked by an expired watchdog of a killed
host is reset (``Device.reset_device``) before anything plays. The helpers that
talk to the driver are in :mod:`masking_lab.device.nidaq_tasks`; tests drive this module through
a recording stand-in of the ``nidaqmx`` package (``tests/nidaqmx_standin``), not NI's driver.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from masking_lab import __version__
from masking_lab.core import waveforms
from masking_lab.core.clock import Clock, RealClock
from masking_lab.core.errors import DeviceError
from masking_lab.core.stimulus import CHANNELS, Channel, Stimulus
from masking_lab.device import safety
from masking_lab.device.base import DeviceIdentity, PlayResult, TrialPlan
from masking_lab.device.config import DeviceConfig, default_device_config
from masking_lab.device.nidaq_tasks import (
    INSTALL_HINT,
    HardwareInfo,
    Watchdog,
    as_device_error,
    driver_errors,
    enable_start_timestamp,
    first_line,
    probe_hardware,
    set_idle_zero,
    watchdog_device,
    watchdog_notice,
)

log = logging.getLogger("masking_lab.device")

POLL_S = 0.005  # how often a playing trial checks for completion; keeps STOP/Ctrl-C prompt
RATE_TOLERANCE = 1e-6  # relative: a coerced rate beyond this would shift every carrier


def build_output_buffer(
    plan: TrialPlan, config: DeviceConfig, sample_rate_hz: float | None = None
) -> NDArray[np.float64]:
    """The (2, n) array of volts a trial writes, rows EV then MV, after the limit check.

    Parameters
    ----------
    plan : TrialPlan
        Stimuli, peak amplitudes (V) and timing (s).
    config : DeviceConfig
        Limits and ramp.
    sample_rate_hz : float, optional
        Rate the buffer is synthesized at, Hz: the rate the driver chose; the config's
        ``waveform.sample_rate_hz`` if None.

    Raises
    ------
    SafetyLimitError
        If an amplitude of ``plan`` exceeds ``config.limits``; no buffer is built.

    Examples
    --------
    >>> from masking_lab.core.stimulus import parse_stimulus
    >>> cfg = default_device_config()
    >>> plan = TrialPlan(parse_stimulus("EV270"), 0.5, 2, stimulus_s=0.1, gap_s=0.05)
    >>> build_output_buffer(plan, cfg).shape  # 1.0 s at 20 kS/s and the closing 0 V sample
    (2, 20001)
    """
    safety.check_plan(plan, config.limits)
    fs = config.waveform.sample_rate_hz if sample_rate_hz is None else sample_rate_hz
    bufs = waveforms.trial_buffers(plan, fs, ramp_s=config.waveform.ramp_s)
    return bufs.stacked()


def resolve_lines(config: DeviceConfig, device_name: str | None = None) -> dict[str, str]:
    """Physical channel of each output: the config's, or from ``--device nidaq:SPEC``.

    Parameters
    ----------
    config : DeviceConfig
        Its ``nidaq.channels`` are used when ``device_name`` is None.
    device_name : str, optional
        ``"EV_LINE,MV_LINE"`` (e.g. ``cDAQ1Mod1/ao0,cDAQ1Mod2/ao0``), or a single device name
        meaning one module with EV on ``ao0`` and MV on ``ao1``.

    Raises
    ------
    DeviceError
        If the spec names the same line twice or is not a device or a pair of lines.

    Examples
    --------
    >>> cfg = default_device_config()
    >>> resolve_lines(cfg)
    {'EV': 'cDAQ1Mod1/ao0', 'MV': 'cDAQ1Mod2/ao0'}
    >>> resolve_lines(cfg, "Dev1")
    {'EV': 'Dev1/ao0', 'MV': 'Dev1/ao1'}
    """
    if not device_name:
        return {ch: config.nidaq.channels[ch] for ch in CHANNELS}
    parts = [p.strip() for p in device_name.split(",")]
    if len(parts) == 1 and "/" not in parts[0]:
        return {"EV": f"{parts[0]}/ao0", "MV": f"{parts[0]}/ao1"}
    if len(parts) == 2 and all("/" in p for p in parts) and parts[0] != parts[1]:
        return dict(zip(CHANNELS, parts, strict=True))
    raise DeviceError(
        f"--device nidaq:{device_name} is not a device or two different lines: write "
        "nidaq:DEVICE (EV on ao0, MV on ao1) or nidaq:EV_LINE,MV_LINE, e.g. "
        "nidaq:cDAQ1Mod1/ao0,cDAQ1Mod2/ao0, or set nidaq.channels in the device config"
    )


def import_nidaqmx() -> Any:
    """Import ``nidaqmx`` or raise DeviceError saying how to install it."""
    try:
        import nidaqmx
        import nidaqmx.constants
        import nidaqmx.errors
        import nidaqmx.system
        import nidaqmx.system.watchdog
    except ImportError as exc:
        raise DeviceError(f"{INSTALL_HINT} ({exc})") from exc
    return nidaqmx


class NidaqDevice:
    """Two analog outputs of NI-DAQmx hardware (EV and MV drive), e.g. two NI 9264 modules.

    Opening reads each module's product type and serial number, zeroes both outputs, arms the
    chassis watchdog with 0 V expiration states where the chassis has one, and asks the driver
    which sample rate it will really run at. Every driver failure, including a missing driver,
    becomes a :class:`DeviceError` that says what to do.

    Parameters
    ----------
    config : DeviceConfig, optional
        Limits, sample rate, ramp and ``nidaq`` wiring (reference rig if None).
    clock : Clock, optional
        Must be a real clock: hardware cannot run in virtual time.
    device_name : str, optional
        Overrides ``config.nidaq.channels`` (``--device nidaq:SPEC``; see :func:`resolve_lines`).

    Attributes
    ----------
    lines : dict[str, str]
        Physical channel of each output channel.
    sample_rate_hz : float
        The rate the driver runs trials at, Hz (read back after committing a task).
    hardware : HardwareInfo
        Product types, serial numbers, chassis and driver version.
    watchdog : Watchdog
        The chassis watchdog and its :attr:`~Watchdog.status`.
    fault_log : list[str]
        Faults met while the device was open (aborted trials, watchdog expiries).

    Examples
    --------
    >>> dev = NidaqDevice(device_name="cDAQ1Mod1/ao0,cDAQ1Mod2/ao0")  # doctest: +SKIP
    >>> dev.identity.model  # doctest: +SKIP
    'NI 9264 cDAQ1Mod1/ao0 (EV) + NI 9264 cDAQ1Mod2/ao0 (MV) in cDAQ-9174 cDAQ1'
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
        self._errors = driver_errors(self._nidaqmx)
        self.lines = resolve_lines(self.config, device_name)
        self.fault_log: list[str] = []
        self.notices: list[str] = []  # said at session start (watchdog, recovery)
        self.idle_output = "not set"
        self.onset_source = "host clock at start"
        self._stamped: set[int] = set()
        # RLock: a SIGTERM handler runs stop() on the main thread, possibly while play_trial
        # (same thread) holds the lock between two driver calls.
        self._lock = threading.RLock()
        self._active: Any = None
        self._aborted = False
        self._closed = True  # until fully open: close() must not touch a half-made device
        self.watchdog = Watchdog(self._nidaqmx, "", list(self.lines.values()), 0.0)
        lines_text = ", ".join(f"{ch}={line}" for ch, line in self.lines.items())
        try:
            self.hardware: HardwareInfo = probe_hardware(self._nidaqmx, self.lines)
            wd_device = watchdog_device(
                self.hardware, self.config.nidaq.watchdog_device, self.lines.values()
            )
            self._zero_or_recover(wd_device)  # 0 V whatever the last program left behind
            self.watchdog = Watchdog(
                self._nidaqmx, wd_device, list(self.lines.values()), self.config.nidaq.watchdog_s
            )
            self.watchdog.start()
            if not self.watchdog.armed:
                self.notices.append(watchdog_notice(self.watchdog.status))
            self.sample_rate_hz = self._probe_rate()
        except self._errors as exc:
            self.watchdog.close()
            raise as_device_error(
                self._nidaqmx, exc, f"opening {lines_text}", self.config.path
            ) from exc
        self.identity = DeviceIdentity(
            backend="nidaq",
            model=self.hardware.model,
            serial_number=self.hardware.serial_number,
            firmware_version=(
                f"NI-DAQmx {self.hardware.driver_version}; masking-lab {__version__}; "
                f"{self.sample_rate_hz:g} S/s; watchdog {self.watchdog.status}"
            ),
            port=None,
            limits=self.config.limits,
            details={
                "watchdog": self.watchdog.status,
                "idle_output": self.idle_output,
                "onsets": self.onset_source,
                "notices": list(self.notices),
            },
        )
        log.info("NI-DAQmx opened: %s; %s", self.identity.model, self.identity.firmware_version)
        self._closed = False
        safety.zero_on_exit(self)

    def play_trial(self, plan: TrialPlan, start_s: float) -> PlayResult:
        """Play ``plan`` as one committed, hardware-timed finite task starting at ``start_s``.

        Raises
        ------
        SafetyLimitError
            An amplitude exceeds the limits; nothing was sent to the driver.
        DeviceError
            The driver failed or the trial was stopped (STOP); both outputs were set to 0 V.
        """
        self._check_open()
        fs = self.sample_rate_hz
        data = build_output_buffer(plan, self.config, fs)
        onsets = waveforms.trial_buffers(plan, fs, ramp_s=self.config.waveform.ramp_s)
        try:
            if self.watchdog.clear_if_expired():
                self.fault_log.append("watchdog had expired before a trial (host stalled)")
            task = self._committed_task(data.shape[1])
            with self._lock:
                task.write(data, auto_start=False)
            self.clock.sleep_until(start_s)
            t0 = self.clock.now()
            with self._lock:
                self._ensure_not_aborted(task)
                task.start()
            t0, source = self._start_time(task, t0)
            self._wait_done(task, plan.duration_s + 2.0)
            with self._lock:
                self._ensure_not_aborted(task)
                self._active = None
                task.stop()
                task.close()
            # the Device contract: return once the trial has ended (a no-op after real hardware)
            self.clock.sleep_until(start_s + plan.duration_s)
        except BaseException as exc:
            # Ctrl-C, SIGTERM's SystemExit, a driver error or STOP: abort the task, then 0 V.
            aborted = self._aborted
            self._zero_quietly()
            if isinstance(exc, self._errors):
                if aborted:
                    raise DeviceError("trial stopped (STOP); outputs set to 0 V") from exc
                self.fault_log.append(f"driver error during a trial: {first_line(exc)}")
                raise DeviceError(
                    f"NI-DAQmx failed during a trial ({first_line(exc)}); outputs set to 0 V. "
                    "Check the chassis and cabling, then `masking-lab resume LOG`"
                ) from exc
            raise
        return PlayResult(
            planned_onsets_s=plan.planned_onsets_s(start_s),
            actual_onsets_s=[t0 + k / fs for k in onsets.onset_samples],
            played_target_v=plan.target_amplitude_v,
            played_masker_v=plan.masker_amplitude_v if plan.masker is not None else 0.0,
            extra={"backend": "nidaq", "start_s": t0, "sample_rate_hz": fs, "onsets": source},
        )

    def set_amplitude(self, channel: Channel, stimulus: Stimulus, amplitude_v: float) -> None:
        """Not supported: streamed rendering needs the serial firmware."""
        raise DeviceError(
            "the nidaq back-end plays timed trials only; streamed amplitudes need the serial "
            "firmware (--device serial:PORT or emulator)"
        )

    def stop(self) -> None:
        """Abort a playing trial (task stop and close), then write 0 V to both outputs.

        Safe to call from another thread or a signal handler while :meth:`play_trial` runs;
        the trial then raises DeviceError.

        Raises
        ------
        DeviceError
            If 0 V cannot be written (driver or chassis gone).
        """
        with self._lock:
            task, self._active = self._active, None
            if task is not None:
                self._aborted = True
                # The NI 9264 holds the last sample of an aborted task: stop and release it so
                # the lines are free for the 0 V write below.
                with contextlib.suppress(*self._errors):
                    task.stop()
                with contextlib.suppress(*self._errors):
                    task.close()
                self.fault_log.append("playing trial aborted; outputs zeroed")
            try:
                self._write_zero()
            except self._errors as exc:
                raise as_device_error(
                    self._nidaqmx, exc, "writing 0 V to both outputs", self.config.path
                ) from exc

    def close(self) -> None:
        """Abort any trial, write 0 V to both outputs and release the watchdog. Idempotent."""
        if self._closed:
            return
        try:
            self.stop()
        finally:
            self._closed = True
            self.watchdog.close()
            safety.forget(self)

    def _check_open(self) -> None:
        if self._closed:
            raise DeviceError("the nidaq device is closed; open it again to play trials")

    def _add_channels(self, task: Any) -> None:
        for ch in CHANNELS:
            limit = self.config.limits.max_drive_v[ch]
            chan = task.ao_channels.add_ao_voltage_chan(
                self.lines[ch], min_val=-limit, max_val=limit
            )
            self.idle_output = set_idle_zero(self._nidaqmx, chan, self.idle_output)

    def _start_time(self, task: Any, software_t0: float) -> tuple[float, str]:
        """When generation began in session time, s: the hardware start-trigger timestamp
        where the task has one, else the host clock read just before start()."""
        if id(task) not in self._stamped:
            return software_t0, "host clock at start"
        errors: tuple[type[BaseException], ...] = (*self._errors, AttributeError)
        try:
            stamp = task.triggers.start_trigger.timestamp_val
        except errors as exc:
            log.warning("no start-trigger timestamp (%s); onsets from the host clock", exc)
            return software_t0, "host clock at start"
        # The stamp is host wall time: map it to the session clock through one paired reading.
        return self.clock.now() - (time.time() - stamp.timestamp()), "hardware start trigger"

    def _zero_or_recover(self, wd_device: str) -> None:
        try:
            self._write_zero()
        except self._errors as exc:
            # NI's documented recovery for a device left locked by an expired watchdog (a host
            # killed mid-session): reset the device, then write 0 V again.
            log.error("NI-DAQmx could not write 0 V (%s); resetting %s", first_line(exc), wd_device)
            self._nidaqmx.system.Device(wd_device).reset_device()
            self._write_zero()
            self.notices.append(
                f"{wd_device} could not be written at opening ({first_line(exc)}): it was reset "
                "(NI-DAQmx Device.reset_device, the documented recovery after an expired "
                "watchdog) and both outputs set to 0 V"
            )

    def _timed_task(self, rate_hz: float, n_samples: int) -> tuple[Any, float]:
        """A new task on both lines, timed and committed; returns it and the rate read back."""
        constants = self._nidaqmx.constants
        task = self._nidaqmx.Task()
        try:
            self._add_channels(task)
            task.timing.cfg_samp_clk_timing(
                rate=rate_hz,
                sample_mode=constants.AcquisitionType.FINITE,
                samps_per_chan=n_samples,
            )
            if enable_start_timestamp(self._nidaqmx, task):
                self._stamped = {id(task)}  # only the current trial's task matters
                self.onset_source = "hardware start trigger"
            # Committing reserves the lines and programs the hardware now, so start() is only
            # the trigger, and it makes the driver settle the rate it will really use.
            task.control(constants.TaskMode.TASK_COMMIT)
            actual = float(task.timing.samp_clk_rate)
        except BaseException:
            with contextlib.suppress(*self._errors):
                task.close()
            raise
        return task, actual

    def _probe_rate(self) -> float:
        wanted = self.config.waveform.sample_rate_hz
        task, actual = self._timed_task(wanted, 2)
        task.close()
        if abs(actual - wanted) > RATE_TOLERANCE * wanted:
            log.warning(
                "NI-DAQmx runs %s at %.9g S/s, not the configured %.9g S/s; trials are "
                "synthesized at the driver's rate",
                "+".join(self.lines.values()),
                actual,
                wanted,
            )
        else:
            log.info("NI-DAQmx sample rate %.9g S/s", actual)
        return actual

    def _committed_task(self, n_samples: int) -> Any:
        with self._lock:
            self._aborted = False
            task, actual = self._timed_task(self.sample_rate_hz, n_samples)
            self._active = task
        if abs(actual - self.sample_rate_hz) > RATE_TOLERANCE * self.sample_rate_hz:
            # The buffer was synthesized at the opening rate: played at another one, every
            # carrier frequency and duration would be off.
            raise DeviceError(
                f"NI-DAQmx changed the sample rate from {self.sample_rate_hz:.9g} to "
                f"{actual:.9g} S/s for this trial; not played. Check that no other task shares "
                "the chassis timing engine, then resume"
            )
        return task

    def _ensure_not_aborted(self, task: Any) -> None:
        if self._active is not task:
            raise DeviceError("trial stopped (STOP); outputs set to 0 V")

    def _wait_done(self, task: Any, timeout_s: float) -> None:
        # Poll instead of wait_until_done(): a blocking driver call would hold off Python's
        # signal handlers (SIGTERM, Ctrl-C) until the whole trial had played.
        deadline = time.monotonic() + timeout_s
        while True:
            with self._lock:
                self._ensure_not_aborted(task)
                if task.is_task_done():
                    return
            if time.monotonic() > deadline:
                raise DeviceError(
                    f"NI-DAQmx trial did not finish within {timeout_s:.1f} s; outputs set to "
                    "0 V. Check the chassis, then `masking-lab resume LOG`"
                )
            time.sleep(POLL_S)

    def _write_zero(self) -> None:
        task = self._nidaqmx.Task()
        try:
            self._add_channels(task)
            task.write([0.0, 0.0], auto_start=True)
        finally:
            with contextlib.suppress(*self._errors):
                task.close()

    def _zero_quietly(self) -> None:
        # The error that got us here is what gets raised; zeroing is best effort on top.
        with contextlib.suppress(Exception):
            self.stop()
