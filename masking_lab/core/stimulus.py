"""Stimuli and their names.

A stimulus is one tactile channel (``EV`` electrovibration or ``MV`` mechanical vibration) at a
carrier frequency, optionally amplitude-modulated by an envelope. Its name is what protocols,
calibrations, logs and exported parameters use:

``EV270``       EV, 270 Hz carrier
``MV120``       MV, 120 Hz carrier
``MV120am40``   MV, 120 Hz carrier, 40 Hz amplitude envelope (the paper's "coarse" texture)
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

from masking_lab.core.errors import InputError

Channel = Literal["EV", "MV"]
CHANNELS: tuple[Channel, ...] = ("EV", "MV")

_NAME = re.compile(r"^(EV|MV)(\d+(?:\.\d+)?)(?:am(\d+(?:\.\d+)?))?$")


@dataclass(frozen=True, order=True)
class Stimulus:
    """One tactile stimulus.

    Attributes
    ----------
    channel : {"EV", "MV"}
        Electrovibration (friction modulation on the panel) or mechanical vibration (piezo).
    carrier_hz : float
        Carrier frequency in Hz.
    envelope_hz : float or None
        Amplitude-modulation frequency in Hz, or None for an unmodulated carrier.

    Raises
    ------
    InputError
        For an unknown channel or a non-positive frequency.

    Examples
    --------
    >>> Stimulus("MV", 120.0, envelope_hz=40.0).name
    'MV120am40'
    >>> str(Stimulus("EV", 270.0))
    'EV270'
    """

    channel: Channel
    carrier_hz: float
    envelope_hz: float | None = None

    def __post_init__(self) -> None:
        if self.channel not in CHANNELS:
            raise InputError(f"channel must be one of {CHANNELS}, got {self.channel!r}")
        if not self.carrier_hz > 0:
            raise InputError(f"carrier_hz must be > 0 Hz, got {self.carrier_hz!r}")
        if self.envelope_hz is not None and not self.envelope_hz > 0:
            raise InputError(f"envelope_hz must be > 0 Hz or None, got {self.envelope_hz!r}")

    @property
    def name(self) -> str:
        """Canonical name, e.g. ``"MV120am40"`` (frequencies in Hz).

        Examples
        --------
        >>> Stimulus("EV", 270.0).name
        'EV270'
        """
        name = f"{self.channel}{_num(self.carrier_hz)}"
        if self.envelope_hz is not None:
            name += f"am{_num(self.envelope_hz)}"
        return name

    def __str__(self) -> str:
        return self.name


def parse_stimulus(name: str) -> Stimulus:
    """Parse a stimulus name such as ``"EV270"`` or ``"MV120am40"``.

    Parameters
    ----------
    name : str
        ``<EV|MV><carrier Hz>[am<envelope Hz>]``; surrounding spaces are ignored.

    Returns
    -------
    Stimulus
        Channel, carrier in Hz and envelope in Hz (or None).

    Examples
    --------
    >>> parse_stimulus("MV120am40")
    Stimulus(channel='MV', carrier_hz=120.0, envelope_hz=40.0)
    >>> parse_stimulus("LRA170")
    Traceback (most recent call last):
    ...
    masking_lab.core.errors.InputError: 'LRA170' is not a stimulus name: write ..., ...

    Raises
    ------
    InputError
        If ``name`` does not follow ``<EV|MV><carrier Hz>[am<envelope Hz>]``.
    """
    match = _NAME.match(str(name).strip())
    if not match:
        raise InputError(
            f"{name!r} is not a stimulus name: write <EV|MV><carrier Hz>[am<envelope Hz>], "
            "for example EV270, MV120 or MV120am40"
        )
    channel, carrier, envelope = match.groups()
    return Stimulus(as_channel(channel), float(carrier), float(envelope) if envelope else None)


def is_stimulus_name(name: str) -> bool:
    """True if ``name`` parses as a stimulus name.

    Parameters
    ----------
    name : str
        Candidate name.

    Returns
    -------
    bool
        Whether :func:`parse_stimulus` would accept it.

    Examples
    --------
    >>> is_stimulus_name("EV270"), is_stimulus_name("MV120am40"), is_stimulus_name("EV")
    (True, True, False)
    """
    return bool(_NAME.match(str(name).strip()))


def as_channel(value: object, what: str = "channel") -> Channel:
    """``value`` as a :data:`Channel`: the checked step from a text field to ``"EV"``/``"MV"``.

    Parameters
    ----------
    value : object
        A field, wire token or column value; ``"EV"`` or ``"MV"`` (exact case).
    what : str
        The field's name, used in the error message.

    Returns
    -------
    Channel
        ``"EV"`` (electrovibration) or ``"MV"`` (mechanical vibration).

    Raises
    ------
    InputError
        If ``value`` is anything else.

    Examples
    --------
    >>> as_channel("MV")
    'MV'
    >>> as_channel("LRA", "tch")
    Traceback (most recent call last):
    ...
    masking_lab.core.errors.InputError: tch is 'LRA': write EV or MV
    """
    if value == "EV":
        return "EV"
    if value == "MV":
        return "MV"
    raise InputError(f"{what} is {value!r}: write EV or MV")


def _num(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else repr(float(x))
