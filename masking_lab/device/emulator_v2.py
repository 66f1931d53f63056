"""Protocol-2 additions of the firmware emulator: HELLO converter fields, attenuator steps in
PLAY, quantised amplitudes in DONE (a minimal shim; fw-core's emulator supersedes it).

Examples
--------
>>> from masking_lab.device.levels_range import Converter
>>> hello_fields({"EV": Converter(12, 10.0), "MV": Converter(12, 10.0)})["att"]
'0'
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from masking_lab.core.trial import TrialPlan
from masking_lab.device import protocol as proto
from masking_lab.device.config import DeviceConfig
from masking_lab.device.levels_range import Converter


def converters_of(config: DeviceConfig, hard_max_v: float) -> dict[str, Converter]:
    """The converters the config describes; a 12-bit DAC at ``hard_max_v`` V elsewhere."""
    return {ch: config.converters.get(ch, Converter(12, hard_max_v)) for ch in ("EV", "MV")}


def hello_fields(converters: Mapping[str, Converter]) -> dict[str, Any]:
    """HELLO's protocol-2 fields for an emulator (build hash unknown: ``000000000000``)."""
    fields: dict[str, Any] = {"build": "000000000000", "clk": "host", "rst": "power"}
    for ch, conv in converters.items():
        fields[f"bits_{ch.lower()}"] = conv.bits
        fields[f"fsv_{ch.lower()}"] = conv.full_scale_v
    fields["att"] = ",".join(f"{a:g}" for a in converters["EV"].steps_db)
    return fields


def play_steps(
    frame: proto.Frame, plan: TrialPlan, converters: Mapping[str, Converter]
) -> dict[str, float]:
    """``{"t": tatt, "m": matt}`` of a PLAY, dB; ValueError (→ ``ERR ARGS``) if not allowed."""
    att = {k: frame.number(f"{k}att") if f"{k}att" in frame.fields else 0.0 for k in "tm"}
    chans = {"t": plan.target.channel, "m": plan.masker.channel if plan.masker else None}
    for key, ch in chans.items():
        if ch is not None and att[key] not in converters[ch].steps_db:
            raise ValueError(f"{key}att={att[key]:g} dB is not an attenuator step")
    if chans["t"] == chans["m"] and att["t"] != att["m"]:
        raise ValueError("target and masker share a channel but not an attenuator step")
    return att


def played(
    plan: TrialPlan, converters: Mapping[str, Converter], att: Mapping[str, float]
) -> dict[str, float]:
    """DONE's ``tamp`` and ``mamp``: what the converters play, V."""
    tamp = converters[plan.target.channel].played_v(plan.target_amplitude_v, att.get("t", 0.0))
    mamp = 0.0
    if plan.masker is not None:
        step = att.get("m", 0.0)
        mamp = converters[plan.masker.channel].played_v(plan.masker_amplitude_v, step)
    return {"tamp": tamp, "mamp": mamp}
