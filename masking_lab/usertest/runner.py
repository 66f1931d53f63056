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

import dataclasses
import hashlib
import json
import math
import secrets
import tempfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import yaml

from masking_lab import __version__
from masking_lab.core.clock import Clock, RealClock, VirtualClock
from masking_lab.core.errors import (
    CalibrationError,
    LevelError,
    LogError,
    MaskingLabError,
    ProtocolError,
    SolverError,
)
from masking_lab.core.levels import db_v_to_volts
from masking_lab.core.stimulus import CHANNELS, Channel, Stimulus, parse_stimulus
from masking_lab.device.base import Device
from masking_lab.formats.calibration import calibration_path, load_calibration
from masking_lab.formats.fileio import write_text_atomic
from masking_lab.formats.session_log import SessionLogWriter, read_log
from masking_lab.rendering.render import Rendering
from masking_lab.rendering.solver import MissingMaskingError, MutualMasking, PairProblem
from masking_lab.session.progress import ProgressLine, format_duration
from masking_lab.session.runner import SessionResult, jsonable
from masking_lab.session.shell import (
    DeviceOpener,
    SessionShell,
    check_device_spec,
    check_header,
    check_participant,
    close_on_failure,
    create_log,
    default_opener,
    device_record,
    device_spec_from_header,
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
from masking_lab.usertest.design import (
    UserTestDesign,
    UserTrial,
    load_usertest,
    render_objects,
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
    DEADBAND_DB,
    REFRESH_S,
    SILENT,
    UPDATE_HZ,
    Exceedance,
    PresentationPlan,
    StimulusLimit,
    Streamer,
    clip_db_v,
    exceedances,
    object_stimuli,
    path_levels_db_sl,
    plan_presentation,
    stimulus_limits,
    tick_offsets_s,
    to_db_v,
)

KIND = "usertest"
RESPONDERS = ("sim", "keys", "psychopy")
RECORD = "usertest_trial"

UserTestResponderMaker = Callable[[str, "UserTestContext"], UserTestResponder]


# --------------------------------------------------------------------------------------------
# Public values


@dataclass(frozen=True)
class UserTestOptions:
    """What ``masking-lab run <usertest protocol>`` was asked to do.

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
    data_dir : Path
        Data folder.
    params : Path or None
        ``masking_params.json`` (needed for the compensated condition).
    seed : int or None
        Session seed (drawn and logged when None); it fixes the trial order.
    allow_clipping : bool
        Play inputs above the rig's rating clipped to it (logged per trial) instead of refusing.
    real_time, ground_truth, device_config, progress, participant_tty
        As in :class:`masking_lab.session.runner.RunOptions`.
    update_hz : float
        Amplitude look-ups per second while a presentation plays, Hz.
    deadband_db : float
        Smallest level change sent, dB.
    """

    protocol: Path
    participant: str
    device: str = "sim"
    responder: str = "sim"
    data_dir: Path = Path("data")
    params: Path | None = None
    seed: int | None = None
    allow_clipping: bool = False
    real_time: bool = False
    ground_truth: Path | None = None
    device_config: Path | None = None
    progress: bool | None = None
    participant_tty: str | None = None
    update_hz: float = UPDATE_HZ
    deadband_db: float = DEADBAND_DB


@dataclass
class UserTestContext:
    """What a user-test responder factory may need.

    Attributes
    ----------
    participant : str
        Participant id.
    seed : int
        Session seed.
    clock : Clock
        The session clock.
    design : UserTestDesign
        The protocol.
    objects : mapping (geometry, texture) → Rendering
        The rendered objects.
    simulated_observer : dict or None
        ``{"ground_truth_path", "population_seed", "truth"}`` for the sim responder.
    device_config : Path or None
        The rig config.
    participant_tty : str or None
        The participant's terminal for the keys responder (None: this one).
    """

    participant: str
    seed: int
    clock: Clock
    design: UserTestDesign
    objects: Mapping[tuple[str, str], Rendering]
    simulated_observer: dict[str, Any] | None = None
    device_config: Path | None = None
    participant_tty: str | None = None


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
# Entry points


def is_usertest_protocol(path: str | Path) -> bool:
    """True if ``path`` parses as a mapping with ``kind: usertest`` (False if unreadable)."""
    try:
        data = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return False
    return isinstance(data, dict) and data.get("kind") == KIND


def is_usertest_log(path: str | Path) -> bool:
    """True if the first line of ``path`` is a user-test session header (False if unreadable)."""
    try:
        with open(path, encoding="utf-8") as fh:
            first = json.loads(fh.readline())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return False
    return isinstance(first, dict) and first.get("kind") == KIND


def run_usertest(
    options: UserTestOptions,
    *,
    open_device: DeviceOpener | None = None,
    make_responder: UserTestResponderMaker | None = None,
    stream: TextIO | None = None,
) -> UserTestResult:
    """Run a user test for one participant and write a new session log.

    Parameters
    ----------
    options : UserTestOptions
        What to run.
    open_device : callable, optional
        ``(spec, clock) -> Device``; default: :func:`masking_lab.device.registry.open_device`.
    make_responder : callable, optional
        ``(name, UserTestContext) -> UserTestResponder``; default builds sim, keys or psychopy.
    stream : text stream, optional
        Progress and messages (stderr by default).

    Raises
    ------
    MaskingLabError
        Found before anything is played: bad protocol or participant id, missing calibration
        (:class:`CalibrationError`; a baseline protocol for the missing stimuli is written into
        the data folder), missing masking functions (:class:`SolverError`; the protocol that
        measures them is written there), objects above the rig's rating without
        ``allow_clipping`` (:class:`LevelError`), a responder that cannot do the tracking.
    """
    out = ProgressLine(stream, force=options.progress)
    participant = check_participant(options.participant)
    if options.responder not in RESPONDERS:
        raise MaskingLabError(
            f"--responder {options.responder!r}: the user test is answered by "
            f"{', '.join(RESPONDERS)}"
        )
    check_device_spec(options.device)
    _check_stream_settings(options.update_hz, options.deadband_db)
    design = load_usertest(options.protocol)
    if design.tracking == "finger" and options.responder == "keys":
        raise ProtocolError(
            design.path,
            "tracking",
            "finger tracking needs a responder that reports the finger's position (sim); the "
            "keys responder cannot — set tracking: cue, or use --responder sim",
        )
    seed = options.seed if options.seed is not None else secrets.randbits(32)
    if seed < 0:
        raise MaskingLabError(f"--seed must be ≥ 0, got {seed}")
    data_dir = Path(options.data_dir)
    calibration = _require_calibration(design, data_dir, participant)
    pairs, params_record = _masking_pairs(design, options.params, data_dir)
    objects = render_objects(design, pairs)
    rig_max = _rig_limits(options.device_config)

    virtual = use_virtual_clock(options.device, options.responder, options.real_time)
    clock: Clock = VirtualClock() if virtual else RealClock()
    observer = observer_record(options.ground_truth) if options.responder == "sim" else None
    context = UserTestContext(
        participant,
        seed,
        clock,
        design,
        objects,
        observer,
        options.device_config,
        options.participant_tty,
    )
    device, responder = open_device_and_responder(
        make_responder or default_responder,
        options.responder,
        context,
        open_device or default_opener(options.device_config),
        options.device,
        clock,
    )
    with close_on_failure(device, responder):
        _check_watchdog(device)
        limits = stimulus_limits(
            _stimuli_of(design), calibration, rig_max, device.identity.limits.max_drive_v
        )
        over = exceedances(design, objects, limits)
        _refuse_or_warn(over, options.allow_clipping, participant, out)
        header = _header(
            design=design,
            participant=participant,
            calibration=calibration,
            device=device,
            responder=options.responder,
            seed=seed,
            virtual=virtual,
            observer=observer,
            device_config=options.device_config,
            pairs=pairs,
            params_record=params_record,
            stream_settings={
                "update_hz": float(options.update_hz),
                "deadband_db": float(options.deadband_db),
                "refresh_s": REFRESH_S,
            },
            allow_clipping=options.allow_clipping,
            rig_max=rig_max,
            limits=limits,
            over=over,
        )
        writer = create_log(data_dir, design.experiment, participant, header)
    out.message(f"session log: {writer.path}")
    session = _UserTestSession(
        design=design,
        objects=objects,
        participant=participant,
        seed=seed,
        limits=limits,
        allow_clipping=options.allow_clipping,
        update_hz=options.update_hz,
        deadband_db=options.deadband_db,
        clock=clock,
        device=device,
        responder=responder,
        writer=writer,
        out=out,
        logged=[],
    )
    return session.run()


def resume_usertest(
    log_path: str | Path,
    *,
    device: str | None = None,
    responder: str | None = None,
    allow_changed_protocol: bool = False,
    device_config: Path | None = None,
    participant_tty: str | None = None,
    open_device: DeviceOpener | None = None,
    make_responder: UserTestResponderMaker | None = None,
    stream: TextIO | None = None,
    progress: bool | None = None,
) -> UserTestResult:
    """Continue an interrupted user test with its next trial, in the same log.

    The protocol, object scenes, masking functions, calibration, seed, stream settings and the
    clipping choice come from the log's header, never from files that may have changed since.

    Raises
    ------
    LogError
        Not a user-test log, a finished session, a changed protocol or scene file (without
        ``allow_changed_protocol``), or logged trials that are not the seed's order.
    LevelError
        The device now has lower limits, so objects exceed them, and clipping was not allowed.
    """
    out = ProgressLine(stream, force=progress)
    path = Path(log_path)
    log = read_log(path)
    header = log.header
    check_header(header, path)
    if header.get("kind") != KIND:
        raise LogError(f"{path}: not a user-test session log; resume it with `masking-lab resume`")
    refuse_finished(log, path)
    ut = header["usertest"]
    design = _design_from_header(header, path, allow_changed_protocol, out)
    pairs = _pairs_from_header(ut, path)
    objects = render_objects(design, pairs)
    participant = str(header["participant"])
    seed = int(header["seed"])
    calibration = {k: float(v) for k, v in header["calibration"].items()}
    trials = trial_list(design, seed)
    logged = [r for r in log.records if r.get("record") == RECORD]
    _check_logged(path, trials, logged, participant)
    responder_name = resume_responder_name(header, responder, RESPONDERS)
    if design.tracking == "finger" and responder_name == "keys":
        raise ProtocolError(design.path, "tracking", "finger tracking cannot be answered by keys")
    settings = ut.get("stream") or {}
    update_hz = float(settings.get("update_hz", UPDATE_HZ))
    deadband_db = float(settings.get("deadband_db", DEADBAND_DB))
    allow_clipping = bool(ut.get("allow_clipping", False))

    clock = resume_clock(header, log)
    observer = resume_observer(header, responder_name)
    config_path = resume_device_config(device_config, header)
    context = UserTestContext(
        participant, seed, clock, design, objects, observer, config_path, participant_tty
    )
    spec = check_device_spec(device or device_spec_from_header(header))
    dev, resp = open_device_and_responder(
        make_responder or default_responder,
        responder_name,
        context,
        open_device or default_opener(config_path),
        spec,
        clock,
    )
    with close_on_failure(dev, resp):
        _check_watchdog(dev)
        rig_max = {k: float(v) for k, v in (ut.get("rig_max_level_db_sl") or {}).items()}
        if device_config is not None:
            rig_max = _rig_limits(device_config)
        limits = stimulus_limits(
            _stimuli_of(design), calibration, rig_max, dev.identity.limits.max_drive_v
        )
        _refuse_or_warn(exceedances(design, objects, limits), allow_clipping, participant, out)
        writer, _ = SessionLogWriter.reopen(path)
    record_resume(writer, log, dev.identity, out, (None, len(logged)))
    out.message(f"resuming {path} at trial {len(logged) + 1} of {len(trials)}")
    session = _UserTestSession(
        design=design,
        objects=objects,
        participant=participant,
        seed=seed,
        limits=limits,
        allow_clipping=allow_clipping,
        update_hz=update_hz,
        deadband_db=deadband_db,
        clock=clock,
        device=dev,
        responder=resp,
        writer=writer,
        out=out,
        logged=logged,
    )
    return session.run()


def default_responder(name: str, context: UserTestContext) -> UserTestResponder:
    """Build the ``sim``, ``keys`` or ``psychopy`` user-test responder."""
    if name == "sim":
        from masking_lab.simulation.observer import ground_truth_from_dict
        from masking_lab.usertest.sim_responder import UserTestSimResponder

        obs = context.simulated_observer or observer_record(None)
        source = str(obs.get("ground_truth_path") or "the ground truth")
        truth = ground_truth_from_dict(obs["truth"], source)
        return UserTestSimResponder.from_ground_truth(
            context.design,
            context.objects,
            truth,
            context.participant,
            context.seed,
            population_seed=int(obs["population_seed"]),
            source=source,
        )
    if name == "keys":
        from masking_lab.usertest.keys_responder import UserTestKeysResponder

        if context.participant_tty:
            return UserTestKeysResponder.open_tty(context.participant_tty)
        return UserTestKeysResponder()
    if name == "psychopy":
        from masking_lab.usertest.design import window_responder as usertest_psychopy

        return usertest_psychopy.make_responder(context)
    raise MaskingLabError(f"responder {name!r}: the user test is answered by {RESPONDERS}")


# --------------------------------------------------------------------------------------------
# Checks before anything is played


def _check_stream_settings(update_hz: float, deadband_db: float) -> None:
    if not (math.isfinite(update_hz) and 1.0 <= update_hz <= 1000.0):
        raise MaskingLabError(f"update rate {update_hz!r} Hz: choose 1–1000 Hz (default 100)")
    if not (math.isfinite(deadband_db) and 0.0 <= deadband_db <= 6.0):
        raise MaskingLabError(f"dead-band {deadband_db!r} dB: choose 0–6 dB (default 0.5)")


def _check_watchdog(device: Device) -> None:
    """The stream re-sends a held level every REFRESH_S s: the device's watchdog must allow it."""
    watchdog_s = float(getattr(device, "watchdog_s", 0.0) or 0.0)
    if 0.0 < watchdog_s < 2 * REFRESH_S:
        raise MaskingLabError(
            f"the device's watchdog zeroes the outputs after {watchdog_s:g} s without a command, "
            f"but a user test may stream a flat stretch with one frame every {REFRESH_S:g} s; "
            f"set serial.watchdog_s to at least {2 * REFRESH_S:g} s in the rig config"
        )


def _stimuli_of(design: UserTestDesign) -> set[str]:
    names: set[str] = set()
    for scene in design.scenes.values():
        if scene.geometry is not None:
            names.add(scene.geometry.stimulus)
        if scene.texture is not None:
            names.add(scene.texture.stimulus)
    return names


def _require_calibration(
    design: UserTestDesign, data_dir: Path, participant: str
) -> dict[str, float]:
    """The participant's unmasked AL of every stimulus the objects play, dB re 1 V."""
    cal = load_calibration(data_dir, participant)
    needed = _stimuli_of(design)
    missing = cal.missing(needed)
    if missing:
        written = write_baseline_protocol(missing, data_dir)
        have = ", ".join(sorted(cal.unmasked_al_db_v)) or "none"
        raise CalibrationError(
            f"{calibration_path(data_dir, participant)}: participant {participant} has no "
            f"unmasked AL for {', '.join(missing)} (calibrated: {have}); the user test plays "
            f"its levels in dB SL. Wrote {written}, a baseline of just these stimuli: run "
            f"masking-lab run {written} --participant {participant} --data {data_dir} "
            "--device ... --responder ..., then start the user test again"
        )
    return {name: float(cal.unmasked_al_db_v[name]) for name in sorted(needed)}


def baseline_protocol(stimuli: Sequence[str]) -> dict[str, Any]:
    """A baseline protocol measuring the unmasked ALs of ``stimuli`` (staircase and timing of
    the shipped ``protocols/baseline.yaml``)."""
    from masking_lab.formats.resources import shipped

    template = yaml.safe_load(shipped("protocols", "baseline.yaml").read_text(encoding="utf-8"))
    names = sorted(set(stimuli))
    return {
        "schema_version": 1,
        "experiment": "baseline_" + "_".join(names),
        "description": f"Unmasked ALs of {', '.join(names)}, which a user test plays and the "
        "participant's calibration lacks. Written by masking-lab run.",
        "kind": "baseline",
        "staircase": template["staircase"],
        "timing": template["timing"],
        "order": {"randomize": True},
        "sets": [{"id": n, "target": n} for n in names],
    }


def write_baseline_protocol(stimuli: Sequence[str], folder: Path) -> Path:
    """Validate :func:`baseline_protocol` and write it to ``folder/<experiment>.yaml``."""
    from masking_lab.formats.protocol import parse_protocol

    protocol = baseline_protocol(stimuli)
    text = "# Written by masking-lab run: the baseline a user test needs.\n" + yaml.safe_dump(
        protocol, sort_keys=False, allow_unicode=True
    )
    path = Path(folder) / f"{protocol['experiment']}.yaml"
    parse_protocol(text.encode("utf-8"), str(path))
    return write_text_atomic(path, text)


def _masking_pairs(
    design: UserTestDesign, params: Path | None, data_dir: Path
) -> tuple[dict[tuple[str, str], MutualMasking], dict[str, Any] | None]:
    """The fitted masking of every stimulus pair, and the params file's path and hash."""
    from masking_lab.formats.masking_params import read_masking_params
    from masking_lab.rendering.render import measurement_protocol, write_measurement_protocol
    from masking_lab.rendering.solver import pair_from_params

    needed = design.stimulus_pairs()
    if params is None:
        if "compensated" not in design.conditions:
            # Nothing is compensated: the objects' inputs are their targets.
            zero = {(mv, ev): MutualMasking(0.0, 0.0, 0.0, 0.0, mv=mv, ev=ev) for mv, ev in needed}
            return zero, None
        listed = ", ".join(f"{mv} with {ev}" for mv, ev in needed)
        raise SolverError(
            f"{design.path}: the compensated condition needs the masking functions of {listed}: "
            "pass --params masking_params.json (written by `masking-lab fit` or `analyze`)"
        )
    doc = read_masking_params(params)
    pairs: dict[tuple[str, str], MutualMasking] = {}
    problems: list[PairProblem] = []
    for mv, ev in needed:
        try:
            pairs[(mv, ev)] = pair_from_params(doc, mv=mv, ev=ev, source=str(params))
        except MissingMaskingError as exc:
            problems += exc.problems
    if problems:
        written = write_measurement_protocol(measurement_protocol(problems), data_dir)
        listed = "; ".join(
            f"{p.target} masked by {p.masker} ("
            + ("no entry" if p.status == "missing" else f"status {p.status!r}")
            + ")"
            for p in problems
        )
        raise SolverError(
            f"{params}: the user test compensates every object, but these masking functions are "
            f"not fitted: {listed}.\n  wrote {written}: the protocol that measures just these "
            f"pairs. Check it with `masking-lab validate {written}`, run it after the "
            "participants' baseline, fit, and start the user test again"
        )
    raw = Path(params).read_bytes()
    record = {"path": str(Path(params).resolve()), "sha256": hashlib.sha256(raw).hexdigest()}
    return pairs, record


def _rig_limits(device_config: Path | None) -> dict[str, float]:
    from masking_lab.device.rig_limits import max_level_db_sl

    return max_level_db_sl(device_config)


_MAX_LISTED = 12


def _refuse_or_warn(
    over: Sequence[Exceedance], allow_clipping: bool, participant: str, out: ProgressLine
) -> None:
    if not over:
        return
    lines = [f"  {e.describe()}" for e in over[:_MAX_LISTED]]
    if len(over) > _MAX_LISTED:
        lines.append(f"  ... and {len(over) - _MAX_LISTED} more")
    listed = "\n".join(lines)
    if not allow_clipping:
        raise LevelError(
            f"the user test cannot be played as designed for participant {participant}: "
            f"{len(over)} object/condition/channel combination(s) need more than the rig "
            f"allows:\n{listed}\nNothing was played. Either use a rig config whose limits cover "
            "these levels (--device-config: channels.<EV|MV>.max_level_db_sl and max_drive_v, "
            "only if the hardware is rated for them), or pass --allow-clipping to play them "
            "clipped at the limit (every trial then logs what was clipped, and compensation is "
            "only partial where it clips)"
        )
    out.message(
        f"--allow-clipping: {len(over)} object/condition/channel combination(s) will be "
        f"clipped at the rig's limits (logged per trial):\n{listed}"
    )


# --------------------------------------------------------------------------------------------
# The header and what resume rebuilds from it


def _header(
    *,
    design: UserTestDesign,
    participant: str,
    calibration: Mapping[str, float],
    device: Device,
    responder: str,
    seed: int,
    virtual: bool,
    observer: dict[str, Any] | None,
    device_config: Path | None,
    pairs: Mapping[tuple[str, str], MutualMasking],
    params_record: dict[str, Any] | None,
    stream_settings: dict[str, float],
    allow_clipping: bool,
    rig_max: Mapping[str, float],
    limits: Mapping[str, StimulusLimit],
    over: Sequence[Exceedance],
) -> dict[str, Any]:
    protocol_text = _text_with_hash(Path(design.path), design.sha256)
    scenes = []
    for (g, t), scene in sorted(design.scenes.items()):
        scenes.append(
            {
                "object": f"{g}_{t}",
                "path": str(Path(scene.source).resolve()),
                "sha256": scene.sha256,
                "text": _text_with_hash(Path(scene.source), scene.sha256),
            }
        )
    header: dict[str, Any] = {
        "schema_version": 1,
        "created_utc": utc_now(),
        "software_version": __version__,
        "protocol": {
            "path": str(Path(design.path).resolve()),
            "sha256": design.sha256,
            "experiment": design.experiment,
            "content": jsonable(design.content),
        },
        "participant": participant,
        "calibration": dict(calibration),
        "device": device_record(device.identity),
        "responder": responder,
        "seed": int(seed),
        "set_order": [],
        "clock": "virtual" if virtual else "real",
        "kind": KIND,
        "usertest": {
            "protocol_text": protocol_text,
            "scenes": scenes,
            "masking": [
                {
                    "mv": p.mv,
                    "ev": p.ev,
                    "a_db": p.a_db,
                    "b": p.b,
                    "c_db": p.c_db,
                    "d": p.d,
                    "f_fitted_range_db_sl": jsonable(p.f_fitted_range_db_sl),
                    "g_fitted_range_db_sl": jsonable(p.g_fitted_range_db_sl),
                }
                for _, p in sorted(pairs.items())
            ],
            "params": params_record,
            "n_trials": design.n_trials,
            "stream": stream_settings,
            "allow_clipping": bool(allow_clipping),
            "rig_max_level_db_sl": {k: float(v) for k, v in sorted(rig_max.items())},
            "max_level_db_sl": {k: round(v.max_db_sl, 6) for k, v in sorted(limits.items())},
            "clipped_objects": [e.as_record() for e in over],
        },
    }
    if observer is not None:
        header["simulated_observer"] = observer
    if device_config is not None:
        header["device_config"] = str(Path(device_config).resolve())
    return header


def _text_with_hash(path: Path, sha256: str) -> str:
    """The file's text, checked against the hash it was loaded with."""
    raw = path.read_bytes()
    if hashlib.sha256(raw).hexdigest() != sha256:
        raise ProtocolError(
            str(path), "", "the file changed while the session was starting; start it again"
        )
    return raw.decode("utf-8")


def _design_from_header(
    header: Mapping[str, Any], path: Path, allow_changed: bool, out: ProgressLine
) -> UserTestDesign:
    """The design as the session started it, from the copies in the header."""
    meta = header["protocol"]
    ut = header["usertest"]
    logged = [(str(meta["path"]), str(meta["sha256"]), "protocol")] + [
        (str(s["path"]), str(s["sha256"]), f"scene {s['object']}") for s in ut["scenes"]
    ]
    changed = []
    for file, sha, what in logged:
        on_disk = Path(file)
        if on_disk.is_file() and hashlib.sha256(on_disk.read_bytes()).hexdigest() != sha:
            changed.append(f"{what} {file}")
    if changed:
        if not allow_changed:
            raise LogError(
                f"{path}: changed since this session started: {'; '.join(changed)}. Restore "
                "them, or resume with --allow-changed-protocol to continue with the copies "
                "stored in the log (the files on disk are never used by resume)"
            )
        out.message(
            f"note: {'; '.join(changed)} changed since the session started; continuing with the "
            "copies stored in the log"
        )
    content = dict(meta["content"])
    content["scenes_dir"] = "scenes"
    try:
        with tempfile.TemporaryDirectory(prefix="masking-lab-usertest-") as tmp:
            folder = Path(tmp)
            (folder / "scenes").mkdir()
            (folder / "usertest.yaml").write_text(
                yaml.safe_dump(content, sort_keys=False), encoding="utf-8"
            )
            for s in ut["scenes"]:
                (folder / "scenes" / f"{s['object']}.yaml").write_text(
                    str(s["text"]), encoding="utf-8"
                )
            design = load_usertest(folder / "usertest.yaml")
    except ProtocolError as exc:
        raise LogError(f"{path}: the user test stored in the header is invalid: {exc}") from exc
    sources = {s["object"]: (str(s["path"]), str(s["sha256"])) for s in ut["scenes"]}
    scenes = {}
    for (g, t), scene in design.scenes.items():
        source, sha = sources[f"{g}_{t}"]
        if scene.sha256 != sha:
            raise LogError(f"{path}: the stored copy of scene {g}_{t} does not match its hash")
        scenes[(g, t)] = dataclasses.replace(scene, source=source)
    return dataclasses.replace(
        design,
        path=str(meta["path"]),
        sha256=str(meta["sha256"]),
        content=dict(meta["content"]),
        scenes=scenes,
    )


def _pairs_from_header(ut: Mapping[str, Any], path: Path) -> dict[tuple[str, str], MutualMasking]:
    pairs = {}
    try:
        for m in ut["masking"]:
            pair = MutualMasking(
                float(m["a_db"]),
                float(m["b"]),
                float(m["c_db"]),
                float(m["d"]),
                mv=str(m["mv"]),
                ev=str(m["ev"]),
                f_fitted_range_db_sl=_pair_or_none(m.get("f_fitted_range_db_sl")),
                g_fitted_range_db_sl=_pair_or_none(m.get("g_fitted_range_db_sl")),
            )
            pairs[(pair.mv, pair.ev)] = pair
    except (KeyError, TypeError, ValueError, SolverError) as exc:
        raise LogError(f"{path}: the header's usertest.masking is unusable ({exc})") from exc
    return pairs


def _pair_or_none(value: Any) -> tuple[float, float] | None:
    return None if value is None else (float(value[0]), float(value[1]))


def _check_logged(
    path: Path, trials: Sequence[UserTrial], logged: Sequence[Mapping[str, Any]], participant: str
) -> None:
    """Logged trials must be the seed's first trials, in order, each once."""
    if len(logged) > len(trials):
        raise LogError(
            f"{path}: {len(logged)} trials logged but the design has {len(trials)}; the log has "
            "been edited or merged and cannot be resumed"
        )
    for i, rec in enumerate(logged):
        t = trials[i]
        want = (i, t.geometry, t.texture, t.condition, t.repeat, participant)
        got = (
            rec.get("trial"),
            rec.get("geometry"),
            rec.get("texture"),
            rec.get("condition"),
            rec.get("repeat"),
            rec.get("participant"),
        )
        if got != want:
            raise LogError(
                f"{path}: logged trial {i} is {got[1]}_{got[2]} {got[3]} (index {got[0]}) but "
                f"the session's seed puts {t.geometry}_{t.texture} {t.condition} there; the log "
                "does not match its design and cannot be resumed"
            )


# --------------------------------------------------------------------------------------------
# The session loop


class _UserTestSession(SessionShell[UserTestResult]):
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
        clipped = {}
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
            stimuli=dict(names),
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
        for ch, levels in (("EV", ev), ("MV", mv)):
            name = object_stimuli(r)[ch]  # type: ignore[index]
            out[ch] = (  # type: ignore[index]
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
