"""The participant-information form drawn in the PsychoPy window and typed into (*shell*).

The form's state and rules are in :mod:`masking_lab.responders.info_form`; this module draws
them with ``visual.TextStim`` and feeds them the keyboard. Characters come from pyglet's
``on_text`` events (so Shift, accents and the keypad type what the keyboard says), Enter,
Backspace and Esc from ``on_key_press``; both are read through handlers pushed onto the
window's pyglet handler stack, in the order they were typed, and popped when the form ends.
PsychoPy's own handlers still see every key; its key buffer is cleared afterwards, so nothing
typed into the form answers a trial or starts a set.

No Qt is needed (``psychopy.gui`` is not used): the form lives in the full-screen window the
session already has.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

from masking_lab.responders.info_form import (
    FormState,
    InfoFieldLike,
    backspace,
    start_form,
    submit,
    type_text,
)

__all__ = ["ERROR_COLOUR", "FormScreen", "ask_in_window"]

ERROR_COLOUR = (235, 90, 80)  # the refusal line, 0–255 RGB; nothing else on screen is red
ANSWER_COLOUR = (255, 255, 255)
HINT = "Enter: next    Backspace: delete    Esc: stop (nothing is saved)"


class FormScreen:
    """The text stimuli of the form on ``win`` (sizes in px; ``text_px`` the letter height)."""

    def __init__(self, visual: Any, win: Any, text_px: float, colour: tuple[int, int, int]):
        width = float(win.size[0]) * 0.85
        step = 2.2 * text_px

        def stim(y_steps: float, rgb: tuple[int, int, int], scale: float = 1.0) -> Any:
            return visual.TextStim(
                win, text="", pos=(0.0, y_steps * step), height=text_px * scale, color=rgb,
                colorSpace="rgb255", wrapWidth=width,
            )  # fmt: skip

        self.title = stim(4.0, colour)
        self.position = stim(3.0, colour, 0.7)
        self.question = stim(1.5, colour)
        self.choices = stim(0.5, colour, 0.8)
        self.answer = stim(-0.8, ANSWER_COLOUR)
        self.error = stim(-2.0, ERROR_COLOUR, 0.8)
        self.hint = stim(-3.5, colour, 0.6)
        self.title.text = "Before we start: about the participant"
        self.hint.text = HINT

    def draw(self, state: FormState, cursor: bool) -> None:
        """Draw (without flipping) ``state``; ``cursor`` shows the text cursor this frame."""
        self.position.text = state.position()
        self.question.text = state.question()
        self.choices.text = state.choices_line()
        self.answer.text = "> " + state.text + ("_" if cursor else " ")
        self.error.text = state.error
        for s in (self.title, self.position, self.question, self.choices, self.answer, self.hint):
            s.draw()
        if state.error:
            self.error.draw()


def ask_in_window(
    win: Any,
    visual: Any,
    event: Any,
    fields: Sequence[InfoFieldLike],
    given: Mapping[str, str],
    flip: Callable[[], None],
    *,
    text_px: float,
    colour: tuple[int, int, int],
) -> dict[str, str]:
    """Ask every field not in ``given`` in the window; the answers as typed.

    Parameters
    ----------
    win, visual, event
        The open ``psychopy.visual.Window`` and PsychoPy's ``visual`` and ``event`` modules.
    fields : sequence of InfoFieldLike
        The protocol's ``info`` fields.
    given : mapping of str to str
        ``--info`` values (already checked); not asked again.
    flip : callable
        Shows the drawn frame (the responder's paced flip).
    text_px : float
        Letter height, px.
    colour : tuple of int
        Text colour, 0–255 RGB.

    Returns
    -------
    dict
        ``given`` plus one answer per other field ("" for a skipped optional one), each accepted
        by the field's checks (required, choices, type).

    Raises
    ------
    KeyboardInterrupt
        Esc: the session stops before its log is written.
    """
    import pyglet

    key = pyglet.window.key
    typed: list[tuple[str, str]] = []  # ("text", chars) or ("key", name), in typing order
    names = {key.RETURN: "enter", key.ENTER: "enter", key.NUM_ENTER: "enter"}
    names |= {key.BACKSPACE: "backspace", key.ESCAPE: "escape"}

    def on_text(text: str) -> None:
        typed.append(("text", text))

    def on_key_press(symbol: int, modifiers: int) -> None:
        if symbol in names:
            typed.append(("key", names[symbol]))

    screen = FormScreen(visual, win, text_px, colour)
    state = start_form(fields, given)
    handle = win.winHandle
    handle.push_handlers(on_text=on_text, on_key_press=on_key_press)
    frame = 0
    try:
        while not state.done:
            screen.draw(state, cursor=(frame // 30) % 2 == 0)
            flip()  # dispatches the window's events into ``typed``
            frame += 1
            while typed and not state.done:
                kind, value = typed.pop(0)
                if kind == "text":
                    state = type_text(state, value)
                elif value == "escape":
                    raise KeyboardInterrupt
                elif value == "backspace":
                    state = backspace(state)
                else:
                    state = submit(state)
    finally:
        handle.remove_handlers(on_text=on_text, on_key_press=on_key_press)
        event.clearEvents()
    return {**given, **state.answers}
