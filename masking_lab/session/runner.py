"""The session runner: run a protocol's sets as 3IFC staircases, or resume a stopped session.

This is the imperative shell around the pure core (:mod:`masking_lab.procedures.staircase`,
:mod:`masking_lab.session.trials`): it opens the device and the responder, writes the session log
one fsynced record at a time, updates the participant's calibration after baseline sets, shows
progress, and turns every fault into a log record, zeroed outputs and a resume hint.

Crash safety: each trial record is appended and fsynced before the next trial starts, and
SIGINT/SIGTERM are held back while a record is being written, so a crash or an interruption
loses at most the trial in flight. :func:`resume_session` rebuilds every set by replaying the
logged responses into the staircase and continues with the same seed-driven target intervals
(and simulated answers), so the continuation equals an uninterrupted run.

Exit codes returned in :class:`SessionResult`: 0 completed, 3 device fault, 130 interrupted
(bad input raises a :class:`~masking_lab.core.errors.MaskingLabError`, which the CLI turns into 2).
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
import os
import secrets
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import yaml

from masking_lab import __version__
from masking_lab.core.clock import Clock, RealClock, VirtualClock
from masking_lab.core.errors import (
    CalibrationError,
    LevelError,
    LogError,
    MaskingLabError,
    ProtocolError,
)
from masking_lab.core.seeding import draw_target_interval
from masking_lab.core.trial import TrialPlan
from masking_lab.device.base import Device, DeviceIdentity
from masking_lab.formats.calibration import load_calibration, record_al, require
from masking_lab.formats.protocol import Protocol, SetSpec, load_protocol, parse_protocol
from masking_lab.formats.session_log import SessionLog, SessionLogWriter, SetRecords, read_log
from masking_lab.procedures.staircase import Staircase, StaircaseSettings, replay, start
from masking_lab.responders.base import Responder, SetInfo, TrialPresentation
from masking_lab.session.progress import ProgressLine, format_progress

# EXIT_* and the signal classes were public here first; the noqa lines re-export them.
from masking_lab.session.shell import (
    EXIT_COMPLETED,  # noqa: F401
    EXIT_DEVICE_FAULT,  # noqa: F401
    EXIT_INTERRUPTED,  # noqa: F401
    DeviceOpener,
    SessionInterrupted,  # noqa: F401
    SessionShell,
    SessionSignals,  # noqa: F401
    check_device_spec,
    check_header,
    check_participant,
    close_on_failure,
    create_log,
    default_opener,
    device_record,
    device_spec_from_header,
    drop_none,
    observer_record,
    open_device_and_responder,
    record_resume,
    refuse_finished,
    resume_clock,
    resume_device_config,
    resume_observer,
    resume_responder_name,
    use_virtual_clock,
    utc_now,
)
from masking_lab.session.trials import (
    UNIT_LABEL,
    SetPlan,
    estimate_time_left_s,
    nominal_seconds_per_trial,
    plan_set,
    plan_trial,
)
from masking_lab.simulation.observer import ground_truth_from_dict, make_participant

RESPONDERS = ("sim", "keys", "psychopy")

ResponderMaker = Callable[[str, "SessionContext"], Responder]


# --------------------------------------------------------------------------------------------
# Public values


@dataclass(frozen=True)
class RunOptions:
    """What ``masking-lab run`` was asked to do.

    Attributes
    ----------
    protocol : Path
        Protocol YAML file.
    participant : str
        Participant id (letters, digits, ``_ - .``); names the data sub-folder.
    device : str
        ``sim``, ``emulator`` or ``serial:PORT``.
    responder : {"sim", "keys", "psychopy"}
        Who answers.
    data_dir : Path
        Data folder; logs and the calibration go to ``data_dir/<participant>/``.
    seed : int or None
        Session seed (drawn and logged when None).
    sets : tuple[str, ...] or None
        Subset of set ids to run (in the seed's order), or None for all.
    real_time : bool
        Use the real clock even with a simulated responder.
    ground_truth : Path or None
        Ground-truth file of the simulated responder (None: the packaged default).
    device_config : Path or None
        Device config file (None: the packaged default).
    progress : bool or None
        Force the progress line on (True) or off (False); None: only on a terminal.
    participant_tty : str or None
        With the keys responder: the participant's terminal (None: this one).
    """

    protocol: Path
    participant: str
    device: str = "sim"
    responder: str = "sim"
    data_dir: Path = Path("data")
    seed: int | None = None
    sets: tuple[str, ...] | None = None
    real_time: bool = False
    ground_truth: Path | None = None
    device_config: Path | None = None
    progress: bool | None = None
    participant_tty: str | None = None


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
        0 completed, 3 device fault, 130 interrupted.
    outcomes : list[SetOutcome]
        Every finished set of the session (including those finished before a resume).
    message : str
        Why the session stopped early, with the resume command (empty when completed).
    """

    log_path: Path
    exit_code: int
    outcomes: list[SetOutcome] = field(default_factory=list)
    message: str = ""


@dataclass
class SessionContext:
    """What a responder factory may need to build a responder.

    Attributes
    ----------
    participant : str
        Participant id.
    seed : int
        Session seed.
    clock : Clock
        The session clock.
    protocol : Protocol
        The protocol being run.
    simulated_observer : dict or None
        ``{"ground_truth_path", "population_seed", "truth"}`` for the sim responder.
    device_config : Path or None
        The rig config (the PsychoPy window reads the monitor size from it).
    participant_tty : str or None
        The participant's terminal for the keys responder (None: this one).
    """

    participant: str
    seed: int
    clock: Clock
    protocol: Protocol
    simulated_observer: dict[str, Any] | None = None
    device_config: Path | None = None
    participant_tty: str | None = None


# --------------------------------------------------------------------------------------------
# Entry points


def run_session(
    options: RunOptions,
    *,
    open_device: DeviceOpener | None = None,
    make_responder: ResponderMaker | None = None,
    stream: TextIO | None = None,
) -> SessionResult:
    """Run a protocol for one participant and write a new session log.

    Parameters
    ----------
    options : RunOptions
        What to run.
    open_device : callable, optional
        ``(spec, clock) -> Device``; default: :func:`masking_lab.device.registry.open_device`
        with ``options.device_config``.
    make_responder : callable, optional
        ``(name, SessionContext) -> Responder``; default builds sim, keys or psychopy.
    stream : text stream, optional
        Where progress and messages go (stderr by default).

    Raises
    ------
    MaskingLabError
        Bad input found before anything is played: protocol, participant id, unknown set ids,
        missing calibration, unknown responder, unreadable ground truth.
    """
    out = ProgressLine(stream, force=options.progress)
    participant = check_participant(options.participant)
    if options.responder not in RESPONDERS:
        raise MaskingLabError(
            f"--responder {options.responder!r}: choose one of {', '.join(RESPONDERS)}"
        )
    check_device_spec(options.device)
    protocol = load_protocol(options.protocol, max_level_db_sl=_rig_limits(options.device_config))
    seed = options.seed if options.seed is not None else secrets.randbits(32)
    if seed < 0:
        raise MaskingLabError(f"--seed must be ≥ 0, got {seed}")
    order = _select_sets(protocol, protocol.set_order(seed), options.sets)
    data_dir = Path(options.data_dir)

    calibration: dict[str, float] = {}
    if protocol.kind == "masked":
        cal = load_calibration(data_dir, participant)
        needed = _stimuli_of(protocol, order)
        require(cal, needed, data_dir)
        calibration = {name: float(cal.unmasked_al_db_v[name]) for name in sorted(needed)}

    virtual = use_virtual_clock(options.device, options.responder, options.real_time)
    clock: Clock = VirtualClock() if virtual else RealClock()
    observer = None
    if options.responder == "sim":
        observer = observer_record(options.ground_truth)
    context = SessionContext(
        participant,
        seed,
        clock,
        protocol,
        observer,
        options.device_config,
        options.participant_tty,
    )
    device, responder = open_device_and_responder(
        make_responder or _default_responder,
        options.responder,
        context,
        open_device or default_opener(options.device_config),
        options.device,
        clock,
    )
    header = _header(
        protocol=protocol,
        participant=participant,
        calibration=calibration,
        device=device.identity,
        responder=options.responder,
        seed=seed,
        order=order,
        virtual=virtual,
        observer=observer,
        device_config=options.device_config,
    )
    with close_on_failure(device, responder):
        writer = create_log(data_dir, protocol.experiment, participant, header)
    out.message(f"session log: {writer.path}")
    session = _Session(
        protocol=protocol,
        participant=participant,
        data_dir=data_dir,
        seed=seed,
        order=order,
        calibration=calibration,
        clock=clock,
        device=device,
        responder=responder,
        writer=writer,
        out=out,
        existing={},
    )
    return session.run()


def resume_session(
    log_path: str | Path,
    *,
    device: str | None = None,
    responder: str | None = None,
    allow_changed_protocol: bool = False,
    device_config: Path | None = None,
    participant_tty: str | None = None,
    open_device: DeviceOpener | None = None,
    make_responder: ResponderMaker | None = None,
    stream: TextIO | None = None,
    progress: bool | None = None,
) -> SessionResult:
    """Continue an interrupted session exactly where it stopped, in the same log.

    The protocol, calibration, seed, set order, clock kind and responder come from the log's
    header, never from files that may have changed since. Each started set is rebuilt by
    replaying its logged responses; the rebuilt levels must equal the logged ones.

    Parameters
    ----------
    log_path : path
        The session log (``DATA/<participant>/<experiment>-<participant>-<UTC>.jsonl``).
    device : str, optional
        Device spec; default: the header's back-end (``serial:<port>`` for a serial device).
    responder : str, optional
        Responder; default: the header's.
    allow_changed_protocol : bool
        Continue although the protocol file on disk differs from the one the session started
        with (the logged copy is used either way).
    device_config, participant_tty
        As in :class:`RunOptions` (default config: the one the session started with).
    open_device, make_responder, stream, progress
        As for :func:`run_session`.

    Raises
    ------
    LogError
        Finished session, protocol file changed (without ``allow_changed_protocol``), a header
        that breaks the schema, or logged trials that do not replay to their logged levels.
    """
    out = ProgressLine(stream, force=progress)
    path = Path(log_path)
    log = read_log(path)
    header = log.header
    check_header(header, path)
    refuse_finished(log, path)
    protocol = _protocol_from_header(header, path, allow_changed_protocol, out)
    participant = str(header["participant"])
    seed = int(header["seed"])
    order = [str(s) for s in header["set_order"]]
    calibration = {k: float(v) for k, v in header["calibration"].items()}
    responder_name = resume_responder_name(header, responder, RESPONDERS)
    existing = log.sets()
    _check_trials(path, protocol, existing)

    clock = resume_clock(header, log)
    observer = resume_observer(header, responder_name)
    config_path = resume_device_config(device_config, header)
    context = SessionContext(
        participant, seed, clock, protocol, observer, config_path, participant_tty
    )
    spec = check_device_spec(device or device_spec_from_header(header))
    dev, resp = open_device_and_responder(
        make_responder or _default_responder,
        responder_name,
        context,
        open_device or default_opener(config_path),
        spec,
        clock,
    )
    with close_on_failure(dev, resp):
        writer, _ = SessionLogWriter.reopen(path)
    record_resume(writer, log, dev.identity, out, _position(log))
    out.message(f"resuming {path}")
    session = _Session(
        protocol=protocol,
        participant=participant,
        data_dir=path.parent.parent,
        seed=seed,
        order=order,
        calibration=calibration,
        clock=clock,
        device=dev,
        responder=resp,
        writer=writer,
        out=out,
        existing=existing,
    )
    return session.run()


# --------------------------------------------------------------------------------------------
# The session loop


class _Session(SessionShell[SessionResult]):
    """One process's part of a session: runs the unfinished sets of ``order``."""

    def __init__(
        self,
        *,
        protocol: Protocol,
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

    # -- top level --------------------------------------------------------------------------

    def run(self) -> SessionResult:
        return self.run_guarded(self._run_sets)

    def _result(self, code: int, message: str) -> SessionResult:
        return SessionResult(self.writer.path, code, self.outcomes, message)

    def _where_text(self) -> str:
        return f"set {self.where[0]}, trial {self.where[1]}"

    def _position(self) -> tuple[str | None, int | None]:
        return self.where

    def _run_sets(self) -> None:
        for rec in self.existing.values():
            if rec.end is not None:
                self.outcomes.append(_outcome_from_end(rec, self.protocol.level_unit))
                if rec.end.get("status") in ("completed", "ceiling", "floor", "trial_cap"):
                    self.finished_trials.append(len(rec.trials))
        first = True
        for k, set_id in enumerate(self.order):
            rec = self.existing.get(set_id)
            if rec is not None and rec.end is not None:
                continue
            if not first:
                self._rest(k)
            first = False
            self._run_set(k, self.protocol.set_by_id(set_id), rec)

    def _run_set(self, k: int, spec: SetSpec, rec: SetRecords | None) -> None:
        unit = self.protocol.level_unit
        self.where = (spec.id, None)
        try:
            plan = plan_set(spec, unit, self.calibration, self.device.identity.limits.max_drive_v)
        except (LevelError, CalibrationError) as exc:
            n = len(rec.trials) if rec else 0
            self._refuse_set(spec, started=rec is not None, n_trials=n, exc=exc)
            return
        if rec is not None:
            plan = dataclasses.replace(plan, staircase=_settings_from_record(rec.start, spec))
        else:
            self._append(self._set_start_record(plan))
        state = replay(plan.staircase, [bool(t["correct"]) for t in (rec.trials if rec else [])])
        self.responder.start_set(
            SetInfo(
                set_id=spec.id,
                set_number=k + 1,
                n_sets=len(self.order),
                target=spec.target,
                masker=spec.masker,
                masker_level_db_sl=spec.masker_level_db_sl,
            )
        )
        while not state.finished:
            try:
                trial = plan_trial(
                    plan,
                    state.level_db,
                    draw_target_interval(self.seed, plan.set_id, state.n_trials),
                    self.protocol.timing,
                )
            except LevelError as exc:
                # Only after a resume on a device with a lower limit than the set started with.
                self._refuse_set(spec, started=True, n_trials=state.n_trials, exc=exc)
                return
            state = self._trial(k, plan, state, trial)
        self._end_set(plan, state)

    def _trial(self, k: int, plan: SetPlan, state: Staircase, trial: TrialPlan) -> Staircase:
        timing = self.protocol.timing
        index = state.n_trials
        self.where = (plan.set_id, index)
        level = state.level_db
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
            masker_level_db_sl=plan.masker_level_db_sl,
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
                "reversal": len(after.reversal_levels_db) > len(state.reversal_levels_db),
                "step_db": state.step_db,
                "next_level_db": None if after.finished else after.level_db,
                "at_bound": after.at_bound,
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

    def _end_set(self, plan: SetPlan, state: Staircase) -> None:
        al = state.al_db
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
            "reversal_levels_db": list(state.reversal_levels_db),
            "t_s": self.clock.now(),
        }
        if state.status != "completed":
            record["reason"] = _bound_reason(state, plan)
        self._append(record)
        self.finished_trials.append(state.n_trials)
        outcome = SetOutcome(
            plan.set_id, state.status, al, plan.level_unit, state.n_trials, record.get("reason", "")
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
                    "staircase": _settings_record(spec.staircase),
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
            "max_level_db": plan.staircase.max_level_db,
            "min_level_db": plan.staircase.min_level_db,
            "staircase": _settings_record(plan.staircase),
            "t_s": self.clock.now(),
        }

    def _show_progress(self, k: int, plan: SetPlan, state: Staircase) -> None:
        if not self.out.enabled:
            return
        sc = plan.staircase
        per_trial = (
            sum(self.trial_seconds) / len(self.trial_seconds)
            if self.trial_seconds
            else nominal_seconds_per_trial(self.protocol.timing)
        )
        left = estimate_time_left_s(
            seconds_per_trial=per_trial,
            trials_done_in_set=state.n_trials,
            reversals_in_set=len(state.reversal_levels_db),
            n_reversals=sc.n_reversals,
            max_trials=sc.max_trials,
            sets_after_current=self._sets_after(k),
            finished_set_trials=self.finished_trials,
            rest_between_sets_s=self.protocol.timing.rest_between_sets_s,
        )
        self.out.update(
            format_progress(
                set_number=k + 1,
                n_sets=len(self.order),
                set_id=plan.set_id,
                trial_index=state.n_trials,
                reversals=len(state.reversal_levels_db),
                n_reversals=sc.n_reversals,
                level_db=state.level_db,
                level_unit=plan.level_unit,
                time_left_s=left,
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


# --------------------------------------------------------------------------------------------
# Defaults for devices and responders


def _default_responder(name: str, context: SessionContext) -> Responder:
    if name == "sim":
        from masking_lab.responders.sim import SimResponder

        obs = context.simulated_observer or observer_record(None)
        truth = ground_truth_from_dict(obs["truth"], str(obs.get("ground_truth_path")))
        participant = make_participant(truth, context.participant, int(obs["population_seed"]))
        return SimResponder(participant, context.seed, str(obs.get("ground_truth_path") or ""))
    if name == "keys":
        from masking_lab.responders.keys import KeysResponder

        if context.participant_tty:
            return KeysResponder.open_tty(context.participant_tty)
        return KeysResponder()
    if name == "psychopy":
        from masking_lab.responders import psychopy_window

        return psychopy_window.make_responder(context)  # type: ignore[attr-defined]
    raise MaskingLabError(f"responder {name!r}: choose one of {', '.join(RESPONDERS)}")


def _rig_limits(device_config: Path | None) -> dict[str, float]:
    from masking_lab.device.rig_limits import max_level_db_sl

    return max_level_db_sl(device_config)


# --------------------------------------------------------------------------------------------
# Records and checks


def _header(
    *,
    protocol: Protocol,
    participant: str,
    calibration: Mapping[str, float],
    device: DeviceIdentity,
    responder: str,
    seed: int,
    order: Sequence[str],
    virtual: bool,
    observer: dict[str, Any] | None,
    device_config: Path | None,
) -> dict[str, Any]:
    header: dict[str, Any] = {
        "schema_version": 1,
        "created_utc": utc_now(),
        "software_version": __version__,
        "protocol": {
            # Absolute, so resume can compare the file from any working directory.
            "path": str(Path(protocol.path).resolve()),
            "sha256": protocol.sha256,
            "experiment": protocol.experiment,
            "content": jsonable(protocol.content),
        },
        "participant": participant,
        "calibration": dict(calibration),
        "device": device_record(device),
        "responder": responder,
        "seed": int(seed),
        "set_order": list(order),
        "clock": "virtual" if virtual else "real",
    }
    if observer is not None:
        header["simulated_observer"] = observer
    if device_config is not None:
        header["device_config"] = str(Path(device_config).resolve())
    return header


def _settings_record(settings: StaircaseSettings) -> dict[str, Any]:
    record = dataclasses.asdict(settings)
    record["step_sizes_db"] = list(settings.step_sizes_db)
    return record


def _settings_from_record(start_record: Mapping[str, Any], spec: SetSpec) -> StaircaseSettings:
    data = dict(start_record.get("staircase") or {})
    if not data:
        return spec.staircase
    known = {f.name for f in dataclasses.fields(StaircaseSettings)}
    data = {k: v for k, v in data.items() if k in known}
    data["step_sizes_db"] = tuple(data.get("step_sizes_db", spec.staircase.step_sizes_db))
    return StaircaseSettings(**data)


def _select_sets(protocol: Protocol, order: list[str], wanted: Sequence[str] | None) -> list[str]:
    if not wanted:
        return order
    known = set(order)
    unknown = [s for s in wanted if s not in known]
    if unknown:
        raise ProtocolError(
            protocol.path,
            "sets",
            f"--sets names {', '.join(repr(s) for s in unknown)}, which the protocol does not "
            f"have; its sets are {', '.join(order)}",
        )
    chosen = set(wanted)
    return [s for s in order if s in chosen]


def _stimuli_of(protocol: Protocol, order: Sequence[str]) -> set[str]:
    names: set[str] = set()
    for set_id in order:
        spec = protocol.set_by_id(set_id)
        names.add(spec.target.name)
        if spec.masker is not None:
            names.add(spec.masker.name)
    return names


def _protocol_from_header(
    header: Mapping[str, Any], path: Path, allow_changed: bool, out: ProgressLine
) -> Protocol:
    meta = header["protocol"]
    logged_sha = str(meta["sha256"])
    on_disk = Path(str(meta["path"]))
    if on_disk.is_file():
        import hashlib

        sha = hashlib.sha256(on_disk.read_bytes()).hexdigest()
        if sha != logged_sha:
            if not allow_changed:
                raise LogError(
                    f"{path}: the protocol file {on_disk} has changed since this session started "
                    f"(sha256 {sha[:12]}… now, {logged_sha[:12]}… in the log). Restore it, or "
                    "resume with --allow-changed-protocol to continue with the copy stored in "
                    "the log (the file on disk is never used by resume)"
                )
            out.message(
                f"note: {on_disk} has changed since the session started; continuing with the "
                "protocol stored in the log"
            )
    text = yaml.safe_dump(dict(meta["content"]), sort_keys=False)
    try:
        protocol = parse_protocol(text.encode("utf-8"), f"{path} (protocol stored in the header)")
    except ProtocolError as exc:
        raise LogError(f"{path}: the protocol stored in the header is invalid: {exc}") from exc
    return dataclasses.replace(protocol, path=str(meta["path"]), sha256=logged_sha)


def _check_trials(path: Path, protocol: Protocol, existing: Mapping[str, SetRecords]) -> None:
    """Logged trials must be contiguous and replay to their logged levels."""
    level_key = "level_db_sl" if protocol.level_unit == "db_sl" else "level_db_v"
    for set_id, rec in existing.items():
        try:
            spec = protocol.set_by_id(set_id)
        except KeyError as exc:
            raise LogError(f"{path}: set {set_id!r} is not in the logged protocol") from exc
        indices = [t.get("trial_index") for t in rec.trials]
        if indices != list(range(len(indices))):
            raise LogError(
                f"{path}: set {set_id}: trial indices {indices} are not 0, 1, 2, …; the log has "
                "been edited or merged and cannot be resumed safely"
            )
        settings = _settings_from_record(rec.start, spec)
        state = start(settings)
        for t in rec.trials:
            logged = t.get(level_key)
            if state.finished or logged is None or abs(float(logged) - state.level_db) > 1e-6:
                raise LogError(
                    f"{path}: set {set_id}, trial {t.get('trial_index')}: logged level {logged} "
                    f"but replaying the logged responses gives {state.level_db}; the log does not "
                    "match its staircase settings and cannot be resumed"
                )
            state = state.update(bool(t["correct"]))


def _position(log: SessionLog) -> tuple[str | None, int | None]:
    set_id: str | None = None
    index: int | None = None
    for rec in log.records:
        kind = rec.get("record")
        if kind == "set_start":
            set_id, index = rec.get("set_id"), 0
        elif kind == "trial":
            set_id, index = rec.get("set_id"), int(rec.get("trial_index", -1)) + 1
        elif kind == "set_end":
            set_id, index = rec.get("set_id"), None
    return set_id, index


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


def _bound_reason(state: Staircase, plan: SetPlan) -> str:
    unit = UNIT_LABEL[plan.level_unit]
    sc = state.settings
    if state.status == "ceiling":
        return (
            f"pinned at the upper bound {sc.max_level_db:.2f} {unit} (protocol max ∩ device "
            f"limit {plan.target_max_v:g} V): a ceiling, not a threshold"
        )
    if state.status == "floor":
        return f"pinned at the lower bound {sc.min_level_db} {unit}: a floor, not a threshold"
    return f"reached the trial cap ({sc.max_trials} trials) before {sc.n_reversals} reversals"


def jsonable(value: Any) -> Any:
    """A JSON-safe copy: mappings, sequences, finite numbers, strings; others as strings."""
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, bool) or value is None or isinstance(value, str | int):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)
    if isinstance(value, dt.date):
        return value.isoformat()
    return str(value)


def _relative(path: Path, base: Path) -> str:
    try:
        return os.path.relpath(path, base)
    except ValueError:
        return str(path)
