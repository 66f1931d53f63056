"""Terminal keypad answers for the user test: the geometry (1–4), then the texture (1–3).

The participant's terminal is handled exactly like the 3IFC keypad's
(:class:`masking_lab.responders.keys.KeysResponder`: non-canonical mode without echo, escape
sequences ignored, settings restored after every trial, Ctrl-C interrupts). Keys typed while the
object plays are discarded, as in the paper ("respond ... immediately after the end of each
trial"); each answer is one key, shown back once pressed, and cannot be taken back. With a
response timeout in the protocol, an answer not given in time is logged as no answer (null).
"""

from __future__ import annotations

from collections.abc import Callable

from masking_lab.responders.keys import KeyReader
from masking_lab.usertest.responder_base import (
    FingerReader,
    StreamResult,
    UserTestAnswer,
    UserTestInfo,
    UserTrialPresentation,
)


class UserTestKeysResponder:
    """Answers user-test trials with two key presses on a terminal.

    Parameters
    ----------
    keys : KeyReader
        The participant's terminal (shared with the 3IFC keypad).
    wait_for_start : bool
        :meth:`start_session` waits for the space bar.
    """

    name = "keys"

    def __init__(self, keys: KeyReader, *, wait_for_start: bool = True) -> None:
        self.keys = keys
        self.wait_for_start = wait_for_start
        self._geometries = tuple(f"geometry {i}" for i in range(1, 5))
        self._textures = tuple(f"texture {i}" for i in range(1, 4))

    def start_session(self, info: UserTestInfo) -> None:
        """Explain the task and the keys; with ``wait_for_start``, wait for the space bar."""
        self._geometries, self._textures = info.geometries, info.textures
        resumed = f" (continuing at trial {info.next_trial + 1})" if info.next_trial else ""
        self.keys.write(
            f"\nUser test: {info.n_trials} trials{resumed}. Each trial presents an object three "
            "times.\nSlide your fingertip left to right during each presentation, then answer:\n"
            f"  geometry: {_keys(self._geometries)}\n  texture:  {_keys(self._textures)}\n"
        )
        if self.wait_for_start:
            self.keys.write("Press the space bar to start.\n")
            self.keys.wait_for_space()

    def trial(
        self,
        presentation: UserTrialPresentation,
        play: Callable[[FingerReader | None], StreamResult],
    ) -> tuple[StreamResult, UserTestAnswer]:
        """Play the object, then read the geometry key and the texture key.

        Answer times run from the end of the last presentation (when ``play()`` returns), s.
        """
        keys = self.keys
        timeout = presentation.timing.response_timeout_s
        answers: list[int | None] = [None, None]  # geometry, texture
        times: list[float | None] = [None, None]
        with keys.keypad():
            keys.write(
                f"\nTrial {presentation.trial.index + 1} of {presentation.n_trials}: feel the "
                "object...\n"
            )
            result = play(None)
            keys.discard_typed()  # only answers after the object count
            t0 = keys.now()
            deadline = None if timeout is None else t0 + timeout
            questions = (("Geometry?", self._geometries), ("Texture? ", self._textures))
            for i, (question, names) in enumerate(questions):
                keys.write(f"{question} {_keys(names)}: ")
                key = keys.read_key(frozenset(str(k) for k in range(1, len(names) + 1)), deadline)
                if key is not None:
                    answers[i], times[i] = int(key), keys.now() - t0
                keys.write(f"{key or '-'}\n")
                if key is None:
                    keys.write("No answer in time; on to the next trial.\n")
                    break
        return result, UserTestAnswer(answers[0], answers[1], times[0], times[1])

    def close(self) -> None:
        """Release the terminal. Idempotent."""
        self.keys.close()


def _keys(names: tuple[str, ...]) -> str:
    return "  ".join(f"{i} {name}" for i, name in enumerate(names, start=1))
