"""Clocks: real time at the rig, virtual time in simulation.

The runner never calls ``time`` directly; it asks a :class:`Clock`. A :class:`VirtualClock` makes a
simulated ten-participant study run in seconds while logging the same onsets a rig would.
"""

from __future__ import annotations

import time
from typing import Protocol


class Clock(Protocol):
    """Monotonic seconds since an arbitrary origin, and a way to wait until a time."""

    virtual: bool

    def now(self) -> float:
        """Current time in s."""
        ...

    def sleep_until(self, t: float) -> None:
        """Block (real) or jump (virtual) until time ``t`` in s; never goes backwards."""
        ...


class RealClock:
    """Wall-clock monotonic time (``time.perf_counter``), s since construction.

    Examples
    --------
    >>> clock = RealClock()
    >>> clock.sleep_until(clock.now() + 0.005)
    >>> clock.now() >= 0.005
    True
    """

    virtual = False

    def __init__(self) -> None:
        self._origin = time.perf_counter()

    def now(self) -> float:
        return time.perf_counter() - self._origin

    def sleep_until(self, t: float) -> None:
        # Sleep coarsely, then spin the last millisecond for onset precision.
        while True:
            remaining = t - self.now()
            if remaining <= 0:
                return
            if remaining > 0.002:
                time.sleep(remaining - 0.001)


class VirtualClock:
    """Simulated time that advances only when asked to; starts at ``start`` s.

    Examples
    --------
    >>> clock = VirtualClock()
    >>> clock.sleep_until(2.5)
    >>> clock.sleep_until(1.0)  # never goes backwards
    >>> clock.now()
    2.5
    """

    virtual = True

    def __init__(self, start: float = 0.0) -> None:
        self._t = float(start)

    def now(self) -> float:
        return self._t

    def sleep_until(self, t: float) -> None:
        self._t = max(self._t, float(t))
