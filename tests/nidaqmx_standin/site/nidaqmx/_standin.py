"""State of the nidaqmx STAND-IN: recorded calls, simulated devices, and knobs for tests.

Not NI's driver. The model of the hardware is deliberately crude: a line holds a level; a
write with auto_start sets it; a timed task that starts holds the buffer's peak until it is
done (then the buffer's last sample); a task stopped mid-buffer leaves the level where it was,
like an NI 9264. Lines are reserved from commit (or an auto-started write) until close.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

IS_STANDIN = True

NOT_FOUND = (
    "Could not find an installation of NI-DAQmx. Please ensure that NI-DAQmx is installed on "
    "this machine or contact National Instruments for support."
)


@dataclass
class Unit:
    """A simulated module or chassis."""

    product_type: str
    serial: int
    chassis: str | None = None
    simulated: bool = False
    has_watchdog: bool = False
    # Capabilities the back-end asks for where the device allows them (the stand-in's model:
    # an X Series board has idle-output control and start-trigger timestamps, the cDAQ
    # modules here have neither; a real device may differ, the back-end handles both).
    idle_zero: bool = False
    start_timestamp: bool = False
    # A watchdog expired and nobody cleared it (a killed host): writes to its lines fail
    # until the expiration is cleared or the device is reset (reset_device).
    expired: bool = False


def _default_units() -> dict[str, Unit]:
    # The paper's rig: two NI 9264 in one CompactDAQ chassis (here a cDAQ-9174).
    return {
        "cDAQ1": Unit("cDAQ-9174", 0x01A2B3C4, has_watchdog=True),
        "cDAQ1Mod1": Unit("NI 9264", 0x01D4E5F6, chassis="cDAQ1"),
        "cDAQ1Mod2": Unit("NI 9264", 0x01D4E5F7, chassis="cDAQ1"),
        "Dev1": Unit(
            "USB-6343", 0x0180C0DE, has_watchdog=False, idle_zero=True, start_timestamp=True
        ),
    }


def _nine_264_rate(requested: float) -> float:
    # Sample clock from a 12.8 MHz timebase divided by an integer, as on cDAQ chassis.
    return 12.8e6 / max(1, round(12.8e6 / requested))


@dataclass
class State:
    """Everything a test can set or inspect."""

    driver_installed: bool = True
    units: dict[str, Unit] = field(default_factory=_default_units)
    driver_version: tuple[int, int, int] = (23, 5, 0)
    coerce_rate: Callable[[float], float] = _nine_264_rate
    # A later trial's task reads back a different rate than the probe (hardware change).
    coerce_rate_after: int | None = None
    polls_until_done: int = 3
    on_poll: Callable[[Any, int], None] | None = None
    fail_on: dict[str, Exception] = field(default_factory=dict)
    calls: list[tuple[Any, ...]] = field(default_factory=list)
    levels: dict[str, float] = field(default_factory=dict)
    reserved: dict[str, int] = field(default_factory=dict)
    watchdogs: list[Any] = field(default_factory=list)
    next_id: int = 1
    # Host time (time.time()) the hardware stamps a start trigger with, minus when start()
    # ran: lets a test tell a hardware timestamp from a software reading.
    timestamp_lag_s: float = 0.0

    def record(self, *call: Any) -> None:
        """Append a call; with NIDAQMX_STANDIN_TRACE set, also write it to that file."""
        self.calls.append(call)
        path = os.environ.get("NIDAQMX_STANDIN_TRACE")
        if path:
            with open(path, "a", encoding="utf-8") as fh:
                fh.write(
                    json.dumps([str(c) if not isinstance(c, (int, float)) else c for c in call])
                    + "\n"
                )

    def ops(self, *names: str) -> list[tuple[Any, ...]]:
        """Recorded calls whose operation is one of ``names`` (all calls if none given)."""
        return [c for c in self.calls if not names or c[0] in names]

    def op_names(self) -> list[str]:
        """Just the operation names, in order."""
        return [c[0] for c in self.calls]

    def check(self, op: str) -> None:
        """Raise what a test armed for ``op``, or DaqNotFoundError without a driver."""
        from nidaqmx.errors import DaqNotFoundError

        if not self.driver_installed:
            raise DaqNotFoundError(NOT_FOUND)
        if op in self.fail_on:
            raise self.fail_on.pop(op)

    def unit_of(self, line: str) -> Unit | None:
        """The unit a physical channel belongs to, or the chassis holding it."""
        return self.units.get(line.split("/")[0])

    def expired_unit(self, line: str) -> str | None:
        """Name of the expired watchdog device that locks ``line`` (module or its chassis)."""
        name = line.split("/")[0]
        unit = self.units.get(name)
        for candidate in (name, unit.chassis if unit else None):
            if candidate and self.units.get(candidate) and self.units[candidate].expired:
                return candidate
        return None


STATE = State()


def reset(**settings: Any) -> State:
    """A fresh state with ``settings`` applied; also becomes the module's ``STATE``."""
    global STATE
    STATE = State(**settings)
    return STATE


def state() -> State:
    """The current state (modules look it up at call time, so reset() takes effect)."""
    return STATE
