"""STAND-IN ``nidaqmx.system.System`` (not NI's driver)."""

from __future__ import annotations

import collections

from nidaqmx import _standin

DriverVersion = collections.namedtuple(
    "DriverVersion", ["major_version", "minor_version", "update_version"]
)


class System:
    """The local NI-DAQmx installation."""

    @staticmethod
    def local() -> System:
        _standin.state().check("System.local")
        return System()

    @property
    def driver_version(self) -> DriverVersion:
        return DriverVersion(*_standin.state().driver_version)
