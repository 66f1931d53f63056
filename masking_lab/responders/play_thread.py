"""A device trial played in a background thread while the window keeps drawing.

The window's main thread must keep flipping frames (the cue moves with the session clock) while
the device plays the trial, so the runner's ``play`` callable runs in a :class:`PlayThread`;
its result, or the exception it raised, is handed back to the main thread afterwards.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Generic, TypeVar, cast

__all__ = ["PlayThread"]

ResultT = TypeVar("ResultT")


class PlayThread(threading.Thread, Generic[ResultT]):
    """Runs ``play()`` once, keeping its result or exception for the main thread.

    Examples
    --------
    >>> player = PlayThread(lambda: 0.5)
    >>> player.start()
    >>> player.result(), player.failed
    (0.5, False)
    >>> failing = PlayThread(lambda: 1 / 0)
    >>> failing.start()
    >>> failing.result()
    Traceback (most recent call last):
    ZeroDivisionError: division by zero
    """

    def __init__(self, play: Callable[[], ResultT]) -> None:
        super().__init__(name="masking-lab-play", daemon=True)
        self._play = play
        self._result: ResultT | None = None
        self._error: BaseException | None = None

    def run(self) -> None:
        try:
            self._result = self._play()
        except BaseException as exc:  # handed back to the main thread in result()
            self._error = exc

    @property
    def failed(self) -> bool:
        """True once ``play()`` has raised."""
        return self._error is not None

    def result(self) -> ResultT:
        """What ``play()`` returned, after waiting for it; re-raises what it raised."""
        self.join()
        if self._error is not None:
            raise self._error
        return cast(ResultT, self._result)
