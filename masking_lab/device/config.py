"""Device (rig) configuration: safety limits, serial link, waveform, NI-DAQmx wiring, display.

A config is a YAML file checked against ``data_schema/device_config.schema.json``; the reference
rig is ``protocols/devices/default.yaml``. :func:`load_device_config` returns an immutable
:class:`DeviceConfig`; every problem is a :class:`~masking_lab.core.errors.DeviceConfigError` naming
the file, the key path and its line.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from masking_lab.core.errors import DeviceConfigError, ProtocolError
from masking_lab.device.base import DeviceLimits
from masking_lab.device.levels_range import DEFAULT_MIN_LSB, Converter
from masking_lab.formats.protocol import _describe, _safe_yaml, _where
from masking_lab.formats.reader import decode_utf8, excerpt, read_limited
from masking_lab.formats.resources import shipped
from masking_lab.formats.schemas import key_path, load_schema, schema_errors

DEFAULT_CONFIG = "protocols/devices/default.yaml"
BOARD_MAX_V = 10.0  # the NI 9264 and the firmware boards put out at most ±10 V


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
    virtual_hang_guard_s : float
        Virtual time only: how long the host waits for any reply before it declares the device
        hung, s. A hang guard, not a timing assumption (load never trips it); a closed link is
        noticed at once.
    """

    baud_rate: int = 115200
    reply_timeout_s: float = 0.5
    done_margin_s: float = 1.0
    boot_timeout_s: float = 4.0
    hello_retry_s: float = 0.25
    max_garbage_lines: int = 16
    watchdog_s: float = 0.5
    virtual_hang_guard_s: float = 120.0


@dataclass(frozen=True)
class WaveformSettings:
    """Waveform synthesis: ``sample_rate_hz`` in Hz, raised-cosine ``ramp_s`` in s."""

    sample_rate_hz: float = 20000.0
    ramp_s: float = 0.01


@dataclass(frozen=True)
class NidaqSettings:
    """NI-DAQmx wiring and hardware safe state.

    Attributes
    ----------
    channels : Mapping[str, str]
        Physical channel of each output, ``{"EV": "cDAQ1Mod1/ao0", "MV": "cDAQ1Mod2/ao0"}``
        (the paper's rig used two NI 9264 modules, one per channel).
    watchdog_s : float
        Timeout of the chassis watchdog that sets both outputs to 0 V if the host stops
        resetting it, s (0 disables it).
    watchdog_device : str or None
        Device that owns the watchdog timer; None means the CompactDAQ chassis of the EV module
        (or the EV module itself outside a chassis).
    """

    channels: Mapping[str, str] = field(
        default_factory=lambda: {"EV": "cDAQ1Mod1/ao0", "MV": "cDAQ1Mod2/ao0"}
    )
    watchdog_s: float = 1.0
    watchdog_device: str | None = None


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
class Amplifier:
    """The amplifier between the board output and the transducer of one channel.

    Attributes
    ----------
    model : str
        Maker and model, e.g. ``"Texas Instruments DRV8662"``.
    gain_db : float or None
        Nominal voltage gain, dB (20·log10 of V out per V in); None if not known.
    max_input_v : float or None
        Largest peak input voltage the amplifier takes at this gain, V; when given, the channel's
        ``max_drive_v`` × attenuator ratio may not exceed it.
    setting : str
        How the gain is set on the board (jumpers, pins, knob), free text.
    """

    model: str
    gain_db: float | None = None
    max_input_v: float | None = None
    setting: str = ""


@dataclass(frozen=True)
class Attenuator:
    """A passive attenuator between the board output and the amplifier input.

    Attributes
    ----------
    model : str
        What it is, e.g. ``"10:1 resistive divider"``.
    ratio : float
        Volts at the amplifier input per volt at the board output, in (0, 1].
    """

    model: str
    ratio: float


@dataclass(frozen=True)
class ChannelRig:
    """What one channel's output drives, for the session log.

    Attributes
    ----------
    amplifier : Amplifier or None
        The amplifier, if recorded.
    transducer : str
        The actuator or panel the amplifier drives (maker, model, how many).
    attenuator : Attenuator or None
        Optional attenuator before the amplifier input.
    measured_gain : Mapping[float, float]
        Carrier frequency, Hz → measured peak volts at the transducer per peak volt at the board
        output (attenuator and amplifier included), V/V.
    """

    amplifier: Amplifier | None = None
    transducer: str = ""
    attenuator: Attenuator | None = None
    measured_gain: Mapping[float, float] = field(default_factory=dict)


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
    rig : Mapping[str, ChannelRig]
        Amplifier, attenuator, transducer and measured gain per channel (``"EV"``, ``"MV"``).
    converters : Mapping[str, Converter]
        Converter bits, full scale and attenuator steps per channel (only channels that give
        ``converter``; a channel without one is not checked for resolution).
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
    rig: Mapping[str, ChannelRig] = field(default_factory=dict)
    converters: Mapping[str, Converter] = field(default_factory=dict)

    def rig_record(self) -> dict[str, Any]:
        """The rig as a plain JSON-able mapping, for the session log header.

        Returns
        -------
        dict
            ``{"name", "config", "channels": {"EV": {...}, "MV": {...}}}``; each channel has
            ``max_drive_v`` (peak V at the board output), ``amplifier`` (``model``, ``gain_db``,
            ``gain_v_per_v``, ``max_input_v``, ``setting``) or None, ``attenuator`` (``model``,
            ``ratio``) or None, ``transducer`` and ``measured_gain`` (a list of
            ``{"frequency_hz", "v_out_per_v_in"}`` sorted by frequency; empty if not measured)
            and ``converter`` (``bits``, ``full_scale_v``, ``attenuator_steps_db``,
            ``min_lsb``, ``linear_codes``) or None.

        Examples
        --------
        >>> cfg = default_device_config()
        >>> record = cfg.rig_record()
        >>> record["channels"]["MV"]["amplifier"]["model"]
        'Texas Instruments DRV8662'
        >>> import json; _ = json.dumps(record)  # plain data, ready for the log header
        """
        channels = {
            ch: _channel_record(self.rig.get(ch, ChannelRig()), self.limits.max_drive_v[ch])
            for ch in ("EV", "MV")
        }
        for ch, record in channels.items():
            conv = self.converters.get(ch)
            record["converter"] = (
                None
                if conv is None
                else {
                    "bits": conv.bits,
                    "full_scale_v": conv.full_scale_v,
                    "attenuator_steps_db": list(conv.steps_db),
                    "min_lsb": conv.min_lsb,
                }
            )
            if conv is not None and conv.linear_codes is not None:
                record["converter"]["linear_codes"] = conv.linear_codes
        return {"name": self.name, "config": self.path, "channels": channels}


def _channel_record(rig: ChannelRig, max_drive_v: float) -> dict[str, Any]:
    amp = rig.amplifier
    return {
        "max_drive_v": float(max_drive_v),
        "amplifier": None
        if amp is None
        else {
            "model": amp.model,
            "gain_db": amp.gain_db,
            "gain_v_per_v": None if amp.gain_db is None else round(10 ** (amp.gain_db / 20), 4),
            "max_input_v": amp.max_input_v,
            "setting": amp.setting,
        },
        "attenuator": None
        if rig.attenuator is None
        else {"model": rig.attenuator.model, "ratio": rig.attenuator.ratio},
        "transducer": rig.transducer,
        "measured_gain": [
            {"frequency_hz": f, "v_out_per_v_in": g} for f, g in sorted(rig.measured_gain.items())
        ],
    }


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
    raw = read_limited(p, what="device config", error=DeviceConfigError)
    return parse_device_config(decode_utf8(raw, str(p), error=DeviceConfigError), str(p))


def parse_device_config(text: str, source: str) -> DeviceConfig:
    """:func:`load_device_config` on text already read; ``source`` names it in messages."""
    return _parse_device_config(text, source)


# Pure in (text, source) and the result is frozen, so one parse serves every caller: a session
# reads its config four times (open, header, level checks, rig limits) and a demo worker runs
# many sessions. A file that changes is new text, so it is parsed (and checked) again; a refused
# text raises every time (exceptions are not cached).
@functools.lru_cache(maxsize=16)
def _parse_device_config(text: str, source: str) -> DeviceConfig:
    try:
        data, lines = _safe_yaml(text, source)
    except ProtocolError as exc:
        raise DeviceConfigError(exc.file, exc.where, exc.message) from exc
    if not isinstance(data, dict):
        raise DeviceConfigError(
            source, "line 1", "a device config is a YAML mapping (key: value lines) at the top"
        )
    # YAML reads .nan and .inf as floats, and JSON Schema bounds let NaN through (every
    # comparison with it is false): refuse them before anything reads a limit.
    for path, value in _non_finite(data, ""):
        raise DeviceConfigError(
            source,
            _where(path, lines),
            f"{value!r} is not a finite number; write a plain number (e.g. 1.8)",
        )
    problems = list(_schema_problems(data, lines))
    if problems:
        where, message = problems[0]
        more = "; ".join(f"{w}: {m}" for w, m in problems[1:4])
        raise DeviceConfigError(source, where, message + (f"\n  also: {more}" if more else ""))
    return _build(data, source, lines)


def default_device_config() -> DeviceConfig:
    """The reference rig's config (``protocols/devices/default.yaml``)."""
    return load_device_config(None)


def _non_finite(value: Any, path: str) -> Iterator[tuple[str, float]]:
    if isinstance(value, float) and not math.isfinite(value):
        yield path or "(top level)", value
    elif isinstance(value, Mapping):
        for key, item in value.items():
            yield from _non_finite(item, f"{path}.{key}" if path else str(key))
    elif isinstance(value, list):
        for i, item in enumerate(value):
            yield from _non_finite(item, f"{path}[{i}]")


def _schema_problems(data: Any, lines: Mapping[str, int]) -> Iterator[tuple[str, str]]:
    schema = load_schema("device_config")
    for err in schema_errors(data, "device_config"):
        path = key_path(err)
        if err.validator == "additionalProperties":
            # additionalProperties reports an object schema and an object instance
            err_schema = err.schema if isinstance(err.schema, Mapping) else {}
            instance = err.instance if isinstance(err.instance, Mapping) else {}
            known = list(err_schema.get("properties", {}))
            for key in [k for k in instance if k not in known]:
                child = f"{path}.{key}" if path != "(top level)" else str(key)
                if path == "nidaq" and key in ("device", "ao_channels"):
                    yield (
                        _where(child, lines),
                        (
                            f"nidaq.{key} was replaced by nidaq.channels, one physical channel per "
                            "output, e.g. channels: {EV: cDAQ1Mod1/ao0, MV: cDAQ1Mod2/ao0}"
                        ),
                    )
                    continue
                yield (
                    _where(child, lines),
                    f"unknown key {excerpt(key)}; known keys: {', '.join(known)}",
                )
            continue
        if err.validator == "required":
            missing = err.message.split("'")[1] if "'" in err.message else err.message
            yield _where(path, lines), f"missing required key {missing!r}"
            continue
        if err.validator == "const" and path == "schema_version":
            yield (
                _where(path, lines),
                f"schema_version must be 1 (the device config format this version of "
                f"masking-lab reads), got {excerpt(err.instance)}",
            )
            continue
        if err.validator == "maximum" and path.endswith("max_drive_v"):
            yield (
                _where(path, lines),
                f"{excerpt(err.instance)} V is above {err.validator_value} V, the largest drive "
                "any back-end can produce; lower it to what your amplifier input is rated for",
            )
            continue
        if path.endswith("attenuator.ratio") and err.validator in ("maximum", "exclusiveMinimum"):
            yield (
                _where(path, lines),
                f"ratio {excerpt(err.instance)} is not in (0, 1]: it is the volts at the amplifier "
                "input per volt at the board output; a stage that amplifies belongs under "
                "amplifier",
            )
            continue
        if err.validator == "pattern" and path.startswith("nidaq.channels"):
            yield (
                _where(path, lines),
                f"{excerpt(err.instance)} is not an analog output: write DEVICE/aoN as NI MAX "
                "names it, e.g. cDAQ1Mod1/ao0",
            )
            continue
        yield _where(path, lines), _describe(err, schema)


def _build(data: Mapping[str, Any], source: str, lines: Mapping[str, int]) -> DeviceConfig:
    channels = data["channels"]
    rig = {ch: _channel_rig(channels[ch], f"channels.{ch}", source, lines) for ch in ("EV", "MV")}
    limits = DeviceLimits(
        {ch: _max_drive_v(channels[ch], rig[ch], f"channels.{ch}", source, lines) for ch in rig}
    )
    db_sl = {
        ch: float(spec["max_level_db_sl"])
        for ch, spec in channels.items()
        if spec.get("max_level_db_sl") is not None
    }
    serial = SerialSettings(**data.get("serial", {}))
    if 0 < serial.boot_timeout_s < serial.hello_retry_s:
        raise DeviceConfigError(
            source,
            _where("serial.hello_retry_s", lines),
            "must not exceed serial.boot_timeout_s (the host would give up before one retry)",
        )
    waveform = WaveformSettings(**{k: float(v) for k, v in data.get("waveform", {}).items()})
    nidaq_data = dict(data.get("nidaq", {}))
    if "channels" in nidaq_data:
        nidaq_data["channels"] = dict(nidaq_data["channels"])
        ev, mv = (nidaq_data["channels"][ch] for ch in ("EV", "MV"))
        if ev.strip().lower() == mv.strip().lower():
            raise DeviceConfigError(
                source,
                _where("nidaq.channels", lines),
                f"EV and MV are both wired to {excerpt(ev)}; give each channel its own analog "
                "output",
            )
    display = DisplaySettings(**data["display"]) if data.get("display") else None
    converters = {
        ch: _converter(channels[ch]["converter"], f"channels.{ch}.converter", source, lines)
        for ch in ("EV", "MV")
        if "converter" in channels[ch]
    }
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
        rig=rig,
        converters=converters,
    )


def _converter(
    spec: Mapping[str, Any], path: str, source: str, lines: Mapping[str, int]
) -> Converter:
    steps = tuple(float(s) for s in spec.get("attenuator_steps_db", [0]))
    if steps[0] != 0 or any(b <= a for a, b in itertools.pairwise(steps)):
        raise DeviceConfigError(
            source,
            _where(f"{path}.attenuator_steps_db", lines),
            f"{list(steps)} must start at 0 dB and ascend (e.g. [0, 20, 40]); write [0] for a "
            "channel without a switchable attenuator",
        )
    return Converter(
        bits=int(spec["bits"]),
        full_scale_v=float(spec["full_scale_v"]),
        steps_db=steps,
        min_lsb=float(spec.get("min_lsb", DEFAULT_MIN_LSB)),
        linear_codes=int(spec["linear_codes"]) if "linear_codes" in spec else None,
    )


def _channel_rig(
    spec: Mapping[str, Any], path: str, source: str, lines: Mapping[str, int]
) -> ChannelRig:
    amp = spec.get("amplifier")
    att = spec.get("attenuator")
    gains: dict[float, float] = {}
    for i, point in enumerate(spec.get("measured_gain", [])):
        freq = float(point["frequency_hz"])
        if freq in gains:
            raise DeviceConfigError(
                source,
                _where(f"{path}.measured_gain[{i}].frequency_hz", lines),
                f"{freq:g} Hz is measured twice; keep one value per carrier frequency",
            )
        gains[freq] = float(point["v_out_per_v_in"])
    return ChannelRig(
        amplifier=None
        if amp is None
        else Amplifier(
            model=str(amp["model"]),
            gain_db=None if amp.get("gain_db") is None else float(amp["gain_db"]),
            max_input_v=None if amp.get("max_input_v") is None else float(amp["max_input_v"]),
            setting=str(amp.get("setting", "")),
        ),
        transducer=str(spec.get("transducer", "")),
        attenuator=None if att is None else Attenuator(str(att["model"]), float(att["ratio"])),
        measured_gain=gains,
    )


def _max_drive_v(
    spec: Mapping[str, Any], rig: ChannelRig, path: str, source: str, lines: Mapping[str, int]
) -> float:
    """The channel's board-output limit, V: given, or derived from the amplifier's input limit.

    An attenuator of ratio r lets the board put out 1/r times the amplifier's input limit; the
    result never exceeds the ±10 V of the analog outputs.
    """
    ratio = rig.attenuator.ratio if rig.attenuator is not None else 1.0
    amp = rig.amplifier
    amp_max = amp.max_input_v if amp is not None else None
    if "max_drive_v" not in spec:
        if amp_max is None:
            raise DeviceConfigError(
                source,
                _where(path, lines),
                "missing required key 'max_drive_v' (peak V at the board output); or give "
                "amplifier.max_input_v to derive it",
            )
        return min(amp_max / ratio, BOARD_MAX_V)
    limit = float(spec["max_drive_v"])
    # A relative tolerance keeps 1.8 V through a 0.5 divider (3.6 V) from failing on rounding.
    if amp is not None and amp_max is not None and limit * ratio > amp_max * (1 + 1e-9):
        through = f" × attenuator ratio {ratio:g} = {limit * ratio:g} V" if ratio != 1.0 else ""
        raise DeviceConfigError(
            source,
            _where(f"{path}.max_drive_v", lines),
            f"{limit:g} V{through} at the input of the {amp.model} exceeds its "
            f"max_input_v of {amp_max:g} V; lower max_drive_v to at most {amp_max / ratio:.4g} V",
        )
    return limit
