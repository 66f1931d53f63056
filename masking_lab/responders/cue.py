"""Where the sliding cue is on the participant's screen, and how finger positions are logged.

The paper's participants slide a fingertip left → right following a graphic object that moves at
a constant 51 mm/s while each 1.8 s stimulus plays. Here each of the three intervals has its own
horizontal *lane* on the screen, stacked top (interval 1) to bottom (interval 3), so the interval
marks double as the answer keys: the cue sweeps lane *k* while interval *k* plays, and waits at
the start of the next lane during the lead-in and the gaps.

Coordinates are those of PsychoPy's ``pix`` units, in mm or px: origin at the screen centre,
x to the right, y up. Pixels are assumed square (``height_mm = height_px · width_mm / width_px``).
Everything here is pure: no clock, no window; times are trial-relative seconds.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

from masking_lab.core.errors import InputError, ProtocolError

CUE_SPEED_MM_S = 51.0
"""Sliding speed of the cue, mm/s (paper §2.3, after typical exploration speeds)."""

FingerSample = tuple[float, float, float]
"""One finger/touch position: ``(t_s, x_mm, y_mm)``, session-clock s and screen mm."""

Phase = Literal["lead_in", "interval", "gap", "response"]


@dataclass(frozen=True)
class DisplayGeometry:
    """Physical size and resolution of the participant's screen.

    Attributes
    ----------
    width_mm : float
        Visible width of the screen (the touch panel), mm.
    width_px, height_px : int
        Resolution, px.
    source : str
        Where the numbers came from (config file path or command-line options), for messages.

    Raises
    ------
    ProtocolError
        For a width that is not a positive number of mm or a resolution that is not whole px.

    Examples
    --------
    A 200 mm wide panel at 1280 × 800 px:

    >>> screen = DisplayGeometry(width_mm=200.0, width_px=1280, height_px=800)
    >>> screen.mm_per_px, screen.height_mm
    (0.15625, 125.0)
    >>> screen.mm_to_px(50.0, -10.0)
    (320.0, -64.0)
    """

    width_mm: float
    width_px: int
    height_px: int
    source: str = "display settings"

    def __post_init__(self) -> None:
        if not (isinstance(self.width_mm, int | float) and math.isfinite(self.width_mm)):
            raise ProtocolError(
                self.source, "display.width_mm", f"must be a number of mm, got {self.width_mm!r}"
            )
        if self.width_mm <= 0:
            raise ProtocolError(
                self.source,
                "display.width_mm",
                f"must be > 0 mm, got {self.width_mm}; measure the visible screen width",
            )
        for key in ("width_px", "height_px"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ProtocolError(
                    self.source,
                    f"display.{key}",
                    f"must be a whole number of pixels ≥ 1, got {value!r}; use the screen's "
                    "native resolution",
                )

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any], source: str) -> DisplayGeometry:
        """Build from a config's ``display:`` mapping (keys width_mm, width_px, height_px).

        Examples
        --------
        >>> DisplayGeometry.from_mapping({"width_mm": 200.0, "width_px": 1280}, "rig.yaml")
        Traceback (most recent call last):
        ...
        masking_lab.core.errors.ProtocolError: rig.yaml: display.height_px: is missing; ...

        Raises
        ------
        ProtocolError
            Naming ``source`` and the missing or bad key.
        """
        if not isinstance(mapping, Mapping):
            raise ProtocolError(
                source, "display", "must be a mapping with width_mm, width_px and height_px"
            )
        for key in ("width_mm", "width_px", "height_px"):
            if key not in mapping:
                raise ProtocolError(
                    source,
                    f"display.{key}",
                    "is missing; the participant window needs the screen's width in mm and its "
                    "resolution in px (width_mm, width_px, height_px)",
                )
        return cls(
            width_mm=mapping["width_mm"],
            width_px=mapping["width_px"],
            height_px=mapping["height_px"],
            source=source,
        )

    @property
    def mm_per_px(self) -> float:
        """Size of one pixel, mm."""
        return self.width_mm / self.width_px

    @property
    def px_per_mm(self) -> float:
        """Pixels per mm."""
        return self.width_px / self.width_mm

    @property
    def height_mm(self) -> float:
        """Visible height, mm (square pixels)."""
        return self.height_px * self.mm_per_px

    def mm_to_px(self, x_mm: float, y_mm: float) -> tuple[float, float]:
        """Screen position in mm → px (both centre-origin, y up).

        Examples
        --------
        >>> DisplayGeometry(200.0, 1280, 800).mm_to_px(10.0, 5.0)
        (64.0, 32.0)
        """
        return x_mm * self.px_per_mm, y_mm * self.px_per_mm

    def px_to_mm(self, x_px: float, y_px: float) -> tuple[float, float]:
        """Screen position in px → mm (both centre-origin, y up).

        Examples
        --------
        >>> DisplayGeometry(200.0, 1280, 800).px_to_mm(64.0, -32.0)
        (10.0, -5.0)
        """
        return x_px * self.mm_per_px, y_px * self.mm_per_px


@dataclass(frozen=True)
class TrialTiming:
    """Timing of one 3IFC trial, s, relative to the trial's start.

    Attributes
    ----------
    lead_in_s : float
        Before the first interval, s.
    stimulus_s : float
        Each interval, s (1.8 s in the paper).
    gap_s : float
        Between intervals, s.
    n_intervals : int
        Intervals per trial (3).

    Examples
    --------
    The paper's trial: 0.6 s lead-in, three 1.8 s intervals, 0.6 s gaps:

    >>> timing = TrialTiming(lead_in_s=0.6, stimulus_s=1.8, gap_s=0.6)
    >>> timing.onset_s(2), timing.offset_s(2), round(timing.duration_s, 6)
    (3.0, 4.8, 7.2)
    """

    lead_in_s: float
    stimulus_s: float
    gap_s: float
    n_intervals: int = 3

    def __post_init__(self) -> None:
        for key in ("lead_in_s", "stimulus_s", "gap_s"):
            value = getattr(self, key)
            if not math.isfinite(value) or value < 0:
                raise InputError(f"{key} must be a finite number of s ≥ 0, got {value!r}")
        if not self.stimulus_s > 0:
            raise InputError(f"stimulus_s must be > 0 s, got {self.stimulus_s!r}")
        if self.n_intervals < 1:
            raise InputError(f"n_intervals must be ≥ 1, got {self.n_intervals!r}")

    @classmethod
    def from_plan(cls, plan: Any) -> TrialTiming:
        """Take the timing of a :class:`~masking_lab.device.base.TrialPlan` (s).

        Examples
        --------
        >>> from masking_lab.core.stimulus import parse_stimulus
        >>> from masking_lab.core.trial import TrialPlan
        >>> TrialTiming.from_plan(TrialPlan(parse_stimulus("EV270"), 0.05, 1))
        TrialTiming(lead_in_s=0.6, stimulus_s=1.8, gap_s=0.6, n_intervals=3)
        """
        return cls(plan.lead_in_s, plan.stimulus_s, plan.gap_s, plan.n_intervals)

    def onset_s(self, interval: int) -> float:
        """Onset of ``interval`` (1-based), s after the trial start."""
        return self.lead_in_s + (interval - 1) * (self.stimulus_s + self.gap_s)

    def offset_s(self, interval: int) -> float:
        """End of ``interval`` (1-based), s after the trial start."""
        return self.onset_s(interval) + self.stimulus_s

    @property
    def duration_s(self) -> float:
        """Trial start to the end of the last interval, s."""
        return self.offset_s(self.n_intervals)


@dataclass(frozen=True)
class IntervalMark:
    """One interval's lane on the screen and its time window.

    Attributes
    ----------
    interval : int
        1-based interval number (the key that chooses it).
    onset_s, offset_s : float
        When the cue sweeps this lane, s after the trial start.
    x_start_mm, x_end_mm : float
        Where the sweep starts and ends, mm (centre-origin).
    y_mm : float
        Height of the lane, mm (centre-origin, y up).
    """

    interval: int
    onset_s: float
    offset_s: float
    x_start_mm: float
    x_end_mm: float
    y_mm: float


@dataclass(frozen=True)
class CueState:
    """The cue at one instant.

    Attributes
    ----------
    phase : {"lead_in", "interval", "gap", "response"}
        What the trial is doing.
    interval : int
        Interval being played (``"interval"``), next to play (``"lead_in"``, ``"gap"``), or the
        last one (``"response"``).
    x_mm, y_mm : float
        Cue position, mm (centre-origin, y up).
    moving : bool
        True while an interval plays (the finger should follow it).
    """

    phase: Phase
    interval: int
    x_mm: float
    y_mm: float
    moving: bool


@dataclass(frozen=True)
class CueLayout:
    """Lanes and cue motion for one trial timing.

    Attributes
    ----------
    timing : TrialTiming
        Trial timing, s.
    speed_mm_s : float
        Cue speed, mm/s (51 mm/s in the paper).
    lane_spacing_mm : float
        Vertical distance between neighbouring lanes, mm.

    Examples
    --------
    At 51 mm/s a 1.8 s interval sweeps 91.8 mm; lane 1 is on top:

    >>> layout = CueLayout(TrialTiming(lead_in_s=0.6, stimulus_s=1.8, gap_s=0.6))
    >>> round(layout.sweep_mm, 6), [layout.lane_y_mm(k) for k in (1, 2, 3)]
    (91.8, [30.0, 0.0, -30.0])
    >>> [(m.interval, m.onset_s, m.offset_s) for m in layout.interval_marks()][:2]
    [(1, 0.6, 2.4), (2, 3.0, 4.8)]
    """

    timing: TrialTiming
    speed_mm_s: float = CUE_SPEED_MM_S
    lane_spacing_mm: float = 30.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.speed_mm_s) and self.speed_mm_s > 0):
            raise InputError(f"speed_mm_s must be > 0 mm/s, got {self.speed_mm_s!r}")
        if not (math.isfinite(self.lane_spacing_mm) and self.lane_spacing_mm > 0):
            raise InputError(f"lane_spacing_mm must be > 0 mm, got {self.lane_spacing_mm!r}")

    @property
    def sweep_mm(self) -> float:
        """Distance the cue travels during one interval, mm (91.8 mm at 51 mm/s × 1.8 s)."""
        return self.speed_mm_s * self.timing.stimulus_s

    @property
    def start_x_mm(self) -> float:
        """Left end of every lane, mm (lanes are centred horizontally)."""
        return -self.sweep_mm / 2

    @property
    def end_x_mm(self) -> float:
        """Right end of every lane, mm."""
        return self.sweep_mm / 2

    def lane_y_mm(self, interval: int) -> float:
        """Height of the lane of ``interval`` (1 on top), mm; the lanes are centred vertically."""
        n = self.timing.n_intervals
        if not 1 <= interval <= n:
            raise ValueError(f"interval must be 1..{n}, got {interval!r}")
        return ((n + 1) / 2 - interval) * self.lane_spacing_mm

    def interval_marks(self) -> list[IntervalMark]:
        """Every interval's lane and time window, interval 1 first."""
        return [
            IntervalMark(
                interval=k,
                onset_s=self.timing.onset_s(k),
                offset_s=self.timing.offset_s(k),
                x_start_mm=self.start_x_mm,
                x_end_mm=self.end_x_mm,
                y_mm=self.lane_y_mm(k),
            )
            for k in range(1, self.timing.n_intervals + 1)
        ]

    def state_at(self, t_s: float) -> CueState:
        """Cue state ``t_s`` seconds after the trial start (negative: not started yet).

        The cue moves only while an interval plays; otherwise it waits at the start of the lane
        that plays next, or, once the last interval is over, at the end of the last lane.

        Parameters
        ----------
        t_s : float
            Time since the trial start, s.

        Returns
        -------
        CueState
            Phase, interval and position in mm.

        Raises
        ------
        ValueError
            If ``t_s`` is NaN.

        Examples
        --------
        Halfway through interval 1 the cue is at the lane's centre; in the gap it waits at the
        start of lane 2:

        >>> layout = CueLayout(TrialTiming(lead_in_s=0.6, stimulus_s=1.8, gap_s=0.6))
        >>> for t_s in (0.0, 1.5, 2.7, 8.0):
        ...     s = layout.state_at(t_s)
        ...     print(s.phase, s.interval, round(s.x_mm, 2), s.y_mm, s.moving)
        lead_in 1 -45.9 30.0 False
        interval 1 0.0 30.0 True
        gap 2 -45.9 0.0 False
        response 3 45.9 -30.0 False
        """
        if math.isnan(t_s):
            raise ValueError("t_s must be a number of s, got NaN")
        timing = self.timing
        n = timing.n_intervals
        if t_s < timing.onset_s(1):
            return CueState("lead_in", 1, self.start_x_mm, self.lane_y_mm(1), False)
        for k in range(1, n + 1):
            if t_s < timing.offset_s(k):
                # Here t_s ≥ onset_s(k): earlier lanes and gaps were handled before.
                x_mm = self.start_x_mm + self.speed_mm_s * (t_s - timing.onset_s(k))
                return CueState("interval", k, x_mm, self.lane_y_mm(k), True)
            if k < n and t_s < timing.onset_s(k + 1):
                return CueState("gap", k + 1, self.start_x_mm, self.lane_y_mm(k + 1), False)
        return CueState("response", n, self.end_x_mm, self.lane_y_mm(n), False)

    def extent_mm(
        self, label_room_mm: float = 0.0, cue_radius_mm: float = 0.0
    ) -> tuple[float, float]:
        """Width and height the lanes need on screen, mm, with room for labels and the cue.

        Parameters
        ----------
        label_room_mm : float
            Room left of and right of each lane for its label, mm.
        cue_radius_mm : float
            Radius of the cue, mm.

        Returns
        -------
        width_mm, height_mm : float

        Examples
        --------
        >>> layout = CueLayout(TrialTiming(0.6, 1.8, 0.6))
        >>> [round(v, 6) for v in layout.extent_mm(label_room_mm=10.0, cue_radius_mm=5.0)]
        [121.8, 70.0]
        """
        width = self.sweep_mm + 2 * (label_room_mm + cue_radius_mm)
        height = (self.timing.n_intervals - 1) * self.lane_spacing_mm + 2 * cue_radius_mm
        return width, height

    def check_fits(
        self, display: DisplayGeometry, label_room_mm: float = 0.0, cue_radius_mm: float = 0.0
    ) -> None:
        """Raise if the lanes do not fit on ``display``.

        Examples
        --------
        >>> CueLayout(TrialTiming(0.6, 1.8, 0.6)).check_fits(DisplayGeometry(80.0, 800, 480))
        Traceback (most recent call last):
        ...
        masking_lab.core.errors.ProtocolError: display settings: display.width_mm: the cue ...

        Raises
        ------
        ProtocolError
            Naming the display settings' source and saying what to change.
        """
        width, height = self.extent_mm(label_room_mm, cue_radius_mm)
        if width > display.width_mm:
            raise ProtocolError(
                display.source,
                "display.width_mm",
                f"the cue travels {self.sweep_mm:.1f} mm per interval ({self.speed_mm_s:g} mm/s "
                f"× {self.timing.stimulus_s:g} s) and needs {width:.1f} mm with its labels, but "
                f"the screen is {display.width_mm:g} mm wide; use a wider screen or check width_mm",
            )
        if height > display.height_mm:
            raise ProtocolError(
                display.source,
                "display.height_px",
                f"the {self.timing.n_intervals} lanes need {height:.1f} mm but the screen is "
                f"{display.height_mm:.1f} mm high; reduce the lane spacing or check the "
                "resolution",
            )


def finger_sample(t_s: float, x_px: float, y_px: float, display: DisplayGeometry) -> FingerSample:
    """One logged finger position: time and pointer position in px → ``(t_s, x_mm, y_mm)``.

    Rounded to 0.1 ms and 0.01 mm: finer than a touch panel resolves, and it keeps logs small.

    Parameters
    ----------
    t_s : float
        Session-clock time, s.
    x_px, y_px : float
        Pointer position, px (centre-origin, y up).
    display : DisplayGeometry
        The screen, for the px → mm conversion.

    Returns
    -------
    FingerSample
        ``(t_s, x_mm, y_mm)``.

    Examples
    --------
    >>> finger_sample(1.23456789, 100.0, -50.0, DisplayGeometry(200.0, 1280, 800))
    (1.2346, 15.62, -7.81)
    """
    x_mm, y_mm = display.px_to_mm(x_px, y_px)
    return (round(float(t_s), 4), round(float(x_mm), 2), round(float(y_mm), 2))


def should_record(
    previous_mm: tuple[float, float] | None,
    x_mm: float,
    y_mm: float,
    pressed: bool,
    min_move_mm: float = 0.05,
) -> bool:
    """Whether a pointer reading is worth a finger-path sample.

    A touching finger (``pressed``) is always recorded, even when still. A pointer reported
    without a touch (a touch panel that only sends motion, or a mouse) is recorded when it moved
    at least ``min_move_mm`` mm since the ``previous_mm`` reading; a pointer that sits still, or
    whose first reading of the trial is all we have, says nothing about a finger.

    Examples
    --------
    >>> should_record(None, 0.0, 0.0, pressed=True)
    True
    >>> should_record((0.0, 0.0), 0.03, 0.0, pressed=False)  # moved 0.03 mm < 0.05 mm
    False
    >>> should_record((0.0, 0.0), 0.1, 0.0, pressed=False)
    True
    """
    if pressed:
        return True
    if previous_mm is None:
        return False
    return math.hypot(x_mm - previous_mm[0], y_mm - previous_mm[1]) >= min_move_mm
