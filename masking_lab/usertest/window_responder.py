"""The participant's PsychoPy window for the user test: the cue, the finger, two answers.

The same window as the 3IFC sessions (:class:`~masking_lab.responders.psychopy_window
.PsychoPyWindowResponder`: lanes, the cue sliding at the protocol's speed, pink noise, Escape
stops the session). Presentation *k* sweeps lane *k*. While the device streams the object in a
background thread, the main thread draws frames and samples the pointer (a touch panel reports
the finger as a mouse); with ``tracking: finger`` the stream follows the last sample taken while
the cue moves (a sample older than :data:`FINGER_STALE_S` counts as a lifted finger). After the
last presentation the window asks for the geometry (keys 1–4), then the texture (keys 1–3);
keys pressed earlier are discarded, and with a response timeout a late answer is none.

Imported only for ``--responder psychopy``; PsychoPy itself is imported when the window opens.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from masking_lab.core.stimulus import Stimulus
from masking_lab.core.trial import TrialPlan
from masking_lab.responders.base import TrialPresentation
from masking_lab.responders.psychopy_window import (
    ABORT_KEYS,
    NoiseSettings,
    PsychoPyWindowResponder,
    display_geometry,
)
from masking_lab.usertest.responder_base import (
    FingerReader,
    StreamResult,
    UserTestAnswer,
    UserTestInfo,
    UserTrialPresentation,
)

FINGER_STALE_S = 0.1
"""A pointer sample older than this no longer positions the stream, s."""

_TIMING_ONLY = Stimulus("EV", 270.0)  # the lanes are drawn from a plan's timing only


def answer_keys(n: int) -> dict[str, int]:
    """PsychoPy key names → 1-based answer, number row and keypad (``"1"``, ``"num_1"``, ...)."""
    keys = {}
    for i in range(1, n + 1):
        keys[str(i)] = i
        keys[f"num_{i}"] = i
    return keys


class UserTestWindowResponder(PsychoPyWindowResponder):
    """Answers user-test trials in the participant window (UserTestResponder protocol).

    Parameters are those of :class:`~masking_lab.responders.psychopy_window
    .PsychoPyWindowResponder`.
    """

    name = "psychopy"

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._geometries: tuple[str, ...] = ()
        self._textures: tuple[str, ...] = ()
        self._finger_lock = threading.Lock()
        self._finger: tuple[float, float] | None = None  # (session s, path mm)

    def start_session(self, info: UserTestInfo) -> None:
        """Show the task and the keys; with ``wait_for_start``, wait for the space bar."""
        self._geometries, self._textures = info.geometries, info.textures
        self._start_noise()
        resumed = f" (continuing at trial {info.next_trial + 1})" if info.next_trial else ""
        self._text.text = (
            f"{info.n_trials} objects{resumed}. Each is presented three times.\n\n"
            "Slide your fingertip from left to right with the yellow dot.\n"
            "Then press the geometry, then the texture:\n\n"
            f"{_listing(self._geometries)}\n{_listing(self._textures)}"
        )
        self._show_instructions()

    # A user-test trial takes other arguments than the 3IFC trial it overrides: the subclass
    # breaks substitution on purpose until the responders share a helper (issue 20, item 4).
    def trial(  # type: ignore[override]  # (see the comment above)
        self,
        presentation: UserTrialPresentation,  # type: ignore[override]  # (as above)
        play: Callable[[FingerReader | None], StreamResult],  # type: ignore[override]  # (above)
    ) -> tuple[StreamResult, UserTestAnswer]:
        """Draw the cue while the object streams in the background, then ask the two answers.

        Answer times run from the planned end of the last presentation (session clock) to the
        frame on which each key was seen, s.
        """
        self._start_noise()
        screen = self.screen_presentation(presentation)
        finger = self.finger_reader(presentation) if presentation.tracking == "finger" else None
        with self._finger_lock:
            self._finger = None

        def track(now_s: float, x_mm: float) -> None:
            with self._finger_lock:
                self._finger = (now_s, x_mm + presentation.sweep_mm / 2)

        result, finger_path = self._play_with_cue(
            lambda: play(finger),
            lambda t_s: self.draw_trial_screen(screen, t_s),
            presentation.start_s,
            presentation.timing.trial_s,
            on_finger=track,
        )
        timeout = presentation.timing.response_timeout_s
        end_s = presentation.end_s
        deadline = None if timeout is None else self._clock.now() + timeout
        self._event.clearEvents("keyboard")  # keys pressed during the object do not count
        geometries = self._geometries or tuple(f"geometry {i}" for i in range(1, 5))
        textures = self._textures or tuple(f"texture {i}" for i in range(1, 4))
        g, g_at = self._ask(screen, presentation, "Geometry?", geometries, deadline)
        t: int | None = None
        t_at: float | None = None
        if g is not None:
            t, t_at = self._ask(screen, presentation, "Texture?", textures, deadline)
        return result, UserTestAnswer(
            g,
            t,
            None if g_at is None else max(0.0, g_at - end_s),
            None if t_at is None else max(0.0, t_at - end_s),
            finger_path,
        )

    # -- pieces -------------------------------------------------------------------------------

    def finger_reader(self, presentation: UserTrialPresentation) -> FingerReader:
        """The stream's view of the finger: the last pointer sample, if recent (path mm)."""

        def reader(t_s: float) -> float | None:
            with self._finger_lock:
                sample = self._finger
            if sample is None or t_s - sample[0] > FINGER_STALE_S:
                return None
            return sample[1]

        return reader

    @staticmethod
    def screen_presentation(presentation: UserTrialPresentation) -> TrialPresentation:
        """The 3IFC screen's view of a user-test trial: its timing, lanes and number."""
        timing = presentation.timing
        plan = TrialPlan(
            target=_TIMING_ONLY,
            target_amplitude_v=0.0,
            target_interval=1,
            stimulus_s=timing.stimulus_s,
            gap_s=timing.gap_s,
            lead_in_s=timing.lead_in_s,
            n_intervals=timing.n_presentations,
        )
        return TrialPresentation(
            "usertest", presentation.trial.index, plan, presentation.start_s, 0.0, None, None
        )

    def _ask(
        self,
        screen: TrialPresentation,
        presentation: UserTrialPresentation,
        question: str,
        names: tuple[str, ...],
        deadline: float | None,
    ) -> tuple[int | None, float | None]:
        """Show ``question`` with the keys; return (key, session time) or (None, None) late."""
        keys = answer_keys(len(names))
        self._prompt.text = f"{question}   {_listing(names)}"
        while True:
            now = self._clock.now()
            if deadline is not None and now >= deadline:
                return None, None
            self.draw_trial_screen(screen, now - presentation.start_s)
            self._prompt.draw()
            self._flip()
            for key in self._event.getKeys(keyList=[*keys, *ABORT_KEYS]):
                if key in ABORT_KEYS:
                    raise KeyboardInterrupt
                return keys[key], now


def _listing(names: tuple[str, ...]) -> str:
    return "   ".join(f"{i} {name}" for i, name in enumerate(names, start=1))


def make_responder(context: Any) -> UserTestWindowResponder:
    """The user-test runner's factory: a full-screen window on the rig config's display.

    Parameters
    ----------
    context : masking_lab.usertest.runner.UserTestContext
        Uses ``design`` (its cue speed), ``device_config``, ``clock`` and ``seed``.

    Raises
    ------
    ProtocolError
        A cue speed other than the window's, or no usable ``display`` in the device config.
    ResponderError
        If PsychoPy is missing or the window cannot be opened.
    """
    from masking_lab.core.errors import ProtocolError
    from masking_lab.device.config import load_device_config
    from masking_lab.responders.cue import CUE_SPEED_MM_S

    design = context.design
    if abs(design.cue_speed_mm_s - CUE_SPEED_MM_S) > 1e-9:
        raise ProtocolError(
            design.path,
            "cue_speed_mm_s",
            f"the participant window draws the cue at {CUE_SPEED_MM_S:g} mm/s but the protocol "
            f"streams at {design.cue_speed_mm_s:g} mm/s; set cue_speed_mm_s: {CUE_SPEED_MM_S:g} "
            "or use another responder",
        )
    config = load_device_config(context.device_config)
    display = display_geometry(config)
    screen = getattr(config.display, "screen", 0)
    return UserTestWindowResponder(
        display, context.clock, screen=screen, noise=NoiseSettings(seed=context.seed)
    )
