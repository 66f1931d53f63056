"""The participant-information form shown in the participant's window, as pure state.

With ``--responder psychopy`` the protocol's ``info`` fields (age, handedness, ...) are asked in
the window, one field at a time, before the first set: the experimenter types, Enter confirms,
Backspace deletes, Esc stops the session before anything is logged. This module holds what the
form *is* (the answers so far, the field being typed, the message after a refused answer) and
how each key changes it; :mod:`masking_lab.responders.window_form` draws it and reads the keys.

The fields are duck-typed (:class:`InfoFieldLike`): ``session.participant_info.InfoField``
satisfies it, and this package may not import ``session`` (it sits below it).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

__all__ = ["FormState", "InfoFieldLike", "backspace", "start_form", "submit", "type_text"]


class InfoFieldLike(Protocol):
    """What the form needs of a field (see ``masking_lab.session.participant_info.InfoField``)."""

    name: str
    type: str
    choices: tuple[str, ...]
    required: bool
    description: str
    unit: str

    def convert(self, text: str) -> Any:
        """The value of ``text``; ValueError saying what is expected."""
        ...


@dataclass(frozen=True)
class FormState:
    """The form at one moment.

    Attributes
    ----------
    fields : tuple of InfoFieldLike
        The protocol's fields, in order.
    answers : mapping of str to str
        Answers as typed so far (the ``--info`` values included); empty text: skipped.
    index : int or None
        Position in ``fields`` of the field being asked; None when every field is answered.
    text : str
        What has been typed into the current field.
    error : str
        Why the last Enter was refused ("" when it was not).
    """

    fields: tuple[InfoFieldLike, ...]
    answers: Mapping[str, str]
    index: int | None
    text: str = ""
    error: str = ""

    @property
    def done(self) -> bool:
        """Every field has an answer (or was skipped as optional)."""
        return self.index is None

    @property
    def field(self) -> InfoFieldLike | None:
        """The field being asked, or None when done."""
        return None if self.index is None else self.fields[self.index]

    def question(self) -> str:
        """The current field's question: description or name, unit, optional or not.

        Examples
        --------
        >>> from masking_lab.session.participant_info import InfoField
        >>> start_form([InfoField("skin_temperature", "number", unit="degC")], {}).question()
        'skin temperature (degC), optional: Enter skips'
        """
        f = self.field
        if f is None:
            return ""
        what = f.description or f.name.replace("_", " ")
        unit = f" ({f.unit})" if f.unit else ""
        return f"{what}{unit}" + ("" if f.required else ", optional: Enter skips")

    def choices_line(self) -> str:
        """The current field's choices with the number that picks each ("" for free text).

        Examples
        --------
        >>> from masking_lab.session.participant_info import InfoField
        >>> f = InfoField("hand", "choice", ("left", "right"))
        >>> start_form([f], {}).choices_line()
        '1 = left    2 = right'
        """
        f = self.field
        if f is None or f.type != "choice":
            return ""
        if _numbers_pick(f):
            return "    ".join(f"{k} = {c}" for k, c in enumerate(f.choices, start=1))
        return " / ".join(f.choices)

    def position(self) -> str:
        """``field 2 of 5``, counting every field of the protocol ("" when done)."""
        if self.index is None:
            return ""
        return f"field {self.index + 1} of {len(self.fields)}"


def _numbers_pick(f: InfoFieldLike) -> bool:
    """Digits pick a choice by number unless some choice is itself a number."""
    return f.type == "choice" and not any(c.strip().isdigit() for c in f.choices)


def _next_missing(
    fields: Sequence[InfoFieldLike], answers: Mapping[str, str], after: int
) -> int | None:
    for k in range(after, len(fields)):
        if fields[k].name not in answers:
            return k
    return None


def start_form(fields: Sequence[InfoFieldLike], given: Mapping[str, str]) -> FormState:
    """The form before any key: the ``given`` (``--info``) answers kept, the next field asked.

    Parameters
    ----------
    fields : sequence of InfoFieldLike
        The protocol's ``info`` fields.
    given : mapping of str to str
        Values already given (``--info``), checked by the caller; empty text counts as not given.

    Examples
    --------
    >>> from masking_lab.session.participant_info import InfoField
    >>> fs = [InfoField("age", "integer", required=True), InfoField("notes")]
    >>> s = start_form(fs, {"age": "24"})
    >>> s.field.name, dict(s.answers)
    ('notes', {'age': '24'})
    """
    answers = {k: v for k, v in given.items() if v.strip()}
    fields = tuple(fields)
    return FormState(fields, answers, _next_missing(fields, answers, 0))


def type_text(state: FormState, chars: str) -> FormState:
    """``chars`` typed into the current field (control characters dropped).

    Examples
    --------
    >>> from masking_lab.session.participant_info import InfoField
    >>> type_text(start_form([InfoField("notes")], {}), "cold\\r room").text
    'cold room'
    """
    if state.done:
        return state
    printable = "".join(c for c in chars if c.isprintable())
    return dataclasses.replace(state, text=state.text + printable) if printable else state


def backspace(state: FormState) -> FormState:
    """The last typed character removed.

    Examples
    --------
    >>> from masking_lab.session.participant_info import InfoField
    >>> backspace(type_text(start_form([InfoField("notes")], {}), "ab")).text
    'a'
    """
    return dataclasses.replace(state, text=state.text[:-1]) if state.text else state


def submit(state: FormState) -> FormState:
    """Enter: the typed answer checked, then kept and the next field asked, or refused.

    An empty answer skips an optional field and is refused for a required one; a choice may be
    typed in full or by its number; numbers must read as numbers (the field's ``convert``).
    A refused answer stays in the box with the reason in ``error``.

    Examples
    --------
    >>> from masking_lab.session.participant_info import InfoField
    >>> fs = [InfoField("age", "integer", required=True),
    ...       InfoField("hand", "choice", ("left", "right"), required=True)]
    >>> s = submit(start_form(fs, {}))
    >>> s.error
    'age is required: type it, then Enter'
    >>> s = submit(type_text(s, "2x"))
    >>> s.field.name, s.error
    ('age', "age: '2x' is not a whole number")
    >>> s = submit(type_text(backspace(s), ""))
    >>> s.field.name, dict(s.answers)
    ('hand', {'age': '2'})
    >>> s = submit(type_text(s, "2"))
    >>> s.done, dict(s.answers)
    (True, {'age': '2', 'hand': 'right'})
    """
    f = state.field
    if f is None:
        return state
    text = state.text.strip()
    if not text:
        if f.required:
            return dataclasses.replace(state, error=f"{f.name} is required: type it, then Enter")
        return _advance(state, "")
    if _numbers_pick(f) and text.isdigit() and text not in f.choices:
        k = int(text)
        if not 1 <= k <= len(f.choices):
            return dataclasses.replace(
                state, error=f"{f.name}: choose 1 to {len(f.choices)} (or type the choice)"
            )
        text = f.choices[k - 1]
    try:
        f.convert(text)
    except ValueError as exc:
        return dataclasses.replace(state, error=str(exc))
    return _advance(state, text)


def _advance(state: FormState, answer: str) -> FormState:
    assert state.index is not None and state.field is not None
    answers = {**state.answers, state.field.name: answer}
    following = _next_missing(state.fields, answers, state.index + 1)
    return FormState(state.fields, answers, following)
