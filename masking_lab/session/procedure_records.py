"""A logged set's procedure settings and the reason a track has no AL (pure).

The record fields themselves are built by :mod:`masking_lab.procedures.log_fields`
(re-exported here for the session loop). Levels are dB in the set's ``level_unit``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from masking_lab.core.errors import LogError, StaircaseError
from masking_lab.formats.protocol import SetSpec
from masking_lab.procedures.base import Procedure
from masking_lab.procedures.log_fields import (
    SetProcedure,
    end_fields,
    settings_record,
    start_fields,
    trial_fields,
)
from masking_lab.procedures.quest_plus import QuestPlus, QuestPlusSettings
from masking_lab.procedures.staircase import Staircase, StaircaseSettings

__all__ = [
    "bound_reason",
    "end_fields",
    "settings_from_record",
    "settings_record",
    "start_fields",
    "trial_fields",
]


def settings_from_record(start_record: Mapping[str, Any], spec: SetSpec) -> SetProcedure:
    """The settings a logged set ran under (its ``set_start``), else the protocol's.

    Raises
    ------
    LogError
        If the logged settings are not valid settings of their kind.

    Examples
    --------
    >>> from masking_lab.core.stimulus import parse_stimulus
    >>> spec = SetSpec("s", parse_stimulus("EV270"), None, None, None,
    ...                QuestPlusSettings(-20.0, 45.0))
    >>> rec = start_fields(QuestPlusSettings(-20.0, 30.0))
    >>> settings_from_record(rec, spec).max_level_db
    30.0
    """
    try:
        procedure = start_record.get("procedure")
        if procedure:
            if procedure.get("kind") != "quest_plus":
                raise LogError(
                    f"set {spec.id}: the log names procedure kind {procedure.get('kind')!r}, "
                    "which this version cannot run (known: staircase, quest_plus)"
                )
            return QuestPlusSettings.from_mapping(procedure)
        data = dict(start_record.get("staircase") or {})
        if not data:
            return spec.settings
        known = {f.name for f in dataclasses.fields(StaircaseSettings)}
        data = {k: v for k, v in data.items() if k in known}
        default = spec.staircase.step_sizes_db if spec.staircase else (4.0,)
        data["step_sizes_db"] = tuple(data.get("step_sizes_db", default))
        return StaircaseSettings(**data)
    except (StaircaseError, OverflowError, TypeError, ValueError) as exc:
        # Not only what the settings refuse: a crafted record's 400-digit number or wrong type.
        raise LogError(
            f"set {spec.id}: the settings in its set_start record: {str(exc)[:200]}"
        ) from exc


def bound_reason(state: Procedure, unit: str, target_max_v: float) -> str:
    """Why a track that did not complete has no AL, for ``set_end.reason``.

    Examples
    --------
    >>> s = QuestPlusSettings(-20.0, 45.0, max_trials=1, target_sd_db=1.0)
    >>> bound_reason(s.start().update(True), "dB SL", 10.0)[:26]
    'reached the trial cap (1 t'
    """
    if isinstance(state, Staircase):
        sc = state.settings
        if state.status == "ceiling":
            return (
                f"pinned at the upper bound {sc.max_level_db:.2f} {unit} (protocol max ∩ device "
                f"limit {target_max_v:g} V): a ceiling, not a threshold"
            )
        if state.status == "floor":
            return f"pinned at the lower bound {sc.min_level_db} {unit}: a floor, not a threshold"
        return f"reached the trial cap ({sc.max_trials} trials) before {sc.n_reversals} reversals"
    assert isinstance(state, QuestPlus)
    qs = state.settings
    lo, hi = qs.threshold_range_db
    where = f"{state.posterior_mean_db:.2f} ± {state.posterior_sd_db:.2f} {unit}"
    if state.status == "ceiling":
        return (
            f"stopped with its posterior mean {where} at the top of the threshold grid "
            f"({hi:g} {unit}, protocol max ∩ device limit {target_max_v:g} V): a ceiling"
        )
    if state.status == "floor":
        return f"stopped with its posterior mean {where} at the grid's bottom ({lo:g} {unit})"
    return (
        f"reached the trial cap ({qs.max_trials} trials) with posterior SD "
        f"{state.posterior_sd_db:.2f} {unit}, above the target {qs.target_sd_db}"
    )
