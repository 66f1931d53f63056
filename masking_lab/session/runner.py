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

import functools
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from masking_lab.core.errors import (
    LogError,
    MaskingLabError,
)
from masking_lab.device.base import Device
from masking_lab.device.rig_limits import max_level_db_sl
from masking_lab.formats.calibration import load_calibration
from masking_lab.formats.protocol import ThresholdProtocol, parse_protocol
from masking_lab.formats.reader import read_limited
from masking_lab.formats.session_log import SessionLog, SetRecords
from masking_lab.responders.base import Responder
from masking_lab.session import frame
from masking_lab.session.header import session_header
from masking_lab.session.opening import DeviceOpener, ResponderContext
from masking_lab.session.progress import ProgressLine

# EXIT_* and the signal classes were public here first; the noqa lines re-export them.
from masking_lab.session.shell import (
    EXIT_COMPLETED,  # noqa: F401
    EXIT_DEVICE_FAULT,  # noqa: F401
    EXIT_INTERRUPTED,  # noqa: F401
    SessionInterrupted,  # noqa: F401
    SessionSignals,  # noqa: F401
)
from masking_lab.session.threshold_loop import SessionResult, ThresholdSession
from masking_lab.session.threshold_plan import (
    check_trials,
    checked_calibration,
    position,
    protocol_from_header,
    select_sets,
)
from masking_lab.simulation.observer import make_participant

RESPONDERS = ("sim", "keys", "psychopy")


# --------------------------------------------------------------------------------------------
# Public values


@dataclass(frozen=True)
class RunOptions(frame.SessionOptions):
    """What ``masking-lab run`` was asked to do with a threshold protocol.

    The fields of :class:`~masking_lab.session.frame.SessionOptions`, and:

    Attributes
    ----------
    protocol : Path
        Protocol YAML file.
    participant : str
        Participant id (letters, digits, ``_ - .``); names the data sub-folder.
    device : str
        ``sim``, ``emulator``, ``serial:PORT`` or ``nidaq[:DEV]``.
    responder : {"sim", "keys", "psychopy"}
        Who answers.
    sets : tuple[str, ...] or None
        Subset of set ids to run (in the seed's order), or None for all.
    info : mapping of str to str
        Participant metadata as typed (``--info key=value``), checked against the protocol's
        ``info`` section (:mod:`masking_lab.session.participant_info`); on a terminal the
        missing fields are asked for.
    """

    protocol: Path
    participant: str
    device: str = "sim"
    responder: str = "sim"
    sets: tuple[str, ...] | None = None
    info: Mapping[str, str] = field(default_factory=dict)


@dataclass
class SessionContext(ResponderContext):
    """What a threshold responder factory may need (see :class:`ResponderContext`).

    Attributes
    ----------
    protocol : ThresholdProtocol
        The protocol being run.
    """

    protocol: ThresholdProtocol


# --------------------------------------------------------------------------------------------
# Entry points


def run_session(
    options: RunOptions,
    *,
    open_device: DeviceOpener | None = None,
    make_responder: frame.ResponderFactory | None = None,
    stream: TextIO | None = None,
) -> SessionResult:
    """Run a protocol for one participant and write a new session log.

    Parameters
    ----------
    options : RunOptions
        What to run.
    open_device, make_responder, stream
        The hooks of :func:`masking_lab.session.frame.start`.

    Raises
    ------
    MaskingLabError
        Bad input found before anything is played: protocol, participant id, unknown set ids,
        missing calibration, unknown responder, unreadable ground truth.
    """
    return frame.start(
        THRESHOLD, options, open_device=open_device, make_responder=make_responder, stream=stream
    )


def resume_session(
    log_path: str | Path,
    options: frame.SessionOptions | None = None,
    *,
    open_device: DeviceOpener | None = None,
    make_responder: frame.ResponderFactory | None = None,
    stream: TextIO | None = None,
) -> SessionResult:
    """Continue an interrupted session exactly where it stopped, in the same log.

    The protocol, calibration, seed, set order, clock kind and responder come from the log's
    header, never from files that may have changed since. Each started set is rebuilt by
    replaying its logged responses; the rebuilt levels must equal the logged ones.

    Parameters
    ----------
    log_path : path
        The session log (``DATA/<participant>/<experiment>-<participant>-<UTC>.jsonl``).
    options : SessionOptions, optional
        What the resume changes (device, responder, rig config, ...).
    open_device, make_responder, stream
        The hooks of :func:`masking_lab.session.frame.start`.

    Raises
    ------
    LogError
        Finished session, protocol file changed (without ``allow_changed_protocol``), a header
        that breaks the schema, or logged trials that do not replay to their logged levels.
    """
    return frame.resume(
        THRESHOLD,
        log_path,
        options,
        open_device=open_device,
        make_responder=make_responder,
        stream=stream,
    )


class ThresholdKind:
    """Threshold sessions (baseline and masked protocols) in the session frame."""

    responders = RESPONDERS

    def default_responder(self, name: str, context: SessionContext) -> Responder:
        return _default_responder(name, context)

    def check_log(self, header: Mapping[str, Any], path: Path) -> None:
        if header.get("kind", "threshold") != "threshold":
            raise LogError(
                f"{path}: a {header.get('kind')} log, not a threshold session; resume it with "
                "`masking-lab resume`, which picks the right session kind"
            )

    def plan_start(
        self, options: RunOptions, participant: str, seed: int, out: ProgressLine
    ) -> _ThresholdPlan:
        protocol = load_protocol_once(options.protocol, max_level_db_sl(options.device_config))
        order = select_sets(protocol, protocol.set_order(seed), options.sets)
        data_dir = Path(options.data_dir)
        calibration = checked_calibration(
            protocol, order, data_dir, participant, options.device_config
        )
        info, pending = _participant_info(protocol, options.info, options.responder)
        return _ThresholdPlan(
            protocol, data_dir, order, calibration, {}, (None, None), info, pending
        )

    def plan_resume(
        self,
        header: Mapping[str, Any],
        log: SessionLog,
        path: Path,
        options: frame.SessionOptions,
        out: ProgressLine,
    ) -> _ThresholdPlan:
        protocol = protocol_from_header(header, path, options.allow_changed_protocol, out)
        existing = log.sets()
        check_trials(path, protocol, existing)
        if protocol.kind == "baseline":  # its ALs go into this file: refuse a broken one now
            load_calibration(path.parent.parent, str(header["participant"]))
        return _ThresholdPlan(
            protocol,
            path.parent.parent,
            [str(s) for s in header["set_order"]],
            {k: float(v) for k, v in header["calibration"].items()},
            existing,
            position(log),
        )


def load_protocol_once(path: str | Path, max_level_db_sl: Mapping[str, float]) -> ThresholdProtocol:
    """``load_protocol(path, max_level_db_sl=...)``, each distinct file content parsed once.

    The file is read every time; only parsing and validating the same bytes again is skipped
    (a demo worker runs the same three protocols in turn: ~6 ms of CPU a session otherwise).

    Parameters
    ----------
    path : str or Path
        The protocol's YAML file.
    max_level_db_sl : mapping of channel → dB SL
        The rig's highest sensation levels (:func:`~masking_lab.device.rig_limits.max_level_db_sl`).

    Returns
    -------
    ThresholdProtocol
        Frozen; the same object for the same bytes, source and limits.

    Raises
    ------
    ProtocolError
        As :func:`~masking_lab.formats.protocol.load_protocol` (a refusal is never kept).

    Examples
    --------
    >>> from masking_lab.formats.resources import shipped
    >>> path = str(shipped("protocols", "baseline.yaml"))
    >>> load_protocol_once(path, {}) is load_protocol_once(path, {})
    True
    """
    p = Path(path)
    limits = tuple(max_level_db_sl.items())
    return _parsed_protocol(read_limited(p, what="file"), str(p), limits)


@functools.lru_cache(maxsize=16)
def _parsed_protocol(
    raw: bytes, source: str, limits: tuple[tuple[str, float], ...]
) -> ThresholdProtocol:
    return parse_protocol(raw, source, max_level_db_sl=dict(limits))


def _participant_info(
    protocol: ThresholdProtocol, given: Mapping[str, str], responder: str
) -> tuple[dict[str, Any], tuple[list[Any], dict[str, str]] | None]:
    """The protocol's ``info`` fields: ``--info`` values, the missing ones asked on a terminal.

    With the PsychoPy window the missing ones are asked in the window once it is open: the
    given values are checked now (a typo is refused before anything opens) and the fields with
    them are returned as pending.
    """
    import sys

    from masking_lab.session.participant_info import ask_missing, info_fields, resolve_info

    fields = info_fields(protocol.content)
    source = str(protocol.path)
    if responder == "psychopy" and any(not given.get(f.name, "").strip() for f in fields):
        return resolve_info(fields, given, source, require=False), (fields, dict(given))
    if fields and sys.stdin is not None and sys.stdin.isatty():
        given = ask_missing(fields, given)
    return resolve_info(fields, given, source), None


@dataclass
class _ThresholdPlan(frame.SessionPlan[SessionResult]):
    """A threshold session's plan for this process (see :class:`frame.SessionPlan`)."""

    protocol: ThresholdProtocol
    data_dir: Path
    order: list[str]
    calibration: dict[str, float]
    existing: Mapping[str, SetRecords]
    stopped_at: tuple[str | None, int | None]
    info: Mapping[str, Any] = field(default_factory=dict)
    # (fields, --info values) still to ask in the participant's window, or None
    info_in_window: tuple[list[Any], dict[str, str]] | None = None

    @property
    def experiment(self) -> str:
        return self.protocol.experiment

    def ask_participant(self, responder: Any, out: ProgressLine) -> None:
        if self.info_in_window is None:
            return
        from masking_lab.session.participant_info import resolve_info

        fields, given = self.info_in_window
        ask = getattr(responder, "ask_info", None)
        if ask is not None:
            out.message("participant information: asked in the participant window (Esc stops)")
            try:
                given = ask(fields, given)
            except KeyboardInterrupt:
                out.message("stopped in the participant form: nothing was played or logged")
                raise
        self.info = resolve_info(fields, given, str(self.protocol.path))
        self.info_in_window = None

    def context(self, opening: frame.Opening) -> SessionContext:
        return opening.context(SessionContext, protocol=self.protocol)

    def header(self, opening: frame.Opening, device: Device) -> dict[str, Any]:
        return session_header(
            source=self.protocol,
            calibration=self.calibration,
            device=device.identity,
            order=self.order,
            **opening.header_fields(),
            **self._info_field(),
        )

    def _info_field(self) -> dict[str, Any]:
        return {"info": dict(self.info)} if self.info else {}

    def position(self) -> tuple[str | None, int | None]:
        return self.stopped_at

    def session(self, opening: frame.Opening, opened: frame.Opened) -> ThresholdSession:
        return ThresholdSession(
            protocol=self.protocol,
            data_dir=self.data_dir,
            order=self.order,
            calibration=self.calibration,
            existing=self.existing,
            **opening.loop_fields(opened),
        )


THRESHOLD = ThresholdKind()


# --------------------------------------------------------------------------------------------
# Defaults for devices and responders


def _default_responder(name: str, context: SessionContext) -> Responder:
    if name == "sim":
        from masking_lab.responders.sim import SimResponder

        truth, population_seed, source = context.simulated_truth()
        participant = make_participant(truth, context.participant, population_seed)
        return SimResponder(participant, context.seed, source)
    if name == "keys":
        from masking_lab.responders.keys import KeyReader, KeysResponder

        return KeysResponder(KeyReader.on_terminal(context.participant_tty))
    if name == "psychopy":
        from masking_lab.responders import psychopy_window

        return psychopy_window.make_responder(context)
    raise MaskingLabError(f"responder {name!r}: choose one of {', '.join(RESPONDERS)}")


# --------------------------------------------------------------------------------------------
# Records and checks
