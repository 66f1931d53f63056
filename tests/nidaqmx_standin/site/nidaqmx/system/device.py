"""STAND-IN ``nidaqmx.system.Device``: product type, serial number, chassis (not NI's driver)."""

from __future__ import annotations

from nidaqmx import _standin
from nidaqmx.errors import DaqError

BAD_DEVICE = -200220
NOT_SUPPORTED = -200197


class Device:
    """A device by name, as NI MAX lists it."""

    def __init__(self, name: str, **_: object) -> None:
        self._name = name

    def _unit(self, attribute: str) -> _standin.Unit:
        st = _standin.state()
        st.record("Device." + attribute, self._name)
        st.check("Device." + attribute)
        unit = st.units.get(self._name)
        if unit is None:
            raise DaqError(
                f"Device identifier is invalid.\nDevice Specified: {self._name}", BAD_DEVICE
            )
        return unit

    @property
    def name(self) -> str:
        return self._name

    def reset_device(self) -> None:
        """NI's documented recovery: abort the device's tasks, back to the initial state (an
        expired watchdog is cleared; its lines stay at their expiration states, 0 V here)."""
        unit = self._unit("reset_device")
        unit.expired = False
        st = _standin.state()
        for other in st.units.values():
            if other.chassis == self._name:
                other.expired = False
        for wd in st.watchdogs:
            if wd.device == self._name:
                wd.expired = False

    @property
    def product_type(self) -> str:
        return self._unit("product_type").product_type

    @property
    def dev_serial_num(self) -> int:
        return self._unit("dev_serial_num").serial

    @property
    def is_simulated(self) -> bool:
        return self._unit("is_simulated").simulated

    @property
    def compact_daq_chassis_device(self) -> Device:
        unit = self._unit("compact_daq_chassis_device")
        if unit.chassis is None:
            raise DaqError("Specified property is not supported by the device.", NOT_SUPPORTED)
        return Device(unit.chassis)
