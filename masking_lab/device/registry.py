"""The one device registry: the device-spec grammar and the back-end each spec opens.

A spec is ``NAME`` or ``NAME:ARG`` (``sim``, ``emulator``, ``serial:PORT``, ``serial:auto``,
``nidaq[:DEVICE]``). Every parser of a spec (``--device``, a resumed log's header) calls
:func:`parse_spec`, so there is one grammar and one error message. A back-end is its module in
``device/`` plus one :class:`Backend` row passed to :func:`register` below; what it can do beyond
the :class:`~masking_lab.device.base.Device` interface is declared in its :class:`Capabilities`,
which the device suite (``tests/test_device_suite.py``) checks both ways.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from masking_lab.core.errors import MaskingLabError

if TYPE_CHECKING:  # kept out of the import: checking a spec loads no device code
    from masking_lab.core.clock import Clock
    from masking_lab.device.base import Device
    from masking_lab.device.config import DeviceConfig


@dataclass(frozen=True)
class Capabilities:
    """What a back-end does beyond what every :class:`~masking_lab.device.base.Device` does.

    Every back-end refuses over-limit drive, zeroes both outputs on stop and close, and reports
    onsets. A False here is a stated absence, not an untested gap: the device suite asserts it.

    Attributes
    ----------
    streaming : bool
        ``set_amplitude`` plays a stream (False: it raises DeviceError and nothing plays).
    watchdog : bool
        The outputs go to 0 V by themselves when the host goes quiet while one is on.
    faults : bool
        The device can fault (link, interlock, driver); a fault zeroes both outputs, raises a
        DeviceError and is recorded in the device's ``fault_log``; the next trial plays.
    virtual_time : bool
        The back-end can run on a :class:`~masking_lab.core.clock.VirtualClock`.

    Examples
    --------
    >>> Capabilities(streaming=True, watchdog=False, faults=False, virtual_time=True).watchdog
    False
    """

    streaming: bool
    watchdog: bool
    faults: bool
    virtual_time: bool


#: ``(arg, config, clock, options) -> Device``; ``options`` holds ``seed`` and back-end extras.
Opener = Callable[[str, "DeviceConfig", "Clock", Mapping[str, Any]], "Device"]


@dataclass(frozen=True)
class Backend:
    """One registered back-end.

    Attributes
    ----------
    name : str
        The spec's ``NAME`` part.
    arg : {"none", "optional", "required"}
        Whether the spec takes ``:ARG``.
    form : str
        How the spec is written, for the error message (e.g. ``serial:PORT``).
    opener : callable or str
        ``(arg, config, clock, options) -> Device``, or ``"module:function"`` naming one (imported
        on first use, so the core runs without the back-end's drivers installed).
    capabilities : Capabilities
        What the back-end declares beyond the interface.

    Examples
    --------
    >>> BACKENDS["nidaq"].capabilities.streaming
    False
    """

    name: str
    arg: Literal["none", "optional", "required"]
    form: str
    opener: Opener | str
    capabilities: Capabilities

    def open(
        self, arg: str, config: DeviceConfig, clock: Clock, options: Mapping[str, Any]
    ) -> Device:
        """Open the device (see :attr:`opener`)."""
        opener = self.opener
        if isinstance(opener, str):
            module, _, name = opener.partition(":")
            opener = getattr(importlib.import_module(module), name)
        return opener(arg, config, clock, options)


BACKENDS: dict[str, Backend] = {}


def register(backend: Backend) -> Backend:
    """Add ``backend`` to :data:`BACKENDS` (its name must be new); return it.

    Examples
    --------
    >>> "sim" in BACKENDS
    True
    """
    if backend.name in BACKENDS or ":" in backend.name:
        raise MaskingLabError(f"device back-end name {backend.name!r} is taken or has a ':'")
    BACKENDS[backend.name] = backend
    return backend


def accepted_forms() -> str:
    """The spec forms the registry accepts, for messages.

    Examples
    --------
    >>> accepted_forms().startswith("sim, emulator, serial:PORT")
    True
    """
    forms = [b.form for b in BACKENDS.values()]
    return ", ".join(forms[:-1]) + " or " + forms[-1] if len(forms) > 1 else "".join(forms)


def parse_spec(spec: str) -> tuple[Backend, str]:
    """The back-end ``spec`` names and its argument (``""`` if none).

    Raises
    ------
    MaskingLabError
        Unknown name, an argument where none is taken (or none where one is needed), or
        control characters; the message names the spec and the accepted forms.

    Examples
    --------
    >>> backend, arg = parse_spec(" serial:/dev/ttyACM0 ")
    >>> backend.name, arg
    ('serial', '/dev/ttyACM0')
    """
    name, colon, arg = spec.strip().partition(":")
    backend = BACKENDS.get(name)
    if (
        backend is None
        or any(ord(c) < 0x20 for c in arg)
        or (colon and (backend.arg == "none" or not arg))
        or (not colon and backend.arg == "required")
    ):
        raise MaskingLabError(f"--device {spec[:60]!a}: choose {accepted_forms()}")
    return backend, arg


def check_device_spec(spec: str) -> str:
    """The device spec without surrounding blanks, if the registry accepts it.

    Raises
    ------
    MaskingLabError
        See :func:`parse_spec`.

    Examples
    --------
    >>> check_device_spec(" sim ")
    'sim'
    """
    parse_spec(spec)
    return spec.strip()


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
        ``nidaq`` / ``nidaq:DEVICE`` (NI-DAQmx analog outputs); see :data:`BACKENDS`.
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
    MaskingLabError
        Unknown spec (:func:`parse_spec`).
    DeviceError
        The device cannot be opened (the message says why and what to do).

    Examples
    --------
    >>> from masking_lab.core.clock import VirtualClock
    >>> dev = open_device("sim", clock=VirtualClock())
    >>> dev.identity.backend
    'sim'
    >>> dev.close()
    """
    from masking_lab.core.clock import RealClock
    from masking_lab.device.config import DeviceConfig, load_device_config

    backend, arg = parse_spec(spec)
    cfg = config if isinstance(config, DeviceConfig) else load_device_config(config)
    return backend.open(arg, cfg, clock or RealClock(), {"seed": seed, **(emulator_options or {})})


# ------------------------------------------------------------------ the built-in back-ends


def _open_sim(arg: str, config: DeviceConfig, clock: Clock, options: Mapping[str, Any]) -> Device:
    from masking_lab.device.sim import SimDevice

    return SimDevice(config, clock, seed=options["seed"])


def _open_emulator(
    arg: str, config: DeviceConfig, clock: Clock, options: Mapping[str, Any]
) -> Device:
    from masking_lab.device.emulator import FirmwareEmulator
    from masking_lab.device.serial_device import SerialDevice

    given = {"virtual_time": clock.virtual, **options}
    conv = config.converters.get("EV")
    if conv is not None:  # the rig's converter, so the emulated HELLO matches the config
        att = tuple(int(a) if float(a).is_integer() else a for a in conv.steps_db)
        given = {"bits": conv.bits, "fsv_v": conv.full_scale_v, "att_db": att, **given}
    emulator = FirmwareEmulator(config, **given).start()
    try:
        device = SerialDevice(
            emulator.port, config, clock, backend="emulator", on_close=emulator.close
        )
    except BaseException:
        emulator.close()
        raise
    device.emulator = emulator
    return device


def _open_serial(
    arg: str, config: DeviceConfig, clock: Clock, options: Mapping[str, Any]
) -> Device:
    from masking_lab.device.serial_device import SerialDevice

    if arg == "auto":
        from masking_lab.device.discovery import find_board

        arg = find_board(config)
    return SerialDevice(arg, config, clock, backend="serial")


def _open_nidaq(arg: str, config: DeviceConfig, clock: Clock, options: Mapping[str, Any]) -> Device:
    from masking_lab.device.nidaq import NidaqDevice

    return NidaqDevice(config, clock, device_name=arg or None)


# What each declares (tests/test_device_suite.py checks every claim, the absences too).
_SIM = Capabilities(streaming=True, watchdog=False, faults=False, virtual_time=True)
_FIRMWARE = Capabilities(streaming=True, watchdog=True, faults=True, virtual_time=True)
_NIDAQ = Capabilities(streaming=False, watchdog=True, faults=True, virtual_time=False)
_SERIAL_FORM = "serial:PORT (e.g. serial:/dev/ttyACM0), serial:auto (find the board by its HELLO)"
register(Backend("sim", "none", "sim", _open_sim, _SIM))
register(Backend("emulator", "none", "emulator", _open_emulator, _FIRMWARE))
register(Backend("serial", "required", _SERIAL_FORM, _open_serial, _FIRMWARE))
register(Backend("nidaq", "optional", "nidaq[:DEVICE]", _open_nidaq, _NIDAQ))
