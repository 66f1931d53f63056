"""STAND-IN ``nidaqmx.system`` (not NI's driver)."""

from nidaqmx.system import watchdog
from nidaqmx.system.device import Device
from nidaqmx.system.system import System
from nidaqmx.system.watchdog import AOExpirationState, WatchdogTask

__all__ = ["AOExpirationState", "Device", "System", "WatchdogTask", "watchdog"]
