"""The user-test session (paper §3.3): play objects, collect two answers, log every trial.

The imperative shell around :mod:`masking_lab.usertest.design` (design, trial order, objects,
levels)
and :mod:`masking_lab.usertest.stream` (ticks, limits, clipping, dead-band). It uses the threshold
runner's pieces (:mod:`masking_lab.session.runner`: participant and device checks, clocks, device
and
responder opening, header records, signals, fault kinds) so a user test runs on the same devices
and writes the same kind of log: a header, one fsynced ``usertest_trial`` record per trial, fault
and resume records, and a ``session_end``.

Per trial: the object plays three times (1.2 s lead-in, 1.8 s presentations, 0.6 s gaps); during
each presentation the EV and MV amplitudes are streamed with ``Device.set_amplitude`` at
:data:`~masking_lab.usertest.stream.UPDATE_HZ`, following the cue (time-locked at the protocol's
``cue_speed_mm_s``) or the finger position the responder reports; then the responder gives the
geometry key and the texture key.

Before anything is played the session refuses: a participant without a calibration for every
stimulus (a baseline protocol for the missing ones is written), compensation without masking
functions for every stimulus pair (the protocol that measures the missing ones is written), and
objects whose inputs exceed the rig's rating — unless clipping is allowed explicitly, in which
case every trial logs what was clipped.

Resume rebuilds the design from the copies stored in the log's header and continues with the next
trial of the same seeded order; a simulated participant answers from per-trial seeds, so the
continuation equals an uninterrupted run. Exit codes as for threshold sessions: 0 completed,
3 device fault, 130 interrupted; bad input raises a MaskingLabError (the CLI's exit 2).
"""

from __future__ import annotations

import json
import shlex
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TextIO

from masking_lab.core.errors import (
    CalibrationError,
    LogError,
    MaskingLabError,
    ProtocolError,
    SolverError,
)
from masking_lab.device.base import Device
from masking_lab.device.rig_limits import max_level_db_sl
from masking_lab.formats.session_log import SessionLog
from masking_lab.rendering.render import Rendering
from masking_lab.rendering.solver import MutualMasking
from masking_lab.session import frame
from masking_lab.session.opening import DeviceOpener, ResponderContext
from masking_lab.session.progress import ProgressLine
from masking_lab.usertest.design import (
    UserTestDesign,
    UserTrial,
    load_usertest,
    trial_list,
)
from masking_lab.usertest.playback import render_objects
from masking_lab.usertest.preparation import (
    KIND,
    RECORD,
    RESPONDERS,
    check_logged,
    check_stream_settings,
    check_watchdog,
    design_from_header,
    header_record,
    masking_pairs,
    pairs_from_header,
    refuse_or_warn,
    require_calibration,
    stimuli_of,
)
from masking_lab.usertest.responder_base import (
    UserTestResponder,
)
from masking_lab.usertest.session_loop import UserTestResult, UserTestSession
from masking_lab.usertest.stream import (
    DEADBAND_DB,
    REFRESH_S,
    UPDATE_HZ,
    Exceedance,
    StimulusLimit,
    exceedances,
    stimulus_limits,
)

# --------------------------------------------------------------------------------------------
# Public values


@dataclass(frozen=True)
class UserTestOptions(frame.SessionOptions):
    """What ``masking-lab run <usertest protocol>`` was asked to do.

    The fields of :class:`~masking_lab.session.frame.SessionOptions`, and:

    Attributes
    ----------
    protocol : Path
        User-test protocol (``kind: usertest``).
    participant : str
        Participant id; the calibration and the log live in ``data_dir/<participant>/``.
    device : str
        ``sim``, ``emulator``, ``serial:PORT`` or ``nidaq[:DEV]``.
    responder : {"sim", "keys", "psychopy"}
        Who answers.
    params : Path or None
        ``masking_params.json`` (needed for the compensated condition).
    allow_clipping : bool
        Play inputs above the rig's rating clipped to it (logged per trial) instead of refusing.
    gamut_map : str
        Map each scene into the rig's gamut first (``clip``, ``scale``, ``compress``; see
        :mod:`masking_lab.rendering.mapping`), or ``none``.
    update_hz : float
        Amplitude look-ups per second while a presentation plays, Hz.
    deadband_db : float
        Smallest level change sent, dB.
    """

    protocol: Path
    participant: str
    device: str = "sim"
    responder: str = "sim"
    params: Path | None = None
    allow_clipping: bool = False
    gamut_map: str = "none"
    update_hz: float = UPDATE_HZ
    deadband_db: float = DEADBAND_DB


@dataclass
class UserTestContext(ResponderContext):
    """What a user-test responder factory may need (see :class:`ResponderContext`).

    Attributes
    ----------
    design : UserTestDesign
        The protocol.
    objects : mapping (geometry, texture) → Rendering
        The rendered objects.
    """

    design: UserTestDesign
    objects: Mapping[tuple[str, str], Rendering]


# --------------------------------------------------------------------------------------------
# Entry points


def is_usertest_protocol(path: str | Path) -> bool:
    """True if ``path`` parses as a mapping with ``kind: usertest`` (False if unreadable)."""
    from masking_lab.formats.reader import load_document

    try:  # the shared reader: no alias bomb, deep nesting or bad byte gets past this probe
        data = load_document(path, what="protocol").data
    except MaskingLabError:
        return False  # the protocol loader reports what is wrong
    return isinstance(data, dict) and data.get("kind") == KIND


def is_usertest_log(path: str | Path) -> bool:
    """True if the first line of ``path`` is a user-test session header (False if unreadable)."""
    try:
        with open(path, encoding="utf-8") as fh:  # bounded: a log may be a 2 GB sparse file
            first = json.loads(fh.readline(8 * 1024 * 1024))
    # ValueError: also a 5,000-digit integer (Python's int-conversion limit)
    except (OSError, ValueError, RecursionError):
        return False  # not a user-test log; the threshold kind's reader says what is wrong
    return isinstance(first, dict) and first.get("kind") == KIND


def run_usertest(
    options: UserTestOptions,
    *,
    open_device: DeviceOpener | None = None,
    make_responder: frame.ResponderFactory | None = None,
    stream: TextIO | None = None,
) -> UserTestResult:
    """Run a user test for one participant and write a new session log.

    Parameters
    ----------
    options : UserTestOptions
        What to run.
    open_device, make_responder, stream
        The hooks of :func:`masking_lab.session.frame.start`.

    Raises
    ------
    MaskingLabError
        Found before anything is played: bad protocol or participant id, missing calibration
        (:class:`CalibrationError`; a baseline protocol for the missing stimuli is written into
        the data folder), missing masking functions (:class:`SolverError`; the protocol that
        measures them is written there), objects above the rig's rating without
        ``allow_clipping`` (:class:`LevelError`), a responder that cannot do the tracking.
    """
    return frame.start(
        USERTEST, options, open_device=open_device, make_responder=make_responder, stream=stream
    )


def resume_usertest(
    log_path: str | Path,
    options: frame.SessionOptions | None = None,
    *,
    open_device: DeviceOpener | None = None,
    make_responder: frame.ResponderFactory | None = None,
    stream: TextIO | None = None,
) -> UserTestResult:
    """Continue an interrupted user test with its next trial, in the same log.

    The protocol, object scenes, masking functions, calibration, seed, stream settings and the
    clipping choice come from the log's header, never from files that may have changed since.

    Parameters
    ----------
    log_path : path
        The user test's session log.
    options : SessionOptions, optional
        What the resume changes (device, responder, rig config, ...).
    open_device, make_responder, stream
        The hooks of :func:`masking_lab.session.frame.start`.

    Raises
    ------
    LogError
        Not a user-test log, a finished session, a changed protocol or scene file (without
        ``allow_changed_protocol``), or logged trials that are not the seed's order.
    LevelError
        The device now has lower limits, so objects exceed them, and clipping was not allowed.
    """
    return frame.resume(
        USERTEST,
        log_path,
        options,
        open_device=open_device,
        make_responder=make_responder,
        stream=stream,
    )


class UserTestKind:
    """The user test (paper §3.3) in the session frame."""

    responders = RESPONDERS

    def default_responder(self, name: str, context: UserTestContext) -> UserTestResponder:
        return default_responder(name, context)

    def check_log(self, header: Mapping[str, Any], path: Path) -> None:
        if header.get("kind") != KIND:
            raise LogError(
                f"{path}: not a user-test session log; resume it with `masking-lab resume`"
            )

    def plan_start(
        self, options: UserTestOptions, participant: str, seed: int, out: ProgressLine
    ) -> _UserTestPlan:
        check_stream_settings(options.update_hz, options.deadband_db)
        design = load_usertest(options.protocol)
        data_dir = Path(options.data_dir)
        # Every refusal at once (calibration, masking functions), each with the command that
        # fixes it, written with this run's own --device and --responder.
        run_options = f"--device {shlex.quote(options.device)} --responder {options.responder}"
        if options.device_config is not None:
            run_options += f" --device-config {shlex.quote(str(options.device_config))}"
        problems: list[MaskingLabError] = []
        try:
            calibration = require_calibration(design, data_dir, participant, run_options)
        except CalibrationError as exc:
            problems.append(exc)
        try:
            pairs, params_record = masking_pairs(design, options.params, data_dir)
        except SolverError as exc:
            problems.append(exc)
        if len(problems) == 1:
            raise problems[0]
        if problems:
            raise CalibrationError(
                f"the user test cannot start yet, for {len(problems)} reasons (fix both, in "
                "this order):\n" + "\n".join(f"{k}. {exc}" for k, exc in enumerate(problems, 1))
            )
        rig_max = max_level_db_sl(options.device_config)
        return _UserTestPlan(
            participant=participant,
            design=design,
            objects=_objects(design, pairs, rig_max, options.gamut_map),
            pairs=pairs,
            params_record=params_record,
            calibration=calibration,
            rig_max=rig_max,
            gamut_map=options.gamut_map,
            update_hz=options.update_hz,
            deadband_db=options.deadband_db,
            allow_clipping=options.allow_clipping,
            logged=[],
            trials=trial_list(design, seed),
        )

    def plan_resume(
        self,
        header: Mapping[str, Any],
        log: SessionLog,
        path: Path,
        options: frame.SessionOptions,
        out: ProgressLine,
    ) -> _UserTestPlan:
        ut = header["usertest"]
        design = design_from_header(header, path, options.allow_changed_protocol, out)
        pairs = pairs_from_header(ut, path)
        trials = trial_list(design, int(header["seed"]))
        logged = [r for r in log.records if r.get("record") == RECORD]
        check_logged(path, trials, logged, str(header["participant"]))
        settings = ut.get("stream") or {}
        rig_max = {k: float(v) for k, v in (ut.get("rig_max_level_db_sl") or {}).items()}
        if options.device_config is not None:
            rig_max = max_level_db_sl(options.device_config)
        gamut_map = str(ut.get("gamut_map", "none"))
        return _UserTestPlan(
            participant=str(header["participant"]),
            design=design,
            objects=_objects(design, pairs, rig_max, gamut_map),
            pairs=pairs,
            params_record=None,
            calibration={k: float(v) for k, v in header["calibration"].items()},
            rig_max=rig_max,
            gamut_map=gamut_map,
            update_hz=float(settings.get("update_hz", UPDATE_HZ)),
            deadband_db=float(settings.get("deadband_db", DEADBAND_DB)),
            allow_clipping=bool(ut.get("allow_clipping", False)),
            logged=logged,
            trials=trials,
        )


@dataclass
class _UserTestPlan(frame.SessionPlan[UserTestResult]):
    """A user test's plan for this process (see :class:`frame.SessionPlan`)."""

    participant: str
    design: UserTestDesign
    objects: dict[tuple[str, str], Rendering]  # mapped in place once the device is open
    pairs: Mapping[tuple[str, str], MutualMasking]
    params_record: dict[str, Any] | None
    calibration: dict[str, float]
    rig_max: dict[str, float]
    update_hz: float
    deadband_db: float
    allow_clipping: bool
    logged: list[Mapping[str, Any]]
    trials: Sequence[UserTrial]
    gamut_map: str = "none"
    limits: Mapping[str, StimulusLimit] = field(default_factory=dict)
    over: Sequence[Exceedance] = ()

    @property
    def experiment(self) -> str:
        return self.design.experiment

    def context(self, opening: frame.Opening) -> UserTestContext:
        return opening.context(UserTestContext, design=self.design, objects=self.objects)

    def check_responder(self, name: str) -> None:
        if self.design.tracking == "finger" and name == "keys":
            raise ProtocolError(
                self.design.path,
                "tracking",
                "finger tracking needs a responder that reports the finger's position (sim); "
                "the keys responder cannot — set tracking: cue, or use --responder sim",
            )

    def check_device(self, device: Device, out: ProgressLine) -> None:
        check_watchdog(device)
        self.limits = stimulus_limits(
            stimuli_of(self.design),
            self.calibration,
            self.rig_max,
            device.identity.limits.max_drive_v,
        )
        if self.gamut_map != "none":
            # Map into what this participant may be played (rig rating or drive limit, the
            # lower), now that the device's drive limit is known. In place: the responder's
            # context already holds this mapping.
            mapped = _objects(self.design, self.pairs, self.limits, self.gamut_map)
            self.objects.clear()
            self.objects.update(mapped)
        self.over = exceedances(self.design, self.objects, self.limits)
        refuse_or_warn(self.over, self.allow_clipping, self.participant, out)

    def header(self, opening: frame.Opening, device: Device) -> dict[str, Any]:
        return header_record(
            design=self.design,
            calibration=self.calibration,
            device=device,
            **opening.header_fields(),
            pairs=self.pairs,
            params_record=self.params_record,
            stream_settings={
                "update_hz": float(self.update_hz),
                "deadband_db": float(self.deadband_db),
                "refresh_s": REFRESH_S,
            },
            allow_clipping=self.allow_clipping,
            gamut_map=self.gamut_map,
            rig_max=self.rig_max,
            limits=self.limits,
            over=self.over,
        )

    def position(self) -> tuple[str | None, int | None]:
        return None, len(self.logged)

    def resume_message(self, path: Path) -> str:
        return f"resuming {path} at trial {len(self.logged) + 1} of {len(self.trials)}"

    def session(self, opening: frame.Opening, opened: frame.Opened) -> UserTestSession:
        return UserTestSession(
            design=self.design,
            objects=self.objects,
            limits=self.limits,
            allow_clipping=self.allow_clipping,
            update_hz=self.update_hz,
            deadband_db=self.deadband_db,
            logged=self.logged,
            **opening.loop_fields(opened),
        )


USERTEST = UserTestKind()


def _objects(design, pairs, limits, gamut_map):
    """The objects rendered; unless ``gamut_map`` is ``none``, each object mapped into the gamut
    of its own stimuli's limits (``limits``: channel or stimulus name → dB SL or StimulusLimit).
    """
    if gamut_map == "none":
        return render_objects(design, pairs)
    out = {}
    for key, scene in design.scenes.items():
        one = replace(design, scenes={key: scene})
        levels = []
        for spec, channel in ((scene.texture, "MV"), (scene.geometry, "EV")):
            lim = limits.get(spec.stimulus if spec is not None else "", limits.get(channel))
            levels.append(getattr(lim, "max_db_sl", lim))
        out.update(
            render_objects(
                one, pairs, max_mv_db_sl=levels[0], max_ev_db_sl=levels[1], gamut_map=gamut_map
            )
        )
    return out


def default_responder(name: str, context: UserTestContext) -> UserTestResponder:
    """Build the ``sim``, ``keys`` or ``psychopy`` user-test responder."""
    if name == "sim":
        from masking_lab.usertest.sim_responder import UserTestSimResponder

        truth, population_seed, source = context.simulated_truth()
        return UserTestSimResponder.from_ground_truth(
            context.design,
            context.objects,
            truth,
            context.participant,
            context.seed,
            population_seed=population_seed,
            source=source or "the ground truth",
        )
    if name == "keys":
        from masking_lab.responders.keys import KeyReader
        from masking_lab.usertest.keys_responder import UserTestKeysResponder

        return UserTestKeysResponder(KeyReader.on_terminal(context.participant_tty))
    if name == "psychopy":
        from masking_lab.usertest import window_responder as usertest_psychopy

        return usertest_psychopy.make_responder(context)
    raise MaskingLabError(f"responder {name!r}: the user test is answered by {RESPONDERS}")
