"""Per-channel sensation-level limits of the rig, read from its device config.

A protocol's masker levels are checked against ``channels.<EV|MV>.max_level_db_sl`` before a
session: the highest level in dB SL the rig may present (comfort and safety), separate from the
electrical ``max_drive_v`` that the device enforces per participant at run time.
"""

from __future__ import annotations

from pathlib import Path

from masking_lab.device.config import load_device_config


def max_level_db_sl(config_path: str | Path | None = None) -> dict[str, float]:
    """Return ``{"EV": dB SL, "MV": dB SL}`` limits from a device config (packaged default if None).

    The config is read and validated in full (``device.config.load_device_config``), so a NaN,
    infinite or mistyped limit is refused rather than letting every level through.
    Channels without ``max_level_db_sl`` are unlimited here (the drive limit still applies).

    Raises
    ------
    DeviceConfigError
        If the config is unreadable or invalid (a :class:`~masking_lab.core.errors.ProtocolError`).

    Examples
    --------
    >>> sorted(max_level_db_sl())
    ['EV', 'MV']
    """
    return dict(load_device_config(config_path).max_level_db_sl)
