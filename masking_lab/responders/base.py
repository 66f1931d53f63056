"""The responder interface: how the runner hands a trial to whoever answers it.

The runner builds a :class:`TrialPresentation` and a ``play`` callable that makes the device
play the trial and returns its :class:`~masking_lab.device.base.PlayResult`. The responder decides
how to interleave playing with its own work (a PsychoPy window animates the cue while the device
plays in a background thread; a simulated observer just plays, then answers) and returns both the
play result and the participant's :class:`Response`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from masking_lab.core.stimulus import Stimulus
from masking_lab.core.trial import PlayResult, TrialPlan


@dataclass(frozen=True)
class SetInfo:
    """What a responder may show or need at the start of a set.

    Attributes
    ----------
    set_id : str
        Set identifier from the protocol.
    set_number, n_sets : int
        1-based position of the set in the session, and the session's set count.
    target, masker : Stimulus, Stimulus or None
        Stimuli of the set.
    masker_level_db_sl : float or None
        Masker level, dB SL.

    Examples
    --------
    >>> from masking_lab.core.stimulus import parse_stimulus
    >>> info = SetInfo("A", 1, 4, parse_stimulus("EV270"), parse_stimulus("MV120"), 10.0)
    >>> f"set {info.set_number}/{info.n_sets}: {info.target} under {info.masker}"
    'set 1/4: EV270 under MV120'
    """

    set_id: str
    set_number: int
    n_sets: int
    target: Stimulus
    masker: Stimulus | None
    masker_level_db_sl: float | None


@dataclass(frozen=True)
class TrialPresentation:
    """One trial as the responder sees it.

    Attributes
    ----------
    set_id : str
        Set identifier.
    trial_index : int
        0-based trial index within the set.
    plan : TrialPlan
        Stimuli, amplitudes (V), target interval and timing (s).
    start_s : float
        Session-clock time at which the trial starts, s.
    level_db_v : float
        Target level, dB re 1 V.
    level_db_sl : float or None
        Target level, dB SL (None in a baseline session).
    masker_level_db_sl : float or None
        Masker level, dB SL.

    Examples
    --------
    The first trial of set A: EV270 at −26 dB re 1 V (0.05 V peak), 8.5 dB above the AL:

    >>> from masking_lab.core.stimulus import parse_stimulus
    >>> plan = TrialPlan(parse_stimulus("EV270"), 0.05, target_interval=2)
    >>> shown = TrialPresentation("A", 0, plan, 0.0, -26.0, 8.5, None)
    >>> shown.plan.target_interval, shown.level_db_sl
    (2, 8.5)
    """

    set_id: str
    trial_index: int
    plan: TrialPlan
    start_s: float
    level_db_v: float
    level_db_sl: float | None
    masker_level_db_sl: float | None


@dataclass(frozen=True)
class Response:
    """The participant's answer.

    Attributes
    ----------
    interval : int
        Chosen interval, 1–3.
    response_time_s : float
        From the end of the last interval to the answer, s.
    finger_path : list of (t_s, x_mm, y_mm)
        Touch positions during the trial, if the window reports them.

    Examples
    --------
    >>> Response(interval=2, response_time_s=0.85)
    Response(interval=2, response_time_s=0.85, finger_path=[])
    """

    interval: int
    response_time_s: float
    finger_path: list[tuple[float, float, float]] = field(default_factory=list)


class Responder(Protocol):
    """Answers trials. Implementations: sim, keys (terminal), psychopy (window)."""

    name: str

    def start_set(self, info: SetInfo) -> None:
        """Called before the first trial of a set (show instructions, rest screen, ...)."""
        ...

    def trial(
        self, presentation: TrialPresentation, play: Callable[[], PlayResult]
    ) -> tuple[PlayResult, Response]:
        """Run one trial: call ``play()`` exactly once and return its result and the answer."""
        ...

    def close(self) -> None:
        """Release windows, terminals, sounds. Idempotent."""
        ...
