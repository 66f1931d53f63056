"""The user-test responder interface: how the runner hands an object to whoever identifies it.

Like the 3IFC interface (:mod:`masking_lab.responders.base`) the runner gives the responder a
``play`` callable and the responder decides how to interleave playing with its own work. Here
``play`` streams the object's amplitudes along the path and takes an optional *finger reader*:
with ``tracking: finger`` the amplitudes follow the position it reports; with ``tracking: cue``
it is ignored. The responder returns what was played and two answers (geometry key, texture key).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from masking_lab.usertest.design import UserTestTiming, UserTrial

FingerReader = Callable[[float], float | None]
"""``reader(t_s) -> path x in mm, or None`` (finger lifted or off the panel) at session time t."""


@dataclass(frozen=True)
class UserTestInfo:
    """What a responder may show or need before the first trial.

    Attributes
    ----------
    geometries, textures : tuple[str, ...]
        Answer keys 1..n in this order.
    n_trials : int
        Trials in the session.
    next_trial : int
        0-based index of the first trial this process runs (> 0 after a resume).
    tracking : {"cue", "finger"}
        What positions the amplitudes.
    """

    geometries: tuple[str, ...]
    textures: tuple[str, ...]
    n_trials: int
    next_trial: int
    tracking: str


@dataclass(frozen=True)
class UserTrialPresentation:
    """One user-test trial as the responder sees it.

    Attributes
    ----------
    trial : UserTrial
        The object, condition and the correct keys.
    n_trials : int
        Trials in the session.
    start_s : float
        Session-clock time of the trial's start, s.
    timing : UserTestTiming
        Lead-in, presentations, gaps, s.
    tracking : {"cue", "finger"}
        What positions the amplitudes.
    cue_speed_mm_s : float
        Cue speed, mm/s.
    sweep_mm : float
        Path length one presentation covers, mm.
    """

    trial: UserTrial
    n_trials: int
    start_s: float
    timing: UserTestTiming
    tracking: str
    cue_speed_mm_s: float
    sweep_mm: float

    @property
    def end_s(self) -> float:
        """Session time when the last presentation ends, s."""
        return self.start_s + self.timing.trial_s


@dataclass(frozen=True)
class ClipStats:
    """How much one channel was clipped during a trial.

    Attributes
    ----------
    n_ticks : int
        Ticks at which the wanted level was above the limit.
    max_excess_db : float
        Largest excess, dB.
    """

    n_ticks: int
    max_excess_db: float


@dataclass(frozen=True)
class StreamResult:
    """What the device was told to play during one trial.

    Attributes
    ----------
    planned_onsets_s, actual_onsets_s : list[float]
        Presentation onsets, session s (actual: when the first frame was acknowledged).
    tick_s : ndarray
        Session time of every tick of every presentation, s.
    x_mm : ndarray
        Path position at each tick, mm (NaN: finger lifted or off the path).
    held_v : Mapping[str, ndarray]
        Peak drive each channel held after each tick, V (0: silent), after any clipping.
    stimuli : Mapping[str, str or None]
        Stimulus played per channel.
    n_frames : int
        Amplitude frames sent (updates, refreshes and zeros).
    clipped : Mapping[str, ClipStats]
        Channels that were clipped (empty when nothing was).
    """

    planned_onsets_s: list[float]
    actual_onsets_s: list[float]
    tick_s: NDArray[np.float64]
    x_mm: NDArray[np.float64]
    held_v: Mapping[str, NDArray[np.float64]]
    stimuli: Mapping[str, str | None]
    n_frames: int
    clipped: Mapping[str, ClipStats] = field(default_factory=dict)


@dataclass(frozen=True)
class UserTestAnswer:
    """The participant's two answers.

    Attributes
    ----------
    geometry, texture : int or None
        Keys pressed (1-based), None when no answer came before the timeout.
    geometry_time_s, texture_time_s : float or None
        From the end of the last presentation to each key, s.
    finger_path : list of (t_s, x_mm, y_mm)
        Touch positions during the trial, if the responder reports them.
    """

    geometry: int | None
    texture: int | None
    geometry_time_s: float | None = None
    texture_time_s: float | None = None
    finger_path: list[tuple[float, float, float]] = field(default_factory=list)

    @property
    def response_time_s(self) -> float:
        """From the end of the last presentation to the second answer, s (0 if none)."""
        times = [t for t in (self.geometry_time_s, self.texture_time_s) if t is not None]
        return max(times) if times else 0.0


class UserTestResponder(Protocol):
    """Identifies user-test objects. Implementations: sim, keys (terminal), psychopy (window)."""

    name: str

    def start_session(self, info: UserTestInfo) -> None:
        """Called once before the first trial this process runs (instructions, start key)."""
        ...

    def trial(
        self,
        presentation: UserTrialPresentation,
        play: Callable[[FingerReader | None], StreamResult],
    ) -> tuple[StreamResult, UserTestAnswer]:
        """Run one trial: call ``play(finger)`` exactly once and return its result and answers."""
        ...

    def close(self) -> None:
        """Release windows and terminals. Idempotent."""
        ...
