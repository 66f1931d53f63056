"""Threshold-session protocols: YAML files checked against ``data_schema/protocol.schema.json``.

:func:`load_protocol` reads a file safely (no object construction), validates it against the
schema and against rules the schema cannot express (duplicate keys or sets, stimulus names, more
reversals averaged than run, masker levels above the rig's limits), and returns an immutable
:class:`ThresholdProtocol` (named so beside :class:`typing.Protocol` and
:mod:`masking_lab.device.protocol`, the wire protocol). Every problem is a
:class:`~masking_lab.core.errors.ProtocolError` naming the file, the key path and the YAML line,
and saying what to do.
"""

from __future__ import annotations

import difflib
import hashlib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from masking_lab.core.errors import ProcedureError, ProtocolError
from masking_lab.core.stimulus import Stimulus, parse_stimulus
from masking_lab.formats.reader import decode_utf8, excerpt, parse_yaml, read_limited, where
from masking_lab.formats.schemas import describe_type_error, key_path, load_schema, schema_errors
from masking_lab.procedures.limits import session_work_problem, trial_work
from masking_lab.procedures.registry import (
    DEFAULT_KIND,
    ProtocolContext,
    SettingsProblem,
    kind_named,
    kind_of,
)
from masking_lab.procedures.staircase import StaircaseSettings

Kind = Literal["baseline", "masked"]

#: The longest trial (lead-in, three intervals and two gaps) a board plays, s:
#: TRIAL_MAX_DURATION_US of firmware/core/trial.h; the schema bounds each part by it too.
MAX_TRIAL_S = 60.0


@dataclass(frozen=True)
class Timing:
    """Trial timing, all in s (paper: 1.8 s intervals)."""

    stimulus_s: float = 1.8
    gap_s: float = 0.6
    lead_in_s: float = 1.2
    inter_trial_s: float = 0.5
    response_timeout_s: float | None = None
    rest_between_sets_s: float = 0.0

    @property
    def trial_s(self) -> float:
        """Duration of the three presentations with their lead-in and gaps, s."""
        return self.lead_in_s + 3 * self.stimulus_s + 2 * self.gap_s


@dataclass(frozen=True)
class SetSpec:
    """One set: a staircase for ``target`` with ``masker`` at ``masker_level_db_sl``.

    Attributes
    ----------
    id : str
        Unique within the protocol.
    target : Stimulus
        Stimulus whose AL is measured.
    masker : Stimulus or None
        Masker played in all three intervals (None in baseline sets).
    masker_level_db_sl : float or None
        Masker level in dB SL of the masker (None in baseline sets).
    staircase : StaircaseSettings or None
        The staircase for this set (start level in the protocol's level unit); None when the
        set runs another procedure and the protocol has no ``staircase`` block.
    procedure : settings of a registered procedure kind, or None
        The set's procedure when it is not the staircase (``procedure: {kind: quest_plus}``);
        None runs ``staircase`` (the default and the paper's choice).
    """

    id: str
    target: Stimulus
    masker: Stimulus | None
    masker_level_db_sl: float | None
    staircase: StaircaseSettings | None
    procedure: Any = None

    @property
    def trial_cap(self) -> int:
        """The most trials this set's track can take (every kind has a finite cap)."""
        return int(kind_of(self.settings).trial_cap(self.settings))

    @property
    def settings(self) -> Any:
        """The settings of the procedure this set runs (levels in the protocol's unit)."""
        chosen = self.procedure if self.procedure is not None else self.staircase
        assert chosen is not None  # the loader gives every set one
        return chosen


@dataclass(frozen=True)
class ThresholdProtocol:
    """A validated threshold-session protocol: its sets, procedure settings and timing.

    Attributes
    ----------
    path : str
        File it came from.
    sha256 : str
        Hash of the file's bytes (logged with every session).
    experiment : str
        Experiment id.
    kind : {"baseline", "masked"}
        Baseline sets run in dB re 1 V; masked sets in dB SL.
    sets : tuple[SetSpec, ...]
        In file order.
    timing : Timing
        Trial timing.
    randomize_order : bool
        Shuffle sets per participant from the session seed.
    interleave : bool
        Run all sets of a session at once, one trial at a time from a set drawn at random
        (seeded) among the unfinished ones, as PsychoPy's MultiStairHandler does.
    content : dict
        The parsed YAML (logged, so a log is self-contained).
    """

    path: str
    sha256: str
    experiment: str
    kind: Kind
    sets: tuple[SetSpec, ...]
    timing: Timing
    randomize_order: bool = True
    description: str = ""
    interleave: bool = False
    content: Mapping[str, Any] = field(default_factory=dict, compare=False, repr=False)

    @property
    def level_unit(self) -> Literal["db_sl", "db_v"]:
        """Unit of staircase levels: ``db_v`` for baseline, ``db_sl`` for masked protocols."""
        return "db_v" if self.kind == "baseline" else "db_sl"

    def set_by_id(self, set_id: str) -> SetSpec:
        """The set with this id (KeyError with the known ids otherwise)."""
        for s in self.sets:
            if s.id == set_id:
                return s
        raise KeyError(f"no set {set_id!r} in {self.path}; sets are {[s.id for s in self.sets]}")

    def set_order(self, seed: int) -> list[str]:
        """Set ids in presentation order for a session with this ``seed`` (pure)."""
        ids = [s.id for s in self.sets]
        if not self.randomize_order:
            return ids
        perm = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5E75])).permutation(
            len(ids)
        )
        return [ids[i] for i in perm]

    def summary(self) -> str:
        """One line for ``validate``: sets, procedures and the trial cap per set.

        Examples
        --------
        >>> from masking_lab.formats.resources import shipped
        >>> load_protocol(shipped("protocols", "experiment1.yaml")).summary()
        'experiment1 (masked, 15 sets; staircase, at most 150 trials per set)'
        """
        kinds = sorted({s.settings.kind for s in self.sets})
        caps = sorted({s.trial_cap for s in self.sets})
        cap = f"{caps[0]}" if len(caps) == 1 else f"{caps[0]}–{caps[-1]}"
        return (
            f"{self.experiment} ({self.kind}, {len(self.sets)} sets; {', '.join(kinds)}, "
            f"at most {cap} trials per set)"
        )

    def stimuli(self) -> set[str]:
        """Names of every stimulus the protocol plays."""
        out = {s.target.name for s in self.sets}
        out |= {s.masker.name for s in self.sets if s.masker is not None}
        return out


# --------------------------------------------------------------------------------------------
# Loading


def load_protocol(
    path: str | Path, *, max_level_db_sl: Mapping[str, float] | None = None
) -> ThresholdProtocol:
    """Read, validate and build a protocol.

    Parameters
    ----------
    path : str or Path
        YAML file.
    max_level_db_sl : mapping of channel → dB SL, optional
        Highest sensation level the rig may present per channel (``"EV"``, ``"MV"``); masker
        levels above it are refused.

    Raises
    ------
    ProtocolError
        Naming the file, key path and line of the first problem(s).
    """
    p = Path(path)
    raw = read_limited(p, what="file")
    return parse_protocol(raw, str(p), max_level_db_sl=max_level_db_sl)


def parse_protocol(
    raw: bytes, source: str, *, max_level_db_sl: Mapping[str, float] | None = None
) -> ThresholdProtocol:
    """:func:`load_protocol` on bytes already read; ``source`` names them in messages."""
    data, lines = _safe_yaml(decode_utf8(raw, source), source)
    return protocol_from_mapping(
        data,
        source,
        sha256=hashlib.sha256(raw).hexdigest(),
        lines=lines,
        max_level_db_sl=max_level_db_sl,
    )


def protocol_from_mapping(
    data: Any,
    source: str,
    *,
    sha256: str,
    lines: Mapping[str, int] | None = None,
    max_level_db_sl: Mapping[str, float] | None = None,
) -> ThresholdProtocol:
    """Validate and build a protocol from an already parsed mapping (no file, no YAML).

    This is how ``resume`` rebuilds the protocol stored in a log header: the mapping is used as
    it is, never written back to YAML and parsed again.

    Parameters
    ----------
    data : mapping
        The protocol's content (what :func:`load_protocol` parses from YAML).
    source : str
        Names the data in error messages.
    sha256 : str
        Hash of the file the content came from (kept on the :class:`ThresholdProtocol`).
    lines : mapping of key path → line, optional
        Where each key stands in the source, for messages; none for data without a file.
    max_level_db_sl : mapping of channel → dB SL, optional
        As for :func:`load_protocol`.

    Raises
    ------
    ProtocolError
        If the content breaks the schema or the rules.

    Examples
    --------
    >>> import yaml
    >>> from masking_lab.formats.resources import shipped
    >>> data = yaml.safe_load(shipped("protocols", "baseline.yaml").read_text())
    >>> protocol_from_mapping(data, "baseline", sha256="0" * 64).kind
    'baseline'
    """
    lines = lines if lines is not None else {}
    if not isinstance(data, dict):
        raise ProtocolError(
            source, "line 1", "a protocol is a YAML mapping (key: value lines) at the top level"
        )
    problems = list(_schema_problems(data, lines))
    if problems:
        raise ProtocolError(source, problems[0][0], _join(problems))
    protocol, problems = _build(data, source, sha256, lines)
    if protocol is not None:
        # What validate accepts must run: the session's trials and placement work are bounded.
        work = session_work_problem([(s.trial_cap, trial_work(s.settings)) for s in protocol.sets])
        if work is not None:
            problems.append((_where("sets", lines), work))
    if max_level_db_sl is not None and protocol is not None:
        problems += list(_limit_problems(protocol, data, lines, max_level_db_sl))
    if problems or protocol is None:
        raise ProtocolError(source, problems[0][0], _join(problems))
    return protocol


def _join(problems: list[tuple[str, str]]) -> str:
    first = problems[0][1]
    if len(problems) == 1:
        return first
    more = "; ".join(f"{where}: {msg}" for where, msg in problems[1:6])
    extra = f" (and {len(problems) - 6} more)" if len(problems) > 6 else ""
    return f"{first}\n  also: {more}{extra}"


def _safe_yaml(text: str, source: str) -> tuple[Any, dict[str, int]]:
    """Parse YAML through the shared reader (limits, no aliases, no duplicate keys, finite
    numbers); return the data and a key-path → line map."""
    return parse_yaml(text, source)


def _where(path: str, lines: Mapping[str, int]) -> str:
    return where(path, lines)


def _schema_problems(data: Any, lines: Mapping[str, int]) -> Iterator[tuple[str, str]]:
    schema = load_schema("protocol")
    for err in schema_errors(data, "protocol"):
        path = key_path(err)
        if err.validator == "additionalProperties":
            # additionalProperties reports an object schema and an object instance
            err_schema = err.schema if isinstance(err.schema, Mapping) else {}
            instance = err.instance if isinstance(err.instance, Mapping) else {}
            parent = err_schema.get("properties", {})
            extras = [k for k in instance if k not in parent]
            for key in extras:
                child = f"{path}.{key}" if path != "(top level)" else str(key)
                hint = difflib.get_close_matches(str(key), list(parent), n=1)
                tip = f"did you mean {hint[0]!r}?" if hint else f"known keys: {', '.join(parent)}"
                yield _where(child, lines), f"unknown key {excerpt(key)}; {tip}"
            continue
        if err.validator == "required":
            missing = err.message.split("'")[1] if "'" in err.message else err.message
            yield _where(path, lines), f"missing required key {missing!r}"
            continue
        if (
            err.validator == "const"
            and err.absolute_path
            and err.absolute_path[-1] == "schema_version"
        ):
            yield _where(path, lines), f"schema_version must be 1, got {excerpt(err.instance)}"
            continue
        desc = _describe(err, schema)
        yield _where(path, lines), desc


def _describe(err: Any, schema: Mapping[str, Any]) -> str:
    v, inst = err.validator, err.instance
    finite = describe_type_error(err)
    if finite is not None:
        return finite
    if v == "type":
        want = err.validator_value
        want = " or ".join(want) if isinstance(want, list) else want
        return f"must be of type {want}, got {type(inst).__name__} {excerpt(inst)}"
    if v in ("minimum", "exclusiveMinimum"):
        op = "≥" if v == "minimum" else ">"
        return f"must be {op} {err.validator_value}, got {excerpt(inst)}"
    if v == "enum":
        return f"must be one of {err.validator_value}, got {excerpt(inst)}"
    if v == "pattern":
        if "EV|MV" in str(err.validator_value):
            return (
                f"{excerpt(inst)} is not a stimulus name: write <EV|MV><carrier Hz>"
                "[am<envelope Hz>], "
                "e.g. EV270, MV120, MV120am40"
            )
        return f"{excerpt(inst)} may only contain letters, digits, '_', '-' and '.'"
    if v == "minItems":
        return f"needs at least {err.validator_value} item(s)"
    if v == "oneOf" and isinstance(inst, str):
        return (
            f"{excerpt(inst)} is not a stimulus name: write <EV|MV><carrier Hz>"
            "[am<envelope Hz>], "
            "or null for no masker"
        )
    return err.message


def _build(
    data: Mapping[str, Any], source: str, sha256: str, lines: Mapping[str, int]
) -> tuple[ThresholdProtocol | None, list[tuple[str, str]]]:
    problems: list[tuple[str, str]] = []
    kind: Kind = data["kind"]
    top_procedure = dict(data.get("procedure") or {"kind": DEFAULT_KIND})
    timing = Timing(**data.get("timing", {}))
    if timing.trial_s > MAX_TRIAL_S:
        # The board refuses a trial longer than this (firmware/core/trial.h): say so here.
        problems.append(
            (
                _where("timing", lines),
                f"lead_in_s + 3 x stimulus_s + 2 x gap_s = {timing.trial_s:g} s, over the "
                f"{MAX_TRIAL_S:g} s a device plays in one trial; shorten the intervals or gaps",
            )
        )
    default_target = data.get("target")
    sets: list[SetSpec] = []
    seen_ids: dict[str, int] = {}
    seen_conditions: dict[tuple[Any, ...], str] = {}

    def note(problem: tuple[str, str]) -> None:
        if problem not in problems:  # a protocol-wide block is reported once
            problems.append(problem)

    for i, s in enumerate(data["sets"]):
        here = f"sets[{i}]"
        sid = s["id"]
        if sid in seen_ids:
            problems.append(
                (
                    _where(f"{here}.id", lines),
                    f"duplicate set id {sid!r} (also sets[{seen_ids[sid]}])",
                )
            )
        seen_ids.setdefault(sid, i)
        target_name = s.get("target", default_target)
        if target_name is None:
            problems.append(
                (
                    _where(here, lines),
                    "no target stimulus: give `target:` in the set or at top level",
                )
            )
            continue
        masker_name = s.get("masker")
        level = s.get("masker_level_db_sl")
        if kind == "baseline" and (masker_name is not None or level is not None):
            problems.append(
                (
                    _where(here, lines),
                    "a baseline protocol measures unmasked ALs: remove masker and "
                    "masker_level_db_sl, or set kind: masked",
                )
            )
        chosen = _set_procedure(top_procedure, s.get("procedure"))
        block_key = "procedure" if s.get("procedure") is None else f"{here}.procedure"
        try:
            proc_kind = kind_named(chosen.get("kind", DEFAULT_KIND))
        except ProcedureError as exc:  # the schema's enum names the kinds first
            note((_where(f"{block_key}.kind", lines), str(exc)))
            continue
        level_missing = level is None and not proc_kind.places_masker
        if kind == "masked" and (masker_name is None or level_missing):
            problems.append(
                (
                    _where(here, lines),
                    "a masked set needs both `masker` (a stimulus name) and `masker_level_db_sl`",
                )
            )
        condition = (target_name, masker_name, level)
        if condition in seen_conditions:
            problems.append(
                (
                    _where(here, lines),
                    f"duplicate set: same target, masker and masker level as set "
                    f"{seen_conditions[condition]!r}; remove one",
                )
            )
        seen_conditions.setdefault(condition, sid)
        ctx = ProtocolContext(chosen, block_key, data, s, here)
        try:
            settings = proc_kind.from_protocol(ctx)
        except SettingsProblem as exc:
            note((_where(exc.key, lines), exc.detail))
            continue
        staircase: StaircaseSettings | None = None
        if proc_kind.name == DEFAULT_KIND:
            staircase, settings = settings, None
        elif "staircase" in data:
            # The protocol's staircase block, kept for `plan` to set beside this procedure.
            try:
                staircase = kind_named(DEFAULT_KIND).from_protocol(
                    ProtocolContext({}, "staircase", data, {}, here)
                )
            except SettingsProblem as exc:
                note((_where(exc.key, lines), exc.detail))
                continue
        sets.append(_set_spec(sid, target_name, masker_name, level, staircase, settings))
    if problems:
        return None, problems
    protocol = ThresholdProtocol(
        path=source,
        sha256=sha256,
        experiment=data["experiment"],
        kind=kind,
        sets=tuple(sets),
        timing=timing,
        randomize_order=bool(data.get("order", {}).get("randomize", True)),
        interleave=bool(data.get("order", {}).get("interleave", False)),
        description=str(data.get("description", "")).strip(),
        content=data,
    )
    return protocol, []


def _set_spec(
    sid: str,
    target_name: str,
    masker_name: str | None,
    level: float | None,
    staircase: StaircaseSettings | None,
    procedure: Any,
) -> SetSpec:
    return SetSpec(
        id=sid,
        target=parse_stimulus(target_name),
        masker=parse_stimulus(masker_name) if masker_name is not None else None,
        masker_level_db_sl=float(level) if level is not None else None,
        staircase=staircase,
        procedure=procedure,
    )


def _set_procedure(top: Mapping[str, Any], own: Mapping[str, Any] | None) -> dict[str, Any]:
    """A set's ``procedure`` block: its own keys over the protocol's when the kinds agree."""
    if not own:
        return dict(top)
    own_kind = own.get("kind", top.get("kind", DEFAULT_KIND))
    if own_kind == top.get("kind", DEFAULT_KIND):
        return {**top, **own}
    return dict(own)


def _limit_problems(
    protocol: ThresholdProtocol,
    data: Mapping[str, Any],
    lines: Mapping[str, int],
    max_level_db_sl: Mapping[str, float],
) -> Iterator[tuple[str, str]]:
    for i, s in enumerate(protocol.sets):
        masker_range = kind_of(s.settings).masker_range_db_sl(s.settings)
        if s.masker is not None and masker_range is not None:
            limit = max_level_db_sl.get(s.masker.channel)
            if limit is not None and masker_range[0] > limit:
                yield (
                    _where("procedure.masker_min_db_sl", lines),
                    f"set {s.id}: masker {s.masker.name} from {masker_range[0]:g} dB SL is "
                    f"above the device limit for {s.masker.channel} ({limit:g} dB SL); the "
                    "procedure needs masker levels the rig can play",
                )
            continue
        if s.masker is None or s.masker_level_db_sl is None:
            continue
        limit = max_level_db_sl.get(s.masker.channel)
        if limit is not None and s.masker_level_db_sl > limit:
            yield (
                _where(f"sets[{i}].masker_level_db_sl", lines),
                f"masker {s.masker.name} at {s.masker_level_db_sl:g} dB SL is above the device "
                f"limit for {s.masker.channel} ({limit:g} dB SL); lower it or use a rig config "
                "whose limit allows it",
            )
