"""Terminal keypad answers for the user test: the geometry (1–4), then the texture (1–3).

The participant's terminal is handled exactly like the 3IFC keypad's
(:class:`masking_lab.responders.keys.KeysResponder`: non-canonical mode without echo, escape
sequences ignored, settings restored after every trial, Ctrl-C interrupts). Keys typed while the
object plays are discarded, as in the paper ("respond ... immediately after the end of each
trial"); each answer is one key, shown back once pressed, and cannot be taken back. With a
response timeout in the protocol, an answer not given in time is logged as no answer (null).
"""

from __future__ import annotations

import termios
import time
from collections.abc import Callable

from masking_lab.responders.keys import KeysResponder
from masking_lab.usertest.responder_base import (
    FingerReader,
    StreamResult,
    UserTestAnswer,
    UserTestInfo,
    UserTrialPresentation,
)


class UserTestKeysResponder(KeysResponder):
    """Answers user-test trials with two key presses on a terminal.

    Parameters are those of :class:`~masking_lab.responders.keys.KeysResponder`
    (``wait_for_start``: :meth:`start_session` waits for the space bar).
    """

    name = "keys"

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._geometries: tuple[str, ...] = ()
        self._textures: tuple[str, ...] = ()

    def start_session(self, info: UserTestInfo) -> None:
        """Explain the task and the keys; with ``wait_for_start``, wait for the space bar."""
        self._geometries, self._textures = info.geometries, info.textures
        resumed = f" (continuing at trial {info.next_trial + 1})" if info.next_trial else ""
        self._write(
            f"\nUser test: {info.n_trials} trials{resumed}. Each trial presents an object three "
            "times.\nSlide your fingertip left to right during each presentation, then answer:\n"
            f"  geometry: {_keys(self._geometries)}\n  texture:  {_keys(self._textures)}\n"
        )
        if self._wait_for_start:
            self._write("Press the space bar to start.\n")
            with self._keypad_mode():
                self._read_key(frozenset(" "))

    # A user-test trial takes other arguments than the 3IFC trial it overrides: the subclass
    # breaks substitution on purpose until the responders share a helper (issue 20, item 4).
    def trial(  # type: ignore[override]  # (see the comment above)
        self,
        presentation: UserTrialPresentation,  # type: ignore[override]  # (as above)
        play: Callable[[FingerReader | None], StreamResult],  # type: ignore[override]  # (above)
    ) -> tuple[StreamResult, UserTestAnswer]:
        """Play the object, then read the geometry key and the texture key.

        Answer times run from the end of the last presentation (when ``play()`` returns), s.
        """
        geometries = self._geometries or tuple(f"geometry {i}" for i in range(1, 5))
        textures = self._textures or tuple(f"texture {i}" for i in range(1, 4))
        timeout = presentation.timing.response_timeout_s
        with self._keypad_mode():
            self._write(
                f"\nTrial {presentation.trial.index + 1} of {presentation.n_trials}: feel the "
                "object...\n"
            )
            result = play(None)
            termios.tcflush(self._in, termios.TCIFLUSH)  # only answers after the object count
            t0 = time.monotonic()
            deadline = None if timeout is None else t0 + timeout
            self._write(f"Geometry? {_keys(geometries)}: ")
            g = self._answer(len(geometries), deadline)
            g_s = time.monotonic() - t0 if g is not None else None
            self._write(f"{g if g is not None else '-'}\n")
            t: int | None = None
            t_s: float | None = None
            if g is not None:
                self._write(f"Texture?  {_keys(textures)}: ")
                t = self._answer(len(textures), deadline)
                t_s = time.monotonic() - t0 if t is not None else None
                self._write(f"{t if t is not None else '-'}\n")
            if g is None or t is None:
                self._write("No answer in time; on to the next trial.\n")
        return result, UserTestAnswer(g, t, g_s, t_s)

    def _answer(self, n: int, deadline: float | None) -> int | None:
        """A key 1..n, or None when ``deadline`` (time.monotonic s) passes first."""
        allowed = frozenset(str(i) for i in range(1, n + 1))
        if deadline is None:
            return int(self._read_key(allowed))
        key = self._read_key_until(allowed, deadline)
        return None if key is None else int(key)


def _keys(names: tuple[str, ...]) -> str:
    return "  ".join(f"{i} {name}" for i, name in enumerate(names, start=1))
