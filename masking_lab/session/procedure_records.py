"""A logged set's procedure settings (pure).

The record fields themselves are built by :mod:`masking_lab.procedures.log_fields`. Levels are
dB in the set's ``level_unit``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from masking_lab.core.errors import LogError, ProcedureError
from masking_lab.formats.protocol import SetSpec
from masking_lab.procedures.log_fields import SetProcedure
from masking_lab.procedures.registry import settings_from_start

__all__ = ["settings_from_record"]


def settings_from_record(start_record: Mapping[str, Any], spec: SetSpec) -> SetProcedure:
    """The settings a logged set ran under (its ``set_start``), else the protocol's.

    Raises
    ------
    LogError
        If the logged settings are not valid settings of their kind.

    Examples
    --------
    >>> from masking_lab.core.stimulus import parse_stimulus
    >>> from masking_lab.procedures.log_fields import start_fields
    >>> from masking_lab.procedures.quest_plus import QuestPlusSettings
    >>> spec = SetSpec("s", parse_stimulus("EV270"), None, None, None,
    ...                QuestPlusSettings(-20.0, 45.0))
    >>> rec = start_fields(QuestPlusSettings(-20.0, 30.0))
    >>> settings_from_record(rec, spec).max_level_db
    30.0
    """
    try:
        return settings_from_start(start_record, spec.settings)
    except (ProcedureError, OverflowError, TypeError, ValueError) as exc:
        # Not only what the settings refuse: a crafted record's 400-digit number or wrong type.
        raise LogError(
            f"set {spec.id}: the settings in its set_start record: {str(exc)[:200]}"
        ) from exc
