"""Open a device from a spec string: ``sim``, ``emulator``, ``serial:PORT`` or ``nidaq[:DEV]``."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from masking_lab.core.clock import Clock, RealClock
from masking_lab.core.errors import DeviceError
from masking_lab.device.base import Device
from masking_lab.device.config import DeviceConfig, load_device_config

SPECS = (
    "sim, emulator, serial:PORT (e.g. serial:/dev/ttyACM0), serial:auto (find the board by its "
    "HELLO) or nidaq[:DEVICE]"
)


def open_device(
    spec: str,
    config: DeviceConfig | str | Path | None = None,
    clock: Clock | None = None,
    *,
    seed: int = 0,
    emulator_options: Mapping[str, Any] | None = None,
) -> Device:
    """Open the device named by ``spec``; close it with ``device.close()``.

    Parameters
    ----------
    spec : str
        ``sim`` (in-process), ``emulator`` (firmware emulator on a fresh pseudo-terminal in a
        background thread, reached through pyserial like real hardware; closed with the device),
        ``serial:PORT`` (a board, or an emulator started with ``masking-lab emulate``),
        ``serial:auto`` (the first serial port whose device answers a masking-lab HELLO) or
        ``nidaq`` / ``nidaq:DEVICE`` (NI-DAQmx analog outputs).
    config : DeviceConfig or path, optional
        Device config (reference rig if None).
    clock : Clock, optional
        Session clock (RealClock if None). A virtual clock makes the emulator run in virtual time.
    seed : int
        Seed of simulated onset lateness (sim and emulator).
    emulator_options : mapping, optional
        Extra keyword arguments for :class:`~masking_lab.device.emulator.FirmwareEmulator`
        (``watchdog_s``, ``boot_delay_s``, ...).

    Raises
    ------
    DeviceError
        Unknown spec, or the device cannot be opened (the message says why and what to do).
    """
    cfg = config if isinstance(config, DeviceConfig) else load_device_config(config)
    clk: Clock = clock or RealClock()
    kind, _, arg = spec.strip().partition(":")
    if kind == "sim" and not arg:
        from masking_lab.device.sim import SimDevice

        return SimDevice(cfg, clk, seed=seed)
    if kind == "emulator" and not arg:
        from masking_lab.device.emulator import FirmwareEmulator
        from masking_lab.device.serial_device import SerialDevice

        options = dict(emulator_options or {})
        options.setdefault("seed", seed)
        options.setdefault("virtual_time", clk.virtual)
        options.update(_converter_options(FirmwareEmulator, cfg, options))
        emulator = FirmwareEmulator(cfg, **options).start()
        try:
            device = SerialDevice(
                emulator.port, cfg, clk, backend="emulator", on_close=emulator.close
            )
        except BaseException:
            emulator.close()
            raise
        device.emulator = emulator
        return device
    if kind == "serial" and arg:
        from masking_lab.device.serial_device import SerialDevice

        if arg == "auto":
            from masking_lab.device.discovery import find_board

            arg = find_board(cfg)
        return SerialDevice(arg, cfg, clk, backend="serial")
    if kind == "nidaq":
        from masking_lab.device.nidaq import NidaqDevice

        return NidaqDevice(cfg, clk, device_name=arg or None)
    raise DeviceError(f"unknown device {spec!r}: choose {SPECS}")


def _converter_options(
    emulator: Any, cfg: DeviceConfig, given: Mapping[str, Any]
) -> dict[str, Any]:
    """The rig config's converter as emulator options, for an emulator that takes them as
    arguments (``bits``, ``fsv_v``, ``att_db``) rather than reading the config: so the emulated
    board's HELLO matches the config the host checks it against."""
    import inspect

    conv = cfg.converters.get("EV")
    params = inspect.signature(emulator).parameters
    if conv is None or "att_db" not in params:
        return {}
    wanted = {
        "bits": conv.bits,
        "fsv_v": conv.full_scale_v,
        "att_db": tuple(int(a) if float(a).is_integer() else a for a in conv.steps_db),
    }
    return {k: v for k, v in wanted.items() if k in params and k not in given}
