"""Fixed-format CSV text for output tables: the same rows always give the same bytes.

Floats are written to 6 significant digits, booleans as ``true``/``false``, and ``None`` or NaN
as an empty field; lines end in ``\\n`` whatever the platform.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np

__all__ = ["csv_column_blocks", "csv_text", "csv_text_columns", "csv_text_rows"]


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


def csv_text_columns(columns: Sequence[str], data: Sequence[Sequence[Any]]) -> str:
    """:func:`csv_text` for a table given column by column (``data[i]``: the values of
    ``columns[i]``, all of one length), formatted a column at a time.

    The same bytes as :func:`csv_text_rows` on the rows; a column of only floats or only
    strings is formatted without a call per cell (the thresholds table of a large study has
    millions of cells).

    Examples
    --------
    >>> csv_text_columns(["a", "b"], [[1.0 / 3, True], [None, "x"]])
    'a,b\\n0.333333,\\ntrue,x\\n'
    """
    return "".join(csv_column_blocks(columns, data))


def csv_column_blocks(columns: Sequence[str], data: Sequence[Sequence[Any]]) -> Iterator[str]:
    """The text of :func:`csv_text_columns` in pieces (the header, then a block of rows at a
    time), to be written as they come: a large table's whole text is never held.

    Examples
    --------
    >>> list(csv_column_blocks(["a", "b"], [[1.0, 2.0], ["x", "y"]]))
    ['a,b\\n', '1,x\\n2,y\\n']
    """
    if len(columns) != len(data):
        raise ValueError(f"{len(columns)} column names for {len(data)} columns")
    return _column_blocks(columns, data)


def _column_blocks(columns: Sequence[str], data: Sequence[Sequence[Any]]) -> Iterator[str]:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(columns)
    yield buf.getvalue()
    n = len(data[0]) if data else 0
    # A block of rows at a time: the formatted cells of a whole large table at once would
    # hold millions of small strings.
    for start in range(0, n, _BLOCK_ROWS):
        cells = [_column_cells(values[start : start + _BLOCK_ROWS]) for values in data]
        if len(columns) < 2:  # csv quotes a lone empty field: leave such tables to it
            buf = io.StringIO()
            csv.writer(buf, lineterminator="\n").writerows(zip(*cells, strict=True))
            yield buf.getvalue()
            continue
        cells = [_quoted(col) for col in cells]
        yield "".join(line + "\n" for line in map(",".join, zip(*cells, strict=True)))


_BLOCK_ROWS = 4096


def _needs_quotes() -> str:
    """The characters that make the csv module quote a field (``QUOTE_MINIMAL``, ``\\n`` line
    ends), asked of the csv module itself so the two writers cannot disagree."""
    out = []
    for ch in ',"\n\r\t ;':
        buf = io.StringIO()
        csv.writer(buf, lineterminator="\n").writerow([f"a{ch}b", "c"])
        if buf.getvalue().startswith('"'):
            out.append(ch)
    return "".join(out)


_NEEDS_QUOTES = _needs_quotes()


def _quoted(col: Sequence[str]) -> Sequence[str]:
    """A column's cells as the csv module writes them: quoted (inner quotes doubled) where a
    cell holds a delimiter, quote or line break."""
    joined = "".join(col)
    if not any(ch in joined for ch in _NEEDS_QUOTES):
        return col
    return [
        '"' + v.replace('"', '""') + '"' if any(ch in v for ch in _NEEDS_QUOTES) else v for v in col
    ]


def _column_cells(values: Sequence[Any]) -> Sequence[str]:
    """The cells of one column as :func:`_cell` writes them, the common column types without
    a call per cell."""
    kinds = set(map(type, values))
    if kinds <= {str}:
        return values
    if kinds <= {str, type(None)}:
        return ["" if v is None else v for v in values]
    if kinds <= {float, type(None)}:
        return ["" if v is None or v != v else f"{v:.6g}" for v in values]  # v != v: NaN
    if kinds <= {int}:  # bool is a type of its own here
        return list(map(str, values))
    if kinds <= {bool}:
        return ["true" if v else "false" for v in values]
    return [_cell(v) for v in values]


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
