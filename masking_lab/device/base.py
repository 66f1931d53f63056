"""The device interface every back-end implements, and the values it exchanges.

Levels cross this boundary as peak drive amplitudes in volts; the host converts dB re 1 V with
:mod:`masking_lab.core.levels`. Every back-end enforces the limits of its :class:`DeviceLimits`
before anything is played and zeroes both outputs on any fault, on :meth:`Device.stop` and on close.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

from masking_lab.core.stimulus import Channel, Stimulus
from masking_lab.core.trial import PlayResult, TrialPlan


@dataclass(frozen=True)
class DeviceLimits:
    """Per-channel safety limits, from the device config.

    Attributes
    ----------
    max_drive_v : dict[str, float]
        Largest peak drive amplitude accepted per channel (``"EV"``, ``"MV"``), V.

    Examples
    --------
    >>> DeviceLimits({"EV": 1.0, "MV": 0.5}).max_drive_v["MV"]
    0.5
    """

    max_drive_v: dict[str, float]


@dataclass(frozen=True)
class DeviceIdentity:
    """What the session log records about the device.

    Attributes
    ----------
    backend : str
        ``"serial"``, ``"emulator"``, ``"sim"`` or ``"nidaq"``.
    model : str
        Device model string reported by the handshake.
    serial_number : str
        Unit identifier reported by the handshake (or ``"n/a"``).
    firmware_version : str
        Firmware (or emulator) version reported by the handshake.
    port : str or None
        Serial port path, if any.
    limits : DeviceLimits
        Limits in force (host config ∩ firmware-reported), V.
    details : Mapping[str, Any]
        What else the handshake said, for the log (serial boards: protocol, build hash, clock
        source, reset cause, converter bits, full scale in V, attenuator steps in dB; NI:
        watchdog support and idle-output behaviour). Empty when there is nothing to add.

    Examples
    --------
    >>> ident = DeviceIdentity("sim", "sim", "n/a", "0.1", None, DeviceLimits({"EV": 1.0}))
    >>> ident.backend, ident.limits.max_drive_v
    ('sim', {'EV': 1.0})
    """

    backend: str
    model: str
    serial_number: str
    firmware_version: str
    port: str | None
    limits: DeviceLimits
    details: Mapping[str, Any] = field(default_factory=dict)


class Device(Protocol):
    """A two-channel (EV, MV) tactile output device."""

    identity: DeviceIdentity

    def play_trial(self, plan: TrialPlan, start_s: float) -> PlayResult:
        """Play the three intervals of ``plan`` starting at host time ``start_s`` and return when
        the last interval has ended. Raises SafetyLimitError (nothing played) or DeviceError."""
        ...

    def set_amplitude(self, channel: Channel, stimulus: Stimulus, amplitude_v: float) -> None:
        """Streamed update for rendering: play ``stimulus`` on ``channel`` at ``amplitude_v`` V."""
        ...

    def stop(self) -> None:
        """Zero both outputs immediately."""
        ...

    def close(self) -> None:
        """Zero both outputs and release the device. Idempotent."""
        ...
