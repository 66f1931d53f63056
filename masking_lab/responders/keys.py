"""Terminal keypad responder: the participant answers 1, 2 or 3 on a terminal.

For rigs without PsychoPy. The participant's terminal is the session's own (stdin/stdout) or a
second one named by its path (``/dev/pts/N``, a serial keypad's tty). Keys are read one at a time
without Enter (non-canonical mode, no echo); every key other than the allowed ones is ignored,
including escape sequences (F5 sends ``ESC [ 1 5 ~``, which must not count as a ``1``). Keys typed
while the stimuli play are discarded, so only an answer given after the last interval counts.
The terminal's settings are restored after every trial, also when Ctrl-C interrupts it.
"""

from __future__ import annotations

import contextlib
import os
import select
import sys
import termios
import time
from collections.abc import Callable, Iterator
from typing import Self

from masking_lab.core.errors import ResponderError
from masking_lab.core.trial import PlayResult
from masking_lab.responders.base import Response, SetInfo, TrialPresentation

INTERRUPT = "\x03"
"""Ctrl-C as a byte (arrives only when the terminal's ISIG is off; otherwise it is SIGINT)."""

ESCAPE_WAIT_S = 0.05
"""How long an unfinished escape sequence waits for its next byte before it counts as Esc, s."""

SIGNAL_CHECK_S = 0.2
"""Longest single wait for a key, s: Python runs its SIGINT handler only between waits.

A Ctrl-C that lands just before the wait begins (or on another thread) interrupts no system
call; an unbounded wait would then sit on it until the next key. Waking this often makes such a
Ctrl-C take effect within this time instead.
"""

_ESC = 0x1B


def parse_keys(data: bytes) -> tuple[list[str], bytes]:
    """Split raw terminal input into key presses.

    Parameters
    ----------
    data : bytes
        Bytes read from the terminal (possibly the unfinished tail of an earlier read first).

    Returns
    -------
    keys : list of str
        One entry per key: a printable ASCII character, ``INTERRUPT`` for Ctrl-C, ``"\\n"`` for
        Enter, or ``""`` for anything to ignore (escape sequences, other control keys, non-ASCII).
    tail : bytes
        An escape sequence cut off at the end of ``data``; prepend it to the next read.

    Examples
    --------
    F5 (``ESC [ 1 5 ~``) is one ignored key, not a ``1``; a cut-off sequence is kept for later:

    >>> parse_keys(b"9\\x1b[15~2")
    (['9', '', '2'], b'')
    >>> parse_keys(b"1\\x1b[")
    (['1'], b'\\x1b[')
    """
    keys: list[str] = []
    i = 0
    n = len(data)
    while i < n:
        b = data[i]
        if b != _ESC:
            if b == 0x03:
                keys.append(INTERRUPT)
            elif b in (0x0A, 0x0D):
                keys.append("\n")
            elif 0x20 <= b < 0x7F:
                keys.append(chr(b))
            else:
                keys.append("")  # other control bytes, UTF-8 bytes of non-ASCII keys
            i += 1
            continue
        # Escape: CSI (ESC [ params final), SS3 (ESC O x), Alt+key (ESC x) or a lone Esc.
        if i + 1 >= n:
            return keys, data[i:]
        nxt = data[i + 1]
        if nxt == ord("["):
            j = i + 2
            while j < n and not 0x40 <= data[j] <= 0x7E:
                j += 1
            if j >= n:
                return keys, data[i:]
            i = j + 1
        elif nxt == ord("O"):
            if i + 2 >= n:
                return keys, data[i:]
            i += 3
        else:
            i += 2  # Alt+key: not a plain key press
        keys.append("")
    return keys, b""


class KeyReader:
    """The participant's terminal as a keypad: the keys and prompts every keypad responder uses.

    Parameters
    ----------
    in_fd : int, optional
        File descriptor the keys come from (default: stdin). Must be a terminal.
    out_fd : int, optional
        File descriptor the prompts go to (default: stdout).
    owns_fds : bool
        Close the descriptors in :meth:`close` (set by :meth:`open_tty`).
    now : callable
        ``() -> s``: the clock response times and deadlines are read on (default:
        ``time.monotonic``; tests give a virtual one, so no answer waits on the wall clock).

    Raises
    ------
    ResponderError
        If ``in_fd`` is not a terminal.

    Examples
    --------
    >>> participant, rig = os.openpty()
    >>> keys = KeyReader(rig, rig)
    >>> with keys.keypad():
    ...     _ = os.write(participant, b"x\\x1b[15~2")  # x, then F5, then 2
    ...     keys.read_key(frozenset("123"))
    '2'
    >>> keys.close(); os.close(rig); os.close(participant)
    """

    def __init__(
        self,
        in_fd: int | None = None,
        out_fd: int | None = None,
        *,
        owns_fds: bool = False,
        now: Callable[[], float] = time.monotonic,
    ) -> None:
        self.in_fd = sys.stdin.fileno() if in_fd is None else in_fd
        self.out_fd = sys.stdout.fileno() if out_fd is None else out_fd
        self.now = now
        self._owns_fds = owns_fds
        self._closed = False
        self._typed: list[str] = []  # keys read but not yet asked for (typed ahead)
        if not os.isatty(self.in_fd):
            raise ResponderError(
                f"the keys responder reads the participant's answers from a terminal, but its "
                f"input (fd {self.in_fd}) is not one; run masking-lab in a terminal, give the "
                "participant's terminal with its /dev/pts path, or use --responder sim"
            )
        self.tty_name = os.ttyname(self.in_fd)

    @classmethod
    def open_tty(cls, path: str) -> Self:
        """Use the terminal at ``path`` (e.g. ``/dev/pts/3``) for both keys and prompts.

        Raises
        ------
        ResponderError
            If the path cannot be opened or is not a terminal.

        Examples
        --------
        >>> KeyReader.open_tty("/dev/null")
        Traceback (most recent call last):
        ...
        masking_lab.core.errors.ResponderError: the keys responder reads ... is not one; ...
        """
        try:
            fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
        except OSError as exc:
            raise ResponderError(
                f"{path}: cannot open the participant's terminal ({exc.strerror}); check the "
                "path (run `tty` in that terminal) and its permissions"
            ) from exc
        try:
            return cls(fd, fd, owns_fds=True)
        except ResponderError:
            os.close(fd)
            raise

    @classmethod
    def on_terminal(cls, path: str | None) -> Self:
        """The participant's terminal at ``path`` (see :meth:`open_tty`), or this one if None.

        Examples
        --------
        >>> KeyReader.on_terminal("/dev/null")
        Traceback (most recent call last):
        ...
        masking_lab.core.errors.ResponderError: the keys responder reads ... is not one; ...
        """
        return cls.open_tty(path) if path else cls()

    def wait_for_space(self) -> None:
        """Block until the space bar is pressed (the participant starts)."""
        with self.keypad():
            self.read_key(frozenset(" "))

    def close(self) -> None:
        """Release the terminal (its settings are already restored after every read)."""
        if self._closed:
            return
        self._closed = True
        if self._owns_fds:
            for fd in {self.in_fd, self.out_fd}:
                with contextlib.suppress(OSError):
                    os.close(fd)

    @contextlib.contextmanager
    def keypad(self) -> Iterator[None]:
        """Non-canonical, no echo, signals kept (Ctrl-C still interrupts); restored on exit."""
        try:
            saved = termios.tcgetattr(self.in_fd)
        except termios.error as exc:
            raise ResponderError(
                f"{self.tty_name}: cannot read the terminal settings ({exc}); the participant's "
                "terminal was closed — resume the session from a working terminal"
            ) from exc
        mode = termios.tcgetattr(self.in_fd)
        mode[3] &= ~(termios.ICANON | termios.ECHO)  # lflag
        mode[6][termios.VMIN] = 1
        mode[6][termios.VTIME] = 0
        termios.tcsetattr(self.in_fd, termios.TCSANOW, mode)
        try:
            yield
        finally:
            # TCSANOW: never block here on output the other side does not read.
            with contextlib.suppress(termios.error):
                termios.tcsetattr(self.in_fd, termios.TCSANOW, saved)

    def discard_typed(self) -> None:
        """Drop the keys typed so far (while the stimuli played): only later answers count."""
        termios.tcflush(self.in_fd, termios.TCIFLUSH)
        self._typed.clear()

    def read_key(self, allowed: frozenset[str], deadline: float | None = None) -> str | None:
        """Wait for one of ``allowed`` until ``deadline`` (on :attr:`now`, s; None: forever).

        Returns the key, or None when the deadline passes first; every other key is ignored.
        Keys typed after it in the same read wait for the next call (two answers typed fast
        are two answers). Ctrl-C (arriving as a byte) raises KeyboardInterrupt; as SIGINT, it
        takes effect within :data:`SIGNAL_CHECK_S` even when it lands just before a wait.
        """
        pending = b""
        while True:
            while self._typed:
                key = self._typed.pop(0)
                if key == INTERRUPT:
                    raise KeyboardInterrupt
                if key in allowed:
                    return key
            left = None if deadline is None else deadline - self.now()
            if left is not None and left <= 0:
                return None
            most = ESCAPE_WAIT_S if pending else SIGNAL_CHECK_S
            wait = most if left is None else min(most, left)
            ready, _, _ = select.select([self.in_fd], [], [], wait)
            if not ready:
                pending = b""  # a lone Esc: nothing followed it (no-op when nothing is pending)
                continue
            try:
                data = os.read(self.in_fd, 64)
            except OSError as exc:
                raise self._gone(exc.strerror) from exc
            if not data:
                raise self._gone("end of input")
            keys, pending = parse_keys(pending + data)
            self._typed.extend(keys)

    def _gone(self, why: str | None) -> ResponderError:
        return ResponderError(
            f"{self.tty_name}: the participant's terminal went away while waiting for a key "
            f"({why}); the trial in flight is not logged — resume the session"
        )

    def write(self, text: str) -> None:
        """Show ``text`` on the participant's terminal."""
        data = text.encode()  # the terminal's own output processing turns \n into \r\n
        try:
            while data:
                written = os.write(self.out_fd, data)
                data = data[written:]
        except OSError as exc:
            raise ResponderError(
                f"{self.tty_name}: cannot write to the participant's terminal "
                f"({exc.strerror}); resume the session from a working terminal"
            ) from exc


class KeysResponder:
    """Answers 3IFC trials with one key press, 1–3, on a terminal.

    Parameters
    ----------
    keys : KeyReader
        The participant's terminal.
    wait_for_start : bool
        If True, :meth:`start_set` waits for the space bar so the participant starts each set.

    Examples
    --------
    A trial answered on a real pseudo-terminal is in ``tests/test_keys_responder.py``:

    >>> participant, rig = os.openpty()
    >>> keys = KeysResponder(KeyReader(rig, rig), wait_for_start=False)
    >>> keys.name
    'keys'
    >>> keys.close(); os.close(rig); os.close(participant)
    """

    name = "keys"

    def __init__(self, keys: KeyReader, *, wait_for_start: bool = True) -> None:
        self.keys = keys
        self.wait_for_start = wait_for_start

    def start_set(self, info: SetInfo) -> None:
        """Tell the participant a set begins; with ``wait_for_start``, wait for the space bar."""
        self.keys.write(
            f"\nSet {info.set_number} of {info.n_sets}. In every trial three intervals play; "
            "one feels different.\nSlide your fingertip left to right during each interval, "
            "then press 1, 2 or 3 for the different one.\n"
        )
        if self.wait_for_start:
            self.keys.write("Press the space bar to start.\n")
            self.keys.wait_for_space()

    def trial(
        self, presentation: TrialPresentation, play: Callable[[], PlayResult]
    ) -> tuple[PlayResult, Response]:
        """Play the trial, then read the answer (1–3).

        The response time runs from the moment ``play()`` returns (the end of the last
        interval), s. Keys pressed while the trial plays are discarded.

        Raises
        ------
        ResponderError
            If the terminal goes away or cannot be written to.
        KeyboardInterrupt
            On Ctrl-C.
        """
        keys = self.keys
        with keys.keypad():
            keys.write(f"\nTrial {presentation.trial_index + 1}: feel the three intervals...\n")
            result = play()
            keys.discard_typed()  # only an answer given after the stimuli counts
            keys.write("Which interval was different? Press 1, 2 or 3: ")
            answered_from = keys.now()
            key = keys.read_key(frozenset("123"))
            response_time_s = keys.now() - answered_from
            keys.write(f"{key}\n")
        assert key is not None  # no deadline: only a key ends the wait
        return result, Response(interval=int(key), response_time_s=response_time_s)

    def close(self) -> None:
        """Release the terminal. Idempotent."""
        self.keys.close()
