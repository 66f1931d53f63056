"""The one registry of adaptive procedures (pure): a procedure kind registers here once.

Everything the rest of the package needs to know about a procedure is one
:class:`ProcedureKind`: how a protocol states it (its schema fragment and how its settings are
built from a protocol), what it puts in the session log and how its settings come back from
it, how it fits under the device's limit, what the progress line says about it, how many
trials it has left and at most, why a track has no AL, how ``analyze`` re-estimates it from its
logged trials, and its vectorised batch for ``plan``. The session loop, the protocol reader,
the log records, pace, progress and the analysis ask the registry; none of them names a kind.

Adding a procedure: a module with its settings and state classes
(:class:`~masking_lab.procedures.base.Procedure`), a ``*_kind`` module defining ``KIND``, and
one line in :data:`_KIND_MODULES`. ``tests/test_procedure_conformance.py`` runs the
conformance checks over every registered kind.

Levels are dB in the set's level unit (dB SL in a masked protocol, dB re 1 V in a baseline).
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from masking_lab.core.errors import ProcedureError
from masking_lab.procedures.base import Procedure

__all__ = [
    "DEFAULT_KIND",
    "ProcedureKind",
    "ProtocolContext",
    "SettingsProblem",
    "kind_named",
    "kind_of",
    "kinds",
    "protocol_schema_fragment",
    "settings_record",
]

#: The kind a set runs when its protocol names none (the paper's choice).
DEFAULT_KIND = "staircase"

#: Modules defining ``KIND``, in the order kinds are listed to users.
_KIND_MODULES = (
    "masking_lab.procedures.staircase_kind",
    "masking_lab.procedures.quest_plus_kind",
    "masking_lab.procedures.functional_kind",
)


class SettingsProblem(ProcedureError):
    """A procedure's settings in a protocol are invalid; ``key`` is the protocol key path.

    Examples
    --------
    >>> SettingsProblem("procedure.max_trials", "must be ≥ 1").key
    'procedure.max_trials'
    """

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}")
        self.key = key
        self.detail = message

    @classmethod
    def of(cls, exc: ProcedureError, kind: str, key: str) -> SettingsProblem:
        """``exc``, a ``<kind> setting NAME: ...`` error, at the protocol key ``key.NAME``.

        Examples
        --------
        >>> SettingsProblem.of(ProcedureError("quest_plus setting lapses: < 0.5"), "quest_plus",
        ...                    "procedure").key
        'procedure.lapses'
        """
        head, _, detail = str(exc).partition(": ")
        name = head.removeprefix(f"{kind} setting ").removeprefix(f"{kind} settings")
        where = f"{key}.{name}" if name and " " not in name else key
        return cls(where, detail or str(exc))


@dataclass(frozen=True)
class ProtocolContext:
    """What a kind may read of a protocol to build one set's settings.

    Attributes
    ----------
    block : mapping
        The set's ``procedure:`` block merged over the protocol's (with ``kind``).
    block_key : str
        Its key path (``procedure`` or ``sets[i].procedure``).
    protocol : mapping
        The whole protocol.
    set_data : mapping
        The set's mapping.
    set_key : str
        Its key path (``sets[i]``).
    """

    block: Mapping[str, Any]
    block_key: str
    protocol: Mapping[str, Any]
    set_data: Mapping[str, Any]
    set_key: str


def _no_masker(_state: Procedure) -> float | None:
    return None


def _no_text(_state: Any, _unit: str) -> str | None:
    return None


def _unchanged(settings: Any, _limit: float) -> Any:
    return settings


def _no_range(_settings: Any) -> tuple[float, float] | None:
    return None


@dataclass(frozen=True)
class ProcedureKind:
    """One adaptive procedure as the rest of the package sees it.

    Attributes
    ----------
    name : str
        The protocol's ``kind``.
    settings_type, state_type : type
        Its settings class (``kind``, ``start()``) and its :class:`Procedure` class.
    log_key : str
        The ``set_start`` key holding its settings (``procedure`` with ``kind`` inside, or
        ``staircase`` for the paper's staircase, as logs always had it).
    schema : mapping
        JSON-Schema properties it adds to the protocol's ``procedure`` block.
    from_protocol : callable(ProtocolContext) → settings
        Builds a set's settings; raises :class:`SettingsProblem` naming the key.
    from_record : callable(mapping, fallback) → settings
        Rebuilds settings from :func:`settings_record` (``fallback``: the protocol's settings).
    start_level_db : callable(settings) → float
        The lowest level the first trial may be at, dB (the device must reach it).
    within_limit : callable(settings, max_db) → settings
        The settings with their stimulus range capped at the device limit ``max_db``.
    trial_fields : callable(before, after) → dict
        Its keys of a ``trial`` record (posterior summaries, reversals).
    end_fields : callable(state) → dict
        Its keys of a ``set_end`` record beyond ``al_db``/``sd_db``/``method``.
    progress : callable(state, unit) → str
        The track's part of the progress line (``reversals 4/11``, ``posterior 3.2 ± 1.5 dB SL``).
    trials_left : callable(state, finished_set_trials) → float
        Expected trials before the running track stops.
    trial_cap : callable(settings) → int
        A hard bound on the trials of one track (every track has one).
    no_al_reason : callable(state, unit, target_max_v) → str
        Why a track that did not complete has no AL.
    estimate_log : callable or None
        ``(settings, levels, correct, estimator, lapse) → ProcedureEstimate``-like tuple
        ``(al, sd, lo, hi, method, status, note)``; None: ``analyze`` estimates it elsewhere
        (the staircase's reversal mean).
    replay_batch : callable(settings, answers) → TrackBatch
        The vectorised replay of an answer matrix (R tracks × T answers).
    simulate_batch : callable(settings, thresholds, scale_db, lapse, rng) → TrackBatch
        R simulated tracks against observers with these thresholds (dB).
    examples : callable() → list of settings
        Small settings the conformance suite runs.
    masker_level_db_sl : callable(state) → float or None
        The masker level of the next trial for procedures that place it (None: the set's).
    start_key : str
        The protocol key to lower when the first trial is above what the device can drive.
    result_text : callable(state, unit) → str or None
        What a completed track found when it is not one AL (a ramp's posterior), for the
        experimenter's set summary; None: the AL says it.
    summary : str
        One phrase for the schema and docs (what the kind is).
    places_masker : bool
        True when the procedure chooses each trial's masker level (its sets then state a
        masker but no ``masker_level_db_sl``).
    within_masker_limit : callable(settings, max_db_sl) → settings
        The settings with their masker range capped at the rig's rating (dB SL of the masker).
    masker_range_db_sl : callable(settings) → (lo, hi) or None
        The masker levels the procedure may play, dB SL (None: the set's one level).
    """

    name: str
    settings_type: type
    state_type: type
    log_key: str
    schema: Mapping[str, Any]
    from_protocol: Callable[[ProtocolContext], Any]
    from_record: Callable[[Mapping[str, Any], Any], Any]
    start_level_db: Callable[[Any], float]
    within_limit: Callable[[Any, float], Any]
    trial_fields: Callable[[Any, Any], dict[str, Any]]
    end_fields: Callable[[Any], dict[str, Any]]
    progress: Callable[[Any, str], str]
    trials_left: Callable[[Any, Sequence[int]], float]
    trial_cap: Callable[[Any], int]
    no_al_reason: Callable[[Any, str, float], str]
    estimate_log: Callable[..., Any] | None
    replay_batch: Callable[[Any, Any], Any]
    simulate_batch: Callable[..., Any]
    examples: Callable[[], list[Any]]
    masker_level_db_sl: Callable[[Any], float | None] = field(default=_no_masker)
    start_key: str = "procedure.min_level_db"
    places_masker: bool = False
    within_masker_limit: Callable[[Any, float], Any] = field(default=_unchanged)
    masker_range_db_sl: Callable[[Any], tuple[float, float] | None] = field(default=_no_range)
    summary: str = ""
    result_text: Callable[[Any, str], str | None] = field(default=_no_text)


@functools.cache
def kinds() -> tuple[ProcedureKind, ...]:
    """Every registered procedure kind, in the order they are listed to users.

    Examples
    --------
    >>> [k.name for k in kinds()][:2]
    ['staircase', 'quest_plus']
    """
    out = tuple(importlib.import_module(m).KIND for m in _KIND_MODULES)
    names = [k.name for k in out]
    if len(set(names)) != len(names):
        raise RuntimeError(f"procedure kinds registered twice: {names}")
    return out


def names() -> list[str]:
    """The registered kinds' names."""
    return [k.name for k in kinds()]


def kind_named(name: object) -> ProcedureKind:
    """The kind a protocol or log calls ``name``.

    Raises
    ------
    ProcedureError
        For a name no kind registered, listing the known ones.

    Examples
    --------
    >>> kind_named("quest_plus").log_key
    'procedure'
    """
    for k in kinds():
        if k.name == name:
            return k
    raise ProcedureError(
        f"unknown procedure kind {name!r}; this version knows {', '.join(names())}"
    )


def kind_of(obj: object) -> ProcedureKind:
    """The kind of a settings object or a track state.

    Examples
    --------
    >>> from masking_lab.procedures.staircase import StaircaseSettings
    >>> kind_of(StaircaseSettings(0.0).start()).name
    'staircase'
    """
    for k in kinds():
        if isinstance(obj, k.settings_type | k.state_type):
            return k
    raise ProcedureError(f"{type(obj).__name__} is not a registered procedure's settings or state")


def settings_record(settings: Any) -> dict[str, Any]:
    """Settings as JSON-ready data (tuples as lists; ``kind`` unless logged under its own key).

    Examples
    --------
    >>> from masking_lab.procedures.quest_plus import QuestPlusSettings
    >>> settings_record(QuestPlusSettings(-20.0, 45.0))["kind"]
    'quest_plus'
    """
    record = dataclasses.asdict(settings)
    for key, value in record.items():
        if isinstance(value, tuple):
            record[key] = list(value)
    k = kind_of(settings)
    if k.log_key == "procedure":
        record = {"kind": k.name, **record}
    return record


def settings_from_start(start: Mapping[str, Any], fallback: Any) -> Any:
    """The settings a ``set_start`` record names (``fallback`` if it names none).

    Raises
    ------
    ProcedureError
        For an unknown kind or settings its kind refuses.

    Examples
    --------
    >>> from masking_lab.procedures.quest_plus import QuestPlusSettings
    >>> rec = {"procedure": settings_record(QuestPlusSettings(-20.0, 30.0))}
    >>> settings_from_start(rec, None).max_level_db
    30.0
    """
    procedure = start.get("procedure")
    if procedure:
        if not isinstance(procedure, Mapping):
            raise ProcedureError("set_start.procedure must be a mapping with a kind")
        return kind_named(procedure.get("kind")).from_record(procedure, fallback)
    for k in kinds():
        if k.log_key != "procedure" and start.get(k.log_key):
            return k.from_record(start[k.log_key], fallback)
    return fallback


def protocol_schema_fragment() -> dict[str, Any]:
    """The ``$defs.procedure`` schema every registered kind's keys make up.

    ``data_schema/protocol.schema.json`` holds exactly this (a test checks it), so a kind's
    keys are stated once, here.

    Examples
    --------
    >>> frag = protocol_schema_fragment()
    >>> frag["properties"]["kind"]["enum"][:2]
    ['staircase', 'quest_plus']
    """
    props: dict[str, Any] = {
        "kind": {
            "enum": names(),
            "description": "The set's adaptive procedure (docs/procedures.md): "
            + "; ".join(f"{k.name}: {k.summary}" for k in kinds())
            + ".",
        }
    }
    for k in kinds():
        for key, schema in k.schema.items():
            if key in props and props[key] != schema:
                raise RuntimeError(f"procedure key {key!r} registered twice with other schemas")
            props[key] = schema
    return {"type": "object", "additionalProperties": False, "properties": props}
