"""NI-DAQmx helpers of the nidaq back-end: driver errors, hardware identity and the watchdog.

Everything here takes the imported ``nidaqmx`` module as an argument, so the back-end imports
NI's package only when it is opened and the tests can hand in a stand-in with the same API
surface (``tests/nidaqmx_standin``; a recording stand-in, not NI's driver).
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from masking_lab.core.errors import DeviceError

log = logging.getLogger("masking_lab.device")

INSTALL_HINT = (
    "the nidaq back-end needs NI's `nidaqmx` Python package and the NI-DAQmx driver: "
    "pip install 'masking-lab[nidaq]' and install NI-DAQmx from ni.com, or choose another "
    "device (--device serial:PORT, emulator or sim)"
)


def driver_errors(nidaqmx: Any) -> tuple[type[BaseException], ...]:
    """The exception types the NI-DAQmx package raises when the driver or hardware fails.

    ``nidaqmx.errors.Error`` is the base of ``DaqError`` (a driver status code),
    ``DaqNotFoundError`` (no driver installed) and ``DaqNotSupportedError`` (platform); older
    releases have ``DaqError`` only. ``OSError`` covers a driver library that exists but
    cannot be loaded.

    Examples
    --------
    >>> import types
    >>> errors = types.SimpleNamespace(Error=RuntimeError)
    >>> driver_errors(types.SimpleNamespace(errors=errors))
    (<class 'RuntimeError'>, <class 'OSError'>)
    """
    errors = getattr(nidaqmx, "errors", None)
    base = getattr(errors, "Error", None) or getattr(errors, "DaqError", None)
    return (base, OSError) if isinstance(base, type) else (OSError,)


def _driver_missing(nidaqmx: Any, exc: BaseException) -> bool:
    errors = getattr(nidaqmx, "errors", None)
    kinds = tuple(
        k
        for k in (getattr(errors, n, None) for n in ("DaqNotFoundError", "DaqNotSupportedError"))
        if isinstance(k, type)
    )
    return isinstance(exc, (*kinds, OSError))


def first_line(exc: BaseException) -> str:
    """The first non-empty line of an exception message (NI's messages run to many lines)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    code = getattr(exc, "error_code", None)
    text = lines[0] if lines else type(exc).__name__
    return f"{text} [NI-DAQmx error {code}]" if code is not None else text


def as_device_error(nidaqmx: Any, exc: BaseException, doing: str, config_path: str) -> DeviceError:
    """A :class:`DeviceError` saying what failed and what to do, for a driver exception.

    Parameters
    ----------
    nidaqmx : module
        The imported ``nidaqmx`` package (or stand-in).
    exc : BaseException
        What the driver raised.
    doing : str
        What the back-end was doing, e.g. ``"opening cDAQ1Mod1/ao0"``.
    config_path : str
        Device config that names the channels, for the message.

    Examples
    --------
    >>> import types
    >>> fake = types.SimpleNamespace(errors=types.SimpleNamespace())
    >>> err = as_device_error(fake, OSError("libnidaqmx.so: not found"), "opening Dev1", "rig.yaml")
    >>> "NI-DAQmx driver is not installed" in str(err)
    True
    """
    if _driver_missing(nidaqmx, exc):
        return DeviceError(
            f"NI-DAQmx driver is not installed or cannot be loaded ({first_line(exc)}) while "
            f"{doing}; {INSTALL_HINT}"
        )
    return DeviceError(
        f"NI-DAQmx failed while {doing}: {first_line(exc)}. Check that the chassis is powered and "
        f"connected and that nidaq.channels in {config_path} match the names NI MAX shows, "
        "or choose another device (--device serial:PORT, emulator or sim)"
    )


@dataclass(frozen=True)
class HardwareInfo:
    """What NI-DAQmx reports about the modules behind the configured lines.

    Attributes
    ----------
    modules : list[dict]
        One entry per module: ``name``, ``product_type``, ``serial_number`` (hex, as NI MAX
        shows it), ``simulated`` (a simulated device in NI MAX) and ``lines`` it carries.
    chassis : dict or None
        ``name``, ``product_type`` and ``serial_number`` of the CompactDAQ chassis, if any.
    driver_version : str
        NI-DAQmx driver version, ``"unknown"`` if the driver does not say.
    """

    modules: list[dict[str, Any]]
    chassis: dict[str, Any] | None
    driver_version: str

    @property
    def model(self) -> str:
        """One line for the log header's device model, e.g. ``NI 9264 cDAQ1Mod1/ao0 (EV) + ...``."""
        parts = []
        for m in self.modules:
            sim = " simulated" if m["simulated"] else ""
            parts.append(f"{m['product_type']}{sim} {', '.join(m['lines'])}")
        text = " + ".join(parts)
        if self.chassis is not None:
            text += f" in {self.chassis['product_type']} {self.chassis['name']}"
        return text

    @property
    def serial_number(self) -> str:
        """Serial numbers of every module (and the chassis), e.g. ``cDAQ1Mod1=1A2B3C4D, ...``."""
        units = [*self.modules, *([self.chassis] if self.chassis else [])]
        return ", ".join(f"{u['name']}={u['serial_number']}" for u in units)


def _serial(device: Any) -> str:
    with contextlib.suppress(Exception):
        return f"{int(device.dev_serial_num):X}"
    return "unknown"


def probe_hardware(nidaqmx: Any, lines: Mapping[str, str]) -> HardwareInfo:
    """Read product type, serial number and chassis of every module behind ``lines``.

    Parameters
    ----------
    nidaqmx : module
        The imported ``nidaqmx`` package (or stand-in).
    lines : Mapping[str, str]
        Physical channel per output channel, e.g. ``{"EV": "cDAQ1Mod1/ao0", ...}``.

    Raises
    ------
    Exception
        Whatever the driver raises for a missing driver or an unknown device name; the caller
        turns it into a DeviceError with :func:`as_device_error`.

    Examples
    --------
    >>> lines = {"EV": "cDAQ1Mod1/ao0", "MV": "cDAQ1Mod2/ao0"}
    >>> info = probe_hardware(nidaqmx, lines)  # doctest: +SKIP
    >>> info.model  # doctest: +SKIP
    'NI 9264 cDAQ1Mod1/ao0 (EV) + NI 9264 cDAQ1Mod2/ao0 (MV) in cDAQ-9174 cDAQ1'
    """
    names: dict[str, list[str]] = {}
    for ch, line in lines.items():
        names.setdefault(line.split("/")[0], []).append(f"{line} ({ch})")
    modules, chassis = [], None
    for name, carried in names.items():
        dev = nidaqmx.system.Device(name)
        simulated = False
        with contextlib.suppress(Exception):
            simulated = bool(dev.is_simulated)
        modules.append(
            {
                "name": name,
                "product_type": str(dev.product_type),
                "serial_number": _serial(dev),
                "simulated": simulated,
                "lines": carried,
            }
        )
        # Outside a CompactDAQ chassis the attribute does not exist and the driver says so.
        with contextlib.suppress(Exception):
            box = dev.compact_daq_chassis_device
            if chassis is None and box is not None and str(box.name):
                chassis = {
                    "name": str(box.name),
                    "product_type": str(box.product_type),
                    "serial_number": _serial(box),
                }
    version = "unknown"
    with contextlib.suppress(Exception):
        v = nidaqmx.system.System.local().driver_version
        version = f"{v.major_version}.{v.minor_version}.{v.update_version}"
    return HardwareInfo(modules=modules, chassis=chassis, driver_version=version)


@dataclass
class Watchdog:
    """The chassis watchdog: both outputs go to 0 V if the host stops resetting it.

    :meth:`start` creates a ``nidaqmx.system.watchdog.WatchdogTask`` on ``device``, configures
    0 V expiration states for ``lines`` (``cfg_watchdog_ao_expir_states``, i.e.
    DAQmxCfgWatchdogAOExpirStates), starts it and resets its timer from a daemon thread every
    quarter period. When the process dies, nothing resets it any more and the hardware zeroes the
    outputs within ``timeout_s``. A chassis without a watchdog raises a driver error: the
    back-end records that in :attr:`status` and goes on without one.

    Attributes
    ----------
    status : str
        ``"0 V after 1 s on cDAQ1"``, ``"disabled (nidaq.watchdog_s = 0)"`` or
        ``"unsupported on cDAQ1: <driver message>"``; recorded in the device identity.
    expirations : int
        How many times the watchdog was found expired (and cleared) before a trial.

    Examples
    --------
    >>> wd = Watchdog(nidaqmx, "cDAQ1", ["cDAQ1Mod1/ao0", "cDAQ1Mod2/ao0"], 1.0)  # doctest: +SKIP
    >>> wd.start(); wd.status  # doctest: +SKIP
    '0 V after 1 s on cDAQ1'
    """

    nidaqmx: Any
    device: str
    lines: list[str]
    timeout_s: float
    status: str = "not started"
    expirations: int = 0
    _task: Any = None
    _stop: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def start(self) -> None:
        """Create, configure and start the watchdog task (or record why there is none)."""
        if self.timeout_s <= 0:
            self.status = "disabled (nidaq.watchdog_s = 0)"
            log.warning("NI-DAQmx watchdog disabled by the device config")
            return
        wd_mod = self.nidaqmx.system.watchdog
        constants = self.nidaqmx.constants
        errors = driver_errors(self.nidaqmx)
        task = None
        try:
            task = wd_mod.WatchdogTask(self.device, timeout=self.timeout_s)
            task.cfg_watchdog_ao_expir_states(
                [
                    wd_mod.AOExpirationState(
                        physical_channel=line,
                        expiration_state=0.0,
                        output_type=constants.WatchdogAOExpirState.VOLTAGE,
                    )
                    for line in self.lines
                ]
            )
            # Network chassis can also expire when the link to the host drops; USB chassis
            # refuse the attribute, which is fine.
            with contextlib.suppress(*errors, AttributeError):
                task.expir_trig_trig_on_network_conn_loss = True
            task.start()
        except errors as exc:
            if task is not None:
                with contextlib.suppress(*errors):
                    task.close()
            if _driver_missing(self.nidaqmx, exc):
                raise
            self.status = f"unsupported on {self.device}: {first_line(exc)}"
            log.warning("NI-DAQmx watchdog %s; outputs are zeroed by the host only", self.status)
            return
        self._task = task
        self.status = f"0 V after {self.timeout_s:g} s on {self.device}"
        self._thread = threading.Thread(target=self._kick, name="nidaq-watchdog", daemon=True)
        self._thread.start()
        log.info("NI-DAQmx watchdog armed: %s", self.status)

    @property
    def armed(self) -> bool:
        """True while a watchdog task is running."""
        return self._task is not None

    def _kick(self) -> None:
        errors = driver_errors(self.nidaqmx)
        while not self._stop.wait(self.timeout_s / 4):
            with self._lock:
                if self._task is None:
                    return
                try:
                    self._task.reset_timer()
                except errors as exc:  # the next trial's check reports the expiry
                    log.error("NI-DAQmx watchdog reset failed: %s", first_line(exc))

    def clear_if_expired(self) -> bool:
        """Clear an expired watchdog so the outputs can be used again; True if it had expired.

        An expiry while the process lives means the host stalled longer than ``timeout_s``;
        the outputs were already at 0 V, so the next trial may play. NI's documented recovery
        is ``WatchdogTask.clear_expiration`` (DAQmx Control Watchdog Task, Clear Expiration);
        if that fails, the device is reset (``Device.reset_device``) and the watchdog re-armed.
        """
        errors = driver_errors(self.nidaqmx)
        with self._lock:
            if self._task is None or not bool(self._task.expired):
                return False
            try:
                self._task.clear_expiration()
                cleared = True
            except errors as exc:
                log.error("clearing the expired watchdog failed (%s); resetting", first_line(exc))
                cleared = False
        if not cleared:
            self.close()
            self.nidaqmx.system.Device(self.device).reset_device()
            self._stop = threading.Event()
            self.start()
        self.expirations += 1
        log.error("NI-DAQmx watchdog had expired (host stalled > %g s); cleared", self.timeout_s)
        return True

    def close(self) -> None:
        """Stop resetting the timer and release the watchdog task. Idempotent."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=max(1.0, self.timeout_s))
        with self._lock:
            task, self._task = self._task, None
        if task is None:
            return
        errors = driver_errors(self.nidaqmx)
        with contextlib.suppress(*errors):
            task.stop()
        with contextlib.suppress(*errors):
            task.close()


def watchdog_notice(status: str) -> str:
    """What running without an analog-output watchdog means, said at session start.

    Examples
    --------
    >>> watchdog_notice("unsupported on Dev1: not supported")[:40]
    'no analog-output watchdog (unsupported o'
    """
    return (
        f"no analog-output watchdog ({status}; X Series boards have none): if this program is "
        "killed, an output keeps its last sample until the device is reset. Every trial's "
        "buffer ends on 0 V, so between trials that is 0 V; a kill mid-trial leaves the "
        "stimulus's instantaneous value on the output. Keep the amplifier's enable or the "
        "E-stop within reach"
    )


def set_idle_zero(nidaqmx: Any, channel: Any, status: str) -> str:
    """Ask ``channel`` to idle at 0 V between tasks; return the status for the log.

    Devices without the property (many C Series modules) refuse it: then the buffers' closing
    0 V sample is what holds the line at 0 V.
    """
    behaviour = getattr(nidaqmx.constants, "AOIdleOutputBehavior", None)
    if behaviour is None or channel is None:
        return "not supported by this nidaqmx"
    errors: tuple[type[BaseException], ...] = (*driver_errors(nidaqmx), AttributeError)
    try:
        channel.ao_idle_output_behavior = behaviour.ZERO_VOLTS
    except errors as exc:
        if status.startswith("unsupported"):
            return status
        return f"unsupported ({first_line(exc)}); buffers end on 0 V"
    return "0 V" if not status.startswith("unsupported") else status


def enable_start_timestamp(nidaqmx: Any, task: Any) -> bool:
    """Ask ``task`` to stamp its start trigger in host time; True where the device can."""
    timescale = getattr(nidaqmx.constants, "Timescale", None)
    errors: tuple[type[BaseException], ...] = (*driver_errors(nidaqmx), AttributeError)
    try:
        trigger = task.triggers.start_trigger
        trigger.timestamp_enable = True
        if timescale is not None:
            trigger.timestamp_timescale = timescale.USE_HOST
    except errors:
        return False
    return True


def watchdog_device(hardware: HardwareInfo, configured: str | None, lines: Iterable[str]) -> str:
    """The device whose watchdog guards the outputs: configured, else chassis, else EV module.

    Examples
    --------
    >>> hw = HardwareInfo([], {"name": "cDAQ1", "product_type": "cDAQ-9174",
    ...                        "serial_number": "1"}, "23.5.0")
    >>> watchdog_device(hw, None, ["cDAQ1Mod1/ao0"])
    'cDAQ1'
    >>> watchdog_device(hw, "cDAQ2", ["cDAQ1Mod1/ao0"])
    'cDAQ2'
    """
    if configured:
        return configured
    if hardware.chassis is not None:
        return str(hardware.chassis["name"])
    return next(iter(lines)).split("/")[0]
