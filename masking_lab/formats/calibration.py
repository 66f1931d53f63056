"""A participant's calibration: unmasked ALs per stimulus (``DATA/<participant>/calibration.json``).

A baseline session writes one entry per completed set (the AL of that stimulus in dB re 1 V);
masked sessions read it to place target and masker levels in dB SL. The file follows
``data_schema/calibration.schema.json`` and is replaced atomically (temp file, fsync, rename), so
a crash leaves the old calibration or the new one, never half of one. Entries merge per
stimulus: re-running the baseline for one stimulus replaces that stimulus only.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from masking_lab.core.errors import CalibrationError
from masking_lab.core.stimulus import is_stimulus_name
from masking_lab.formats.fileio import write_text_atomic
from masking_lab.formats.reader import excerpt, load_document
from masking_lab.formats.schemas import (
    first_problem,
    key_path,
    schema_errors,
)

FILENAME = "calibration.json"


@dataclass(frozen=True)
class Calibration:
    """Unmasked ALs of one participant.

    Attributes
    ----------
    participant : str
        Participant id.
    unmasked_al_db_v : Mapping[str, float]
        Unmasked AL per stimulus name, dB re 1 V.
    sources : tuple[str, ...]
        Session logs the ALs came from (paths relative to the data folder where possible).
    updated_utc : str or None
        When the file was last written (ISO 8601, UTC).
    """

    participant: str
    unmasked_al_db_v: Mapping[str, float] = field(default_factory=dict)
    sources: tuple[str, ...] = ()
    updated_utc: str | None = None

    def missing(self, stimuli: Iterable[str]) -> list[str]:
        """Stimulus names of ``stimuli`` without an unmasked AL, sorted."""
        return sorted({s for s in stimuli if s not in self.unmasked_al_db_v})

    def to_json(self) -> dict[str, Any]:
        """The record as written to ``calibration.json``."""
        out: dict[str, Any] = {
            "participant": self.participant,
            "unmasked_al_db_v": dict(sorted(self.unmasked_al_db_v.items())),
            "sources": list(self.sources),
        }
        if self.updated_utc is not None:
            out["updated_utc"] = self.updated_utc
        return out


def calibration_path(data_dir: str | Path, participant: str) -> Path:
    """``DATA/<participant>/calibration.json``."""
    return Path(data_dir) / participant / FILENAME


def with_al(
    calibration: Calibration, stimulus: str, al_db_v: float, source: str, updated_utc: str
) -> Calibration:
    """Return ``calibration`` with ``stimulus``'s unmasked AL set to ``al_db_v`` (pure).

    Parameters
    ----------
    calibration : Calibration
        Current calibration.
    stimulus : str
        Stimulus name, e.g. ``"EV270"``.
    al_db_v : float
        Unmasked AL, dB re 1 V (finite).
    source : str
        Session log it came from; added to ``sources`` once.
    updated_utc : str
        Time stamp of the change (ISO 8601, UTC).

    Raises
    ------
    CalibrationError
        For a malformed stimulus name or a non-finite AL.
    """
    if not is_stimulus_name(stimulus):
        raise CalibrationError(f"{stimulus!r} is not a stimulus name (e.g. EV270, MV120am40)")
    if not math.isfinite(al_db_v):
        raise CalibrationError(
            f"unmasked AL of {stimulus} must be a finite dB re 1 V value, got {al_db_v!r}; "
            "a set that ended at a bound has no AL to calibrate with"
        )
    als = {**calibration.unmasked_al_db_v, stimulus: float(al_db_v)}
    sources = (
        calibration.sources if source in calibration.sources else (*calibration.sources, source)
    )
    return replace(calibration, unmasked_al_db_v=als, sources=sources, updated_utc=updated_utc)


def parse_calibration(
    data: Any, source: str, lines: Mapping[str, int] | None = None
) -> Calibration:
    """Build a :class:`Calibration` from the parsed JSON of ``source``.

    Raises
    ------
    CalibrationError
        Naming ``source`` and the offending key, if ``data`` breaks the schema.
    """
    problem = first_problem(data, "calibration", lines)
    if problem:
        at, what = problem
        raise CalibrationError(
            f"{source}: {at}: {what}; fix the file or delete it and re-run the baseline "
            "protocol for this participant"
        )
    return Calibration(
        participant=data["participant"],
        unmasked_al_db_v={k: float(v) for k, v in data["unmasked_al_db_v"].items()},
        sources=tuple(data["sources"]),
        updated_utc=data.get("updated_utc"),
    )


def read_calibration(path: str | Path) -> Calibration:
    """Read and validate a calibration file.

    Raises
    ------
    CalibrationError
        If the file cannot be read, is not JSON or breaks the schema.
    """
    doc = load_document(path, what="calibration", fmt="json", error=_calibration_error)
    return parse_calibration(doc.data, doc.source, doc.lines)


def _calibration_error(file: str, where: str, message: str) -> CalibrationError:
    head = f"{file}: {where}: " if where else f"{file}: "
    return CalibrationError(
        f"{head}{message}; fix the file or delete it and re-run the baseline protocol for this "
        "participant"
    )


def load_calibration(data_dir: str | Path, participant: str) -> Calibration:
    """The participant's calibration, or an empty one if the file does not exist yet.

    Raises
    ------
    CalibrationError
        If the file exists but is unreadable, invalid, or belongs to another participant.
    """
    path = calibration_path(data_dir, participant)
    if not path.exists():
        return Calibration(participant=participant)
    cal = read_calibration(path)
    if cal.participant != participant:
        raise CalibrationError(
            f"{path}: participant is {excerpt(cal.participant)} but the folder is {participant!r}; "
            "the file was copied from another participant — move it back or delete it"
        )
    return cal


def require(calibration: Calibration, stimuli: Iterable[str], data_dir: str | Path) -> None:
    """Refuse a masked session whose stimuli are not all calibrated.

    Raises
    ------
    CalibrationError
        Naming the missing stimuli and the baseline command that measures them.
    """
    missing = calibration.missing(stimuli)
    if missing:
        path = calibration_path(data_dir, calibration.participant)
        have = ", ".join(sorted(calibration.unmasked_al_db_v)) or "none"
        raise CalibrationError(
            f"{path}: participant {calibration.participant} has no unmasked AL for "
            f"{', '.join(missing)} (calibrated: {have}). Masked levels are in dB SL, so measure "
            f"them first: masking-lab run protocols/baseline.yaml --participant "
            f"{calibration.participant} --data {data_dir} --device ... --responder ..."
        )


def write_calibration(data_dir: str | Path, calibration: Calibration) -> Path:
    """Validate and atomically write ``calibration`` to its file; return the path.

    Raises
    ------
    CalibrationError
        If the record would break the schema (nothing is written then).
    """
    record = calibration.to_json()
    path = calibration_path(data_dir, calibration.participant)
    errors = schema_errors(record, "calibration")
    if errors:
        raise CalibrationError(
            f"{path}: refusing to write: {key_path(errors[0])}: {errors[0].message}"
        )
    return write_text_atomic(path, json.dumps(record, indent=2, ensure_ascii=False) + "\n")


def record_al(
    data_dir: str | Path,
    participant: str,
    stimulus: str,
    al_db_v: float,
    source: str,
    updated_utc: str,
) -> tuple[Calibration, float | None]:
    """Merge one unmasked AL into the participant's calibration file.

    Returns
    -------
    (Calibration, float or None)
        The calibration as written, and the AL it replaced (dB re 1 V) if there was one.
    """
    current = load_calibration(data_dir, participant)
    previous = current.unmasked_al_db_v.get(stimulus)
    updated = with_al(current, stimulus, al_db_v, source, updated_utc)
    write_calibration(data_dir, updated)
    return updated, previous
