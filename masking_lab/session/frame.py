"""The one session frame: how every kind of session starts and resumes.

A threshold session (:mod:`masking_lab.session.runner`) and a user test
(:mod:`masking_lab.usertest.runner`) differ in what they play, not in how a session is framed.
:func:`start` and :func:`resume` hold that frame once: participant id, responder and device
checks, the seed, the clock kind (virtual in simulation, real at the rig), the simulated
observer, opening the responder and the device (closing what is open if a later step fails),
creating or reopening the fsynced log, the resume records, and finally the kind's session loop.
A session kind plugs in through :class:`SessionKind` (what to check and prepare before anything
opens) and the :class:`SessionPlan` it returns (context for the responder factory, checks of the
opened device, the log header, the loop).

Bad input raises a :class:`~masking_lab.core.errors.MaskingLabError` before anything is played;
once the loop runs, every stop is a log record and an exit code in the result.
"""

from __future__ import annotations

import dataclasses
import secrets
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, Protocol, TextIO, TypedDict, TypeVar

from masking_lab.core.clock import Clock, RealClock, VirtualClock
from masking_lab.core.errors import DeviceTimeModeError, LogError, MaskingLabError
from masking_lab.device.base import Device
from masking_lab.formats.log_lock import LogLock, RunnerLock
from masking_lab.formats.session_log import SessionLog, SessionLogWriter, read_log
from masking_lab.session.blas_threads import one_blas_thread
from masking_lab.session.opening import (
    DeviceOpener,
    ResponderContext,
    check_device_spec,
    check_participant,
    close_on_failure,
    create_log,
    default_opener,
    observer_record,
    open_device_and_responder,
    sync_policy,
    use_virtual_clock,
)
from masking_lab.session.progress import ProgressLine
from masking_lab.session.resuming import (
    check_header,
    device_spec_from_header,
    record_resume,
    refuse_damaged,
    refuse_finished,
    resume_clock,
    resume_device_config,
    resume_observer,
    resume_responder_name,
)
from masking_lab.session.shell import Closable, SessionShell, resume_command

__all__ = [
    "Opened",
    "Opening",
    "PlanDefaults",
    "ResumeChanges",
    "ResumeKeywords",
    "ResumeOptions",
    "SessionHooks",
    "SessionKind",
    "SessionPlan",
    "StartOptions",
    "resume",
    "resume_with",
    "start",
]

ResultT = TypeVar("ResultT")
ContextT = TypeVar("ContextT", bound=ResponderContext)
ResponderFactory = Callable[[str, Any], Any]


class StartOptions(Protocol):
    """What every ``run`` states, whatever the session kind (the kind's options add more).

    Read-only properties, so that a frozen dataclass of options satisfies the protocol.
    """

    @property
    def participant(self) -> str: ...
    @property
    def device(self) -> str: ...
    @property
    def responder(self) -> str: ...
    @property
    def data_dir(self) -> Path: ...
    @property
    def seed(self) -> int | None: ...
    @property
    def real_time(self) -> bool: ...
    @property
    def ground_truth(self) -> Path | None: ...
    @property
    def device_config(self) -> Path | None: ...
    @property
    def progress(self) -> bool | None: ...
    @property
    def participant_tty(self) -> str | None: ...


@dataclass(frozen=True)
class ResumeOptions:
    """What ``resume`` may change; everything else comes from the log's header.

    Attributes
    ----------
    device : str or None
        Device spec; default: the header's back-end (``serial:<port>`` for a serial device).
    responder : str or None
        Responder; default: the header's.
    allow_changed_protocol : bool
        Continue although protocol or scene files changed on disk (the logged copies are used).
    device_config : Path or None
        Rig config; default: the one the session started with.
    participant_tty : str or None
        The participant's terminal for the keys responder.
    progress : bool or None
        Force the progress line on or off (default: on a terminal only).
    """

    device: str | None = None
    responder: str | None = None
    allow_changed_protocol: bool = False
    device_config: Path | None = None
    participant_tty: str | None = None
    progress: bool | None = None


class ResumeChanges(TypedDict, total=False):
    """The keyword form of :class:`ResumeOptions` taken by the kinds' ``resume_*`` functions."""

    device: str | None
    responder: str | None
    allow_changed_protocol: bool
    device_config: Path | None
    participant_tty: str | None
    progress: bool | None


class SessionHooks(TypedDict, total=False):
    """Where a session's device, responder and messages come from (tests, embedding programs).

    ``open_device``: ``(spec, clock) -> Device`` (default: the registry with the rig config);
    ``make_responder``: ``(name, context) -> responder`` (default: the kind's sim, keys or
    psychopy); ``stream``: where progress and messages go (default: stderr).
    """

    open_device: DeviceOpener | None
    make_responder: ResponderFactory | None
    stream: TextIO | None


class ResumeKeywords(SessionHooks, ResumeChanges, total=False):
    """The keywords of the kinds' ``resume_*`` functions: hooks and what resume may change."""


def resume_with(
    kind: SessionKind[ResultT], log_path: str | Path, keywords: Mapping[str, Any]
) -> ResultT:
    """:func:`resume` with :class:`ResumeKeywords` (hooks and changes in one mapping).

    Examples
    --------
    >>> resume_with(None, "nowhere.jsonl", {"colour": "red"})  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    TypeError: ...unexpected keyword argument 'colour'
    """
    hooks = {k: v for k, v in keywords.items() if k in SessionHooks.__annotations__}
    changes = {k: v for k, v in keywords.items() if k not in hooks}
    return resume(kind, log_path, ResumeOptions(**changes), **hooks)


@dataclass(frozen=True)
class Opening:
    """What the frame worked out for this process, handed to the kind's plan.

    Attributes
    ----------
    participant : str
        Checked participant id.
    seed : int
        Session seed (≥ 0).
    clock : Clock
        The session clock (s since the session started).
    virtual : bool
        True for a virtual clock (simulation).
    observer : dict or None
        The simulated observer record (sim responder only).
    device_config : Path or None
        The rig config in force.
    participant_tty : str or None
        The participant's terminal.
    responder : str
        The responder's name.
    """

    participant: str
    seed: int
    clock: Clock
    virtual: bool
    observer: dict[str, Any] | None
    device_config: Path | None
    participant_tty: str | None
    responder: str

    def context(self, kind_context: type[ContextT], **kind_fields: Any) -> ContextT:
        """The kind's responder context: the opening's part (:class:`ResponderContext`), and
        ``kind_fields``, what the kind's responders play."""
        return kind_context(
            self.participant,
            self.seed,
            self.clock,
            simulated_observer=self.observer,
            device_config=self.device_config,
            participant_tty=self.participant_tty,
            **kind_fields,
        )

    def header_fields(self) -> dict[str, Any]:
        """The fields every kind's log header takes from the opening."""
        names = ("participant", "responder", "seed", "virtual", "observer", "device_config")
        return {name: getattr(self, name) for name in names}

    def loop_fields(self, opened: Opened) -> dict[str, Any]:
        """The session loop's common fields: the opening's plus what was opened for it."""
        return {
            "participant": self.participant,
            "seed": self.seed,
            "clock": self.clock,
            **vars(opened),  # not asdict: that would deep-copy the device
        }


@dataclass(frozen=True)
class Opened:
    """What the frame opened for the session loop: device, responder, log writer, progress."""

    device: Device
    responder: Any
    writer: SessionLogWriter
    out: ProgressLine


class SessionPlan(Protocol[ResultT]):
    """One session kind's plan for one process, made before any device or window opens."""

    @property
    def experiment(self) -> str:
        """The experiment id the log's file name and header carry."""
        ...

    def context(self, opening: Opening) -> Any:
        """What the responder factory gets (the kind's context object)."""
        ...

    def check_responder(self, name: str) -> None:
        """Refuse a responder this session cannot be answered with."""
        ...

    def check_device(self, device: Device, out: ProgressLine) -> None:
        """Checks that need the opened device (limits, watchdog); raise to close it again."""
        ...

    def ask_participant(self, responder: Any, out: ProgressLine) -> None:
        """Questions asked through the opened responder before the log exists (the window's
        participant form); KeyboardInterrupt stops the start with nothing logged."""
        ...

    def header(self, opening: Opening, device: Device) -> dict[str, Any]:
        """The log header of a new session."""
        ...

    def position(self) -> tuple[str | None, int | None]:
        """Where a resumed session stopped: (set id, trial index)."""
        ...

    def resume_message(self, path: Path) -> str:
        """What to say when a resumed session continues."""
        ...

    def session(self, opening: Opening, opened: Opened) -> SessionShell[ResultT]:
        """The session loop for the trials still to run."""
        ...


class PlanDefaults:
    """What a plan does when its kind has nothing to add: no extra checks, a plain message.

    A kind's plan inherits these and overrides only what it needs (see :class:`SessionPlan`).
    """

    def check_responder(self, name: str) -> None:
        """Every responder of the kind will do."""

    def check_device(self, device: Device, out: ProgressLine) -> None:
        """The frame's checks of the opened device are enough."""

    def ask_participant(self, responder: Any, out: ProgressLine) -> None:
        """Nothing is asked through the responder."""

    def resume_message(self, path: Path) -> str:
        """``resuming <path>``."""
        return f"resuming {path}"


class SessionKind(Protocol[ResultT]):
    """A kind of session (threshold, user test): its responders and how it plans a session."""

    @property
    def responders(self) -> tuple[str, ...]:
        """The responder names the kind accepts."""
        ...

    def responder_error(self, name: str) -> str:
        """The message for an unknown responder name."""
        ...

    def default_responder(self, name: str, context: Any) -> Any:
        """Build the named responder from the plan's context."""
        ...

    def check_log(self, header: Mapping[str, Any], path: Path) -> None:
        """Refuse a log of another kind."""
        ...

    def plan_start(
        self, options: Any, participant: str, seed: int, out: ProgressLine
    ) -> SessionPlan[ResultT]:
        """Load and check everything a new session needs; nothing is opened yet."""
        ...

    def plan_resume(
        self,
        header: Mapping[str, Any],
        log: SessionLog,
        path: Path,
        options: ResumeOptions,
        out: ProgressLine,
    ) -> SessionPlan[ResultT]:
        """Rebuild the plan from the log's header and check the logged trials."""
        ...


@dataclass
class _Frame(Generic[ResultT]):
    kind: SessionKind[ResultT]
    open_device: DeviceOpener | None
    make_responder: ResponderFactory | None
    out: ProgressLine

    def open(
        self, plan: SessionPlan[ResultT], opening: Opening, spec: str
    ) -> tuple[Device, Closable]:
        return open_device_and_responder(
            self.make_responder or self.kind.default_responder,
            opening.responder,
            plan.context(opening),
            self.open_device or default_opener(opening.device_config),
            spec,
            opening.clock,
        )


def start(
    kind: SessionKind[ResultT],
    options: StartOptions,
    *,
    open_device: DeviceOpener | None = None,
    make_responder: ResponderFactory | None = None,
    stream: TextIO | None = None,
) -> ResultT:
    """Start a new session of ``kind`` and run it to its end (or its first fault).

    Parameters
    ----------
    kind : SessionKind
        The session kind (threshold or user test).
    options : StartOptions
        The kind's options (they carry the common fields).
    open_device : callable, optional
        ``(spec, clock) -> Device``; default: :func:`masking_lab.device.registry.open_device`
        with ``options.device_config``.
    make_responder : callable, optional
        ``(name, context) -> responder``; default: the kind's.
    stream : text stream, optional
        Where progress and messages go (stderr by default).

    Returns
    -------
    The kind's result (log path, exit code, message, outcomes).

    Raises
    ------
    MaskingLabError
        Bad input found before anything is played.
    """
    frame = _Frame(kind, open_device, make_responder, ProgressLine(stream, force=options.progress))
    participant = check_participant(options.participant)
    if options.responder not in kind.responders:
        raise MaskingLabError(kind.responder_error(options.responder))
    check_device_spec(options.device)
    seed = options.seed if options.seed is not None else secrets.randbits(32)
    if seed < 0:
        raise MaskingLabError(f"--seed must be ≥ 0, got {seed}")
    plan = kind.plan_start(options, participant, seed, frame.out)
    plan.check_responder(options.responder)
    # One runner per participant and protocol: a second one is refused before anything opens.
    runner = RunnerLock.acquire(Path(options.data_dir) / participant, participant, plan.experiment)
    try:
        return _start_locked(frame, plan, participant, seed, options)
    finally:
        runner.release()


def _start_locked(
    frame: _Frame[ResultT],
    plan: SessionPlan[ResultT],
    participant: str,
    seed: int,
    options: StartOptions,
) -> ResultT:
    virtual = use_virtual_clock(options.device, options.responder, options.real_time)
    opening = Opening(
        participant=participant,
        seed=seed,
        clock=VirtualClock() if virtual else RealClock(),
        virtual=virtual,
        observer=observer_record(options.ground_truth) if options.responder == "sim" else None,
        device_config=options.device_config,
        participant_tty=options.participant_tty,
        responder=options.responder,
    )
    device, responder, opening = _open_in_device_time(frame, plan, opening, options)
    with close_on_failure(device, responder):
        plan.check_device(device, frame.out)
        plan.ask_participant(responder, frame.out)  # before the log: Esc leaves nothing behind
        header = plan.header(opening, device)
        writer = create_log(
            Path(options.data_dir),
            plan.experiment,
            participant,
            header,
            sync=sync_policy(opening.virtual),
        )
    frame.out.message(f"session log: {writer.path}")
    for note in device.identity.details.get("notices", ()):  # e.g. no hardware watchdog
        frame.out.message(f"device: {note}")
    return _run(plan, opening, Opened(device, responder, writer, frame.out), options.device)


def _open_in_device_time(
    frame: _Frame[ResultT], plan: SessionPlan[ResultT], opening: Opening, options: StartOptions
) -> tuple[Device, Closable, Opening]:
    """Open the device; a simulated participant on a serial device follows the device's time.

    Whether a serial device runs in virtual time (the emulator or the host-built firmware with
    ``--virtual-time``) is known only from its HELLO. With a sim responder and no
    ``--real-time``, the session first asks for virtual time and, if the device runs in real
    time, opens it again with a real clock.
    """
    serial_sim = (
        options.device.startswith("serial:")
        and options.responder == "sim"
        and not options.real_time
    )
    if not serial_sim:
        device, responder = frame.open(plan, opening, options.device)
        return device, responder, opening
    opening = dataclasses.replace(opening, clock=VirtualClock(), virtual=True)
    try:
        device, responder = frame.open(plan, opening, options.device)
    except DeviceTimeModeError as exc:
        if exc.device_virtual:
            raise
        opening = dataclasses.replace(opening, clock=RealClock(), virtual=False)
        device, responder = frame.open(plan, opening, options.device)
    return device, responder, opening


def resume(
    kind: SessionKind[ResultT],
    log_path: str | Path,
    options: ResumeOptions,
    *,
    open_device: DeviceOpener | None = None,
    make_responder: ResponderFactory | None = None,
    stream: TextIO | None = None,
) -> ResultT:
    """Continue an interrupted session of ``kind`` where it stopped, in the same log.

    Everything but what :class:`ResumeOptions` names comes from the log's header.

    Raises
    ------
    LogError
        A finished session, a log of another kind, a header that breaks the schema, changed
        files (without ``allow_changed_protocol``), or logged trials that do not replay.
    """
    frame = _Frame(kind, open_device, make_responder, ProgressLine(stream, force=options.progress))
    path = Path(log_path)
    # Locked before it is read: a second resume of this log is refused here, before anything
    # opens. The lock passes to the writer and lives as long as the session.
    lock = LogLock.acquire(path)
    try:
        return _resume_locked(kind, frame, path, lock, options)
    finally:
        lock.release()


def _resume_locked(
    kind: SessionKind[ResultT],
    frame: _Frame[ResultT],
    path: Path,
    lock: LogLock,
    options: ResumeOptions,
) -> ResultT:
    log = read_log(path)
    if log.value_problems:  # replaying NaN or infinite levels or indices cannot be right
        raise LogError(
            f"{path}: {log.value_problems[0]}; a log holding non-finite numbers was edited or "
            "damaged and cannot be resumed: start a new session"
        )
    header = log.header
    check_header(header, path)
    kind.check_log(header, path)
    protocol = header.get("protocol")
    experiment = protocol.get("experiment") if isinstance(protocol, dict) else None
    runner = RunnerLock.acquire(path.parent, str(header["participant"]), str(experiment))
    try:
        return _resume_runner_locked(kind, frame, path, lock, options, log)
    finally:
        runner.release()


def _resume_runner_locked(
    kind: SessionKind[ResultT],
    frame: _Frame[ResultT],
    path: Path,
    lock: LogLock,
    options: ResumeOptions,
    log: SessionLog,
) -> ResultT:
    header = log.header
    refuse_finished(log, path)
    plan = kind.plan_resume(header, log, path, options, frame.out)
    refuse_damaged(log, path)  # after the kind's own replay checks, which say more
    responder_name = resume_responder_name(header, options.responder, kind.responders)
    plan.check_responder(responder_name)
    config_path = resume_device_config(options.device_config, header)
    opening = Opening(
        participant=str(header["participant"]),
        seed=int(header["seed"]),
        clock=resume_clock(header, log),
        virtual=header["clock"] == "virtual",
        observer=resume_observer(header, responder_name),
        device_config=config_path,
        participant_tty=options.participant_tty,
        responder=responder_name,
    )
    spec = check_device_spec(options.device or device_spec_from_header(header))
    device, responder = frame.open(plan, opening, spec)
    with close_on_failure(device, responder):
        plan.check_device(device, frame.out)
        writer, _ = SessionLogWriter.reopen(path, lock=lock, sync=sync_policy(opening.virtual))
    record_resume(writer, log, device.identity, frame.out, plan.position())
    frame.out.message(plan.resume_message(path))
    for note in device.identity.details.get("notices", ()):
        frame.out.message(f"device: {note}")
    return _run(plan, opening, Opened(device, responder, writer, frame.out), spec)


def _run(plan: SessionPlan[ResultT], opening: Opening, opened: Opened, spec: str) -> ResultT:
    session = plan.session(opening, opened)
    session.resume_command = resume_command(opened.writer.path, spec, opening.device_config)
    with one_blas_thread():  # a busy core must not stall a trial's placement (blas_threads)
        return session.run()
