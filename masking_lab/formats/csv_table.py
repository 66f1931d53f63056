"""Fixed-format CSV text for output tables: the same rows always give the same bytes.

Floats are written to 6 significant digits, booleans as ``true``/``false``, and ``None`` or NaN
as an empty field; lines end in ``\\n`` whatever the platform.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

__all__ = ["csv_text"]


def csv_text(columns: Sequence[str], rows: Iterable[Mapping[str, Any]]) -> str:
    """CSV with a header line and fixed formatting.

    Parameters
    ----------
    columns : sequence of str
        Column names, in order; keys of a row not named here are left out.
    rows : iterable of mapping
        One mapping per line; a missing key is an empty field.

    Returns
    -------
    str
        The CSV text, ``\\n`` line ends, floats to 6 significant digits (units as the caller's
        values), ``None`` and NaN as empty fields.

    Examples
    --------
    >>> csv_text(["a", "b"], [{"a": 1.0 / 3, "b": None}, {"a": True}])
    'a,b\\n0.333333,\\ntrue,\\n'
    """
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for row in rows:
        w.writerow([_cell(row.get(c)) for c in columns])
    return buf.getvalue()


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool | np.bool_):
        return "true" if v else "false"
    if isinstance(v, float | np.floating):
        if isinstance(v, float) and math.isnan(v):
            return ""
        return f"{float(v):.6g}"
    return str(v)
