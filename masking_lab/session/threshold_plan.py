"""What a threshold session needs before its first trial, and what its log header holds.

The header of a new session, the sets to run, the stimuli they need calibrated, and on resume
the protocol copy from the header, the check that logged trials replay to their logged levels,
and where the session stopped.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from masking_lab.core.errors import (
    LogError,
    ProtocolError,
)
from masking_lab.device.level_check import refuse_unplayable
from masking_lab.formats.calibration import load_calibration, require
from masking_lab.formats.protocol import ThresholdProtocol, protocol_from_mapping
from masking_lab.formats.session_log import SessionLog, SetRecords
from masking_lab.session.procedure_records import settings_from_record
from masking_lab.session.progress import ProgressLine


def select_sets(
    protocol: ThresholdProtocol, order: list[str], wanted: Sequence[str] | None
) -> list[str]:
    if not wanted:
        return order
    known = set(order)
    unknown = [s for s in wanted if s not in known]
    if unknown:
        raise ProtocolError(
            protocol.path,
            "sets",
            f"--sets names {', '.join(repr(s) for s in unknown)}, which the protocol does not "
            f"have; its sets are {', '.join(order)}",
        )
    chosen = set(wanted)
    return [s for s in order if s in chosen]


def stimuli_of(protocol: ThresholdProtocol, order: Sequence[str]) -> set[str]:
    names: set[str] = set()
    for set_id in order:
        spec = protocol.set_by_id(set_id)
        names.add(spec.target.name)
        if spec.masker is not None:
            names.add(spec.masker.name)
    return names


def checked_calibration(
    protocol: ThresholdProtocol,
    order: Sequence[str],
    data_dir: Path,
    participant: str,
    device_config: str | Path | None,
) -> dict[str, float]:
    """What a new session checks before its first trial; the unmasked ALs it plays from, dB V.

    The participant's calibration file reads (a baseline writes its ALs there, so a broken file
    must not surface after a set was played), holds the unmasked AL of every stimulus of a
    masked protocol's sets in ``order``, and every level those sets may ask for is playable on
    the rig (converter resolution). ``run`` and ``validate --data --participant`` both call it.

    Raises
    ------
    CalibrationError, LevelError
        The file is unreadable or lacks an AL; a level is out of the rig's reach.
    """
    calibration: dict[str, float] = {}
    cal = load_calibration(data_dir, participant)
    if protocol.kind == "masked":
        needed = stimuli_of(protocol, order)
        require(cal, needed, data_dir)
        calibration = {name: float(cal.unmasked_al_db_v[name]) for name in sorted(needed)}
    refuse_unplayable(protocol, list(order), calibration, device_config)
    return calibration


def protocol_from_header(
    header: Mapping[str, Any], path: Path, allow_changed: bool, out: ProgressLine
) -> ThresholdProtocol:
    meta = header["protocol"]
    logged_sha = str(meta["sha256"])
    on_disk = Path(str(meta["path"]))
    try:
        raw = on_disk.read_bytes() if on_disk.is_file() else None
    except OSError:
        # A logged path the OS cannot look up or read (too long, no permission): nothing to
        # compare; resume runs the stored copy either way (campaign seed 62: a traceback).
        raw = None
    if raw is not None:
        import hashlib

        sha = hashlib.sha256(raw).hexdigest()
        if sha != logged_sha:
            if not allow_changed:
                raise LogError(
                    f"{path}: the protocol file {on_disk} has changed since this session started "
                    f"(sha256 {sha[:12]}… now, {logged_sha[:12]}… in the log). Restore it, or "
                    "resume with --allow-changed-protocol to continue with the copy stored in "
                    "the log (the file on disk is never used by resume)"
                )
            out.message(
                f"note: {on_disk} has changed since the session started; continuing with the "
                "protocol stored in the log"
            )
    try:
        protocol = protocol_from_mapping(
            dict(meta["content"]), f"{path} (protocol stored in the header)", sha256=logged_sha
        )
    except ProtocolError as exc:
        raise LogError(f"{path}: the protocol stored in the header is invalid: {exc}") from exc
    return dataclasses.replace(protocol, path=str(meta["path"]))


def check_trials(
    path: Path, protocol: ThresholdProtocol, existing: Mapping[str, SetRecords]
) -> None:
    """Logged trials must be contiguous and replay to their logged levels (any procedure)."""
    level_key = "level_db_sl" if protocol.level_unit == "db_sl" else "level_db_v"
    for set_id, rec in existing.items():
        try:
            spec = protocol.set_by_id(set_id)
        except KeyError as exc:
            raise LogError(f"{path}: set {set_id!r} is not in the logged protocol") from exc
        indices = [t.get("trial_index") for t in rec.trials]
        if indices != list(range(len(indices))):
            raise LogError(
                f"{path}: set {set_id}: trial indices {indices} are not 0, 1, 2, …; the log has "
                "been edited or merged and cannot be resumed safely"
            )
        settings = settings_from_record(rec.start, spec)
        state = settings.start()
        for t in rec.trials:
            logged = t.get(level_key)
            level = state.next_level()
            if state.finished or logged is None or abs(float(logged) - level) > 1e-6:
                raise LogError(
                    f"{path}: set {set_id}, trial {t.get('trial_index')}: logged level {logged} "
                    f"but replaying the logged responses gives {level}; the log does not "
                    f"match its {settings.kind} settings and cannot be resumed"
                )
            correct = t.get("correct")
            if not isinstance(correct, bool):
                raise LogError(
                    f"{path}: set {set_id}, trial {t.get('trial_index')}: 'correct' is "
                    f"{correct!r}, not true or false; the log has been edited and cannot be "
                    "resumed"
                )
            state = state.update(correct)


def position(log: SessionLog) -> tuple[str | None, int | None]:
    set_id: str | None = None
    index: int | None = None
    for rec in log.records:
        kind = rec.get("record")
        if kind == "set_start":
            set_id, index = rec.get("set_id"), 0
        elif kind == "trial":
            set_id, index = rec.get("set_id"), int(rec.get("trial_index", -1)) + 1
        elif kind == "set_end":
            set_id, index = rec.get("set_id"), None
    return set_id, index
