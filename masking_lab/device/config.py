"""Device (rig) configuration: safety limits, serial link, waveform, NI-DAQmx wiring, display.

A config is a YAML file checked against ``data_schema/device_config.schema.json``; the reference
rig is ``protocols/devices/default.yaml``. :func:`load_device_config` returns an immutable
:class:`DeviceConfig`; every problem is a :class:`~masking_lab.core.errors.DeviceConfigError` naming
the file, the key path and its line.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from masking_lab.device.base import DeviceLimits
from masking_lab.core.errors import DeviceConfigError, ProtocolError
from masking_lab.formats.protocol import _describe, _safe_yaml, _where
from masking_lab.formats.resources import shipped
from masking_lab.formats.schemas import key_path, load_schema, schema_errors

DEFAULT_CONFIG = "protocols/devices/default.yaml"


@dataclass(frozen=True)
class SerialSettings:
    """Serial-link settings (all times in s).

    Attributes
    ----------
    baud_rate : int
        Baud rate (ignored by pseudo-terminals).
    reply_timeout_s : float
        Wait for the OK/ERR reply to a command, s.
    done_margin_s : float
        Wait past a trial's planned end for the device's DONE report, s.
    boot_timeout_s : float
        Keep retrying HELLO this long while a board boots after the port opens, s.
    hello_retry_s : float
        Interval between HELLO retries, s.
    max_garbage_lines : int
        Unframed or corrupted lines discarded in a row before the link is declared faulty.
    watchdog_s : float
        Firmware watchdog period, s (0 disables; used by the emulator).
    """

    baud_rate: int = 115200
    reply_timeout_s: float = 0.5
    done_margin_s: float = 1.0
    boot_timeout_s: float = 4.0
    hello_retry_s: float = 0.25
    max_garbage_lines: int = 16
    watchdog_s: float = 0.5


@dataclass(frozen=True)
class WaveformSettings:
    """Waveform synthesis: ``sample_rate_hz`` in Hz, raised-cosine ``ramp_s`` in s."""

    sample_rate_hz: float = 20000.0
    ramp_s: float = 0.01


@dataclass(frozen=True)
class NidaqSettings:
    """NI-DAQmx wiring: device name and the analog output line of each channel."""

    device: str = "cDAQ1Mod1"
    ao_channels: Mapping[str, str] = field(default_factory=lambda: {"EV": "ao0", "MV": "ao1"})


@dataclass(frozen=True)
class EmulatorSettings:
    """What the firmware emulator reports, and its simulated onset lateness SD in s."""

    model: str = "ML-EMU-2CH"
    serial_number: str = "EMU-0001"
    onset_jitter_s: float = 50e-6


@dataclass(frozen=True)
class DisplaySettings:
    """The participant's monitor: visible width in mm and resolution in pixels."""

    width_mm: float
    width_px: int
    height_px: int
    screen: int = 0


@dataclass(frozen=True)
class DeviceConfig:
    """A validated device config.

    Attributes
    ----------
    path : str
        File it came from (or a description of where it came from).
    name : str
        Rig name.
    limits : DeviceLimits
        Per-channel peak drive limits, V.
    max_level_db_sl : Mapping[str, float]
        Per-channel masker-level limits for protocol validation, dB SL (may be empty).
    serial, waveform, nidaq, emulator : settings
        Section settings (defaults where the file omits a section).
    display : DisplaySettings or None
        Participant monitor, if configured.
    """

    path: str
    name: str
    limits: DeviceLimits
    max_level_db_sl: Mapping[str, float] = field(default_factory=dict)
    serial: SerialSettings = field(default_factory=SerialSettings)
    waveform: WaveformSettings = field(default_factory=WaveformSettings)
    nidaq: NidaqSettings = field(default_factory=NidaqSettings)
    emulator: EmulatorSettings = field(default_factory=EmulatorSettings)
    display: DisplaySettings | None = None


def load_device_config(path: str | Path | None = None) -> DeviceConfig:
    """Load and validate a device config; the reference rig when ``path`` is None.

    Raises
    ------
    DeviceConfigError
        If the file cannot be read, is not YAML, or breaks the schema; the message names the
        file, the key path and its line, and says what to do.
    """
    if path is None:
        ref = shipped("protocols", "devices/default.yaml")
        return parse_device_config(ref.read_text(encoding="utf-8"), DEFAULT_CONFIG)
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise DeviceConfigError(
            str(p), "", f"cannot read the device config ({exc.strerror or exc}); check the path"
        ) from exc
    return parse_device_config(text, str(p))


def parse_device_config(text: str, source: str) -> DeviceConfig:
    """:func:`load_device_config` on text already read; ``source`` names it in messages."""
    try:
        data, lines = _safe_yaml(text, source)
    except ProtocolError as exc:
        raise DeviceConfigError(exc.file, exc.where, exc.message) from exc
    if not isinstance(data, dict):
        raise DeviceConfigError(
            source, "line 1", "a device config is a YAML mapping (key: value lines) at the top"
        )
    problems = list(_schema_problems(data, lines))
    if problems:
        where, message = problems[0]
        more = "; ".join(f"{w}: {m}" for w, m in problems[1:4])
        raise DeviceConfigError(source, where, message + (f"\n  also: {more}" if more else ""))
    return _build(data, source)


def default_device_config() -> DeviceConfig:
    """The reference rig's config (``protocols/devices/default.yaml``)."""
    return load_device_config(None)


def _schema_problems(data: Any, lines: Mapping[str, int]):
    schema = load_schema("device_config")
    for err in schema_errors(data, "device_config"):
        path = key_path(err)
        if err.validator == "additionalProperties":
            known = list(err.schema.get("properties", {}))
            for key in [k for k in err.instance if k not in known]:
                child = f"{path}.{key}" if path != "(top level)" else str(key)
                yield _where(child, lines), f"unknown key {key!r}; known keys: {', '.join(known)}"
            continue
        if err.validator == "required":
            missing = err.message.split("'")[1] if "'" in err.message else err.message
            yield _where(path, lines), f"missing required key {missing!r}"
            continue
        if err.validator == "const" and path == "schema_version":
            yield (
                _where(path, lines),
                f"schema_version must be 1 (the device config format this version of "
                f"masking-lab reads), got {err.instance!r}",
            )
            continue
        if err.validator == "maximum" and path.endswith("max_drive_v"):
            yield (
                _where(path, lines),
                f"{err.instance!r} V is above {err.validator_value} V, the largest drive any "
                "back-end can produce; lower it to what your amplifier input is rated for",
            )
            continue
        yield _where(path, lines), _describe(err, schema)


def _build(data: Mapping[str, Any], source: str) -> DeviceConfig:
    channels = data["channels"]
    limits = DeviceLimits({ch: float(channels[ch]["max_drive_v"]) for ch in ("EV", "MV")})
    db_sl = {
        ch: float(spec["max_level_db_sl"])
        for ch, spec in channels.items()
        if spec.get("max_level_db_sl") is not None
    }
    serial = SerialSettings(**data.get("serial", {}))
    if 0 < serial.boot_timeout_s < serial.hello_retry_s:
        raise DeviceConfigError(
            source,
            "serial.hello_retry_s",
            "must not exceed serial.boot_timeout_s (the host would give up before one retry)",
        )
    waveform = WaveformSettings(**{k: float(v) for k, v in data.get("waveform", {}).items()})
    nidaq_data = dict(data.get("nidaq", {}))
    if "ao_channels" in nidaq_data:
        nidaq_data["ao_channels"] = dict(nidaq_data["ao_channels"])
        if nidaq_data["ao_channels"]["EV"] == nidaq_data["ao_channels"]["MV"]:
            raise DeviceConfigError(
                source, "nidaq.ao_channels", "EV and MV must be wired to different outputs"
            )
    display = DisplaySettings(**data["display"]) if data.get("display") else None
    return DeviceConfig(
        path=source,
        name=str(data.get("name", Path(source).stem)),
        limits=limits,
        max_level_db_sl=db_sl,
        serial=serial,
        waveform=waveform,
        nidaq=NidaqSettings(**nidaq_data),
        emulator=EmulatorSettings(**data.get("emulator", {})),
        display=display,
    )
