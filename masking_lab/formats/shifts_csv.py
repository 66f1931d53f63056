"""The long CSV of AL shifts that ``masking-lab fit`` reads (see ``data_schema/shifts.csv``).

One row per cell (and participant): ``target, masker, masker_level_db_sl, shift_db`` are
required; ``participant``, ``masker_frequency_hz`` (the masker's carrier, checked against its
name), ``mv_frequency_hz`` and ``experiment`` are optional. Lines starting with ``#`` are
comments. Every problem is reported with the file, line and column.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping
from pathlib import Path

import pandas as pd

from masking_lab.core.errors import AnalysisError
from masking_lab.core.stimulus import is_stimulus_name, parse_stimulus

__all__ = ["OPTIONAL_COLUMNS", "REQUIRED_COLUMNS", "read_shifts_csv"]

REQUIRED_COLUMNS = ("target", "masker", "masker_level_db_sl", "shift_db")
OPTIONAL_COLUMNS = ("participant", "masker_frequency_hz", "mv_frequency_hz", "experiment")


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
    try:
        text = p.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise AnalysisError(f"{p}: cannot read the file ({exc.strerror or exc})") from exc
    lines = [
        (n, line)
        for n, line in enumerate(text.splitlines(), start=1)
        if line.strip() and not line.lstrip().startswith("#")
    ]
    if not lines:
        raise AnalysisError(f"{p}: the file is empty; expected a header line and shift rows")
    reader = csv.reader([line for _, line in lines])
    header = [h.strip() for h in next(reader)]
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise AnalysisError(
            f"{p}: line {lines[0][0]}: missing column(s) {', '.join(missing)}; the header must "
            f"name {', '.join(REQUIRED_COLUMNS)} (and optionally {', '.join(OPTIONAL_COLUMNS)})"
        )
    unknown = [c for c in header if c not in REQUIRED_COLUMNS + OPTIONAL_COLUMNS]
    if unknown:
        raise AnalysisError(
            f"{p}: line {lines[0][0]}: unknown column(s) {', '.join(unknown)}; allowed: "
            f"{', '.join(REQUIRED_COLUMNS + OPTIONAL_COLUMNS)}"
        )
    has_participants = "participant" in header
    records = []
    seen: dict[tuple, int] = {}
    for (lineno, _), values in zip(lines[1:], reader, strict=True):
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
    return pd.DataFrame(records), has_participants


def _shift_record(p: Path, lineno: int, row: Mapping[str, str], has_participants: bool) -> dict:
    where = f"{p}: line {lineno}"
    names = {}
    for col in ("target", "masker"):
        if not is_stimulus_name(row[col]):
            raise AnalysisError(
                f"{where}: {col} {row[col]!r} is not a stimulus name; write e.g. EV270 or MV120"
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
            raise AnalysisError(f"{where}: {col} {row[col]!r} is not a number") from None
        if not math.isfinite(numbers[col]):
            raise AnalysisError(f"{where}: {col} must be a finite number, got {row[col]!r}")
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
