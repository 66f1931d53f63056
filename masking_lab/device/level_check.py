"""Is every level a protocol can ask for playable on this rig? Checked before the first trial.

For each set, the range its procedure may visit (staircase or QUEST+ floor up to its ceiling or
the channel's drive limit) and its masker level are converted to peak volts (dB SL through the
unmasked ALs) and rendered through the channel's :class:`~masking_lab.device.levels_range.
Converter` at the attenuator step the host would pick. A level played more than 1 dB off (or as
silence) is a problem, named with the set, the level and what to change. Pure: no I/O.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Collection, Mapping
from dataclasses import dataclass, replace
from pathlib import Path

from masking_lab.core.errors import LevelError
from masking_lab.core.levels import db_v_to_volts, volts_to_db_v
from masking_lab.core.stimulus import Stimulus
from masking_lab.device.config import load_device_config
from masking_lab.device.levels_range import MAX_ERROR_DB, Converter
from masking_lab.formats.protocol import ThresholdProtocol

SAMPLE_DB = 0.05  # spacing of the levels checked across a range, dB


@dataclass(frozen=True)
class LevelRange:
    """Levels one set may play on one channel.

    Attributes
    ----------
    set_id : str
        The set.
    role : str
        ``"target"`` or ``"masker"``.
    stimulus : Stimulus
        What is played.
    low_db_v, high_db_v : float
        Lowest and highest level, dB re 1 V (equal for a masker).
    low_key : str
        The protocol key that sets the low end (named in messages).
    """

    set_id: str
    role: str
    stimulus: Stimulus
    low_db_v: float
    high_db_v: float
    low_key: str


def set_ranges(
    protocol: ThresholdProtocol,
    calibration_db_v: Mapping[str, float],
    max_drive_v: Mapping[str, float],
) -> list[LevelRange]:
    """The level range of every set of ``protocol`` that has a floor, dB re 1 V.

    Parameters
    ----------
    protocol : ThresholdProtocol
        The protocol.
    calibration_db_v : mapping of stimulus name → dB re 1 V
        Unmasked ALs (dB SL protocols); a set whose stimuli lack one is skipped.
    max_drive_v : mapping of channel → V
        Drive limits: the ceiling when the procedure has none.
    """
    out: list[LevelRange] = []
    sl = protocol.level_unit == "db_sl"
    for spec in protocol.sets:
        names = [spec.target.name] + ([spec.masker.name] if spec.masker else [])
        if sl and any(n not in calibration_db_v for n in names):
            continue
        base = float(calibration_db_v[spec.target.name]) if sl else 0.0
        settings = spec.settings
        ceiling = volts_to_db_v(max_drive_v[spec.target.channel])
        if settings.max_level_db is not None:
            ceiling = min(ceiling, base + settings.max_level_db)
        key = "procedure.min_level_db" if spec.procedure is not None else "staircase.min_level_db"
        floor = settings.min_level_db
        if floor is None:  # no floor: the start level is all that is known beforehand
            floor = getattr(settings, "start_level_db", None)
            key = "staircase.start_level_db"
        if floor is not None:
            low = base + floor
            out.append(LevelRange(spec.id, "target", spec.target, low, max(low, ceiling), key))
        if spec.masker is not None and spec.masker_level_db_sl is not None:
            level = float(calibration_db_v[spec.masker.name]) + spec.masker_level_db_sl
            out.append(
                LevelRange(spec.id, "masker", spec.masker, level, level, "masker_level_db_sl")
            )
    return out


@functools.lru_cache(maxsize=1024)  # pure; a protocol's sets share ranges (18 of 34 in the demo)
def worst_in_range(converter: Converter, low_db_v: float, high_db_v: float) -> tuple[float, float]:
    """The level (dB re 1 V) in ``[low, high]`` played furthest off, and how far off (dB).

    Levels are sampled every :data:`SAMPLE_DB` dB, both ends included, each at the attenuator
    step the host would pick for it.

    Examples
    --------
    >>> conv = Converter(12, 10.0, (0.0,))
    >>> level, err = worst_in_range(conv, -60.0, 0.0)
    >>> level, math.isinf(err)  # 1 mV is under half an LSB (2.4 mV): silence
    (-60.0, True)
    """
    n = max(1, math.ceil((high_db_v - low_db_v) / SAMPLE_DB))
    worst = (low_db_v, -1.0)
    for k in range(n + 1):
        level = min(high_db_v, low_db_v + k * SAMPLE_DB)
        amp = db_v_to_volts(level)
        if amp > converter.full_scale_v:
            continue  # above full scale: the drive limit refuses it, not the resolution
        err = converter.error_db(amp, converter.pick_step([amp]))
        if err > worst[1]:
            worst = (level, err)
    return worst


def level_problems(
    protocol: ThresholdProtocol,
    converters: Mapping[str, Converter],
    calibration_db_v: Mapping[str, float],
    max_drive_v: Mapping[str, float],
    *,
    al_source: str = "the participant's calibration",
) -> list[str]:
    """Every set level of ``protocol`` the rig cannot play within 1 dB, in words.

    Parameters
    ----------
    protocol : ThresholdProtocol
        The protocol.
    converters : mapping of channel → Converter
        The rig's converters; a channel without one is not checked.
    calibration_db_v : mapping of stimulus name → dB re 1 V
        Unmasked ALs that place dB SL levels.
    max_drive_v : mapping of channel → V
        Drive limits.
    al_source : str
        Where the ALs came from, for the message.

    Returns
    -------
    list of str
        One message per set and role; empty when everything plays.
    """
    problems = []
    for rng in set_ranges(protocol, calibration_db_v, max_drive_v):
        conv = converters.get(rng.stimulus.channel)
        if conv is None:
            continue
        level, err = worst_in_range(conv, rng.low_db_v, rng.high_db_v)
        if err <= MAX_ERROR_DB:
            continue
        played = "as silence" if math.isinf(err) else f"{err:.1f} dB off"
        via = f" (ALs from {al_source})" if protocol.level_unit == "db_sl" else ""
        problems.append(
            f"set {rng.set_id}: {rng.role} {rng.stimulus.name} at {level:.1f} dB re 1 V "
            f"({db_v_to_volts(level) * 1e3:.3g} mV){via} plays {played} on the "
            f"{rng.stimulus.channel} converter ({conv.bits} bits, {conv.full_scale_v:g} V full "
            f"scale, attenuator steps {'/'.join(f'{s:g}' for s in conv.steps_db)} dB); raise "
            f"{rng.low_key} or give channels.{rng.stimulus.channel}.converter."
            "attenuator_steps_db a deeper step"
        )
    return problems


def refuse_unplayable(
    protocol: ThresholdProtocol,
    set_ids: Collection[str],
    calibration_db_v: Mapping[str, float],
    device_config: str | Path | None,
) -> None:
    """Before a session: raise LevelError if a level of the sets ``set_ids`` cannot be played.

    Parameters
    ----------
    protocol : ThresholdProtocol
        The protocol.
    set_ids : collection of str
        The sets this session runs.
    calibration_db_v : mapping of stimulus name → dB re 1 V
        The participant's unmasked ALs (empty for a baseline).
    device_config : path or None
        The rig config (reference rig if None); without converters nothing is checked.

    Raises
    ------
    LevelError
        Naming each set, level and what to change; nothing has been played.
    """
    config = load_device_config(device_config)
    if not config.converters:
        return
    chosen = replace(protocol, sets=tuple(s for s in protocol.sets if s.id in set(set_ids)))
    problems = level_problems(
        chosen, config.converters, calibration_db_v, config.limits.max_drive_v
    )
    if problems:
        more = f" (and {len(problems) - 3} more)" if len(problems) > 3 else ""
        raise LevelError(
            f"{protocol.path}: levels the rig {config.path} cannot play, refused before the "
            f"first trial: {'; '.join(problems[:3])}{more}"
        )
