"""Per-channel sensation-level limits of the rig, read from its device config.

A protocol's masker levels are checked against ``channels.<EV|MV>.max_level_db_sl`` before a
session: the highest level in dB SL the rig may present (comfort and safety), separate from the
electrical ``max_drive_v`` that the device enforces per participant at run time.
"""

from __future__ import annotations

from pathlib import Path

import yaml

from masking_lab.core.errors import ProtocolError
from masking_lab.formats.resources import shipped


def max_level_db_sl(config_path: str | Path | None = None) -> dict[str, float]:
    """Return ``{"EV": dB SL, "MV": dB SL}`` limits from a device config (packaged default if None).

    Channels without ``max_level_db_sl`` are unlimited here (the drive limit still applies).
    """
    if config_path is None:
        ref = shipped("protocols", "devices/default.yaml")
        if not ref.is_file():
            return {}
        text, source = ref.read_text(encoding="utf-8"), "protocols/devices/default.yaml"
    else:
        try:
            text, source = Path(config_path).read_text(encoding="utf-8"), str(config_path)
        except OSError as exc:
            raise ProtocolError(str(config_path), "", f"cannot read ({exc.strerror})") from exc
    try:
        data = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:
        raise ProtocolError(source, "", f"malformed YAML: {exc}") from exc
    out: dict[str, float] = {}
    for channel, spec in (data.get("channels") or {}).items():
        if isinstance(spec, dict) and spec.get("max_level_db_sl") is not None:
            out[str(channel)] = float(spec["max_level_db_sl"])
    return out
