"""The user test's session loop: play each object along its path, collect two answers, log.

One :class:`UserTestSession` runs the trials of the seeded order that are not yet logged: it
streams EV and MV amplitudes along the path (cue or finger), clips only where the session allows
it, and appends one fsynced ``usertest_trial`` record per trial.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from masking_lab.core.clock import Clock
from masking_lab.core.errors import (
    LevelError,
    MaskingLabError,
)
from masking_lab.core.levels import db_v_to_volts
from masking_lab.core.stimulus import CHANNELS, Channel, Stimulus, parse_stimulus
from masking_lab.device.base import Device
from masking_lab.formats.session_log import SessionLogWriter
from masking_lab.rendering.render import Rendering
from masking_lab.session.progress import ProgressLine, format_duration
from masking_lab.session.runner import SessionResult
from masking_lab.session.shell import SessionShell
from masking_lab.usertest.design import (
    UserTestDesign,
    UserTrial,
    trial_list,
    trial_record,
)
from masking_lab.usertest.responder_base import (
    ClipStats,
    FingerReader,
    StreamResult,
    UserTestAnswer,
    UserTestInfo,
    UserTestResponder,
    UserTrialPresentation,
)
from masking_lab.usertest.stream import (
    REFRESH_S,
    SILENT,
    PresentationPlan,
    StimulusLimit,
    Streamer,
    clip_db_v,
    object_stimuli,
    path_levels_db_sl,
    plan_presentation,
    tick_offsets_s,
    to_db_v,
)


@dataclass
class UserTestResult(SessionResult):
    """A :class:`~masking_lab.session.runner.SessionResult` with the user test's counts.

    Attributes
    ----------
    n_trials : int
        Trials in the design.
    n_logged : int
        Trials in the log (including those logged before a resume).
    correct : dict
        ``{condition: {"n": trials, "both": k, "geometry": k, "texture": k}}`` over the log.
    """

    n_trials: int = 0
    n_logged: int = 0
    correct: dict[str, dict[str, int]] = field(default_factory=dict)

    def summary_lines(self) -> list[str]:
        """Lines for the experimenter: trials logged and correct answers per condition."""
        lines = [f"user test: {self.n_logged} of {self.n_trials} trials logged"]
        for cond, c in sorted(self.correct.items()):
            n = c["n"]
            lines.append(
                f"  {cond:<13} both {c['both']}/{n}, geometry {c['geometry']}/{n}, "
                f"texture {c['texture']}/{n}"
            )
        return lines


# --------------------------------------------------------------------------------------------
# The session loop


class UserTestSession(SessionShell[UserTestResult]):
    """One process's part of a user test: runs the trials not yet logged."""

    def __init__(
        self,
        *,
        design: UserTestDesign,
        objects: Mapping[tuple[str, str], Rendering],
        participant: str,
        seed: int,
        limits: Mapping[str, StimulusLimit],
        allow_clipping: bool,
        update_hz: float,
        deadband_db: float,
        clock: Clock,
        device: Device,
        responder: UserTestResponder,
        writer: SessionLogWriter,
        out: ProgressLine,
        logged: Sequence[Mapping[str, Any]],
    ) -> None:
        super().__init__(clock=clock, device=device, responder=responder, writer=writer, out=out)
        self.responder: UserTestResponder = responder
        self.design = design
        self.objects = objects
        self.participant = participant
        self.trials = trial_list(design, seed)
        self.limits = limits
        self.allow_clipping = allow_clipping
        self.deadband_db = float(deadband_db)
        self.ticks_s = tick_offsets_s(design.timing.stimulus_s, update_hz)
        self.logged = list(logged)
        self.where: int | None = None
        self.trial_seconds: list[float] = []
        self._plans: dict[tuple[tuple[str, str], str], PresentationPlan] = {}
        self.max_drive_v = dict(device.identity.limits.max_drive_v)

    # -- top level --------------------------------------------------------------------------

    def run(self) -> UserTestResult:
        return self.run_guarded(self._run_trials)

    def _run_trials(self) -> None:
        design = self.design
        first = len(self.logged)
        if first >= len(self.trials):
            return  # every trial was logged before the stop; only session_end is missing
        self.responder.start_session(
            UserTestInfo(
                geometries=design.geometries,
                textures=design.textures,
                n_trials=len(self.trials),
                next_trial=first,
                tracking=design.tracking,
            )
        )
        for trial in self.trials[first:]:
            self._trial(trial)

    def _trial(self, trial: UserTrial) -> None:
        self.where = trial.index
        self._show_progress(trial)
        design = self.design
        t0 = self.clock.now()
        start_s = t0
        presentation = UserTrialPresentation(
            trial=trial,
            n_trials=len(self.trials),
            start_s=start_s,
            timing=design.timing,
            tracking=design.tracking,
            cue_speed_mm_s=design.cue_speed_mm_s,
            sweep_mm=design.sweep_mm,
        )

        def play(finger: FingerReader | None = None) -> StreamResult:
            return self._play(trial, start_s, finger)

        played, answer = self.responder.trial(presentation, play)
        self.clock.sleep_until(start_s + design.timing.trial_s)
        if self.clock.virtual:
            # Simulated time passes while the simulated participant answers.
            self.clock.sleep_until(self.clock.now() + answer.response_time_s)
        record = self._record(trial, start_s, played, answer)
        # Either the record is on disk before the next trial or the trial never happened.
        self._append(record)
        self.logged.append(record)
        self.clock.sleep_until(self.clock.now() + design.timing.inter_trial_s)
        self.trial_seconds.append(self.clock.now() - t0)

    # -- playing ----------------------------------------------------------------------------

    def _play(self, trial: UserTrial, start_s: float, finger: FingerReader | None) -> StreamResult:
        r = self.objects[trial.object]
        names = object_stimuli(r)
        stimuli = {ch: parse_stimulus(n) for ch, n in names.items() if n is not None}
        timing = self.design.timing
        planned: list[float] = []
        actual: list[float] = []
        ticks: list[np.ndarray] = []
        xs: list[np.ndarray] = []
        held: dict[Channel, list[np.ndarray]] = {ch: [] for ch in CHANNELS}
        excess: dict[Channel, list[np.ndarray]] = {ch: [] for ch in CHANNELS}
        n_frames = 0
        for k in range(1, timing.n_presentations + 1):
            onset = start_s + timing.onset_s(k)
            planned.append(onset)
            if self.design.tracking == "finger":
                if finger is None:
                    raise MaskingLabError(
                        f"responder {self.responder.name!r} gave no finger position, which "
                        "tracking: finger needs; use a responder that reports the finger"
                    )
                plan, first = self._follow_finger(trial, onset, finger, stimuli)
            else:
                plan = self._cue_plan(trial)
                first = self._send_all(plan, onset, stimuli)
            n_frames += len(plan.frames)
            actual.append(first if first is not None else onset)
            ticks.append(onset + plan.tick_s)
            xs.append(plan.x_mm)
            for ch in CHANNELS:
                held[ch].append(plan.held_db_v[ch])
                excess[ch].append(plan.excess_db[ch])
        clipped: dict[str, ClipStats] = {}
        for ch in CHANNELS:
            e = np.concatenate(excess[ch])
            if np.any(e > 1e-6):
                clipped[ch] = ClipStats(int(np.sum(e > 1e-6)), float(np.max(e)))
        return StreamResult(
            planned_onsets_s=planned,
            actual_onsets_s=actual,
            tick_s=np.concatenate(ticks),
            x_mm=np.concatenate(xs),
            held_v={ch: _volts(np.concatenate(held[ch])) for ch in CHANNELS},
            stimuli={str(ch): name for ch, name in names.items()},
            n_frames=n_frames,
            clipped=clipped,
        )

    def _max_db_v(self, trial: UserTrial) -> dict[Channel, float]:
        out: dict[Channel, float] = {}
        for ch, name in object_stimuli(self.objects[trial.object]).items():
            if name is not None:
                out[ch] = self.limits[name].max_db_v
        return out

    def _wanted_db_v(self, trial: UserTrial, x_mm: np.ndarray) -> dict[Channel, np.ndarray]:
        r = self.objects[trial.object]
        ev, mv = path_levels_db_sl(r, x_mm, compensated=trial.compensated)
        out: dict[Channel, np.ndarray] = {}
        by_channel: tuple[tuple[Channel, np.ndarray], ...] = (("EV", ev), ("MV", mv))
        for ch, levels in by_channel:
            name = object_stimuli(r)[ch]
            out[ch] = (
                np.full(levels.shape, SILENT)
                if name is None
                else to_db_v(levels, self.limits[name].unmasked_al_db_v)
            )
        return out

    def _cue_plan(self, trial: UserTrial) -> PresentationPlan:
        """The frames of one presentation following the cue (the same for all three)."""
        key = (trial.object, trial.condition)
        if key not in self._plans:
            x = self.design.cue_speed_mm_s * self.ticks_s
            plan = plan_presentation(
                self._wanted_db_v(trial, x),
                self.ticks_s,
                x,
                self.design.timing.stimulus_s,
                max_db_v=self._max_db_v(trial),
                deadband_db=self.deadband_db,
            )
            self._check_clipping(trial, plan.excess_db)
            self._plans[key] = plan
        return self._plans[key]

    def _send_all(
        self, plan: PresentationPlan, onset: float, stimuli: Mapping[Channel, Stimulus]
    ) -> float | None:
        first = None
        for frame in plan.frames:
            self.clock.sleep_until(onset + frame.t_s)
            self._send(frame.channel, stimuli, frame.level_db_v)
            if first is None:
                first = self.clock.now()
        return first

    def _follow_finger(
        self,
        trial: UserTrial,
        onset: float,
        finger: FingerReader,
        stimuli: Mapping[Channel, Stimulus],
    ) -> tuple[PresentationPlan, float | None]:
        """Stream one presentation tick by tick from the finger's reported position."""
        streamer = Streamer(self.deadband_db, REFRESH_S)
        max_db_v = self._max_db_v(trial)
        n = self.ticks_s.size
        x_mm = np.full(n, np.nan)
        held = {ch: np.empty(n) for ch in CHANNELS}
        excess = {ch: np.zeros(n) for ch in CHANNELS}
        frames = []
        first = None
        for i, offset in enumerate(self.ticks_s):
            self.clock.sleep_until(onset + offset)
            pos = finger(self.clock.now())
            x = math.nan if pos is None or not math.isfinite(pos) else float(pos)
            x_mm[i] = x
            wanted = self._wanted_db_v(trial, np.array([x]))
            levels: dict[Channel, float] = {}
            for ch in CHANNELS:
                clipped, over = clip_db_v(wanted[ch], max_db_v.get(ch, math.inf))
                levels[ch] = float(clipped[0])
                excess[ch][i] = float(over[0])
            self._check_clipping(trial, excess)
            for frame in streamer.tick(float(offset), levels):
                self._send(frame.channel, stimuli, frame.level_db_v)
                frames.append(frame)
                if first is None:
                    first = self.clock.now()
            for ch in CHANNELS:
                held[ch][i] = streamer.held[ch]
        end = self.design.timing.stimulus_s
        self.clock.sleep_until(onset + end)
        for frame in streamer.silence(end):
            self._send(frame.channel, stimuli, frame.level_db_v)
            frames.append(frame)
        plan = PresentationPlan(tuple(frames), self.ticks_s, x_mm, held, excess)
        return plan, first

    def _check_clipping(self, trial: UserTrial, excess: Mapping[Channel, np.ndarray]) -> None:
        # The design was checked up front; this only guards against a gap in that check.
        if self.allow_clipping:
            return
        for ch, e in excess.items():
            if np.any(e > 1e-6):
                raise LevelError(
                    f"trial {trial.index + 1}: {trial.geometry}_{trial.texture} "
                    f"{trial.condition} asks {ch} for {float(np.max(e)):.2f} dB more than its "
                    "limit; nothing above the limit was played (pass --allow-clipping to clip)"
                )

    def _send(self, channel: Channel, stimuli: Mapping[Channel, Stimulus], level: float) -> None:
        stimulus = stimuli.get(channel)
        if stimulus is None:
            return
        # Levels are at or below the limit here; min() only removes float noise at the limit.
        volts = min(db_v_to_volts(level), float(self.max_drive_v[channel]))
        self.device.set_amplitude(channel, stimulus, volts)

    # -- records ----------------------------------------------------------------------------

    def _record(
        self, trial: UserTrial, start_s: float, played: StreamResult, answer: UserTestAnswer
    ) -> dict[str, Any]:
        extra: dict[str, Any] = {
            "geometry_key": trial.geometry_key,
            "texture_key": trial.texture_key,
            "correct_geometry": answer.geometry == trial.geometry_key,
            "correct_texture": answer.texture == trial.texture_key,
            "t_s": start_s,
            "planned_onsets_s": [float(t) for t in played.planned_onsets_s],
            "actual_onsets_s": [float(t) for t in played.actual_onsets_s],
            "geometry_time_s": _nonneg(answer.geometry_time_s),
            "texture_time_s": _nonneg(answer.texture_time_s),
            "response_time_s": max(0.0, float(answer.response_time_s)),
            "n_frames": int(played.n_frames),
            "played": self._played_summary(played),
        }
        if played.clipped:
            extra["clipped"] = {
                ch: {"n_ticks": c.n_ticks, "max_excess_db": round(c.max_excess_db, 4)}
                for ch, c in sorted(played.clipped.items())
            }
        if self.design.tracking == "finger":
            extra["touched_mm"] = _touched(played, self.design.timing.n_presentations)
        if answer.finger_path:
            extra["finger_path"] = [[float(v) for v in p] for p in answer.finger_path]
        return trial_record(trial, self.participant, answer.geometry, answer.texture, **extra)

    def _played_summary(self, played: StreamResult) -> dict[str, Any]:
        """Per channel: stimulus and the range of levels held while sounding, dB SL."""
        out: dict[str, Any] = {}
        for ch in CHANNELS:
            name = played.stimuli.get(ch)
            if name is None:
                continue
            v = played.held_v[ch]
            on = v[v > 0]
            if on.size == 0:
                out[ch] = {"stimulus": name, "min_db_sl": None, "max_db_sl": None}
                continue
            al = self.limits[name].unmasked_al_db_v
            db = 20.0 * np.log10(on) - al
            out[ch] = {
                "stimulus": name,
                "min_db_sl": round(float(db.min()), 4),
                "max_db_sl": round(float(db.max()), 4),
            }
        return out

    def _result(self, code: int, message: str) -> UserTestResult:
        return UserTestResult(
            self.writer.path,
            code,
            [],
            message,
            n_trials=len(self.trials),
            n_logged=len(self.logged),
            correct=correct_counts(self.logged),
        )

    def _show_progress(self, trial: UserTrial) -> None:
        if not self.out.enabled:
            return
        timing = self.design.timing
        per_trial = (
            sum(self.trial_seconds) / len(self.trial_seconds)
            if self.trial_seconds
            else timing.trial_s + timing.inter_trial_s + 2.0
        )
        left = per_trial * (len(self.trials) - trial.index)
        self.out.update(
            f"user test | trial {trial.index + 1}/{len(self.trials)} | {trial.condition} | "
            f"{format_duration(left)} left"
        )

    def _where_text(self) -> str:
        if self.where is None:
            return "user-test trial (before the first trial)"
        return f"user-test trial {self.where + 1} of {len(self.trials)}"

    def _position(self) -> tuple[str | None, int | None]:
        return None, self.where


def correct_counts(records: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, int]]:
    """Per condition: trials, and how many had both / the geometry / the texture right."""
    out: dict[str, dict[str, int]] = {}
    for rec in records:
        c = out.setdefault(str(rec["condition"]), {"n": 0, "both": 0, "geometry": 0, "texture": 0})
        g = rec.get("geometry_answer") == rec.get("geometry_key")
        t = rec.get("texture_answer") == rec.get("texture_key")
        c["n"] += 1
        c["geometry"] += int(g)
        c["texture"] += int(t)
        c["both"] += int(g and t)
    return out


def _volts(level_db_v: np.ndarray) -> np.ndarray:
    return np.where(np.isfinite(level_db_v), np.power(10.0, level_db_v / 20.0), 0.0)


def _nonneg(value: float | None) -> float | None:
    return None if value is None else max(0.0, float(value))


def _touched(played: StreamResult, n_presentations: int) -> list[list[float] | None]:
    """Per presentation, the first and last path position the finger reported, mm."""
    out: list[list[float] | None] = []
    for part in np.array_split(played.x_mm, n_presentations):
        ok = part[np.isfinite(part)]
        out.append([round(float(ok.min()), 3), round(float(ok.max()), 3)] if ok.size else None)
    return out
