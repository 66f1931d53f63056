"""STAND-IN ``nidaqmx.Task``: records calls and models line levels (not NI's driver)."""

from __future__ import annotations

import datetime as dt
import time
from typing import Any

import numpy as np

from nidaqmx import _standin
from nidaqmx.constants import AcquisitionType, TaskMode
from nidaqmx.errors import DaqError

INVALID_TASK = -200088
RESERVED = -50103
BAD_DEVICE = -200220
NOT_SUPPORTED = -200452
WATCHDOG_EXPIRED = -1  # the stand-in's own code: the message is what tests read


class _AOChannel:
    """One analog output channel: its idle output behaviour (where the device has one)."""

    def __init__(self, line: str) -> None:
        self.line = line
        self._idle: Any = None

    @property
    def ao_idle_output_behavior(self) -> Any:
        return self._idle

    @ao_idle_output_behavior.setter
    def ao_idle_output_behavior(self, value: Any) -> None:
        st = _standin.state()
        st.record("ao_idle_output_behavior", self.line, value.name)
        unit = st.unit_of(self.line)
        if unit is None or not unit.idle_zero:
            raise DaqError(
                "Specified property is not supported by the device or is not applicable to the "
                f"task.\nProperty: AO.IdleOutputBehavior\nChannel: {self.line}",
                NOT_SUPPORTED,
            )
        self._idle = value


class _StartTrigger:
    """The start trigger: a hardware timestamp of when generation began, where supported."""

    def __init__(self, task: Task) -> None:
        self._task = task
        self._enabled = False
        self.timestamp_timescale: Any = None

    @property
    def timestamp_enable(self) -> bool:
        return self._enabled

    @timestamp_enable.setter
    def timestamp_enable(self, value: bool) -> None:
        st = _standin.state()
        st.record("start_trigger.timestamp_enable", self._task.id, bool(value))
        units = [st.unit_of(line) for line in self._task.lines]
        if value and not all(u is not None and u.start_timestamp for u in units):
            raise DaqError(
                "Specified property is not supported by the device or is not applicable to the "
                "task.\nProperty: StartTrig.TimestampEnable",
                NOT_SUPPORTED,
            )
        self._enabled = bool(value)

    @property
    def timestamp_val(self) -> dt.datetime:
        st = _standin.state()
        st.record("start_trigger.timestamp_val", self._task.id)
        if not self._enabled or self._task.started_at is None:
            raise DaqError("Timestamp is not available.", NOT_SUPPORTED)
        return dt.datetime.fromtimestamp(self._task.started_at + st.timestamp_lag_s, dt.UTC)


class _Triggers:
    def __init__(self, task: Task) -> None:
        self.start_trigger = _StartTrigger(task)


class _Channels:
    def __init__(self, task: Task) -> None:
        self._task = task

    def add_ao_voltage_chan(
        self,
        physical_channel: str,
        name_to_assign_to_channel: str = "",
        min_val: float = -10.0,
        max_val: float = 10.0,
        **_: Any,
    ) -> _AOChannel:
        st = _standin.state()
        self._task._alive()
        st.record("add_ao_voltage_chan", self._task.id, physical_channel, min_val, max_val)
        st.check("add_ao_voltage_chan")
        device = physical_channel.split("/")[0]
        if device not in st.units:
            raise DaqError(f"Device identifier is invalid.\nDevice Specified: {device}", BAD_DEVICE)
        self._task.lines.append(physical_channel)
        self._task.ranges.append((min_val, max_val))
        return _AOChannel(physical_channel)


class _Timing:
    def __init__(self, task: Task) -> None:
        self._task = task

    def cfg_samp_clk_timing(
        self,
        rate: float,
        source: str = "",
        active_edge: Any = None,
        sample_mode: AcquisitionType = AcquisitionType.CONTINUOUS,
        samps_per_chan: int = 1000,
    ) -> None:
        st = _standin.state()
        self._task._alive()
        st.record("cfg_samp_clk_timing", self._task.id, rate, sample_mode.name, samps_per_chan)
        st.check("cfg_samp_clk_timing")
        self._task.requested_rate = rate
        self._task.samps_per_chan = samps_per_chan
        self._task.timed = True

    @property
    def samp_clk_rate(self) -> float:
        st = _standin.state()
        self._task._alive()
        rate = st.coerce_rate(self._task.requested_rate)
        if st.coerce_rate_after is not None and self._task.id > st.coerce_rate_after:
            rate *= 1.001
        st.record("samp_clk_rate", self._task.id, rate)
        return rate


class Task:
    """A task on some analog output lines."""

    def __init__(self, new_task_name: str = "", **_: Any) -> None:
        st = _standin.state()
        st.check("Task")
        self.id = st.next_id
        st.next_id += 1
        self.lines: list[str] = []
        self.ranges: list[tuple[float, float]] = []
        self.requested_rate = 1000.0
        self.samps_per_chan = 0
        self.timed = False
        self.buffer: np.ndarray | None = None
        self.running = False
        self.polls = 0
        self.closed = False
        self.ao_channels = _Channels(self)
        self.timing = _Timing(self)
        self.triggers = _Triggers(self)
        self.started_at: float | None = None
        st.record("Task", self.id)

    def __enter__(self) -> Task:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _alive(self) -> None:
        if self.closed:
            raise DaqError("Task specified is invalid or does not exist.", INVALID_TASK)

    def _reserve(self) -> None:
        st = _standin.state()
        for line in self.lines:
            owner = st.reserved.get(line)
            if owner is not None and owner != self.id:
                raise DaqError(
                    f"The specified resource is reserved.\nResource: {line}, held by task {owner}",
                    RESERVED,
                )
        for line in self.lines:
            st.reserved[line] = self.id

    def control(self, action: TaskMode) -> None:
        st = _standin.state()
        self._alive()
        st.record("control", self.id, action.name)
        st.check("control")
        if action is TaskMode.TASK_COMMIT:
            self._reserve()

    def write(self, data: Any, auto_start: bool = False, timeout: float = 10.0) -> int:
        st = _standin.state()
        self._alive()
        arr = np.asarray(data, dtype=float)
        st.record("write", self.id, list(arr.shape), bool(auto_start))
        st.check("write")
        if arr.ndim == 1:
            arr = arr.reshape(len(self.lines), -1)
        for row, (rmin, rmax) in zip(arr, self.ranges, strict=True):
            if row.min() < rmin or row.max() > rmax:
                raise DaqError("Data exceeds the channel's voltage range.", -200561)
        self.buffer = arr
        for line in self.lines:
            locked = st.expired_unit(line)
            if locked is not None and auto_start:
                raise DaqError(
                    f"The watchdog timer of {locked} expired; its outputs are held in their "
                    "expiration states until the expiration is cleared or the device is reset.",
                    WATCHDOG_EXPIRED,
                )
        if auto_start and not self.timed:
            self._reserve()
            for line, row in zip(self.lines, arr, strict=True):
                st.levels[line] = float(row[-1])
        return arr.shape[-1]

    def start(self) -> None:
        st = _standin.state()
        self._alive()
        st.record("start", self.id)
        st.check("start")
        self._reserve()
        self.running = True
        self.polls = 0
        self.started_at = time.time()
        assert self.buffer is not None
        for line, row in zip(self.lines, self.buffer, strict=True):
            # While it plays the line swings up to the buffer's peak.
            st.levels[line] = float(np.max(np.abs(row)))

    def is_task_done(self) -> bool:
        st = _standin.state()
        self._alive()
        self.polls += 1
        st.record("is_task_done", self.id)
        if st.on_poll is not None:
            st.on_poll(self, self.polls)
        self._alive()
        if self.running and self.polls >= st.polls_until_done:
            self._finish()
        return not self.running

    def wait_until_done(self, timeout: float = 10.0) -> None:
        st = _standin.state()
        self._alive()
        st.record("wait_until_done", self.id, timeout)
        self._finish()

    def _finish(self) -> None:
        st = _standin.state()
        if self.running and self.buffer is not None:
            for line, row in zip(self.lines, self.buffer, strict=True):
                st.levels[line] = float(row[-1])
        self.running = False

    def stop(self) -> None:
        st = _standin.state()
        self._alive()
        st.record("stop", self.id, "mid-buffer" if self.running else "done")
        # An aborted generation leaves the line at whatever it was putting out (NI 9264).
        self.running = False

    def close(self) -> None:
        st = _standin.state()
        if self.closed:
            return
        st.record("close", self.id)
        self.closed = True
        self.running = False
        for line in self.lines:
            if st.reserved.get(line) == self.id:
                del st.reserved[line]
