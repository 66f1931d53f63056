"""Did a participant's sessions all run on one rig? (pure)

An AL shift is a masked AL minus the unmasked AL of the same participant, so both must come
from one signal chain: a different amplifier gain, attenuator or actuator between the baseline
and the masked sessions moves every shift by the change in volts-out per volt-in. Each log
header carries the rig record of its device config (:meth:`DeviceConfig.rig_record
<masking_lab.device.config.DeviceConfig.rig_record>`); this module compares them per
participant. The config file's path is not compared (one rig may be described by copies of
one file on two computers); its name, drive limits, amplifiers, attenuators, transducers and
measured gains are.
"""

from __future__ import annotations

import json
from collections import defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

__all__ = ["RigUse", "rig_changes", "rig_use"]


@dataclass(frozen=True)
class RigUse:
    """One session log's rig, as its header records it.

    Attributes
    ----------
    participant : str
        Participant id.
    log_name : str
        The log's file name (how the warning names it).
    experiment : str
        The protocol's experiment id (``baseline``, ``I``, ``II``...).
    rig : mapping or None
        The header's ``rig`` record; None for logs written before rig records existed.
    """

    participant: str
    log_name: str
    experiment: str
    rig: Mapping[str, Any] | None


def rig_use(header: Mapping[str, Any], log_name: str) -> RigUse:
    """The :class:`RigUse` of one log, from its header (as :func:`read_log` gives it).

    Examples
    --------
    >>> rig_use({"participant": "S01", "protocol": {"experiment": "I"}}, "m.jsonl")
    RigUse(participant='S01', log_name='m.jsonl', experiment='I', rig=None)
    """
    protocol = header.get("protocol")
    experiment = protocol.get("experiment") if isinstance(protocol, Mapping) else None
    rig = header.get("rig")
    return RigUse(
        str(header.get("participant", "")),
        log_name,
        str(experiment or "?"),
        rig if isinstance(rig, Mapping) else None,
    )


def _identity(rig: Mapping[str, Any]) -> str:
    return json.dumps({k: v for k, v in rig.items() if k != "config"}, sort_keys=True)


def rig_changes(uses: Iterable[RigUse]) -> list[str]:
    """One warning per participant whose sessions ran on more than one rig record.

    Parameters
    ----------
    uses : iterable of RigUse
        Every analysed session log.

    Returns
    -------
    list of str
        Warnings, sorted by participant; each names the rigs and the logs (with their
        experiments) that used them. Logs without a rig record are not compared.

    Examples
    --------
    >>> a = {"name": "rig A", "config": "/x/a.yaml", "channels": {"MV": {"max_drive_v": 10.0}}}
    >>> b = {**a, "config": "/y/a.yaml"}  # the same rig, described by a copy of its file
    >>> rig_changes([RigUse("S01", "b.jsonl", "baseline", a), RigUse("S01", "m.jsonl", "I", b)])
    []
    >>> c = {**a, "channels": {"MV": {"max_drive_v": 1.8}}}
    >>> print(rig_changes([RigUse("S01", "b.jsonl", "baseline", a),
    ...                    RigUse("S01", "m.jsonl", "I", c)])[0][:74])
    S01: sessions ran on 2 different rig records (rig A: b.jsonl [baseline]; r
    """
    by_participant: dict[str, dict[str, list[RigUse]]] = defaultdict(lambda: defaultdict(list))
    for use in uses:
        if use.rig is not None:
            by_participant[use.participant][_identity(use.rig)].append(use)
    warnings = []
    for participant in sorted(by_participant):
        rigs = by_participant[participant]
        if len(rigs) < 2:
            continue
        groups = "; ".join(
            f"{_rig_name(group[0])}: "
            + ", ".join(f"{u.log_name} [{u.experiment}]" for u in sorted(group, key=_name))
            for group in sorted(rigs.values(), key=lambda g: _name(min(g, key=_name)))
        )
        warnings.append(
            f"{participant}: sessions ran on {len(rigs)} different rig records ({groups}); "
            "AL shifts compare masked with unmasked ALs, so both must come from one signal "
            "chain — check the device configs (amplifier gain, attenuator, actuator) or "
            "re-measure on one rig"
        )
    return warnings


def _name(use: RigUse) -> str:
    return use.log_name


def _rig_name(use: RigUse) -> str:
    return (use.rig or {}).get("name") or "unnamed rig"
