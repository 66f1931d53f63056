"""The threshold session's loop: each unfinished set of the order, trial by trial.

One :class:`ThresholdSession` runs the sets a process still has to run: it plans each set
(:mod:`masking_lab.session.trials`), asks the set's procedure (any
:class:`~masking_lab.procedures.base.Procedure`: the staircase or QUEST+) for the next level,
plays the trial, logs it fsynced before the next, shows progress, rests between sets, writes the
calibration after baseline sets, and ends each set with its AL or the reason it has none. With
``order: {interleave: true}`` all sets run at once, each trial from a set drawn by
:func:`masking_lab.session.interleave.next_set`.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from masking_lab.core.clock import Clock
from masking_lab.core.errors import CalibrationError, LevelError, MaskingLabError
from masking_lab.core.seeding import draw_target_interval
from masking_lab.core.trial import TrialPlan
from masking_lab.device.base import Device
from masking_lab.formats.calibration import record_al
from masking_lab.formats.protocol import SetSpec, ThresholdProtocol
from masking_lab.formats.records import jsonable
from masking_lab.formats.session_log import SessionLogWriter, SetRecords
from masking_lab.procedures.base import Procedure, replay
from masking_lab.procedures.log_fields import end_fields, start_fields, trial_fields
from masking_lab.procedures.registry import kind_of
from masking_lab.responders.base import Responder, SetInfo, TrialPresentation
from masking_lab.session.interleave import next_set
from masking_lab.session.pace import session_time_left_s, track_trials_left
from masking_lab.session.priority import placement_priority
from masking_lab.session.procedure_records import settings_from_record
from masking_lab.session.progress import ProgressLine, format_progress
from masking_lab.session.shell import SessionShell, drop_none, utc_now
from masking_lab.session.trials import (
    UNIT_LABEL,
    SetPlan,
    nominal_seconds_per_trial,
    plan_set,
    plan_trial,
)


@dataclass(frozen=True)
class SetOutcome:
    """How one set ended.

    Attributes
    ----------
    set_id : str
        Set identifier.
    status : str
        ``completed``, ``ceiling``, ``floor``, ``trial_cap`` or ``aborted``.
    al_db : float or None
        AL in ``level_unit`` (None unless completed).
    level_unit : str
        ``db_sl`` or ``db_v``.
    n_trials : int
        Trials run.
    reason : str
        Why an aborted set was refused (empty otherwise).
    """

    set_id: str
    status: str
    al_db: float | None
    level_unit: str
    n_trials: int
    reason: str = ""

    def summary(self) -> str:
        """One line for the experimenter: ``MV120_10  completed  AL 12.30 dB SL (57 trials)``."""
        unit = UNIT_LABEL.get(self.level_unit, self.level_unit)
        if self.al_db is not None:
            what = f"AL {self.al_db:.2f} {unit}"
        elif self.status == "aborted":
            what = f"no AL: {self.reason}"
        elif self.status == "completed" and self.reason:
            what = self.reason  # a procedure whose result is not one AL (a ramp)
        else:
            what = "no AL (a track that ends at a bound or the trial cap is not a threshold)"
        return f"{self.set_id:<12} {self.status:<9} {what} ({self.n_trials} trials)"


@dataclass
class SessionResult:
    """What a run or resume ended with.

    Attributes
    ----------
    log_path : Path
        The session log.
    exit_code : int
        0 completed, 2 every set refused before its first trial (nothing played), 3 device
        fault, 130 interrupted.
    outcomes : list[SetOutcome]
        Every finished set of the session (including those finished before a resume).
    message : str
        Why the session stopped early, with the resume command (empty when completed).
    """

    log_path: Path
    exit_code: int
    outcomes: list[SetOutcome] = field(default_factory=list)
    message: str = ""


class ThresholdSession(SessionShell[SessionResult]):
    """One process's part of a session: runs the unfinished sets of ``order``."""

    def __init__(
        self,
        *,
        protocol: ThresholdProtocol,
        participant: str,
        data_dir: Path,
        seed: int,
        order: Sequence[str],
        calibration: Mapping[str, float],
        clock: Clock,
        device: Device,
        responder: Responder,
        writer: SessionLogWriter,
        out: ProgressLine,
        existing: Mapping[str, SetRecords],
    ) -> None:
        super().__init__(clock=clock, device=device, responder=responder, writer=writer, out=out)
        self.protocol = protocol
        self.participant = participant
        self.data_dir = data_dir
        self.seed = seed
        self.order = list(order)
        self.calibration = dict(calibration)
        self.responder: Responder = responder
        self.existing = dict(existing)
        self.outcomes: list[SetOutcome] = []
        self.finished_trials: list[int] = []
        self.trial_seconds: list[float] = []
        self.where: tuple[str | None, int | None] = (None, None)
        self.interleaved_tracks: dict[str, tuple[int, SetPlan, Procedure]] = {}
        self.refused: list[str] = []  # sets refused in this process (nothing played)

    # -- top level --------------------------------------------------------------------------

    def run(self) -> SessionResult:
        return self.run_guarded(self._run_sets)

    def _result(self, code: int, message: str) -> SessionResult:
        nothing = all(o.n_trials == 0 for o in self.outcomes)
        if code == 0 and self.refused and len(self.refused) == len(self.outcomes) and nothing:
            # Nothing was measured: a session that "completed" by refusing every set is a bad
            # input (protocol, calibration or rig config), not a success (issue 21.9).
            code = 2
            message = (
                f"every set was refused, nothing was played ({len(self.refused)} sets: "
                f"{', '.join(self.refused)}); fix the protocol, the calibration or the rig "
                "config as each refusal above says"
            )
            self.out.message(message)
        return SessionResult(self.writer.path, code, self.outcomes, message)

    def _where_text(self) -> str:
        # 1-based, as the progress line numbers trials (the fault record keeps the 0-based
        # trial_index of the log).
        set_id, index = self.where
        return f"set {set_id}" + ("" if index is None else f", trial {index + 1}")

    def _position(self) -> tuple[str | None, int | None]:
        return self.where

    def _run_sets(self) -> None:
        for rec in self.existing.values():
            if rec.end is not None:
                self.outcomes.append(_outcome_from_end(rec, self.protocol.level_unit))
                if rec.end.get("status") in ("completed", "ceiling", "floor", "trial_cap"):
                    self.finished_trials.append(len(rec.trials))
        if self.protocol.interleave:
            self._run_interleaved()
            return
        first = True
        for k, set_id in enumerate(self.order):
            logged = self.existing.get(set_id)
            if logged is not None and logged.end is not None:
                continue
            if not first:
                self._rest(k)
            first = False
            opened = self._open_set(self.protocol.set_by_id(set_id), logged)
            if opened is None:
                continue
            plan, state = opened
            self._start_responder_set(k, plan)
            self._run_track(k, plan, state)

    def _run_track(self, k: int, plan: SetPlan, state: Procedure) -> None:
        while not state.finished:
            after = self._next_trial(k, plan, state)
            if after is None:
                return  # refused and logged as aborted
            state = after
        self._end_set(plan, state)

    def _run_interleaved(self) -> None:
        """All unfinished sets at once; each trial's set drawn from (seed, trials so far)."""
        tracks: dict[str, tuple[int, SetPlan, Procedure]] = {}
        for k, set_id in enumerate(self.order):
            rec = self.existing.get(set_id)
            if rec is not None and rec.end is not None:
                continue
            opened = self._open_set(self.protocol.set_by_id(set_id), rec)
            if opened is not None:
                tracks[set_id] = (k, *opened)
        done = sum(len(rec.trials) for rec in self.existing.values())
        introduced: set[str] = set()
        self.interleaved_tracks = tracks
        for set_id, (_, plan, state) in list(tracks.items()):
            if state.finished:  # stopped by its last logged trial before set_end was written
                self._end_set(plan, state)
                del tracks[set_id]
        while tracks:
            running = [s for s in self.order if s in tracks]
            set_id = next_set(self.seed, done, running)
            k, plan, state = tracks[set_id]
            if set_id not in introduced:
                self._start_responder_set(k, plan)
                introduced.add(set_id)
            after = self._next_trial(k, plan, state)
            if after is None:
                del tracks[set_id]
                continue
            done += 1
            if after.finished:
                self._end_set(plan, after)
                del tracks[set_id]
            else:
                tracks[set_id] = (k, plan, after)

    def _open_set(self, spec: SetSpec, rec: SetRecords | None) -> tuple[SetPlan, Procedure] | None:
        """Plan a set and rebuild its track from the log; None if the device refuses it."""
        unit = self.protocol.level_unit
        self.where = (spec.id, None)
        try:
            plan = plan_set(spec, unit, self.calibration, self.device.identity.limits.max_drive_v)
        except (LevelError, CalibrationError) as exc:
            n = len(rec.trials) if rec else 0
            self._refuse_set(spec, started=rec is not None, n_trials=n, exc=exc)
            return None
        if rec is not None:
            plan = dataclasses.replace(plan, procedure=settings_from_record(rec.start, spec))
        else:
            self._append(self._set_start_record(plan))
        state = replay(plan.procedure, [bool(t["correct"]) for t in (rec.trials if rec else [])])
        return plan, state

    def _start_responder_set(self, k: int, plan: SetPlan) -> None:
        self.responder.start_set(
            SetInfo(
                set_id=plan.set_id,
                set_number=k + 1,
                n_sets=len(self.order),
                target=plan.target,
                masker=plan.masker,
                masker_level_db_sl=plan.masker_level_db_sl,
            )
        )

    def _next_trial(self, k: int, plan: SetPlan, state: Procedure) -> Procedure | None:
        """Play the track's next trial; None (set refused and logged) if the device cannot."""
        try:
            trial = plan_trial(
                plan,
                state.next_level(),
                draw_target_interval(self.seed, plan.set_id, state.n_trials),
                self.protocol.timing,
                kind_of(state).masker_level_db_sl(state),
            )
        except LevelError as exc:
            # Only after a resume on a device with a lower limit than the set started with.
            spec = self.protocol.set_by_id(plan.set_id)
            self._refuse_set(spec, started=True, n_trials=state.n_trials, exc=exc)
            return None
        return self._trial(k, plan, state, trial)

    def _trial(self, k: int, plan: SetPlan, state: Procedure, trial: TrialPlan) -> Procedure:
        timing = self.protocol.timing
        index = state.n_trials
        self.where = (plan.set_id, index)
        level = state.next_level()
        masker_db_sl = kind_of(state).masker_level_db_sl(state)
        if masker_db_sl is None:
            masker_db_sl = plan.masker_level_db_sl
        interval = trial.target_interval
        self._show_progress(k, plan, state)
        t0 = self.clock.now()
        start_s = t0
        presentation = TrialPresentation(
            set_id=plan.set_id,
            trial_index=index,
            plan=trial,
            start_s=start_s,
            level_db_v=plan.level_db_v(level),
            level_db_sl=plan.level_db_sl(level),
            masker_level_db_sl=masker_db_sl,
        )
        played, response = self.responder.trial(
            presentation, lambda: self.device.play_trial(trial, start_s)
        )
        # A virtual clock jumps to the end of the trial if the device did not move it there.
        self.clock.sleep_until(start_s + trial.duration_s)
        if self.clock.virtual:
            # Simulated time passes while the (simulated) participant answers; a real clock
            # has already waited for a real one.
            self.clock.sleep_until(self.clock.now() + response.response_time_s)
        correct = response.interval == interval
        with placement_priority(not self.clock.virtual):  # priority: a busy core must wait
            after = state.update(correct)
        record = drop_none(
            {
                "record": "trial",
                "set_id": plan.set_id,
                "trial_index": index,
                "level_db_sl": plan.level_db_sl(level),
                "level_db_v": plan.level_db_v(level),
                "target_interval": interval,
                "response_interval": int(response.interval),
                "correct": correct,
                **trial_fields(state, after),
                "planned_onsets_s": trial.planned_onsets_s(start_s),
                "actual_onsets_s": list(played.actual_onsets_s),
                "response_time_s": max(0.0, float(response.response_time_s)),
                "played_target_v": played.played_target_v,
                "played_masker_v": played.played_masker_v,
                "finger_path": [list(p) for p in response.finger_path] or None,
                "device_extra": jsonable(played.extra) or None,
            }
        )
        # Either the record is on disk before the next trial or the trial never happened.
        self._append(record)
        self.clock.sleep_until(self.clock.now() + timing.inter_trial_s)
        self.trial_seconds.append(self.clock.now() - t0)
        return after

    def _end_set(self, plan: SetPlan, state: Procedure) -> None:
        ends = end_fields(state)
        al = ends["al_db"]
        if self.protocol.kind == "baseline" and al is not None:
            # Calibration first: a crash before set_end replays the set and writes it again.
            source = _relative(self.writer.path, self.data_dir)
            _, previous = record_al(
                self.data_dir, self.participant, plan.target.name, al, source, utc_now()
            )
            was = f" (was {previous:.2f})" if previous is not None and previous != al else ""
            self.out.message(
                f"calibration: {self.participant} {plan.target.name} unmasked AL "
                f"{al:.2f} dB re 1 V{was}"
            )
        record = {
            "record": "set_end",
            "set_id": plan.set_id,
            "status": state.status,
            "al_db": al,
            "al_db_v": plan.level_db_v(al) if al is not None else None,
            "al_db_sl": plan.level_db_sl(al) if al is not None else None,
            "n_trials": state.n_trials,
            "reversal_levels_db": ends["reversal_levels_db"],
            "method": ends["method"],
            "t_s": self.clock.now(),
        }
        # What else the procedure reports at the end (sd_db; a ramp's posterior summary).
        record.update({k: v for k, v in ends.items() if k not in record})
        if state.status != "completed":
            unit = UNIT_LABEL[plan.level_unit]
            record["reason"] = kind_of(state).no_al_reason(state, unit, plan.target_max_v)
        self._append(record)
        self.finished_trials.append(state.n_trials)
        found = kind_of(state).result_text(state, UNIT_LABEL[plan.level_unit])
        outcome = SetOutcome(
            plan.set_id,
            state.status,
            al,
            plan.level_unit,
            state.n_trials,
            record.get("reason", found or ""),
        )
        self.outcomes.append(outcome)
        self.out.message(f"set done: {outcome.summary()}")

    def _refuse_set(
        self, spec: SetSpec, *, started: bool, n_trials: int, exc: MaskingLabError
    ) -> None:
        """Log a set the device cannot play as aborted; nothing (more) is played in it."""
        unit = self.protocol.level_unit
        if not started:
            self._append(
                {
                    "record": "set_start",
                    "set_id": spec.id,
                    "target": spec.target.name,
                    "masker": spec.masker.name if spec.masker else None,
                    "masker_level_db_sl": spec.masker_level_db_sl,
                    "level_unit": unit,
                    **start_fields(spec.settings),
                    "t_s": self.clock.now(),
                }
            )
        self._fault("level_refused", str(exc))
        n = n_trials
        self._append(
            {
                "record": "set_end",
                "set_id": spec.id,
                "status": "aborted",
                "al_db": None,
                "al_db_v": None,
                "al_db_sl": None,
                "n_trials": n,
                "reversal_levels_db": [],
                "reason": str(exc),
                "t_s": self.clock.now(),
            }
        )
        self.outcomes.append(SetOutcome(spec.id, "aborted", None, unit, n, str(exc)))
        self.refused.append(spec.id)
        self.out.message(f"set {spec.id} refused, nothing played: {exc}")

    # -- helpers ----------------------------------------------------------------------------

    def _set_start_record(self, plan: SetPlan) -> dict[str, Any]:
        return {
            "record": "set_start",
            "set_id": plan.set_id,
            "target": plan.target.name,
            "masker": plan.masker.name if plan.masker else None,
            "masker_level_db_sl": plan.masker_level_db_sl,
            "masker_level_db_v": plan.masker_level_db_v,
            "unmasked_al_db_v": plan.unmasked_al_db_v,
            "level_unit": plan.level_unit,
            "max_level_db": plan.procedure.max_level_db,
            "min_level_db": plan.procedure.min_level_db,
            **start_fields(plan.procedure),
            "t_s": self.clock.now(),
        }

    def _show_progress(self, k: int, plan: SetPlan, state: Procedure) -> None:
        if not self.out.enabled:
            return
        per_trial = (
            sum(self.trial_seconds) / len(self.trial_seconds)
            if self.trial_seconds
            else nominal_seconds_per_trial(self.protocol.timing)
        )
        if self.protocol.interleave:
            # Every running track shares the session: the time left is theirs together.
            running = [s for _, _, s in self.interleaved_tracks.values()]
            trials = sum(track_trials_left(s, self.finished_trials) for s in running)
            left = trials * per_trial
        else:
            left = session_time_left_s(
                state,
                seconds_per_trial=per_trial,
                sets_after_current=self._sets_after(k),
                finished_set_trials=self.finished_trials,
                rest_between_sets_s=self.protocol.timing.rest_between_sets_s,
            )
        unit = UNIT_LABEL.get(plan.level_unit, plan.level_unit)
        self.out.update(
            format_progress(
                set_number=k + 1,
                n_sets=len(self.order),
                set_id=plan.set_id,
                trial_index=state.n_trials,
                reversals=0,
                n_reversals=0,
                level_db=state.next_level(),
                level_unit=plan.level_unit,
                time_left_s=left,
                track_text=kind_of(state).progress(state, unit),
            )
        )

    def _sets_after(self, k: int) -> int:
        later = self.order[k + 1 :]
        return sum(1 for s in later if s not in self.existing or self.existing[s].end is None)

    def _rest(self, k: int) -> None:
        rest = self.protocol.timing.rest_between_sets_s
        if rest <= 0:
            return
        end = self.clock.now() + rest
        if self.clock.virtual:
            self.clock.sleep_until(end)
            return
        self.out.message(
            f"rest {rest:.0f} s before set {k + 1}/{len(self.order)} "
            "(Ctrl-C stops the session; resume it later)"
        )
        while (left := end - self.clock.now()) > 0:
            self.out.update(f"rest: {int(left // 60)}:{int(left % 60):02d} left")
            self.clock.sleep_until(min(end, self.clock.now() + 1.0))


def _outcome_from_end(rec: SetRecords, unit: str) -> SetOutcome:
    end = rec.end or {}
    return SetOutcome(
        set_id=str(end.get("set_id")),
        status=str(end.get("status")),
        al_db=end.get("al_db"),
        level_unit=str(rec.start.get("level_unit", unit)),
        n_trials=int(end.get("n_trials", len(rec.trials))),
        reason=str(end.get("reason", "")),
    )


def _relative(path: Path, base: Path) -> str:
    try:
        return os.path.relpath(path, base)
    except ValueError:
        return str(path)
