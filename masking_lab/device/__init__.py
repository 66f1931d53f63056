"""Tactile output devices behind one small interface (:class:`~masking_lab.device.base.Device`).

Back-ends: ``serial:PORT`` (our line protocol over pyserial, to the firmware in ``firmware/``),
``emulator`` (the firmware's Python twin on a real pseudo-terminal), ``sim`` (in-process) and
``nidaq`` (optional, NI-DAQmx, the paper's rig).

- ``base``: the interface; ``registry``: device spec → back-end; ``config``: rig configs and the
  rig record; ``rig_limits``, ``safety``: drive limits and zeroed outputs.
- ``protocol``: wire frames and CRC; ``serial_device`` (+ ``serial_faults``), ``emulator``
  (+ ``emulator_state``), ``nidaq`` (+ ``nidaq_tasks``), ``sim``: the back-ends.
"""

from masking_lab.core.exports import lazy_exports

_HOME = {
    "Device": "base",
    "DeviceConfig": "config",
    "DeviceIdentity": "base",
    "DeviceLimits": "base",
    "FirmwareEmulator": "emulator",
    "SerialDevice": "serial_device",
    "SimDevice": "sim",
    "load_device_config": "config",
    "open_device": "registry",
}
__all__ = sorted(_HOME)
__getattr__, __dir__ = lazy_exports(__name__, _HOME)
