"""Streaming a user-test object to the device: ticks, rating limits, clipping and dead-band.

Pure (no I/O, no clock, no RNG); :mod:`masking_lab.usertest.runner` drives it.

While a 1.8 s presentation plays, the runner looks up the levels along the path every
``1 / UPDATE_HZ`` s (100 Hz: every 10 ms, i.e. every 0.51 mm of path at 51 mm/s). A tick sends a
channel's level only when it has moved at least ``DEADBAND_DB`` (0.5 dB, well under the ~1–2 dB
intensity JND of touch) from the level last sent, or when the channel switches between silence
and sound; flat stretches cost nothing. When nothing has been sent for ``REFRESH_S`` (0.125 s)
while an output is on, the held level is sent again, which feeds the firmware's watchdog (0.5 s
on the reference rig). Each presentation starts from silence and ends with both channels at 0 V.
The frames depend on nothing but the levels, so every device gets the same stream and a log does
not depend on the back-end.

Limits: a stimulus may not exceed the rig's ``channels.<EV|MV>.max_level_db_sl`` nor the device's
``max_drive_v`` (converted to dB SL with the participant's unmasked AL). :func:`exceedances` lists
every object × condition whose inputs would; the runner refuses such a design unless clipping is
allowed explicitly, and then :func:`clip_db_v` clips and says by how much.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from masking_lab.core.errors import CalibrationError, LevelError
from masking_lab.core.levels import volts_to_db_v
from masking_lab.core.stimulus import CHANNELS, Channel, parse_stimulus
from masking_lab.rendering.render import Rendering, runs_mm
from masking_lab.usertest.design import UserTestDesign

UPDATE_HZ = 100.0
"""Amplitude look-ups per second while a presentation plays, Hz."""

DEADBAND_DB = 0.5
"""Smallest level change worth a frame, dB."""

REFRESH_S = 0.125
"""Longest quiet stretch while an output is on before the held level is re-sent, s (a quarter
of the reference rig's 0.5 s watchdog, the cadence the host PINGs at during a trial)."""

SILENT = -math.inf


# --------------------------------------------------------------------------------------------
# Limits


@dataclass(frozen=True)
class StimulusLimit:
    """The highest level one stimulus may be played at for one participant.

    Attributes
    ----------
    stimulus : str
        Stimulus name.
    channel : {"EV", "MV"}
        Its output channel.
    unmasked_al_db_v : float
        The participant's unmasked AL, dB re 1 V.
    rig_max_db_sl : float or None
        The rig config's ``max_level_db_sl`` for the channel, dB SL (None: not set).
    max_drive_v : float
        The device's drive limit for the channel, V.

    Examples
    --------
    With an AL of −30 dB re 1 V, a 1 V drive limit is 30 dB SL, stricter than a 40 dB SL rig
    limit:

    >>> limit = StimulusLimit("MV180", "MV", -30.0, rig_max_db_sl=40.0, max_drive_v=1.0)
    >>> limit.drive_max_db_sl, limit.max_db_sl, limit.max_db_v
    (30.0, 30.0, 0.0)
    >>> limit.binding
    "the MV max_drive_v 1 V at this participant's AL"
    """

    stimulus: str
    channel: Channel
    unmasked_al_db_v: float
    rig_max_db_sl: float | None
    max_drive_v: float

    @property
    def drive_max_db_sl(self) -> float:
        """``max_drive_v`` as a sensation level for this participant, dB SL."""
        return volts_to_db_v(self.max_drive_v) - self.unmasked_al_db_v

    @property
    def max_db_sl(self) -> float:
        """The stricter of the two limits, dB SL."""
        if self.rig_max_db_sl is None:
            return self.drive_max_db_sl
        return min(self.rig_max_db_sl, self.drive_max_db_sl)

    @property
    def max_db_v(self) -> float:
        """:attr:`max_db_sl` as a drive level, dB re 1 V."""
        return self.max_db_sl + self.unmasked_al_db_v

    @property
    def binding(self) -> str:
        """Which limit binds, in words (for messages)."""
        if self.rig_max_db_sl is not None and self.rig_max_db_sl <= self.drive_max_db_sl:
            return f"the rig's {self.channel} max_level_db_sl"
        return f"the {self.channel} max_drive_v {self.max_drive_v:g} V at this participant's AL"


def stimulus_limits(
    stimuli: Iterable[str],
    calibration: Mapping[str, float],
    max_level_db_sl: Mapping[str, float],
    max_drive_v: Mapping[str, float],
) -> dict[str, StimulusLimit]:
    """Per stimulus, the highest level the session may play.

    Parameters
    ----------
    stimuli : iterable of str
        Stimulus names.
    calibration : mapping stimulus → dB re 1 V
        The participant's unmasked ALs.
    max_level_db_sl : mapping channel → dB SL
        The rig config's sensation-level limits (a channel may be absent: no limit).
    max_drive_v : mapping channel → V
        The device's drive limits in force.

    Returns
    -------
    dict of str to StimulusLimit
        By stimulus name, sorted.

    Raises
    ------
    CalibrationError
        A stimulus without an unmasked AL.

    Examples
    --------
    >>> limits = stimulus_limits(["MV180", "EV270"], {"MV180": -30.0, "EV270": -20.0},
    ...                          {"MV": 15.0}, {"EV": 1.0, "MV": 1.0})
    >>> {name: lim.max_db_sl for name, lim in limits.items()}
    {'EV270': 20.0, 'MV180': 15.0}
    """
    out: dict[str, StimulusLimit] = {}
    for name in sorted(set(stimuli)):
        if name not in calibration:
            raise CalibrationError(f"no unmasked AL for {name}; run its baseline first")
        channel = parse_stimulus(name).channel
        rig = max_level_db_sl.get(channel)
        out[name] = StimulusLimit(
            name,
            channel,
            float(calibration[name]),
            None if rig is None else float(rig),
            float(max_drive_v[channel]),
        )
    return out


@dataclass(frozen=True)
class Exceedance:
    """An object whose inputs, in one condition, exceed a channel's limit somewhere on the path.

    Attributes
    ----------
    geometry, texture, condition : str
        The object and condition.
    stimulus : str
        The stimulus that would be played too strongly.
    need_db_sl : float
        Highest input along the path, dB SL.
    limit : StimulusLimit
        The limit it breaks.
    n_points, n_total : int
        Interaction points above the limit, and on the path.
    spans_mm : tuple of (float, float)
        Where along the path, mm.
    """

    geometry: str
    texture: str
    condition: str
    stimulus: str
    need_db_sl: float
    limit: StimulusLimit
    n_points: int
    n_total: int
    spans_mm: tuple[tuple[float, float], ...]

    def describe(self) -> str:
        """One line: ``bump_rough compensated: MV180 needs up to 58.5 dB SL ...``."""
        spans = ", ".join(f"{a:.1f}-{b:.1f}" for a, b in self.spans_mm[:3])
        more = ", ..." if len(self.spans_mm) > 3 else ""
        return (
            f"{self.geometry}_{self.texture} {self.condition}: {self.stimulus} needs up to "
            f"{self.need_db_sl:.1f} dB SL, above its limit of {self.limit.max_db_sl:.1f} dB SL "
            f"({self.limit.binding}) at {self.n_points} of {self.n_total} points ({spans}{more} "
            "mm)"
        )

    def as_record(self) -> dict[str, object]:
        """JSON-ready summary for the session log's header."""
        return {
            "object": f"{self.geometry}_{self.texture}",
            "condition": self.condition,
            "stimulus": self.stimulus,
            "need_db_sl": round(self.need_db_sl, 3),
            "max_db_sl": round(self.limit.max_db_sl, 3),
            "n_points": self.n_points,
        }


def exceedances(
    design: UserTestDesign,
    objects: Mapping[tuple[str, str], Rendering],
    limits: Mapping[str, StimulusLimit],
) -> list[Exceedance]:
    """Every object × condition × channel whose inputs exceed the stimulus's limit.

    Linear interpolation between interaction points never exceeds the larger neighbour, so
    checking the points covers every position a cue or a finger can reach.

    Parameters
    ----------
    design : UserTestDesign
        Supplies the conditions.
    objects : mapping (geometry, texture) → Rendering
        Rendered objects.
    limits : mapping stimulus → StimulusLimit
        From :func:`stimulus_limits`.

    Returns
    -------
    list of Exceedance

    Examples
    --------
    Compensating the bump's masking asks for MV180 at 18.1 dB SL, over a 15 dB SL rig limit:

    >>> from masking_lab.formats.resources import shipped
    >>> from masking_lab.rendering.pair import MutualMasking
    >>> from masking_lab.rendering.render import render_scene
    >>> from masking_lab.rendering.scene import GeometrySpec, PathSpec, Scene, TextureSpec
    >>> from masking_lab.usertest.design import load_usertest
    >>> design = load_usertest(str(shipped("protocols", "usertest.yaml")))
    >>> scene = Scene("bump_rough", PathSpec(), GeometrySpec("bump"),
    ...               TextureSpec("rough", "MV180", 12.0))
    >>> pair = MutualMasking(a_db=-2.0, b=0.5, c_db=-1.0, d=0.4, mv="MV180", ev="EV270")
    >>> limits = stimulus_limits(["MV180", "EV270"], {"MV180": -30.0, "EV270": -20.0},
    ...                          {"MV": 15.0}, {"EV": 1.0, "MV": 1.0})
    >>> found = exceedances(design, {("bump", "rough"): render_scene(scene, pair)}, limits)
    >>> print(found[0].describe())  # doctest: +NORMALIZE_WHITESPACE
    bump_rough compensated: MV180 needs up to 18.1 dB SL, above its limit of 15.0 dB SL (the
    rig's MV max_level_db_sl) at 284 of 919 points (17.5-45.8 mm)
    """
    found: list[Exceedance] = []
    for (g, t), r in objects.items():
        for condition in design.conditions:
            mv, ev = r.inputs(condition == "compensated")
            for name, values in ((_stimulus(r, "EV"), ev), (_stimulus(r, "MV"), mv)):
                if name is None:
                    continue
                limit = limits[name]
                # 1 µdB of slack: a level computed at the limit is not above it.
                over = np.asarray(values, dtype=float) > limit.max_db_sl + 1e-6
                if over.any():
                    found.append(
                        Exceedance(
                            g,
                            t,
                            condition,
                            name,
                            float(np.nanmax(values)),
                            limit,
                            int(over.sum()),
                            int(over.size),
                            tuple(runs_mm(over, r.x_mm)),
                        )
                    )
    return found


def object_stimuli(r: Rendering) -> dict[Channel, str | None]:
    """``{"EV": name or None, "MV": name or None}`` of a rendered object.

    Examples
    --------
    >>> from masking_lab.rendering.render import render_scene
    >>> from masking_lab.rendering.scene import GeometrySpec, PathSpec, Scene
    >>> object_stimuli(render_scene(Scene("bump", PathSpec(), GeometrySpec("bump"), None), None))
    {'EV': 'EV270', 'MV': None}
    """
    return {"EV": _stimulus(r, "EV"), "MV": _stimulus(r, "MV")}


def _stimulus(r: Rendering, channel: Channel) -> str | None:
    scene = r.scene
    if channel == "EV":
        return scene.geometry.stimulus if scene.geometry is not None else None
    return scene.texture.stimulus if scene.texture is not None else None


# --------------------------------------------------------------------------------------------
# Levels along the path


def tick_offsets_s(stimulus_s: float, update_hz: float = UPDATE_HZ) -> NDArray[np.float64]:
    """Tick times within one presentation, s from its onset: ``0, 1/f, 2/f, … < stimulus_s``.

    Parameters
    ----------
    stimulus_s : float
        Presentation length, s.
    update_hz : float
        Look-ups per second, Hz.

    Returns
    -------
    ndarray
        Tick times, s.

    Examples
    --------
    >>> ticks = tick_offsets_s(1.8)  # 100 Hz
    >>> len(ticks), float(ticks[1]), float(ticks[-1])
    (180, 0.01, 1.79)
    """
    if not (math.isfinite(update_hz) and update_hz > 0):
        raise ValueError(f"update_hz must be a positive number of Hz, got {update_hz!r}")
    # 1 ns slack: 1.8 s × 100 Hz is 180 ticks, not 181 from float noise.
    n = max(1, math.ceil(stimulus_s * update_hz - 1e-9))
    return np.arange(n) / update_hz


def path_levels_db_sl(
    r: Rendering, x_mm: ArrayLike, *, compensated: bool
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(ev_db_sl, mv_db_sl)`` inputs at path positions ``x_mm`` mm (vectorised).

    The same rule as :func:`masking_lab.usertest.design.levels_at`: linear between interaction
    points, silent (``-inf``) off the path or where the position is NaN (finger lifted).

    Examples
    --------
    >>> from masking_lab.rendering.pair import MutualMasking
    >>> from masking_lab.rendering.render import render_scene
    >>> from masking_lab.rendering.scene import GeometrySpec, PathSpec, Scene, TextureSpec
    >>> scene = Scene("bump_rough", PathSpec(), GeometrySpec("bump"),
    ...               TextureSpec("rough", "MV180", 12.0))
    >>> r = render_scene(scene, MutualMasking(-2.0, 0.5, -1.0, 0.4, mv="MV180", ev="EV270"))
    >>> ev, mv = path_levels_db_sl(r, [41.0, float("nan"), 100.0], compensated=True)
    >>> np.round(ev, 2).tolist(), np.round(mv, 2).tolist()  # lifted finger, off the path
    ([16.25, -inf, -inf], [18.12, -inf, -inf])
    """
    x = np.atleast_1d(np.asarray(x_mm, dtype=float))
    mv_in, ev_in = r.inputs(compensated)
    on = (x >= r.x_mm[0]) & (x <= r.x_mm[-1])  # False for NaN
    ev = np.full(x.shape, SILENT)
    mv = np.full(x.shape, SILENT)
    if on.any():
        ev[on] = np.interp(x[on], r.x_mm, ev_in)
        mv[on] = np.interp(x[on], r.x_mm, mv_in)
    # An absent channel is -inf everywhere; interpolating -inf can give NaN: keep it silent.
    ev[np.isnan(ev)] = SILENT
    mv[np.isnan(mv)] = SILENT
    return ev, mv


def to_db_v(level_db_sl: NDArray[np.float64], unmasked_al_db_v: float) -> NDArray[np.float64]:
    """dB SL → dB re 1 V (``-inf`` stays ``-inf``: silence).

    Examples
    --------
    >>> to_db_v(np.array([10.0, -np.inf]), unmasked_al_db_v=-30.0).tolist()
    [-20.0, -inf]
    """
    return np.asarray(level_db_sl, dtype=float) + float(unmasked_al_db_v)


def clip_db_v(
    level_db_v: NDArray[np.float64], max_db_v: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Clip drive levels at ``max_db_v``; return the clipped levels and the excess, dB (≥ 0).

    Examples
    --------
    >>> clipped, excess = clip_db_v(np.array([-25.0, -15.0, -np.inf]), max_db_v=-20.0)
    >>> clipped.tolist(), excess.tolist()
    ([-25.0, -20.0, -inf], [0.0, 5.0, 0.0])
    """
    level = np.asarray(level_db_v, dtype=float)
    clipped = np.minimum(level, max_db_v)
    with np.errstate(invalid="ignore"):
        excess = np.where(np.isfinite(level), np.maximum(level - max_db_v, 0.0), 0.0)
    return clipped, excess


# --------------------------------------------------------------------------------------------
# Frames


@dataclass(frozen=True)
class Frame:
    """One amplitude update to send.

    Attributes
    ----------
    t_s : float
        When, s (on whatever time base the ticks use).
    channel : {"EV", "MV"}
        Output channel.
    level_db_v : float
        Drive level, dB re 1 V; ``-inf`` is 0 V.
    kind : {"update", "refresh", "zero"}
        A new level, the held level re-sent (watchdog), or the end of a presentation.
    """

    t_s: float
    channel: Channel
    level_db_v: float
    kind: str = "update"


class Streamer:
    """Decides, tick by tick, which amplitude frames to send (a pure state machine).

    Parameters
    ----------
    deadband_db : float
        Smallest change of a sounding channel's level that is sent, dB (≥ 0).
    refresh_s : float
        Re-send the held level after this long without a frame while an output is on, s.

    Examples
    --------
    A 0.2 dB step is inside the 0.5 dB dead-band; 0.6 dB is sent; after 0.125 s of quiet the
    held level is re-sent for the watchdog:

    >>> s = Streamer()
    >>> for t_s, level in [(0.0, -20.0), (0.01, -19.8), (0.02, -19.4), (0.15, -19.4)]:
    ...     for f in s.tick(t_s, {"EV": level}):
    ...         print(f.t_s, f.channel, f.level_db_v, f.kind)
    0.0 EV -20.0 update
    0.02 EV -19.4 update
    0.15 EV -19.4 refresh
    >>> s.silence(1.8)
    [Frame(t_s=1.8, channel='EV', level_db_v=-inf, kind='zero')]
    """

    def __init__(self, deadband_db: float = DEADBAND_DB, refresh_s: float = REFRESH_S) -> None:
        if not (math.isfinite(deadband_db) and deadband_db >= 0):
            raise ValueError(f"deadband_db must be ≥ 0 dB, got {deadband_db!r}")
        if not (refresh_s > 0):
            raise ValueError(f"refresh_s must be > 0 s, got {refresh_s!r}")
        self.deadband_db = float(deadband_db)
        self.refresh_s = float(refresh_s)
        self.held: dict[Channel, float] = dict.fromkeys(CHANNELS, SILENT)
        self._last_frame_s = -math.inf

    def tick(self, t_s: float, levels_db_v: Mapping[Channel, float]) -> list[Frame]:
        """Frames to send at ``t_s`` s for the wanted ``levels_db_v`` (``-inf``: silent).

        Raises
        ------
        ValueError
            If a level is NaN.
        """
        frames: list[Frame] = []
        for ch in CHANNELS:
            new = float(levels_db_v.get(ch, SILENT))
            if math.isnan(new):
                raise LevelError(f"{ch} level at {t_s} s is NaN; a level is dB re 1 V or -inf")
            old = self.held[ch]
            if new == old:
                continue
            if new == SILENT or old == SILENT or abs(new - old) >= self.deadband_db:
                frames.append(Frame(t_s, ch, new))
                self.held[ch] = new
        if frames:
            self._last_frame_s = t_s
            return frames
        on = [ch for ch in CHANNELS if self.held[ch] != SILENT]
        # 1 ns slack so that ten 10 ms ticks make 0.1 s.
        if on and t_s - self._last_frame_s >= self.refresh_s - 1e-9:
            self._last_frame_s = t_s
            return [Frame(t_s, on[0], self.held[on[0]], "refresh")]
        return []

    def silence(self, t_s: float) -> list[Frame]:
        """Frames that zero every channel still sounding (end of a presentation)."""
        frames = [Frame(t_s, ch, SILENT, "zero") for ch in CHANNELS if self.held[ch] != SILENT]
        for f in frames:
            self.held[f.channel] = SILENT
        if frames:
            self._last_frame_s = t_s
        return frames


@dataclass(frozen=True)
class PresentationPlan:
    """The frames of one cue-tracked presentation, times from its onset.

    Attributes
    ----------
    frames : tuple[Frame, ...]
        In order; the last ones zero both channels at ``stimulus_s``.
    tick_s : ndarray
        Tick times, s from the onset.
    x_mm : ndarray
        Cue position along the path at each tick, mm.
    held_db_v : Mapping[channel, ndarray]
        Level each channel holds after each tick, dB re 1 V (what the device outputs).
    excess_db : Mapping[channel, ndarray]
        How far above the limit the wanted level was at each tick, dB (0: not clipped).
    """

    frames: tuple[Frame, ...]
    tick_s: NDArray[np.float64]
    x_mm: NDArray[np.float64]
    held_db_v: Mapping[Channel, NDArray[np.float64]]
    excess_db: Mapping[Channel, NDArray[np.float64]]


def plan_presentation(
    wanted_db_v: Mapping[Channel, Sequence[float] | NDArray[np.float64]],
    tick_s: NDArray[np.float64],
    x_mm: NDArray[np.float64],
    stimulus_s: float,
    *,
    max_db_v: Mapping[Channel, float],
    deadband_db: float = DEADBAND_DB,
    refresh_s: float = REFRESH_S,
) -> PresentationPlan:
    """All frames of one presentation whose wanted levels are known in advance (cue tracking).

    Parameters
    ----------
    wanted_db_v : mapping channel → array
        Wanted drive level at each tick, dB re 1 V (``-inf``: silent), before clipping.
    tick_s, x_mm : ndarray
        Tick times, s from the onset, and the path position at each, mm.
    stimulus_s : float
        Presentation length, s; both channels are zeroed then.
    max_db_v : mapping channel → dB re 1 V
        Clip levels above these (``+inf``: no clipping); the excess is reported per tick.
    deadband_db, refresh_s : float
        As for :class:`Streamer`.

    Returns
    -------
    PresentationPlan

    Examples
    --------
    Five 10 ms ticks of EV, clipped at −20 dB re 1 V:

    >>> ticks = tick_offsets_s(0.05)
    >>> plan = plan_presentation({"EV": [-30.0, -29.8, -29.0, -15.0, -15.0]}, ticks,
    ...                          ticks * 51.0, 0.05, max_db_v={"EV": -20.0})
    >>> [(f.t_s, f.level_db_v, f.kind) for f in plan.frames]
    [(0.0, -30.0, 'update'), (0.02, -29.0, 'update'), (0.03, -20.0, 'update'), (0.05, -inf, 'zero')]
    >>> plan.excess_db["EV"].tolist()
    [0.0, 0.0, 0.0, 5.0, 5.0]
    """
    streamer = Streamer(deadband_db, refresh_s)
    clipped: dict[Channel, NDArray[np.float64]] = {}
    excess: dict[Channel, NDArray[np.float64]] = {}
    for ch in CHANNELS:
        clipped[ch], excess[ch] = clip_db_v(
            np.asarray(wanted_db_v.get(ch, np.full(tick_s.shape, SILENT)), dtype=float),
            max_db_v.get(ch, math.inf),
        )
    held = {ch: np.empty(tick_s.shape) for ch in CHANNELS}
    frames: list[Frame] = []
    for i, t in enumerate(tick_s):
        frames += streamer.tick(float(t), {ch: float(clipped[ch][i]) for ch in CHANNELS})
        for ch in CHANNELS:
            held[ch][i] = streamer.held[ch]
    frames += streamer.silence(float(stimulus_s))
    return PresentationPlan(tuple(frames), tick_s, x_mm, held, excess)
