"""Find and apply the JSON Schemas shipped in ``data_schema/``.

The schemas are installed as the package ``masking_lab.data_schema`` so that a plain
``pip install .`` finds them; an editable install maps the same folder.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable, Mapping
from functools import cache
from typing import Any

import jsonschema

from masking_lab.formats.resources import shipped


@cache
def load_schema(name: str) -> dict[str, Any]:
    """Return the parsed schema ``data_schema/<name>.schema.json``.

    Parameters
    ----------
    name : str
        Schema stem, e.g. ``"protocol"`` or ``"masking_params"``.
    """
    text = shipped("data_schema", f"{name}.schema.json").read_text(encoding="utf-8")
    return json.loads(text)


def _finite_number(checker: Any, instance: Any) -> bool:
    # NaN passes every JSON Schema bound (each comparison with it is false) and inf passes
    # "minimum": a number in our files is always meant to be finite.
    if isinstance(instance, bool) or not isinstance(instance, int | float):
        return False
    return math.isfinite(instance) if isinstance(instance, float) else abs(instance) <= 1e308


def _finite_integer(checker: Any, instance: Any) -> bool:
    if isinstance(instance, float):
        return math.isfinite(instance) and instance.is_integer()
    return _finite_number(checker, instance)


@cache
def _validator(name: str) -> Any:
    schema = load_schema(name)
    base = jsonschema.validators.validator_for(schema)
    types = base.TYPE_CHECKER.redefine_many({"number": _finite_number, "integer": _finite_integer})
    cls = jsonschema.validators.extend(base, type_checker=types)
    return cls(schema, format_checker=jsonschema.FormatChecker())


def schema_errors(instance: Any, name: str) -> list[jsonschema.ValidationError]:
    """All validation errors of ``instance`` against schema ``name``, in document order.

    ``number`` and ``integer`` mean *finite* numbers here: NaN, ±inf and integers beyond
    float range (about 1.8e308) fail the ``type`` check, whatever bounds the schema states.

    Examples
    --------
    >>> cal = {"participant": "P1", "sources": [], "unmasked_al_db_v": {"EV270": float("nan")}}
    >>> [e.validator for e in schema_errors(cal, "calibration")]
    ['type']
    """
    checked = _records_checked(instance, _record_arrays(name))
    return sorted(
        _validator(name).iter_errors(checked), key=lambda e: [str(p) for p in e.absolute_path]
    )


# Schema keywords whose meaning a record array's check below fully covers (annotations aside);
# any other keyword (a format, a bound, a branch, a reference) leaves the array to jsonschema.
_NOTES = frozenset({"description", "title", "$comment", "examples"})
_OBJECT_KEYS = _NOTES | {"type", "properties", "required", "additionalProperties"}
_ROOT_KEYS = _OBJECT_KEYS | {"$schema", "$id", "$defs"}
_ARRAY_KEYS = _NOTES | {"type", "items"}
_STRING_KEYS = _NOTES | {"type", "pattern"}

RecordCheck = Callable[[Any], bool]


@cache
def _record_arrays(name: str) -> tuple[tuple[tuple[str, ...], RecordCheck], ...]:
    """Key paths of schema ``name``'s arrays of flat string records (reached through plain
    objects' ``properties``), each with a check of one item that is true exactly when
    jsonschema finds nothing wrong with it: a 10,000-log study's ``provenance.inputs`` took
    jsonschema 0.35 s, ~35 µs per item, and a plain loop takes ~1 µs."""
    found: list[tuple[tuple[str, ...], RecordCheck]] = []

    def walk(node: Any, path: tuple[str, ...], allowed: frozenset[str]) -> None:
        if not isinstance(node, dict) or not set(node) <= allowed:
            return
        if node.get("type", "object") != "object":
            return
        for key, sub in node.get("properties", {}).items():
            check = _record_check(sub)
            if check is not None:
                found.append(((*path, key), check))
            else:
                walk(sub, (*path, key), _OBJECT_KEYS)

    walk(load_schema(name), (), _ROOT_KEYS)
    return tuple(found)


def _record_check(array: Any) -> RecordCheck | None:
    """The item check of an array of objects whose properties are all (patterned) strings, or
    None for any other schema."""
    if not isinstance(array, dict) or not set(array) <= _ARRAY_KEYS:
        return None
    item = array.get("items")
    if array.get("type") != "array" or not isinstance(item, dict):
        return None
    if not set(item) <= _OBJECT_KEYS or item.get("type") != "object":
        return None
    extra_keys = item.get("additionalProperties", True)
    props = item.get("properties", {})
    required = item.get("required", [])
    if (
        extra_keys not in (True, False)
        or not isinstance(props, dict)
        or not isinstance(required, list)
    ):
        return None
    strings: list[tuple[str, Callable[[str], Any] | None]] = []
    for key, prop in props.items():
        if not isinstance(prop, dict) or not set(prop) <= _STRING_KEYS:
            return None
        if prop.get("type") != "string" or not isinstance(prop.get("pattern", ""), str):
            return None
        pattern = prop.get("pattern")
        strings.append((key, re.compile(pattern).search if pattern is not None else None))
    known, needed = frozenset(props), frozenset(required)

    def check(record: Any) -> bool:
        if not isinstance(record, dict) or not needed <= record.keys():
            return False
        if not extra_keys and not record.keys() <= known:
            return False
        for key, search in strings:
            if key in record:
                value = record[key]
                if not isinstance(value, str) or (search is not None and search(value) is None):
                    return False
        return True

    return check


def _records_checked(instance: Any, arrays: tuple[tuple[tuple[str, ...], RecordCheck], ...]) -> Any:
    """``instance`` with each record array whose every item passes its check replaced by an
    empty list (copies along the way; the caller's document is not changed). jsonschema then
    reports exactly what it reports of ``instance``: such an array has no error of its own,
    and its parents' keywords (type, required, closed keys) do not look at its items."""
    for path, check in arrays:
        instance = _emptied(instance, path, check)
    return instance


def _emptied(node: Any, path: tuple[str, ...], check: RecordCheck) -> Any:
    if not isinstance(node, dict) or path[0] not in node:
        return node
    value = node[path[0]]
    if len(path) > 1:
        inner = _emptied(value, path[1:], check)
        return node if inner is value else {**node, path[0]: inner}
    if isinstance(value, list) and value and all(map(check, value)):
        return {**node, path[0]: []}
    return node


def most_relevant(errors: list[jsonschema.ValidationError]) -> jsonschema.ValidationError:
    """The error to report first: for ``oneOf``/``anyOf`` the failing branch's own error (its
    key path and a short message), not the whole-instance "not valid under any" message.

    Examples
    --------
    >>> cal = {"participant": "P1", "sources": [], "unmasked_al_db_v": {"EV270": "x"}}
    >>> key_path(most_relevant(schema_errors(cal, "calibration")))
    'unmasked_al_db_v.EV270'
    """
    return jsonschema.exceptions.best_match(errors) or errors[0]


def describe_type_error(error: jsonschema.ValidationError) -> str | None:
    """``"must be a finite number, got nan"`` for a non-finite number failing ``type``, else None.

    Examples
    --------
    >>> cal = {"participant": "P1", "sources": [], "unmasked_al_db_v": {"EV270": float("inf")}}
    >>> err = schema_errors(cal, "calibration")[0]
    >>> describe_type_error(err)
    'must be a finite number, got inf'
    """
    inst = error.instance
    if error.validator != "type" or isinstance(inst, bool):
        return None
    if isinstance(inst, float) and not math.isfinite(inst):
        return f"must be a finite number, got {inst!r}"
    if isinstance(inst, int) and abs(inst) > 1e308:
        return f"must be a finite number, got a {len(str(inst))}-digit integer"
    return None


def key_path(error: jsonschema.ValidationError) -> str:
    """A dotted key path such as ``sets[3].masker_level_db_sl`` for a validation error."""
    out = ""
    for part in error.absolute_path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "(top level)"


def describe(error: jsonschema.ValidationError) -> str:
    """A short message for a schema error, quoting at most a sanitised excerpt of the input.

    Examples
    --------
    >>> cal = {"participant": "P1", "sources": [], "unmasked_al_db_v": {"EV270": "x" * 500}}
    >>> describe(schema_errors(cal, "calibration")[0])
    "must be of type number, got str 'xxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxx…"
    """
    from masking_lab.formats.reader import excerpt

    finite = describe_type_error(error)
    if finite is not None:
        return finite
    v, inst, want = error.validator, error.instance, error.validator_value
    if v == "type":
        want = " or ".join(want) if isinstance(want, list) else want
        return f"must be of type {want}, got {type(inst).__name__} {excerpt(inst)}"
    if v in ("minimum", "exclusiveMinimum", "maximum", "exclusiveMaximum"):
        op = {"minimum": "≥", "exclusiveMinimum": ">", "maximum": "≤", "exclusiveMaximum": "<"}
        return f"must be {op[v]} {want}, got {excerpt(inst)}"
    if v in ("enum", "const"):
        return f"must be {'one of ' if v == 'enum' else ''}{want!r}, got {excerpt(inst)}"
    if v == "pattern":
        return f"{excerpt(inst)} does not match the pattern {want}"
    if v == "additionalProperties" and isinstance(inst, dict):
        schema = error.schema if isinstance(error.schema, Mapping) else {}
        known = set(schema.get("properties", {}))
        extra = [excerpt(k) for k in inst if k not in known][:3]
        return f"unknown key(s) {', '.join(extra)}; known keys: {', '.join(sorted(known))}"
    if v == "required":
        return f"{error.message}: add it"
    if v in ("maxItems", "minItems") and isinstance(inst, list):
        # jsonschema's own words quote the whole list; the count is what matters.
        bound = "at most" if v == "maxItems" else "at least"
        return f"must have {bound} {want} items, got {len(inst)}"
    return excerpt(error.message, 160)


def first_problem(
    instance: Any,
    name: str,
    lines: Mapping[str, int] | None = None,
    describe_error: Callable[[jsonschema.ValidationError], str] = describe,
) -> tuple[str, str] | None:
    """Where and what the most relevant problem of ``instance`` under schema ``name`` is.

    Parameters
    ----------
    instance : Any
        The parsed document.
    name : str
        Schema stem, e.g. ``"scene"``.
    lines : mapping of key path → line, optional
        Where each key stands in the source file (see :func:`~masking_lab.formats.reader.where`).
    describe_error : callable, optional
        Words for one error (default :func:`describe`); a file kind may say more.

    Returns
    -------
    (str, str) or None
        The key path (with its line when known) and the message, which counts the other
        problems; None if ``instance`` is valid.

    Examples
    --------
    >>> cal = {"participant": "P1", "sources": [], "unmasked_al_db_v": {"EV270": "x"}}
    >>> first_problem(cal, "calibration", {"unmasked_al_db_v": 3})
    ('unmasked_al_db_v.EV270 (line 3)', "must be of type number, got str 'x'")
    >>> first_problem({}, "calibration")
    ('(top level)', "'participant' is a required property: add it (and 2 more problem(s))")
    """
    from masking_lab.formats.reader import where

    errors = schema_errors(instance, name)
    if not errors:
        return None
    err = most_relevant(errors)
    more = f" (and {len(errors) - 1} more problem(s))" if len(errors) > 1 else ""
    return where(key_path(err), lines or {}), f"{describe_error(err)}{more}"
