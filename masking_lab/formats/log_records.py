"""Typed session-log records (msgspec Structs), one class per record kind.

Every line of a session log is one of the records below, told apart by its ``record`` field
(schema: ``data_schema/session_log.schema.json``). Two families of Structs describe them:

- the *full* records (:class:`Header`, :class:`SetStart`, :class:`Trial`, :class:`SetEnd`,
  :class:`Fault`, :class:`Resume`, :class:`UsertestTrial`, :class:`SessionEnd`, the union
  :data:`LogRecord`): every field the writer may write, typed; the writer checks each record
  against them (:func:`check_record`) before it reaches the disk, and :func:`decode_record`
  turns one line into one of them;
- the *analysis view* (:data:`AnalysisRecord`): only the fields ``analyze`` uses, decoded by
  :data:`ANALYSIS_DECODER` straight from the file's bytes (no dict per record, the rest of each
  line skipped), about six times faster than ``json.loads``. Its records answer ``rec["key"]``
  and ``rec.get("key")`` like the dicts :func:`~masking_lab.formats.session_log.read_log`
  returns, so the same threshold code runs on either.

Every field but ``record`` is optional here (``UNSET`` when absent): the schema says which
are required, and old logs (before ``seq``) still decode. ``seq`` is the record's line number,
written by the writer for continuity checks (:mod:`masking_lab.formats.log_integrity`).
Units: levels in dB re 1 V (``_db_v``) or dB SL (``_db_sl``), times in s on the session clock.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import msgspec
from msgspec import UNSET, UnsetType

__all__ = [
    "ANALYSIS_DECODER",
    "AnalysisRecord",
    "Fault",
    "Header",
    "LogRecord",
    "Resume",
    "SessionEnd",
    "SetEnd",
    "SetStart",
    "Trial",
    "UsertestTrial",
    "check_record",
    "decode_record",
    "record_kind",
    "view_keys",
]

Float = float | UnsetType
OptFloat = float | None | UnsetType
Int = int | UnsetType
OptInt = int | None | UnsetType
Str = str | UnsetType
OptStr = str | None | UnsetType
Bool = bool | UnsetType
Obj = dict[str, Any] | UnsetType
Floats = list[float] | UnsetType


class _Base(msgspec.Struct, tag_field="record", kw_only=True, omit_defaults=True):
    """Fields every record may carry: ``seq``, its 1-based line number in the log."""

    seq: Int = UNSET


class Header(_Base, tag="header"):
    """The first line: who, what protocol, which device, seed and clock (see the schema)."""

    schema_version: Int = UNSET
    session_id: Str = UNSET
    created_utc: Str = UNSET
    software_version: Str = UNSET
    protocol: Obj = UNSET
    participant: Str = UNSET
    calibration: dict[str, float] | UnsetType = UNSET
    device: Obj = UNSET
    responder: Str = UNSET
    seed: Int = UNSET
    set_order: list[str] | UnsetType = UNSET
    clock: Str = UNSET
    rig: Obj = UNSET
    simulated_observer: Obj = UNSET
    device_config: Str = UNSET
    kind: Str = UNSET
    usertest: Obj = UNSET


class SetStart(_Base, tag="set_start"):
    """A set begins: target, masker and its level (dB SL, dB re 1 V), staircase settings."""

    set_id: Str = UNSET
    target: Str = UNSET
    masker: OptStr = UNSET
    masker_level_db_sl: OptFloat = UNSET
    masker_level_db_v: OptFloat = UNSET
    unmasked_al_db_v: OptFloat = UNSET
    level_unit: Str = UNSET
    max_level_db: OptFloat = UNSET
    min_level_db: OptFloat = UNSET
    staircase: Obj = UNSET
    procedure: Obj = UNSET
    t_s: Float = UNSET


class Trial(_Base, tag="trial"):
    """One 3IFC trial: level (dB SL, dB re 1 V), intervals, answer, onsets (s)."""

    set_id: Str = UNSET
    trial_index: Int = UNSET
    level_db_sl: OptFloat = UNSET
    level_db_v: Float = UNSET
    target_interval: Int = UNSET
    response_interval: Int = UNSET
    correct: Bool = UNSET
    reversal: Bool = UNSET
    step_db: Float = UNSET
    next_level_db: OptFloat = UNSET
    posterior: Obj = UNSET
    at_bound: OptStr = UNSET
    planned_onsets_s: Floats = UNSET
    actual_onsets_s: Floats = UNSET
    response_time_s: Float = UNSET
    played_target_v: Float = UNSET
    played_masker_v: Float = UNSET
    device_extra: Obj = UNSET
    finger_path: list[list[float]] | UnsetType = UNSET


class SetEnd(_Base, tag="set_end"):
    """A set ends: status, AL (dB in the set's unit, dB re 1 V, dB SL), reversal levels."""

    set_id: Str = UNSET
    status: Str = UNSET
    al_db: OptFloat = UNSET
    al_db_v: OptFloat = UNSET
    al_db_sl: OptFloat = UNSET
    n_trials: Int = UNSET
    reversal_levels_db: Floats = UNSET
    reason: Str = UNSET
    sd_db: Float = UNSET
    method: Str = UNSET
    t_s: Float = UNSET


class Fault(_Base, tag="fault"):
    """Why the session stopped (device fault, interruption, unclean stop, disk error)."""

    kind: Str = UNSET
    message: Str = UNSET
    set_id: OptStr = UNSET
    trial_index: OptInt = UNSET
    t_s: Float = UNSET


class Resume(_Base, tag="resume"):
    """The session continues (``masking-lab resume``), with the device now used."""

    resumed_utc: Str = UNSET
    software_version: Str = UNSET
    dropped_partial_line: Bool = UNSET
    device: Obj = UNSET


class UsertestTrial(_Base, tag="usertest_trial"):
    """One answered user-test trial (answers are 1-based keys; times in s)."""

    participant: Str = UNSET
    trial: Int = UNSET
    geometry: Str = UNSET
    texture: Str = UNSET
    condition: Str = UNSET
    repeat: Int = UNSET
    geometry_answer: OptInt = UNSET
    texture_answer: OptInt = UNSET
    geometry_key: Int = UNSET
    texture_key: Int = UNSET
    correct_geometry: Bool = UNSET
    correct_texture: Bool = UNSET
    t_s: Float = UNSET
    planned_onsets_s: Floats = UNSET
    actual_onsets_s: Floats = UNSET
    geometry_time_s: OptFloat = UNSET
    texture_time_s: OptFloat = UNSET
    response_time_s: Float = UNSET
    n_frames: Int = UNSET
    played: Obj = UNSET
    clipped: Obj = UNSET
    touched_mm: list[list[float] | None] | UnsetType = UNSET
    finger_path: list[list[float]] | UnsetType = UNSET


class SessionEnd(_Base, tag="session_end"):
    """The session finished (``completed``) or was ended for good (``aborted``)."""

    status: Str = UNSET
    ended_utc: Str = UNSET


LogRecord = Header | SetStart | Trial | SetEnd | Fault | Resume | UsertestTrial | SessionEnd
_DECODER = msgspec.json.Decoder(LogRecord)


def record_kind(record: msgspec.Struct) -> str:
    """The ``record`` field of a typed record (its tag).

    Examples
    --------
    >>> record_kind(Trial(set_id="A", trial_index=0))
    'trial'
    """
    return str(record.__struct_config__.tag)


def check_record(record: Mapping[str, Any]) -> LogRecord:
    """The typed record for a record mapping the writer is about to write.

    Parameters
    ----------
    record : mapping
        A record with a known ``record`` kind; fields of the wrong type are refused, unknown
        fields are kept by the writer but not checked.

    Returns
    -------
    LogRecord
        The typed record.

    Raises
    ------
    ValueError
        Unknown record kind or a field of the wrong type (a bug in the code writing it).

    Examples
    --------
    >>> check_record({"record": "trial", "set_id": "A", "trial_index": 0}).trial_index
    0
    """
    try:
        return msgspec.convert(record, LogRecord)
    except msgspec.ValidationError as exc:
        raise ValueError(f"not a valid {record.get('record')!r} log record: {exc}") from exc


def decode_record(line: bytes | str) -> LogRecord:
    """One log line (JSON, without or with its newline) as a typed record.

    Raises
    ------
    msgspec.DecodeError
        Not JSON, or not a record of a known kind with fields of the right types (a
        ``ValueError``).

    Examples
    --------
    >>> rec = decode_record(b'{"record":"set_end","set_id":"A","status":"completed","al_db":-20}')
    >>> type(rec).__name__, rec.set_id, rec.al_db
    ('SetEnd', 'A', -20.0)
    """
    return _DECODER.decode(line)


# --------------------------------------------------------------------------------------------
# The analysis view: only what `analyze` reads


class _View(msgspec.Struct, tag_field="record", kw_only=True):
    """A record that answers like a dict: ``rec["key"]`` (KeyError if absent), ``rec.get``.

    Asking for a field the view does not decode is a bug (the answer would silently be
    "absent"), so it raises :class:`AttributeError`: add the field to the view.
    """

    seq: Int = UNSET
    # Typed, so a log whose set ids are not text falls back to the general reader, which
    # reports the line instead of grouping records by an unhashable id.
    set_id: str | UnsetType | None = UNSET
    _index: ClassVar[str | None] = None  # the field continuity counts (see log_integrity)

    def get(self, key: str, default: Any = None) -> Any:
        if key == "record":
            return self.__struct_config__.tag
        value = getattr(self, key, _ABSENT)
        if value is _ABSENT:
            raise AttributeError(
                f"the analysis view of {self.__struct_config__.tag!r} records does not decode "
                f"{key!r}; add it in masking_lab/formats/log_records.py"
            )
        return default if value is UNSET else value

    def __getitem__(self, key: str) -> Any:
        value = self.get(key, UNSET)
        if value is UNSET:
            raise KeyError(key)
        return value

    def __contains__(self, key: object) -> bool:
        return isinstance(key, str) and self.get(key, UNSET) is not UNSET


_ABSENT = object()


class _Order(msgspec.Struct):
    interleave: Any = UNSET


class _Content(msgspec.Struct):
    order: _Order | UnsetType = UNSET
    info: Any = UNSET  # the participant questions' specifications (participants.json)


class _Experiment(msgspec.Struct):
    experiment: Any = UNSET
    content: _Content | UnsetType = UNSET


class AHeader(_View, tag="header"):
    """Header fields the analysis uses (participant, experiment, ids, calibration in dB re 1 V)."""

    schema_version: Any = UNSET  # refused when newer than this version reads (log_bytes)
    participant: Any = UNSET
    session_id: Any = UNSET
    created_utc: Any = UNSET
    kind: Any = UNSET
    protocol: _Experiment | UnsetType = UNSET
    calibration: dict[str, Any] | UnsetType = UNSET
    rig: Any = UNSET  # compared per participant (analysis.rig_check)
    set_order: Any = UNSET  # the study matrix's planned sets (analysis.study_status)
    info: Any = UNSET  # the participant's answers (participants.tsv)

    def as_dict(self) -> dict[str, Any]:
        """The header as the dict :func:`read_log` would give, for the fields decoded."""
        out: dict[str, Any] = {"record": "header"}
        names = (
            "schema_version",
            "participant",
            "session_id",
            "created_utc",
            "kind",
            "calibration",
            "rig",
            "set_order",
            "info",
            "seq",
        )
        for name in names:
            value = getattr(self, name)
            if value is not UNSET:
                out[name] = value
        if not isinstance(self.protocol, UnsetType):
            exp = self.protocol.experiment
            out["protocol"] = {} if exp is UNSET else {"experiment": exp}
            content = self.protocol.content
            if not isinstance(content, UnsetType):
                order = content.order
                out["protocol"]["content"] = (
                    {}
                    if isinstance(order, UnsetType)
                    else {
                        "order": {}
                        if order.interleave is UNSET
                        else {"interleave": order.interleave}
                    }
                )
                if content.info is not UNSET:
                    out["protocol"]["content"]["info"] = content.info
        return out


class ASetStart(_View, tag="set_start"):
    target: Any = UNSET
    masker: Any = UNSET
    masker_level_db_sl: Any = UNSET
    unmasked_al_db_v: Any = UNSET
    level_unit: Any = UNSET
    staircase: Any = UNSET
    procedure: Any = UNSET


class ATrial(_View, tag="trial"):
    _index: ClassVar[str | None] = "trial_index"
    trial_index: Int = UNSET
    level_db_sl: OptFloat = UNSET
    level_db_v: OptFloat = UNSET
    correct: Bool = UNSET
    reversal: Bool = UNSET
    posterior: Any = UNSET
    played_target_v: OptFloat = UNSET  # compared with the request (analysis.played_levels)


class ASetEnd(_View, tag="set_end"):
    _index: ClassVar[str | None] = "n_trials"
    status: Any = UNSET
    n_trials: Any = UNSET
    reversal_levels_db: list[float] | UnsetType = UNSET
    reason: Any = UNSET
    al_db: Any = UNSET
    sd_db: Any = UNSET
    method: Any = UNSET


class AFault(_View, tag="fault"):
    pass


class AResume(_View, tag="resume"):
    pass


class AUsertestTrial(_View, tag="usertest_trial"):
    _index: ClassVar[str | None] = "trial"
    trial: Any = UNSET


class ASessionEnd(_View, tag="session_end"):
    status: Any = UNSET  # a completed session counts once per participant (analysis.batch)


AnalysisRecord = (
    AHeader | ASetStart | ATrial | ASetEnd | AFault | AResume | AUsertestTrial | ASessionEnd
)
ANALYSIS_DECODER = msgspec.json.Decoder(AnalysisRecord)
_VIEWS = (AHeader, ASetStart, ATrial, ASetEnd, AFault, AResume, AUsertestTrial, ASessionEnd)
_TAG = {cls: cls.__struct_config__.tag for cls in _VIEWS}
_INDEX = {cls: cls._index for cls in _VIEWS}


def view_keys(lines: list[int], records: list[Any]) -> list[tuple[int, Any, Any, Any, Any]]:
    """(line, kind, seq, set_id, index) of typed view records, absent values as None.

    The continuity checks' input (:func:`masking_lab.formats.log_integrity.record_key` says
    what ``index`` is), built without a method call per record: ~10x faster than asking each.

    Examples
    --------
    >>> recs = ANALYSIS_DECODER.decode_lines(b'{"record":"trial","set_id":"A","trial_index":0}\\n')
    >>> view_keys([2], recs)
    [(2, 'trial', None, 'A', 0)]
    """
    out = []
    for line, r in zip(lines, records, strict=True):
        cls = type(r)
        field = _INDEX[cls]
        index = getattr(r, field) if field else None
        out.append(
            (
                line,
                _TAG[cls],
                None if r.seq is UNSET else r.seq,
                None if r.set_id is UNSET else r.set_id,
                None if index is UNSET else index,
            )
        )
    return out
