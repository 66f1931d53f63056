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

__all__ = ["csv_text", "csv_text_rows"]


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


def csv_text_rows(columns: Sequence[str], rows: Iterable[Sequence[Any]]) -> str:
    """:func:`csv_text` for rows given as sequences in ``columns`` order (no dict per row).

    Examples
    --------
    >>> csv_text_rows(["a", "b"], [[1.0 / 3, None], [True, "x"]])
    'a,b\\n0.333333,\\ntrue,x\\n'
    """
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    w.writerows([_cell(v) for v in row] for row in rows)
    return buf.getvalue()


def _cell(v: Any) -> str:
    kind = type(v)  # the common exact types first: this runs once per cell
    if kind is str:
        return v
    if kind is float:
        return "" if v != v else f"{v:.6g}"  # v != v: NaN
    if v is None:
        return ""
    if isinstance(v, bool | np.bool_):
        return "true" if v else "false"
    if isinstance(v, float | np.floating):
        if isinstance(v, float) and math.isnan(v):
            return ""
        return f"{float(v):.6g}"
    return str(v)
