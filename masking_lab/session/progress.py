"""The experimenter's live progress line (on stderr).

``set 3/15 MV120_10 | trial 17 | reversals 4/11 | level 12.0 dB SL | ~6 min left``

On a terminal the line is redrawn in place; piped to a file it stays quiet unless forced, and
then writes one line per update. Formatting is pure (:func:`format_progress`,
:func:`format_duration`); :class:`ProgressLine` only writes.
"""

from __future__ import annotations

import math
import sys
from typing import TextIO

from masking_lab.session.trials import UNIT_LABEL


def format_duration(seconds: float) -> str:
    """A rough human duration: ``"~40 s"``, ``"~6 min"``, ``"~1 h 05 min"``.

    Parameters
    ----------
    seconds : float
        Duration in s (negative or NaN counts as 0; +inf prints ``"?"``).
    """
    if math.isnan(seconds) or seconds <= 0:
        return "~0 s"
    if math.isinf(seconds):
        return "?"
    if seconds < 60:
        return f"~{round(seconds / 5) * 5 or 5:d} s"
    minutes = round(seconds / 60)
    if minutes < 60:
        return f"~{minutes:d} min"
    hours, minutes = divmod(minutes, 60)
    return f"~{hours:d} h {minutes:02d} min"


def format_progress(
    *,
    set_number: int,
    n_sets: int,
    set_id: str,
    trial_index: int,
    reversals: int,
    n_reversals: int,
    level_db: float,
    level_unit: str,
    time_left_s: float,
    track: str = "",
    track_text: str | None = None,
) -> str:
    """The progress line for the trial about to be played.

    Parameters
    ----------
    set_number, n_sets : int
        1-based position of the set in the session, and the session's set count.
    set_id : str
        Set identifier.
    trial_index : int
        0-based index of the trial about to be played (shown 1-based).
    reversals, n_reversals : int
        Reversals so far, and the count that ends the set.
    level_db : float
        Level of the trial, in ``level_unit``.
    level_unit : {"db_sl", "db_v"}
        Unit of the staircase.
    time_left_s : float
        Estimated session time left, s.
    track : str
        The track's state for procedures without reversals (``"posterior 12.3 ± 1.4"``, dB);
        shown instead of the reversal count when given.
    track_text : str or None
        The track's part of the line exactly as its procedure kind words it
        (:attr:`masking_lab.procedures.registry.ProcedureKind.progress`); overrides the two
        above.

    Examples
    --------
    >>> format_progress(set_number=1, n_sets=2, set_id="A", trial_index=4, reversals=0,
    ...                 n_reversals=0, level_db=3.0, level_unit="db_sl", time_left_s=600,
    ...                 track="posterior 3.2 ± 1.5")
    'set 1/2 A | trial 5 | posterior 3.2 ± 1.5 dB SL | level 3.0 dB SL | ~10 min left'
    """
    unit = UNIT_LABEL.get(level_unit, level_unit)
    if track_text is None:
        track_text = f"{track} {unit}" if track else f"reversals {reversals}/{n_reversals}"
    return (
        f"set {set_number}/{n_sets} {set_id} | trial {trial_index + 1} | "
        f"{track_text} | "
        f"level {level_db:.1f} {unit} | "
        f"{format_duration(time_left_s)} left"
    )


class ProgressLine:
    """Writes progress to ``stream`` (stderr by default).

    Parameters
    ----------
    stream : text stream, optional
        Where to write.
    force : bool or None
        True: always write (one line per update when not a terminal); False: never;
        None: only when ``stream`` is a terminal.
    """

    def __init__(self, stream: TextIO | None = None, force: bool | None = None) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.tty = _isatty(self.stream)
        self.enabled = self.tty if force is None else bool(force)
        self._drawn = False

    def update(self, line: str) -> None:
        """Show ``line`` as the current progress."""
        if not self.enabled:
            return
        if self.tty:
            self.stream.write("\r\x1b[K" + line)
            self._drawn = True
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def clear(self) -> None:
        """Remove the progress line (before other output, or at the end)."""
        if self.enabled and self.tty and self._drawn:
            self.stream.write("\r\x1b[K")
            self.stream.flush()
        self._drawn = False

    def message(self, text: str) -> None:
        """Print ``text`` on its own line (always, even when progress is quiet)."""
        self.clear()
        self.stream.write(text + "\n")
        self.stream.flush()


def _isatty(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False
