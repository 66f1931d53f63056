"""Participant metadata a protocol asks for (PsychoPy's ``expInfo``): age, handedness, finger...

A protocol declares its fields in an ``info`` section::

    info:
      - {name: age, type: integer, required: true, unit: years}
      - {name: handedness, type: choice, choices: [left, right, ambidextrous], required: true}
      - {name: skin_temperature, type: number, unit: degC}
      - {name: notes, type: text, description: experimenter's notes}

``run`` takes the values from ``--info key=value`` and asks for the missing ones: on a terminal,
or with ``--responder psychopy`` in the participant's window
(:mod:`masking_lab.responders.window_form`); they are checked here (type, choices, required,
unknown names: every problem at once) and written into the session header's ``info``.
``analyze`` gathers them into ``participants.tsv``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from masking_lab.core.errors import InputError, ProtocolError

__all__ = [
    "INFO_TYPES",
    "InfoField",
    "ask_missing",
    "info_fields",
    "parse_info_args",
    "resolve_info",
]

INFO_TYPES = ("text", "integer", "number", "choice")


@dataclass(frozen=True)
class InfoField:
    """One field of a protocol's ``info`` section.

    Attributes
    ----------
    name : str
        Key in the header's ``info`` and column of ``participants.tsv``.
    type : {"text", "integer", "number", "choice"}
        How the value is read.
    choices : tuple of str
        The allowed values of a ``choice`` field.
    required : bool
        ``run`` refuses to start without it.
    description, unit : str
        For the prompt and the ``participants.json`` sidecar.
    """

    name: str
    type: str = "text"
    choices: tuple[str, ...] = ()
    required: bool = False
    description: str = ""
    unit: str = ""

    def prompt(self) -> str:
        """The question asked on a terminal."""
        what = self.description or self.name.replace("_", " ")
        hint = f" [{'/'.join(self.choices)}]" if self.choices else ""
        unit = f" ({self.unit})" if self.unit else ""
        return f"{what}{unit}{hint}{'' if self.required else ' (optional, Enter to skip)'}: "

    def convert(self, text: str) -> Any:
        """The value of ``text``, or InputError (a ValueError) saying what is expected.

        Examples
        --------
        >>> InfoField("age", "integer").convert("24"), InfoField("t", "number").convert("31.5")
        (24, 31.5)
        >>> InfoField("hand", "choice", ("left", "right")).convert("up")
        Traceback (most recent call last):
        ...
        masking_lab.core.errors.InputError: hand: 'up' is not one of left, right
        """
        text = text.strip()
        if self.type == "integer":
            try:
                return int(text)
            except ValueError:
                raise InputError(f"{self.name}: {text!r} is not a whole number") from None
        if self.type == "number":
            try:
                value = float(text)
            except ValueError:
                raise InputError(f"{self.name}: {text!r} is not a number") from None
            if not math.isfinite(value):
                raise InputError(f"{self.name}: {text!r} is not a finite number")
            return value
        if self.type == "choice" and text not in self.choices:
            raise InputError(f"{self.name}: {text!r} is not one of {', '.join(self.choices)}")
        return text


def info_fields(content: Mapping[str, Any]) -> list[InfoField]:
    """The fields of a (schema-checked) protocol's ``info`` section, in order.

    Examples
    --------
    >>> [f.name for f in info_fields({"info": [{"name": "age", "type": "integer"}]})]
    ['age']
    """
    out = []
    for spec in content.get("info") or []:
        out.append(
            InfoField(
                name=str(spec["name"]),
                type=str(spec.get("type", "text")),
                choices=tuple(str(c) for c in spec.get("choices") or ()),
                required=bool(spec.get("required", False)),
                description=str(spec.get("description", "")),
                unit=str(spec.get("unit", "")),
            )
        )
    return out


def parse_info_args(items: Sequence[str]) -> dict[str, str]:
    """``--info key=value`` options as a mapping (the last of a repeated key wins).

    Raises
    ------
    ProtocolError
        For an item without ``=``.

    Examples
    --------
    >>> parse_info_args(["age=24", "notes=cold room, 19 °C"])
    {'age': '24', 'notes': 'cold room, 19 °C'}
    """
    out: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ProtocolError("--info", "", f"{item!r}: write KEY=VALUE, e.g. --info age=24")
        out[key.strip()] = value
    return out


def resolve_info(
    fields: Sequence[InfoField],
    given: Mapping[str, str],
    source: str = "protocol",
    *,
    require: bool = True,
) -> dict[str, Any]:
    """Check and convert the given values against the fields; every problem in one error.

    Parameters
    ----------
    fields : sequence of InfoField
        The protocol's ``info`` section.
    given : mapping of str to str
        Values as typed (``--info`` or the prompts); empty text counts as not given.
    source : str
        The protocol file, named in the error.
    require : bool
        Refuse missing required fields; False checks only what was given (the window asks
        for the rest).

    Returns
    -------
    dict
        Field name → converted value, in the protocol's order (fields not given left out).

    Raises
    ------
    ProtocolError
        Naming every unknown name, unreadable value and missing required field.

    Examples
    --------
    >>> fs = [InfoField("age", "integer", required=True), InfoField("notes")]
    >>> resolve_info(fs, {"age": "31"})
    {'age': 31}
    >>> try:
    ...     resolve_info(fs, {"agee": "31"})
    ... except ProtocolError as exc:
    ...     print(str(exc).replace("; ", ";\\n"))
    protocol: info: unknown field agee (the protocol asks for age, notes);
    missing required age: give --info age=...
    """
    names = [f.name for f in fields]
    problems = []
    unknown = [k for k in given if k not in names]
    if unknown:
        asked = ", ".join(names) if names else "nothing: it has no info section"
        problems.append(f"unknown field {', '.join(unknown)} (the protocol asks for {asked})")
    out: dict[str, Any] = {}
    for f in fields:
        text = given.get(f.name, "")
        if text.strip() == "":
            continue
        try:
            out[f.name] = f.convert(text)
        except ValueError as exc:
            problems.append(str(exc))
    missing = [f.name for f in fields if f.required and f.name not in out] if require else []
    missing = [m for m in missing if not any(p.startswith(f"{m}:") for p in problems)]
    if missing:
        problems.append(
            f"missing required {', '.join(missing)}: give "
            + " ".join(f"--info {m}=..." for m in missing)
        )
    if problems:
        raise ProtocolError(source, "info", "; ".join(problems))
    return out


def ask_missing(
    fields: Sequence[InfoField],
    given: Mapping[str, str],
    ask: Callable[[str], str] = input,
) -> dict[str, str]:
    """``given`` plus an answer, asked with ``ask``, for every field not given (shell).

    A wrong answer is asked again with the reason, so a typo never ends the session.

    Examples
    --------
    >>> answers = iter(["abc", "24", ""])
    >>> ask_missing([InfoField("age", "integer", required=True), InfoField("notes")], {},
    ...             ask=lambda q: next(answers))
    age: 'abc' is not a whole number
    {'age': '24', 'notes': ''}
    """
    out = dict(given)
    for f in fields:
        if out.get(f.name, "").strip():
            continue
        while True:
            text = ask(f.prompt())
            if not text.strip():
                if f.required:
                    print(f"{f.name} is required")
                    continue
                out[f.name] = ""
                break
            try:
                f.convert(text)
            except ValueError as exc:
                print(exc)
                continue
            out[f.name] = text
            break
    return out
