"""The participant's PsychoPy window: sliding cue, three interval lanes, keys 1–3, pink noise.

Imported only when ``--responder psychopy`` is chosen; PsychoPy itself is imported when the window
opens, so this module imports (and fails with a clear message) without it.

During a trial the device plays in a background thread (the ``play`` callable from the runner)
while the main thread draws one frame after another: the cue's position comes from the session
clock (``clock.now() − presentation.start_s``) through :mod:`masking_lab.responders.cue`, so the
cue sweeps lane *k* exactly while the device plays interval *k*. The pointer (a touch panel
reports the finger as a mouse) is sampled every frame while a lane is swept and logged as
``[t_s, x_mm, y_mm]``. After the last interval the participant answers with 1, 2 or 3 (number row
or keypad); keys pressed earlier are discarded. Escape stops the session like Ctrl-C (after the
trial in flight has finished playing).

Pink masking noise loops in the headphones from the first set until :meth:`close`. Without an
audio back-end the window logs a warning and runs without it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from masking_lab.core.clock import Clock
from masking_lab.core.errors import ProtocolError
from masking_lab.core.trial import PlayResult
from masking_lab.responders.base import Response, SetInfo, TrialPresentation
from masking_lab.responders.cue import DisplayGeometry
from masking_lab.responders.participant_window import (
    ANSWER_KEYS,
    NoiseSettings,
    ParticipantWindow,
    WindowLook,
)


def display_geometry(
    config: Any = None,
    *,
    width_mm: float | None = None,
    width_px: int | None = None,
    height_px: int | None = None,
) -> DisplayGeometry:
    """The participant screen's geometry from explicit settings, else the device config.

    Parameters
    ----------
    config : DeviceConfig, optional
        A loaded device config (:func:`masking_lab.device.config.load_device_config`); its
        ``display`` section (width_mm, width_px, height_px) is used for what is not given.
    width_mm, width_px, height_px : optional
        Explicit settings (e.g. from the command line), mm and px.

    Raises
    ------
    ProtocolError
        If a value is missing or invalid; the message names the config file and the key.
    """
    section = getattr(config, "display", None) if config is not None else None
    source = getattr(config, "path", None) or "the device config"
    explicit = {"width_mm": width_mm, "width_px": width_px, "height_px": height_px}
    values: dict[str, Any] = {  # Any: from the config; DisplayGeometry checks each value
        key: value if value is not None else getattr(section, key, None)
        for key, value in explicit.items()
    }
    missing = [key for key, value in values.items() if value is None]
    if missing:
        raise ProtocolError(
            source,
            f"display.{missing[0]}",
            "the participant window needs the monitor's visible width in mm and its resolution: "
            "add a display section (width_mm, width_px, height_px) to the device config or give "
            "the monitor settings explicitly",
        )
    if any(value is not None for value in explicit.values()):
        source = f"{source} + explicit monitor settings"
    return DisplayGeometry(source=source, **values)


def make_responder(context: Any) -> PsychoPyWindowResponder:
    """The runner's factory: a full-screen window on the rig config's display.

    Parameters
    ----------
    context : masking_lab.session.runner.SessionContext
        Uses ``device_config`` (path, None for the reference rig), ``clock`` and ``seed``.

    Raises
    ------
    ProtocolError
        If the device config has no usable ``display`` section.
    ResponderError
        If PsychoPy is missing or the window cannot be opened.
    """
    from masking_lab.device.config import load_device_config

    config = load_device_config(context.device_config)
    display = display_geometry(config)
    screen = getattr(config.display, "screen", 0)
    return PsychoPyWindowResponder(
        display, context.clock, screen=screen, noise=NoiseSettings(seed=context.seed)
    )


class PsychoPyWindowResponder:
    """Answers 3IFC trials in the participant's window (Responder protocol).

    Parameters are those of :class:`~masking_lab.responders.participant_window
    .ParticipantWindow`, which it opens and holds as :attr:`window`.

    Raises
    ------
    ResponderError
        If PsychoPy is missing or the window cannot be opened.
    ProtocolError
        If the lanes do not fit on the display.
    """

    name = "psychopy"

    def __init__(self, display: DisplayGeometry, clock: Clock, **window: Any) -> None:
        self.window = ParticipantWindow(display, clock, **window)
        self._set: SetInfo | None = None

    def ask_info(self, fields: Any, given: dict[str, str]) -> dict[str, str]:
        """Ask the protocol's participant fields not in ``given`` in the window (before set 1;
        Esc: KeyboardInterrupt)."""
        return self.window.ask_info(fields, given)

    def start_set(self, info: SetInfo) -> None:
        """Show the instructions for a set; with ``wait_for_start``, wait for the space bar."""
        self._set = info
        self.window.show_instructions(
            f"Set {info.set_number} of {info.n_sets}\n\n"
            "Three intervals per trial; one feels different.\n"
            "Slide your fingertip from left to right with the yellow dot in each interval.\n"
            "Then press 1, 2 or 3 for the different one."
        )

    def trial(
        self, presentation: TrialPresentation, play: Callable[[], PlayResult]
    ) -> tuple[PlayResult, Response]:
        """Animate the cue while ``play()`` runs in the background, then collect the answer.

        ``response_time_s`` runs from the planned end of the last interval (session clock) to
        the frame on which the key was seen, s, never below 0.
        """
        window = self.window
        window.start_noise()
        duration_s = window.layout_for(presentation.plan).timing.duration_s
        result, finger_path = window.play_with_cue(
            play,
            lambda t_s: self.draw_trial_screen(presentation, t_s),
            presentation.start_s,
            duration_s,
        )
        interval, answered_s = window.ask_key(
            lambda now: self.draw_trial_screen(presentation, now - presentation.start_s),
            "Which interval was different? Press 1, 2 or 3.",
            ANSWER_KEYS,
        )
        assert interval is not None and answered_s is not None  # no deadline: a key ends it
        end_s = presentation.start_s + duration_s
        response = Response(interval, max(0.0, answered_s - end_s), finger_path=finger_path)
        return result, response

    def draw_trial_screen(self, presentation: TrialPresentation, t_s: float) -> Any:
        """The window's trial screen at ``t_s`` s, with the set in the progress line."""
        info = self._set
        progress = f"Set {info.set_number} of {info.n_sets} · " if info is not None else ""
        return self.window.draw_trial_screen(presentation, t_s, progress)

    def close(self) -> None:
        """Stop the noise and close the window. Idempotent."""
        self.window.close()


__all__ = [
    "NoiseSettings",
    "PsychoPyWindowResponder",
    "WindowLook",
    "display_geometry",
    "make_responder",
]
