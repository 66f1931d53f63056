"""The participant's PsychoPy window: lanes, the sliding cue, the finger, keys, pink noise.

What the 3IFC window (:mod:`masking_lab.responders.psychopy_window`) and the user test's
(:mod:`masking_lab.usertest.window_responder`) both hold: the window opened at the display's
size, instructions, a trial screen drawn frame after frame from the session clock while the
device plays in a background thread, the pointer sampled as the finger, one answer key at a time
(Escape stops the session), and the masking noise. PsychoPy is imported when a window opens.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from masking_lab.core.clock import Clock
from masking_lab.core.errors import ProtocolError, ResponderError
from masking_lab.responders import pink_noise
from masking_lab.responders.base import TrialPresentation
from masking_lab.responders.cue import (
    CueLayout,
    CueState,
    DisplayGeometry,
    FingerSample,
    TrialTiming,
    finger_sample,
    should_record,
)
from masking_lab.responders.play_thread import PlayThread

ResultT = TypeVar("ResultT")

log = logging.getLogger(__name__)

# Colours, 0–255 RGB on a black screen (a dim room; the cue is the brightest thing on it).
BACKGROUND = (0, 0, 0)
LANE = (90, 90, 90)
LANE_ACTIVE = (210, 210, 210)
TEXT = (170, 170, 170)
CUE_MOVING = (255, 200, 0)
CUE_WAITING = (128, 100, 0)

ANSWER_KEYS = {"1": 1, "2": 2, "3": 3, "num_1": 1, "num_2": 2, "num_3": 3}
START_KEYS = ("space",)
ABORT_KEYS = ("escape",)


@dataclass(frozen=True)
class NoiseSettings:
    """Pink masking noise in the participant's headphones.

    Attributes
    ----------
    level_db_fs : float
        RMS level of the digital signal, dB re full scale. Set the amplifier so this gives about
        80 dB SPL at the headphones (paper §2.3); see docs/participant-window.md.
    loop_s : float
        Length of the seamless loop, s.
    sample_rate_hz : float
        Sample rate, Hz.
    f_min_hz : float
        Lowest frequency in the noise, Hz.
    seed : int or None
        Seed of the noise (None: fresh noise each session).
    """

    level_db_fs: float = -20.0
    loop_s: float = 20.0
    sample_rate_hz: float = 44100.0
    f_min_hz: float = 20.0
    seed: int | None = None


@dataclass(frozen=True)
class WindowLook:
    """Sizes on screen, mm.

    Attributes
    ----------
    lane_spacing_mm : float
        Between neighbouring lanes.
    cue_radius_mm : float
        Radius of the cue disc.
    tick_mm : float
        Height of the marks at both ends of a lane (the interval boundaries).
    lane_width_mm : float
        Thickness of a lane line.
    label_offset_mm : float
        From a lane's start to the centre of its number.
    text_mm : float
        Height of text.
    """

    lane_spacing_mm: float = 30.0
    cue_radius_mm: float = 4.0
    tick_mm: float = 8.0
    lane_width_mm: float = 1.0
    label_offset_mm: float = 12.0
    text_mm: float = 7.0


class ParticipantWindow:
    """The participant's window, shared by the 3IFC and the user-test window responders.

    Parameters
    ----------
    display : DisplayGeometry
        Width (mm) and resolution (px) of the participant's screen.
    clock : Clock
        The session clock the runner and the device use; the cue follows it.
    screen : int
        Screen number for the window.
    fullscr : bool
        Full-screen window (the rig); False opens a window of the display's pixel size.
    look : WindowLook
        Sizes of lanes, cue and text, mm.
    noise : NoiseSettings or None
        Pink masking noise; None for silence.
    wait_for_start : bool
        :meth:`show_instructions` waits for the space bar.
    hide_pointer : bool
        Hide the mouse pointer (a touch panel moves it to the finger).
    max_frame_rate_hz : float
        Upper bound on redraws, Hz; without vertical sync (virtual displays) the frame loop
        would otherwise spin.
    noise_player : callable, optional
        ``(samples, sample_rate_hz) -> player`` with ``play()`` and ``stop()``; default plays
        through ``psychopy.sound``.
    events : module-like, optional
        Where keys come from (``clearEvents``, ``getKeys``); default ``psychopy.event``. Tests
        inject keys through a stand-in that wraps it.

    Raises
    ------
    ResponderError
        If PsychoPy is missing or the window cannot be opened.
    ProtocolError
        If the lanes do not fit on the display.

    Examples
    --------
    Opening one needs a display; ``tests/test_psychopy_window.py`` opens it on Xvfb:

    >>> ParticipantWindow.__name__
    'ParticipantWindow'
    """

    def __init__(
        self,
        display: DisplayGeometry,
        clock: Clock,
        *,
        screen: int = 0,
        fullscr: bool = True,
        look: WindowLook | None = None,
        noise: NoiseSettings | None = None,
        wait_for_start: bool = True,
        hide_pointer: bool = True,
        max_frame_rate_hz: float = 120.0,
        noise_player: Callable[[np.ndarray, float], Any] | None = None,
        events: Any = None,
    ) -> None:
        self.display = display
        self.look = look or WindowLook()
        self.clock = clock
        self._noise_settings = noise
        self._noise_player_factory = noise_player or _psychopy_noise_player
        self._noise: Any = None
        self._noise_tried = False
        self.wait_for_start = wait_for_start
        self._min_frame_s = 1.0 / max_frame_rate_hz
        self._last_flip = 0.0
        self._closed = False
        self._layout: CueLayout | None = None
        self._lanes: list[Any] = []
        try:
            from psychopy import event, monitors, visual
        except ImportError as exc:
            raise ResponderError(
                f"--responder psychopy needs PsychoPy ({exc}); install it with "
                "pip install 'masking-lab[psychopy]' (Python < 3.13) or use --responder keys"
            ) from exc
        except Exception as exc:  # pyglet opens the X display while PsychoPy imports
            raise _no_window(screen, exc) from exc
        self._visual = visual
        self._event = event if events is None else events
        size = (display.width_px, display.height_px)
        monitor = monitors.Monitor("masking-lab", width=display.width_mm / 10.0, distance=50.0)
        monitor.setSizePix(list(size))
        try:
            self.win = visual.Window(
                size=size,
                fullscr=fullscr,
                screen=screen,
                units="pix",
                color=BACKGROUND,
                colorSpace="rgb255",
                winType="pyglet",
                allowGUI=not fullscr,
                monitor=monitor,
                checkTiming=False,
            )
        except Exception as exc:  # pyglet raises a variety of types without a display
            raise _no_window(screen, exc) from exc
        opened = tuple(int(v) for v in self.win.size)
        if opened != size:
            self.win.close()
            raise ProtocolError(
                display.source,
                "display.width_px",
                f"the window opened at {opened[0]}×{opened[1]} px but the settings say "
                f"{size[0]}×{size[1]} px; give the screen's actual resolution so that mm on "
                "screen are right",
            )
        self.mouse = event.Mouse(visible=not hide_pointer, win=self.win)
        self._text = self._make_text("", (0.0, 0.0))
        self._progress = self._make_text("", (0.0, display.height_mm / 2 - 3 * self.look.text_mm))
        self._prompt = self._make_text("", (0.0, -display.height_mm / 2 + 3 * self.look.text_mm))
        self._cue = visual.Circle(
            self.win,
            radius=self._px(self.look.cue_radius_mm),
            edges=64,
            fillColor=CUE_MOVING,
            lineColor=None,
            colorSpace="rgb255",
        )

    def ask_info(self, fields: Any, given: dict[str, str]) -> dict[str, str]:
        """Ask the protocol's participant fields not in ``given`` in this window (before set 1):
        :func:`masking_lab.responders.window_form.ask_in_window` (Esc: KeyboardInterrupt)."""
        from masking_lab.responders.window_form import ask_in_window

        where = (self.win, self._visual, self._event, fields, given, self.flip)
        return ask_in_window(*where, text_px=self._px(self.look.text_mm), colour=TEXT)

    def show_instructions(self, text: str) -> None:
        """Show ``text``; with ``wait_for_start``, wait for the space bar (Esc aborts)."""
        self.start_noise()
        self._text.text = text
        self._prompt.text = "Press the space bar to start." if self.wait_for_start else ""
        self._event.clearEvents()
        while True:
            self._text.draw()
            self._prompt.draw()
            self.flip()
            if not self.wait_for_start:
                return
            keys = self._event.getKeys(keyList=[*START_KEYS, *ABORT_KEYS])
            if any(key in ABORT_KEYS for key in keys):
                raise KeyboardInterrupt
            if keys:
                return

    def play_with_cue(
        self,
        play: Callable[[], ResultT],
        draw: Callable[[float], CueState],
        start_s: float,
        duration_s: float,
        on_finger: Callable[[float, float], None] | None = None,
    ) -> tuple[ResultT, list[FingerSample]]:
        """Draw frame after frame (``draw(s since start_s)``) while ``play()`` runs behind.

        While the cue moves, the pointer is sampled every frame; the samples kept form the
        finger path, and ``on_finger(session s, x mm)`` hears each. Returns what ``play``
        returned (re-raising its error) and the path. Escape raises KeyboardInterrupt, but
        only once the device has finished the trial.
        """
        player = PlayThread(play)
        finger_path: list[FingerSample] = []
        previous_mm: tuple[float, float] | None = None
        abort = False
        self._event.clearEvents()
        player.start()
        try:
            while True:
                now = self.clock.now()
                state = draw(now - start_s)
                self.flip()
                if state.moving:
                    x_px, y_px = self.mouse.getPos()
                    x_mm, y_mm = self.display.px_to_mm(float(x_px), float(y_px))
                    pressed = bool(self.mouse.getPressed()[0])
                    if should_record(previous_mm, x_mm, y_mm, pressed):
                        finger_path.append(finger_sample(now, x_px, y_px, self.display))
                        if on_finger is not None:
                            on_finger(now, x_mm)
                    previous_mm = (x_mm, y_mm)
                if self._event.getKeys(keyList=list(ABORT_KEYS)):
                    abort = True
                # Done when the device has finished and the cue has too (a virtual clock does
                # not move while we draw); a device fault ends the trial at once.
                ended = now - start_s >= duration_s or self.clock.virtual
                if not player.is_alive() and (ended or player.failed):
                    break
        except BaseException:
            # Ctrl-C or a drawing failure: let the device finish the trial before the runner
            # stops it, so two threads never talk to the device at once.
            player.join()
            raise
        result = player.result()  # re-raises a DeviceError from play()
        if abort:
            raise KeyboardInterrupt
        return result, finger_path

    def close(self) -> None:
        """Stop the noise and close the window. Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._noise is not None:
            try:
                self._noise.stop()
            except Exception as exc:  # closing must not fail over audio
                log.warning("could not stop the masking noise cleanly: %s", exc)
            self._noise = None
        self.win.close()

    def draw_trial_screen(
        self, presentation: TrialPresentation, t_s: float, progress: str = ""
    ) -> CueState:
        """Draw (without flipping) the trial screen ``t_s`` s after the trial's start.

        Lanes with their boundary marks and numbers, the progress line (``progress`` then the
        trial's number) and the cue; the lane being swept is brighter. Returns the cue state.
        """
        layout = self.layout_for(presentation.plan)
        state = layout.state_at(t_s)
        for k, (lane, ticks, label) in enumerate(self._lanes, start=1):
            active = state.moving and state.interval == k
            lane.fillColor = LANE_ACTIVE if active else LANE
            lane.draw()
            for tick in ticks:
                tick.draw()
            label.draw()
        self._progress.text = f"{progress}trial {presentation.trial_index + 1}"
        self._progress.draw()
        self._cue.pos = self.display.mm_to_px(state.x_mm, state.y_mm)
        self._cue.fillColor = CUE_MOVING if state.moving else CUE_WAITING
        self._cue.draw()
        return state

    def save_screenshot(
        self, presentation: TrialPresentation, t_s: float, path: Path, progress: str = ""
    ) -> Path:
        """Draw the trial screen at ``t_s`` s, save it as an image (PNG) and show it."""
        self.draw_trial_screen(presentation, t_s, progress)
        image = self.win.getMovieFrame(buffer="back")
        self.win.movieFrames.clear()  # getMovieFrame also queues the frame for a movie
        image.save(path)
        self.flip()
        return Path(path)

    def ask_key(
        self,
        draw: Callable[[float], object],
        prompt: str,
        keys: Mapping[str, int],
        deadline: float | None = None,
    ) -> tuple[int | None, float | None]:
        """Show ``prompt`` under ``draw(session s)`` until one of ``keys`` is pressed.

        Keys pressed earlier (while the stimuli played) are discarded. Returns the answer
        (``keys[name]``) and the session time of the frame it was seen on, s; (None, None)
        once ``deadline`` (session s) passes. Escape raises KeyboardInterrupt.
        """
        self._event.clearEvents("keyboard")
        self._prompt.text = prompt
        while True:
            now = self.clock.now()
            if deadline is not None and now >= deadline:
                return None, None
            draw(now)
            self._prompt.draw()
            self.flip()
            for key in self._event.getKeys(keyList=[*keys, *ABORT_KEYS]):
                if key in ABORT_KEYS:
                    raise KeyboardInterrupt
                return keys[key], now

    def layout_for(self, plan: Any) -> CueLayout:
        timing = TrialTiming.from_plan(plan)
        if self._layout is None or self._layout.timing != timing:
            layout = CueLayout(timing, lane_spacing_mm=self.look.lane_spacing_mm)
            layout.check_fits(
                self.display,
                label_room_mm=self.look.label_offset_mm + self.look.text_mm,
                cue_radius_mm=self.look.cue_radius_mm,
            )
            self._layout = layout
            self._build_lanes(layout)
        return self._layout

    def _build_lanes(self, layout: CueLayout) -> None:
        visual = self._visual
        look = self.look
        self._lanes = []
        for mark in layout.interval_marks():
            centre = self.display.mm_to_px((mark.x_start_mm + mark.x_end_mm) / 2, mark.y_mm)
            lane = visual.Rect(
                self.win,
                width=self._px(mark.x_end_mm - mark.x_start_mm),
                height=max(1.0, self._px(look.lane_width_mm)),
                pos=centre,
                fillColor=LANE,
                lineColor=None,
                colorSpace="rgb255",
            )
            ticks = [
                visual.Rect(
                    self.win,
                    width=max(2.0, self._px(look.lane_width_mm)),
                    height=self._px(look.tick_mm),
                    pos=self.display.mm_to_px(x_mm, mark.y_mm),
                    fillColor=LANE,
                    lineColor=None,
                    colorSpace="rgb255",
                )
                for x_mm in (mark.x_start_mm, mark.x_end_mm)
            ]
            label = self._make_text(
                str(mark.interval), (mark.x_start_mm - look.label_offset_mm, mark.y_mm)
            )
            self._lanes.append((lane, ticks, label))

    def _make_text(self, text: str, pos_mm: tuple[float, float]) -> Any:
        return self._visual.TextStim(
            self.win,
            text=text,
            pos=self.display.mm_to_px(*pos_mm),
            height=self._px(self.look.text_mm),
            color=TEXT,
            colorSpace="rgb255",
            wrapWidth=self.display.width_px * 0.9,
        )

    def _px(self, mm: float) -> float:
        return mm * self.display.px_per_mm

    def flip(self) -> None:
        self.win.flip()
        # Without vertical sync (a virtual display) flip returns at once: pace the loop.
        wait = self._last_flip + self._min_frame_s - time.perf_counter()
        if wait > 0:
            time.sleep(wait)
        self._last_flip = time.perf_counter()

    # -- masking noise ------------------------------------------------------------------------

    def start_noise(self) -> None:
        if self._noise_tried or self._noise_settings is None:
            return
        self._noise_tried = True
        settings = self._noise_settings
        try:
            samples = pink_noise.loop_buffer(
                settings.loop_s,
                np.random.default_rng(settings.seed),
                sample_rate_hz=settings.sample_rate_hz,
                level_db_fs=settings.level_db_fs,
                f_min_hz=settings.f_min_hz,
            )
            player = self._noise_player_factory(samples, settings.sample_rate_hz)
            player.play()
        except Exception as exc:  # no sound card, no back-end: run on without noise
            log.warning(
                "pink masking noise is OFF: no usable audio output (%s: %s). Auditory cues from "
                "the actuators are not masked; fix the audio set-up or have the participant wear "
                "noise played from another source.",
                type(exc).__name__,
                exc,
            )
            return
        self._noise = player


def _no_window(screen: int, exc: Exception) -> ResponderError:
    return ResponderError(
        f"cannot open the participant window on screen {screen} ({type(exc).__name__}: {exc}); "
        "check that the monitor is connected and DISPLAY is set, or use --responder keys"
    )


def _psychopy_noise_player(samples: np.ndarray, sample_rate_hz: float) -> Any:
    """A looping ``psychopy.sound.Sound`` of ``samples`` (mono, −1..1)."""
    from psychopy import sound

    return sound.Sound(value=samples, sampleRate=round(sample_rate_hz), loops=-1)
