"""STAND-IN ``nidaqmx.system.watchdog``: WatchdogTask and AOExpirationState (not NI's driver).

On a unit with ``has_watchdog`` False, ``cfg_watchdog_ao_expir_states`` fails with a driver
error, as a chassis without a watchdog timer would. ``expire()`` lets a test play the
hardware's part: the configured lines go to their expiration states.
"""

from __future__ import annotations

import collections
from typing import Any

from nidaqmx import _standin
from nidaqmx.constants import WDTTaskAction
from nidaqmx.errors import DaqError

AOExpirationState = collections.namedtuple(
    "AOExpirationState", ["physical_channel", "expiration_state", "output_type"]
)

NOT_SUPPORTED = -200452


class WatchdogTask:
    """A watchdog timer task on one device."""

    def __init__(self, device_name: str, task_name: str = "", timeout: float = 10, **_: Any):
        st = _standin.state()
        st.check("WatchdogTask")
        self.device = device_name
        self._timeout = timeout
        self.states: list[AOExpirationState] = []
        self.running = False
        self.expired = False
        self.closed = False
        self.resets = 0
        st.record("WatchdogTask", device_name, timeout)
        st.watchdogs.append(self)

    def cfg_watchdog_ao_expir_states(self, expiration_states: list[Any]) -> list[Any]:
        st = _standin.state()
        st.record(
            "cfg_watchdog_ao_expir_states",
            [
                (e.physical_channel, e.expiration_state, e.output_type.name)
                for e in expiration_states
            ],
        )
        st.check("cfg_watchdog_ao_expir_states")
        unit = st.units.get(self.device)
        if unit is None or not unit.has_watchdog:
            raise DaqError(
                "Specified property is not supported by the device or is not applicable to the "
                f"task.\nDevice: {self.device}",
                NOT_SUPPORTED,
            )
        self.states = list(expiration_states)
        return self.states

    @property
    def expir_trig_trig_on_network_conn_loss(self) -> bool:
        return False

    @expir_trig_trig_on_network_conn_loss.setter
    def expir_trig_trig_on_network_conn_loss(self, value: bool) -> None:
        st = _standin.state()
        st.record("expir_trig_trig_on_network_conn_loss", value)
        # A USB chassis has no network link to lose.
        raise DaqError("Specified property is not supported by the device.", NOT_SUPPORTED)

    def start(self) -> None:
        _standin.state().record("watchdog.start", self.device)
        self.running = True

    def reset_timer(self) -> None:
        self.resets += 1  # not recorded: it runs from a thread every quarter period

    def _control_watchdog_task(self, action: WDTTaskAction) -> None:
        if action is WDTTaskAction.CLEAR_EXPIRATION:
            self.expired = False

    def clear_expiration(self) -> None:
        st = _standin.state()
        st.record("watchdog.clear_expiration", self.device)
        st.check("watchdog.clear_expiration")
        self._control_watchdog_task(WDTTaskAction.CLEAR_EXPIRATION)
        if self.device in st.units:
            st.units[self.device].expired = False

    def expire(self) -> None:
        """Play the hardware: the timer ran out, lines go to their expiration states."""
        st = _standin.state()
        self.expired = True
        if self.device in st.units:
            st.units[self.device].expired = True
        for e in self.states:
            st.levels[e.physical_channel] = float(e.expiration_state)

    def stop(self) -> None:
        _standin.state().record("watchdog.stop", self.device)
        self.running = False

    def close(self) -> None:
        _standin.state().record("watchdog.close", self.device)
        self.closed = True
