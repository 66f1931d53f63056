"""The participant's PsychoPy window for the user test: the cue, the finger, two answers.

The window the 3IFC sessions use too (:class:`~masking_lab.responders.participant_window
.ParticipantWindow`, held, not inherited: lanes, the cue sliding at the protocol's speed, pink
noise, Escape stops the session). Presentation *k* sweeps lane *k*. While the device streams
the object in a background thread, the main thread draws frames and samples the pointer (a
touch panel reports the finger as a mouse); with ``tracking: finger`` the stream follows the
last sample taken while the cue moves (a sample older than :data:`FINGER_STALE_S` counts as a
lifted finger). After the last presentation the window asks for the geometry (keys 1–4), then
the texture (keys 1–3); keys pressed earlier are discarded, and with a response timeout a late
answer is none.

Imported only for ``--responder psychopy``; PsychoPy itself is imported when the window opens.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from masking_lab.core.clock import Clock
from masking_lab.core.stimulus import Stimulus
from masking_lab.core.trial import TrialPlan
from masking_lab.responders.base import TrialPresentation
from masking_lab.responders.cue import DisplayGeometry
from masking_lab.responders.participant_window import NoiseSettings, ParticipantWindow
from masking_lab.responders.psychopy_window import display_geometry
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
    """PsychoPy key names → 1-based answer, number row and keypad (``"1"``, ``"num_1"``, ...).

    Examples
    --------
    >>> answer_keys(2)
    {'1': 1, 'num_1': 1, '2': 2, 'num_2': 2}
    """
    keys = {}
    for i in range(1, n + 1):
        keys[str(i)] = i
        keys[f"num_{i}"] = i
    return keys


class UserTestWindowResponder:
    """Answers user-test trials in the participant window (UserTestResponder protocol).

    Parameters are those of :class:`~masking_lab.responders.participant_window
    .ParticipantWindow`, which it opens and holds as :attr:`window`.
    """

    name = "psychopy"

    def __init__(self, display: DisplayGeometry, clock: Clock, **window: Any) -> None:
        self.window = ParticipantWindow(display, clock, **window)
        self._geometries = tuple(f"geometry {i}" for i in range(1, 5))
        self._textures = tuple(f"texture {i}" for i in range(1, 4))
        self._finger_lock = threading.Lock()
        self._finger: tuple[float, float] | None = None  # (session s, path mm)

    def start_session(self, info: UserTestInfo) -> None:
        """Show the task and the keys; with ``wait_for_start``, wait for the space bar."""
        self._geometries, self._textures = info.geometries, info.textures
        resumed = f" (continuing at trial {info.next_trial + 1})" if info.next_trial else ""
        self.window.show_instructions(
            f"{info.n_trials} objects{resumed}. Each is presented three times.\n\n"
            "Slide your fingertip from left to right with the yellow dot.\n"
            "Then press the geometry, then the texture:\n\n"
            f"{_listing(self._geometries)}\n{_listing(self._textures)}"
        )

    def trial(
        self,
        presentation: UserTrialPresentation,
        play: Callable[[FingerReader | None], StreamResult],
    ) -> tuple[StreamResult, UserTestAnswer]:
        """Draw the cue while the object streams in the background, then ask the two answers.

        Answer times run from the planned end of the last presentation (session clock) to the
        frame on which each key was seen, s.
        """
        window = self.window
        window.start_noise()
        screen = self.screen_presentation(presentation)
        finger = self.finger_reader(presentation) if presentation.tracking == "finger" else None
        with self._finger_lock:
            self._finger = None

        def track(now_s: float, x_mm: float) -> None:
            with self._finger_lock:
                self._finger = (now_s, x_mm + presentation.sweep_mm / 2)

        result, finger_path = window.play_with_cue(
            lambda: play(finger),
            lambda t_s: window.draw_trial_screen(screen, t_s),
            presentation.start_s,
            presentation.timing.trial_s,
            on_finger=track,
        )
        timeout = presentation.timing.response_timeout_s
        deadline = None if timeout is None else window.clock.now() + timeout
        answers: list[int | None] = [None, None]  # geometry, texture
        times: list[float | None] = [None, None]
        questions = (("Geometry?", self._geometries), ("Texture?", self._textures))
        for i, (question, names) in enumerate(questions):
            key, at_s = window.ask_key(
                lambda now: window.draw_trial_screen(screen, now - presentation.start_s),
                f"{question}   {_listing(names)}",
                answer_keys(len(names)),
                deadline,
            )
            if key is None or at_s is None:
                break
            answers[i], times[i] = key, max(0.0, at_s - presentation.end_s)
        return result, UserTestAnswer(answers[0], answers[1], times[0], times[1], finger_path)

    def close(self) -> None:
        """Stop the noise and close the window. Idempotent."""
        self.window.close()

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
