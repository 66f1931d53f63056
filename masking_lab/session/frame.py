"""The one session frame: how every kind of session starts and resumes.

A threshold session (:mod:`masking_lab.session.runner`) and a user test
(:mod:`masking_lab.usertest.runner`) differ in what they play, not in how a session is framed.
:func:`start` and :func:`resume` hold that frame once: participant id, responder and device
checks, the seed, the clock kind (virtual in simulation, real at the rig), the simulated
observer, opening the responder and the device (closing what is open if a later step fails),
creating or reopening the fsynced log, the resume records, and finally the kind's session loop.

The public surface is four types and two functions: :class:`SessionOptions` (what both ``run``
and ``resume`` are given; a kind's options extend it), :class:`SessionKind` (what to check and
prepare before anything opens), the :class:`SessionPlan` it returns (responder context, checks of
the opened device, the log header, the loop) with :class:`Opening` and :class:`Opened` handed to
it. docs/architecture.md has a worked example of a kind.

Bad input raises a :class:`~masking_lab.core.errors.MaskingLabError` before anything is played;
once the loop runs, every stop is a log record and an exit code in the result.
"""

from __future__ import annotations

import dataclasses
import secrets
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, TextIO, TypeVar

from masking_lab.core.blas_threads import one_blas_thread
from masking_lab.core.clock import Clock, RealClock, VirtualClock
from masking_lab.core.errors import DeviceTimeModeError, LogError, MaskingLabError
from masking_lab.device import registry
from masking_lab.device.base import Device
from masking_lab.formats.log_lock import LogLock, RunnerLock
from masking_lab.formats.session_log import SessionLog, SessionLogWriter, read_log
from masking_lab.session.opening import (
    DeviceOpener,
    ResponderContext,
    check_device_spec,
    check_participant,
    close_on_failure,
    create_log,
    observer_record,
    sync_policy,
    use_virtual_clock,
)
from masking_lab.session.priority import placement_priority_note
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
    "SessionKind",
    "SessionOptions",
    "SessionPlan",
    "resume",
    "start",
]

ResultT = TypeVar("ResultT")
OptionsT = TypeVar("OptionsT", bound="SessionOptions")
OptionsT_contra = TypeVar("OptionsT_contra", bound="SessionOptions", contravariant=True)
ContextT = TypeVar("ContextT", bound=ResponderContext)
ResponderFactory = Callable[[str, Any], Any]


@dataclass(frozen=True)
class SessionOptions:
    """What a session is started or resumed with; each kind's options extend it.

    A new session reads every field. A resumed one takes the rest from its log's header and
    reads only ``device``, ``responder``, ``device_config``, ``participant_tty``, ``progress``
    and ``allow_changed_protocol`` (None: the header's).

    Attributes
    ----------
    protocol : Path or None
        The protocol file of a new session (a resume uses the log's copy).
    participant : str
        Participant id (letters, digits, ``_ - .``); names the data sub-folder.
    device : str or None
        ``sim``, ``emulator``, ``serial:PORT`` or ``nidaq[:DEV]``; None: ``sim`` for a new
        session, the log's back-end on resume (``serial`` needs the port again).
    responder : str or None
        ``sim``, ``keys`` or ``psychopy``; None: ``sim`` for a new session, the log's on resume.
    data_dir : Path
        Data folder; logs go to ``data_dir/<participant>/``.
    seed : int or None
        Session seed (drawn and logged when None).
    real_time : bool
        Use the real clock even with a simulated responder.
    ground_truth : Path or None
        Ground truth of the simulated responder (None: the packaged default).
    device_config : Path or None
        Rig config (None: the packaged reference rig; on resume, required again if the session
        started with one).
    progress : bool or None
        Force the progress line on or off (None: on a terminal only).
    participant_tty : str or None
        With the keys responder: the participant's terminal (None: this one).
    allow_changed_protocol : bool
        Resume although the protocol or scene files changed (the logged copies are used).

    Examples
    --------
    >>> SessionOptions(device="emulator").responder is None
    True
    """

    protocol: Path | None = None
    participant: str = ""
    device: str | None = None
    responder: str | None = None
    data_dir: Path = Path("data")
    seed: int | None = None
    real_time: bool = False
    ground_truth: Path | None = None
    device_config: Path | None = None
    progress: bool | None = None
    participant_tty: str | None = None
    allow_changed_protocol: bool = False


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
    """One session kind's plan for one process, made before any device or window opens.

    A plan subclasses this protocol to inherit the defaults (no extra checks, a plain resume
    message) and defines ``experiment``, :meth:`context`, :meth:`header`, :meth:`position` and
    :meth:`session`.
    """

    @property
    def experiment(self) -> str:
        """The experiment id the log's file name and header carry."""
        ...

    def context(self, opening: Opening) -> Any:
        """What the responder factory gets (the kind's context object)."""
        ...

    def header(self, opening: Opening, device: Device) -> dict[str, Any]:
        """The log header of a new session."""
        ...

    def position(self) -> tuple[str | None, int | None]:
        """Where a resumed session stopped: (set id, trial index)."""
        ...

    def session(self, opening: Opening, opened: Opened) -> SessionShell[ResultT]:
        """The session loop for the trials still to run."""
        ...

    def check_responder(self, name: str) -> None:
        """Refuse a responder this session cannot be answered with (default: none refused)."""
        return None  # a default, not an abstract method

    def check_device(self, device: Device, out: ProgressLine) -> None:
        """Checks that need the opened device (limits, watchdog); raise to close it again."""
        return None  # a default, not an abstract method

    def ask_participant(self, responder: Any, out: ProgressLine) -> None:
        """Questions asked through the opened responder before the log exists (the window's
        participant form); KeyboardInterrupt stops the start with nothing logged."""
        return None  # a default, not an abstract method

    def resume_message(self, path: Path) -> str:
        """What to say when a resumed session continues (default: ``resuming <path>``)."""
        return f"resuming {path}"


class SessionKind(Protocol[OptionsT_contra, ResultT]):
    """A kind of session (threshold, user test): its responders and how it plans a session."""

    @property
    def responders(self) -> tuple[str, ...]:
        """The responder names the kind accepts."""
        ...

    def default_responder(self, name: str, context: Any) -> Any:
        """Build the named responder from the plan's context."""
        ...

    def check_log(self, header: Mapping[str, Any], path: Path) -> None:
        """Refuse a log of another kind."""
        ...

    def plan_start(
        self, options: OptionsT_contra, participant: str, seed: int, out: ProgressLine
    ) -> SessionPlan[ResultT]:
        """Load and check everything a new session needs; nothing is opened yet."""
        ...

    def plan_resume(
        self,
        header: Mapping[str, Any],
        log: SessionLog,
        path: Path,
        options: SessionOptions,
        out: ProgressLine,
    ) -> SessionPlan[ResultT]:
        """Rebuild the plan from the log's header and check the logged trials."""
        ...


def start(
    kind: SessionKind[OptionsT, ResultT],
    options: OptionsT,
    *,
    open_device: DeviceOpener | None = None,
    make_responder: ResponderFactory | None = None,
    stream: TextIO | None = None,
) -> ResultT:
    """Start a new session of ``kind`` and run it to its end (or its first fault).

    Parameters
    ----------
    kind : SessionKind
        The session kind (threshold, user test).
    options : SessionOptions
        The kind's options.
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

    Examples
    --------
    >>> from masking_lab.session.runner import THRESHOLD, RunOptions
    >>> start(THRESHOLD, RunOptions(Path("p.yaml"), "S 01"))
    Traceback (most recent call last):
    masking_lab.core.errors.MaskingLabError: --participant 'S 01': use letters, ...
    """
    out = ProgressLine(stream, force=options.progress)
    participant = check_participant(options.participant)
    responder = options.responder or "sim"
    if responder not in kind.responders:
        raise MaskingLabError(
            f"--responder {responder!r}: choose one of {', '.join(kind.responders)}"
        )
    device_spec = check_device_spec(options.device or "sim")
    seed = options.seed if options.seed is not None else secrets.randbits(32)
    if seed < 0:
        raise MaskingLabError(f"--seed must be ≥ 0, got {seed}")
    plan = kind.plan_start(options, participant, seed, out)
    plan.check_responder(responder)
    virtual = use_virtual_clock(device_spec, responder, options.real_time)
    opening = Opening(
        participant=participant,
        seed=seed,
        clock=VirtualClock() if virtual else RealClock(),
        virtual=virtual,
        observer=observer_record(options.ground_truth) if responder == "sim" else None,
        device_config=options.device_config,
        participant_tty=options.participant_tty,
        responder=responder,
    )
    opener = _Opener(kind, open_device, make_responder, plan, device_spec)
    # One runner per participant and protocol: a second one is refused before anything opens.
    runner = RunnerLock.acquire(Path(options.data_dir) / participant, participant, plan.experiment)
    try:
        device, responder_obj, opening = opener.open_in_device_time(opening, options.real_time)
        with close_on_failure(device, responder_obj):
            plan.check_device(device, out)
            plan.ask_participant(responder_obj, out)  # before the log: Esc leaves nothing behind
            writer = create_log(
                Path(options.data_dir),
                plan.experiment,
                participant,
                plan.header(opening, device),
                sync=sync_policy(opening.virtual),
            )
        out.message(f"session log: {writer.path}")
        return _run(plan, opening, Opened(device, responder_obj, writer, out), device_spec)
    finally:
        runner.release()


@dataclass(frozen=True)
class _Opener:
    """Opens the responder and the device of one session (the hooks or the kind's defaults)."""

    kind: SessionKind[Any, Any]
    open_device: DeviceOpener | None
    make_responder: ResponderFactory | None
    plan: SessionPlan[Any]
    spec: str

    def open(self, opening: Opening) -> tuple[Device, Closable]:
        """Build the responder, then open the device; close the responder if that fails."""
        make = self.make_responder or self.kind.default_responder
        responder = make(opening.responder, self.plan.context(opening))
        try:
            if self.open_device is not None:
                return self.open_device(self.spec, opening.clock), responder
            return registry.open_device(self.spec, opening.device_config, opening.clock), responder
        except BaseException:
            responder.close()
            raise

    def open_in_device_time(
        self, opening: Opening, real_time: bool
    ) -> tuple[Device, Closable, Opening]:
        """Open; a simulated participant on a serial device follows the device's time.

        Whether a serial device runs in virtual time (the emulator or the host-built firmware
        with ``--virtual-time``) is known only from its HELLO. With a sim responder and no
        ``--real-time``, the session first asks for virtual time and, if the device runs in
        real time, opens it again with a real clock.
        """
        if not (self.spec.startswith("serial:") and opening.responder == "sim" and not real_time):
            return (*self.open(opening), opening)
        opening = dataclasses.replace(opening, clock=VirtualClock(), virtual=True)
        try:
            return (*self.open(opening), opening)
        except DeviceTimeModeError as exc:
            if exc.device_virtual:
                raise
        opening = dataclasses.replace(opening, clock=RealClock(), virtual=False)
        return (*self.open(opening), opening)


def resume(
    kind: SessionKind[Any, ResultT],
    log_path: str | Path,
    options: SessionOptions | None = None,
    *,
    open_device: DeviceOpener | None = None,
    make_responder: ResponderFactory | None = None,
    stream: TextIO | None = None,
) -> ResultT:
    """Continue an interrupted session of ``kind`` where it stopped, in the same log.

    Everything but what :class:`SessionOptions` lets a resume change comes from the log's
    header; the hooks are those of :func:`start`.

    Raises
    ------
    LogError
        A finished session, a log of another kind, a header that breaks the schema, changed
        files (without ``allow_changed_protocol``), or logged trials that do not replay.

    Examples
    --------
    >>> from masking_lab.session.runner import THRESHOLD
    >>> resume(THRESHOLD, "no-such-log.jsonl")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    masking_lab.core.errors.LogError: no-such-log.jsonl: cannot read session log ...
    """
    options = options or SessionOptions()
    out = ProgressLine(stream, force=options.progress)
    path = Path(log_path)
    # Locked before it is read: a second resume of this log is refused here, before anything
    # opens. The lock passes to the writer and lives as long as the session.
    lock = LogLock.acquire(path)
    try:
        log = read_log(path)
        if log.value_problems:  # replaying NaN or infinite levels or indices cannot be right
            raise LogError(
                f"{path}: {log.value_problems[0]}; a log holding non-finite numbers was edited "
                "or damaged and cannot be resumed: start a new session"
            )
        check_header(log.header, path)
        kind.check_log(log.header, path)
        protocol = log.header.get("protocol")
        experiment = protocol.get("experiment") if isinstance(protocol, dict) else None
        runner = RunnerLock.acquire(path.parent, str(log.header["participant"]), str(experiment))
        try:
            hooks = (open_device, make_responder)
            return _resume_locked(kind, hooks, log, path, lock, options, out)
        finally:
            runner.release()
    finally:
        lock.release()


def _resume_locked(
    kind: SessionKind[Any, ResultT],
    hooks: tuple[DeviceOpener | None, ResponderFactory | None],
    log: SessionLog,
    path: Path,
    lock: LogLock,
    options: SessionOptions,
    out: ProgressLine,
) -> ResultT:
    header = log.header
    refuse_finished(log, path)
    plan = kind.plan_resume(header, log, path, options, out)
    refuse_damaged(log, path)  # after the kind's own replay checks, which say more
    responder_name = resume_responder_name(header, options.responder, kind.responders)
    plan.check_responder(responder_name)
    opening = Opening(
        participant=str(header["participant"]),
        seed=int(header["seed"]),
        clock=resume_clock(header, log),
        virtual=header["clock"] == "virtual",
        observer=resume_observer(header, responder_name),
        device_config=resume_device_config(options.device_config, header),
        participant_tty=options.participant_tty,
        responder=responder_name,
    )
    spec = check_device_spec(options.device or device_spec_from_header(header))
    device, responder = _Opener(kind, *hooks, plan, spec).open(opening)
    with close_on_failure(device, responder):
        plan.check_device(device, out)
        writer, _ = SessionLogWriter.reopen(path, lock=lock, sync=sync_policy(opening.virtual))
    record_resume(writer, log, device.identity, out, plan.position())
    out.message(plan.resume_message(path))
    return _run(plan, opening, Opened(device, responder, writer, out), spec)


def _run(plan: SessionPlan[ResultT], opening: Opening, opened: Opened, spec: str) -> ResultT:
    for note in opened.device.identity.details.get("notices", ()):  # e.g. no hardware watchdog
        opened.out.message(f"device: {note}")
    if not opening.virtual:  # a participant waits for each placement (session/priority.py)
        opened.out.message(placement_priority_note())
    session = plan.session(opening, opened)
    session.resume_command = resume_command(opened.writer.path, spec, opening.device_config)
    with one_blas_thread():  # a busy core must not stall a trial's placement (core/blas_threads)
        return session.run()
