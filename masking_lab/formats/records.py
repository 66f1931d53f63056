"""Session-log records on the wire: one encoding, one policy for non-finite numbers.

Every JSON Lines record a session log holds (header, ``set_start``, ``trial``, ``set_end``,
``fault``, ``resume``, ``usertest_trial``, ``session_end``; fields in
``data_schema/session_log.schema.json``, types in :mod:`masking_lab.formats.log_records`) is
written by :func:`encode_record` through the one writer,
:class:`~masking_lab.formats.session_log.SessionLogWriter`, whoever writes it: the threshold and
user-test runners, resume and the synthetic logs of :mod:`masking_lab.simulation.synthetic_logs`.

The policy for non-finite numbers, in one place:

- a measured or computed value that is NaN or ±inf never becomes a JSON number: the encoder
  refuses it (``ValueError``), so a bug surfaces before the record is written, not months later
  in an analysis;
- a *copy* of what a user wrote (a protocol's or a user test's content kept in the header for
  resume) goes through :func:`jsonable` first, which keeps non-finite floats as the strings
  ``"inf"``, ``"-inf"``, ``"nan"``, so the copy stays faithful and valid JSON;
- a computed number in an output document (a rendering's summary, ``solve --json``) goes
  through :func:`json_number`: NaN ("no answer") becomes ``null``, ±inf (a channel that is
  absent, −inf dB) the strings ``"-inf"``/``"inf"``.
"""

from __future__ import annotations

import datetime as dt
import json
import math
from collections.abc import Mapping
from typing import Any

__all__ = ["encode_record", "json_number", "jsonable"]


def encode_record(record: Mapping[str, Any]) -> str:
    """One record as one compact JSON line, without the newline.

    Parameters
    ----------
    record : mapping
        The record; values are JSON types with finite numbers only.

    Returns
    -------
    str
        Compact JSON (no spaces), UTF-8 characters kept as they are.

    Raises
    ------
    ValueError
        If a number in ``record`` is NaN or infinite.

    Examples
    --------
    >>> encode_record({"record": "trial", "level_db_sl": 4.5, "correct": True})
    '{"record":"trial","level_db_sl":4.5,"correct":true}'
    """
    return json.dumps(record, separators=(",", ":"), allow_nan=False, ensure_ascii=False)


_KEPT = frozenset({int, str, bool, type(None)})  # exact types jsonable returns as they are


def jsonable(value: Any) -> Any:
    """A JSON-safe copy of user content: mappings, sequences, finite numbers, strings.

    Non-finite floats become ``"inf"``, ``"-inf"`` or ``"nan"``; dates their ISO form; anything
    else its ``str``.

    Examples
    --------
    >>> jsonable({"levels": (1.0, float("inf")), 3: None})
    {'levels': [1.0, 'inf'], '3': None}
    """
    # The common exact types first (a trial's device details: a dict of numbers and lists),
    # leaves kept without a call; subclasses and anything else take the general checks.
    kind = type(value)
    if kind is dict:
        return {str(k): v if type(v) in _KEPT else jsonable(v) for k, v in value.items()}
    if kind is list or kind is tuple:
        return [v if type(v) in _KEPT else jsonable(v) for v in value]
    if kind is float:
        return value if math.isfinite(value) else str(value)
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, bool) or value is None or isinstance(value, str | int):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)
    if isinstance(value, dt.date):
        return value.isoformat()
    return str(value)


def json_number(x: float) -> float | str | None:
    """A computed number for an output JSON document: NaN → None, ±inf → ``"inf"``/``"-inf"``.

    Examples
    --------
    >>> [json_number(v) for v in (2.5, float("nan"), float("-inf"))]
    [2.5, None, '-inf']
    """
    x = float(x)
    if math.isnan(x):
        return None
    if math.isinf(x):
        return "-inf" if x < 0 else "inf"
    return x
