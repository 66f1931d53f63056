"""The long CSV of AL shifts that ``masking-lab fit`` reads (see ``data_schema/shifts.csv``).

One row per cell (and participant): ``target, masker, masker_level_db_sl, shift_db`` are
required; ``participant``, ``masker_frequency_hz`` (the masker's carrier, checked against its
name), ``mv_frequency_hz`` and ``experiment`` are optional. Lines starting with ``#`` are
comments. Every problem is reported with the file, line and column.
"""

from __future__ import annotations

import csv
import itertools
import math
from collections.abc import Mapping
from pathlib import Path

import pandas as pd

from masking_lab.core.errors import AnalysisError
from masking_lab.core.stimulus import is_stimulus_name, parse_stimulus
from masking_lab.formats.reader import decode_utf8, excerpt, read_limited

__all__ = ["OPTIONAL_COLUMNS", "REQUIRED_COLUMNS", "levels_told_apart", "read_shifts_csv"]

REQUIRED_COLUMNS = ("target", "masker", "masker_level_db_sl", "shift_db")
#: Largest magnitude of a level, shift (dB) or frequency (Hz) accepted in a row.
MAX_ABS_VALUE = 10_000.0
#: Largest shifts CSV accepted, bytes (a paper-sized study is a few kB).
MAX_CSV_BYTES = 16 * 1024 * 1024
OPTIONAL_COLUMNS = ("participant", "masker_frequency_hz", "mv_frequency_hz", "experiment")
#: Closest two different masker levels of one pair may be, dB: closer ones cannot be told apart
#: (a fit over them is singular), so they are refused rather than fitted.
MIN_LEVEL_SPACING_DB = 1e-6


def read_shifts_csv(path: str | Path) -> tuple[pd.DataFrame, bool]:
    """Read a long CSV of AL shifts.

    Parameters
    ----------
    path : str or Path
        The CSV file (UTF-8, a byte-order mark is allowed). Columns ``target, masker,
        masker_level_db_sl`` (dB SL), ``shift_db`` (dB) are required; ``participant``,
        ``masker_frequency_hz`` (Hz, the masker's carrier, checked against its name),
        ``mv_frequency_hz`` (Hz) and ``experiment`` (default: the direction, ``EV270|MV`` or
        ``MV|EV270``) are optional.

    Returns
    -------
    shifts : DataFrame
        Columns ``experiment, participant, target, masker, mv_stimulus, mv_frequency_hz,
        masker_level_db_sl, shift_db``: the long table
        :func:`masking_lab.analysis.experiment.analyze_shifts` takes (``participant`` is ``""``
        without a participant column).
    has_participants : bool
        Whether a participant column with values is present.

    Raises
    ------
    AnalysisError
        Naming the file, line and column of the first problem.

    Examples
    --------
    >>> shifts, has_participants = read_shifts_csv("data_schema/shifts.csv")  # doctest: +SKIP
    >>> has_participants  # doctest: +SKIP
    False
    """
    p = Path(path)
    raw = read_limited(p, what="file", error=_error, max_bytes=MAX_CSV_BYTES)
    text = decode_utf8(raw, str(p), error=_error)
    lines = [
        (n, line)
        for n, line in enumerate(text.splitlines(), start=1)
        if line.strip() and not line.lstrip().startswith("#")
    ]
    if not lines:
        raise AnalysisError(f"{p}: the file is empty; expected a header line and shift rows")
    rows = [_split(p, n, line) for n, line in lines]
    header = [h.strip() for h in rows[0]]
    twice = sorted({c for c in header if header.count(c) > 1})
    if twice:
        raise AnalysisError(
            f"{p}: line {lines[0][0]}: column(s) {', '.join(ascii(c)[1:-1][:40] for c in twice)}"
            " named more than once; give each column once (which one is meant cannot be told)"
        )
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise AnalysisError(
            f"{p}: line {lines[0][0]}: missing column(s) {', '.join(missing)}; the header must "
            f"name {', '.join(REQUIRED_COLUMNS)} (and optionally {', '.join(OPTIONAL_COLUMNS)})"
        )
    unknown = [c for c in header if c not in REQUIRED_COLUMNS + OPTIONAL_COLUMNS]
    if unknown:
        shown = ", ".join(ascii(c)[1:-1][:40] for c in unknown[:5])  # escaped, unquoted
        raise AnalysisError(
            f"{p}: line {lines[0][0]}: unknown column(s) {shown}; allowed: "
            f"{', '.join(REQUIRED_COLUMNS + OPTIONAL_COLUMNS)}"
        )
    has_participants = "participant" in header
    records = []
    seen: dict[tuple, int] = {}
    for (lineno, _), values in zip(lines[1:], rows[1:], strict=True):
        if len(values) != len(header):
            raise AnalysisError(
                f"{p}: line {lineno}: {len(values)} fields, expected {len(header)} "
                f"({', '.join(header)})"
            )
        row = dict(zip(header, (v.strip() for v in values), strict=True))
        rec = _shift_record(p, lineno, row, has_participants)
        key = (
            rec["experiment"],
            rec["participant"],
            rec["target"],
            rec["masker"],
            rec["masker_level_db_sl"],
        )
        if key in seen:
            who = f"participant {rec['participant']}, " if has_participants else ""
            raise AnalysisError(
                f"{p}: line {lineno}: {who}{rec['target']}|{rec['masker']} at "
                f"{rec['masker_level_db_sl']:g} dB SL repeats line {seen[key]}; give one shift per "
                "cell"
                + (" and participant" if has_participants else " (or add a participant column)")
            )
        seen[key] = lineno
        records.append(rec)
    if not records:
        raise AnalysisError(f"{p}: no data rows after the header")
    table = pd.DataFrame(records)
    levels_told_apart(table, str(p))
    return table, has_participants


def levels_told_apart(shifts: pd.DataFrame, source: str) -> None:
    """Refuse masker levels of one pair that differ by less than :data:`MIN_LEVEL_SPACING_DB`.

    Parameters
    ----------
    shifts : DataFrame
        Columns ``experiment, target, masker, masker_level_db_sl`` (dB SL).
    source : str
        Names the input in the message (a file or a data folder).

    Raises
    ------
    AnalysisError
        Naming the pair and the two levels.

    Examples
    --------
    >>> t = pd.DataFrame({"experiment": ["e"] * 2, "target": ["EV270"] * 2,
    ...                   "masker": ["MV120"] * 2, "masker_level_db_sl": [5.0, 5.0 + 1e-12]})
    >>> levels_told_apart(t, "s.csv")
    Traceback (most recent call last):
    ...
    masking_lab.core.errors.AnalysisError: s.csv: EV270|MV120 (e): masker levels 5.0 and ...
    """
    if shifts.empty:
        return
    keys = ["experiment", "target", "masker"]
    for (experiment, target, masker), group in shifts.groupby(keys, sort=True):
        levels = sorted(set(group["masker_level_db_sl"].astype(float)))
        for lo, hi in itertools.pairwise(levels):
            if hi - lo < MIN_LEVEL_SPACING_DB:
                raise AnalysisError(
                    f"{source}: {target}|{masker} ({experiment}): masker levels {lo!r} and {hi!r}"
                    f" dB SL differ by less than {MIN_LEVEL_SPACING_DB:g} dB, so no fit can tell "
                    "them apart; write one level for the cells measured at it"
                )


def _error(file: str, where: str, message: str) -> AnalysisError:
    return AnalysisError(f"{file}: {where}: {message}" if where else f"{file}: {message}")


def _split(p: Path, lineno: int, line: str) -> list[str]:
    """One CSV line's fields (a quoted field never spans lines in this format)."""
    try:
        fields = next(csv.reader([line], strict=True))
    except (csv.Error, StopIteration) as exc:
        raise AnalysisError(
            f"{p}: line {lineno}: not a CSV row ({excerpt(str(exc), 80)}); check its quotes"
        ) from None
    if any(len(f) > 200 for f in fields):
        raise AnalysisError(f"{p}: line {lineno}: a field is longer than 200 characters")
    return fields


def _shift_record(p: Path, lineno: int, row: Mapping[str, str], has_participants: bool) -> dict:
    where = f"{p}: line {lineno}"
    names = {}
    for col in ("target", "masker"):
        if not is_stimulus_name(row[col]):
            raise AnalysisError(
                f"{where}: {col} {excerpt(row[col])} is not a stimulus name; write e.g. EV270 "
                "or MV120"
            )
        names[col] = parse_stimulus(row[col])
    target, masker = names["target"], names["masker"]
    numbers = {}
    for col in ("masker_level_db_sl", "shift_db", "masker_frequency_hz", "mv_frequency_hz"):
        if col not in row or (col not in REQUIRED_COLUMNS and row[col] == ""):
            continue
        try:
            numbers[col] = float(row[col])
        except ValueError:
            raise AnalysisError(f"{where}: {col} {excerpt(row[col])} is not a number") from None
        if not math.isfinite(numbers[col]):
            raise AnalysisError(f"{where}: {col} must be a finite number, got {excerpt(row[col])}")
        if abs(numbers[col]) > MAX_ABS_VALUE:
            # A level or shift of 1e308 dB is no measurement, and it overflows the fits.
            raise AnalysisError(
                f"{where}: {col} {excerpt(row[col])} is outside ±{MAX_ABS_VALUE:g}; check the value"
            )
    mv = masker if masker.channel == "MV" or target.channel != "MV" else target
    if "masker_frequency_hz" in numbers and numbers["masker_frequency_hz"] != masker.carrier_hz:
        raise AnalysisError(
            f"{where}: masker_frequency_hz {numbers['masker_frequency_hz']:g} does not match the "
            f"masker {masker.name} ({masker.carrier_hz:g} Hz); the column is the masker's carrier "
            "(the frequency factor is taken from the MV stimulus name)"
        )
    if "mv_frequency_hz" in numbers and numbers["mv_frequency_hz"] != mv.carrier_hz:
        raise AnalysisError(
            f"{where}: mv_frequency_hz {numbers['mv_frequency_hz']:g} does not match the pair's "
            f"MV stimulus {mv.name}"
        )
    participant = row.get("participant", "") if has_participants else ""
    if has_participants and not participant:
        raise AnalysisError(f"{where}: participant is empty; fill it in or drop the column")
    experiment = row.get("experiment") or (
        f"{target.name}|MV" if mv is masker else f"MV|{masker.name}"
    )
    return {
        "experiment": experiment,
        "participant": participant,
        "target": target.name,
        "masker": masker.name,
        "mv_stimulus": mv.name,
        "mv_frequency_hz": mv.carrier_hz,
        "masker_level_db_sl": numbers["masker_level_db_sl"],
        "shift_db": numbers["shift_db"],
    }
