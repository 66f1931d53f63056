"""What a Bayesian procedure's intervals assume when its settings fix the slope or the lapse
(pure).

A QUEST+ or functional track whose psychometric scale or lapse rate is a single value computes
its 95 % intervals as if the observer had exactly that slope and lapse. Measured with observers
of twice the scale or a lapse of 0.08, such intervals cover the truth far less often than 95 %
(docs/procedures.md, "Intervals when the observer is not the model"); with both marginalised
(the defaults) they hold. ``validate`` warns about such a protocol and ``analyze`` prints the
note beside the intervals. The check reads the settings' ``scales_db`` and ``lapses`` (a
settings object or its logged record), whatever the procedure's kind.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

__all__ = ["COVERAGE_DOC", "STATED_MODEL", "stated_model_note"]

#: Where the coverage table is.
COVERAGE_DOC = 'docs/procedures.md, "Intervals when the observer is not the model"'
#: The note's opening words (``analyze`` finds its notes by them).
STATED_MODEL = "95 % intervals assume the stated slope/lapse"
#: Coverage of the known-slope QUEST+ protocol's intervals in the table's cells with twice the
#: scale or lapse 0.08 (benchmarks/interval_coverage.py, 200 tracks per cell, seed 0).
KNOWN_COVERAGE = "52-87 %"


def _values(settings: Any, name: str) -> tuple[float, ...] | None:
    value = settings.get(name) if isinstance(settings, Mapping) else getattr(settings, name, None)
    if value is None:
        return None
    if isinstance(value, int | float) and not isinstance(value, bool):
        return (float(value),)
    try:
        return tuple(float(v) for v in value)
    except (TypeError, ValueError):
        return None


def stated_model_note(settings: Any) -> str | None:
    """The caveat of a procedure whose slope or lapse is a single value, else None.

    Parameters
    ----------
    settings : settings object or mapping
        A Bayesian procedure's settings, or the ``procedure`` record of a ``set_start`` log
        line (keys ``scales_db`` in dB and ``lapses``). Anything without both keys (a
        staircase) has no such caveat.

    Returns
    -------
    str or None
        One line: what is assumed, the measured coverage when it is wrong, and where the
        table is.

    Examples
    --------
    >>> stated_model_note({"kind": "quest_plus", "scales_db": [1.5], "lapses": [0.02]})[:71]
    '95 % intervals assume the stated slope/lapse (scale 1.5 dB, lapse 0.02)'
    >>> stated_model_note({"scales_db": [0.75, 1.5, 3.0], "lapses": [0, 0.04, 0.08]}) is None
    True
    >>> stated_model_note({"kind": "staircase"}) is None
    True
    """
    scales = _values(settings, "scales_db")
    lapses = _values(settings, "lapses")
    if scales is None or lapses is None or (len(scales) > 1 and len(lapses) > 1):
        return None
    fixed = []
    if len(scales) == 1:
        fixed.append(f"scale {scales[0]:g} dB")
    if len(lapses) == 1:
        fixed.append(f"lapse {lapses[0]:g}")
    return (
        f"{STATED_MODEL} ({', '.join(fixed)}); measured coverage when the observer's scale is "
        f"twice that or its lapse 0.08: {KNOWN_COVERAGE} of 95 % ({COVERAGE_DOC}); list "
        "several scales_db and lapses to marginalise them"
    )
