"""Error types. Every message says what went wrong, where, and what to do next."""

from __future__ import annotations


class MaskingLabError(Exception):
    """Base class for every error masking_lab raises on purpose.

    Examples
    --------
    Catch this to handle any deliberate error; value errors are also ``ValueError``:

    >>> issubclass(LevelError, MaskingLabError), issubclass(LevelError, ValueError)
    (True, True)
    """


class LevelError(MaskingLabError, ValueError):
    """A level or amplitude cannot be converted (0 V, NaN, ±inf, above the device's rating)."""


class InputError(MaskingLabError, ValueError):
    """A value given in a file, on the command line or in a form is malformed or out of range
    (a stimulus name, a channel, a participant-info answer, a cue or observer setting).

    The message names the field and what to write instead; a ``ValueError`` too, so callers that
    check values with ``except ValueError`` keep working.

    Examples
    --------
    >>> issubclass(InputError, ValueError)
    True
    """


class ProtocolError(MaskingLabError):
    """A protocol, scene or config file is malformed.

    Parameters
    ----------
    file : str
        Path of the offending file.
    where : str
        Key path (``staircase.n_down``) or ``line N`` locating the problem.
    message : str
        What is wrong and how to fix it.

    Examples
    --------
    >>> str(ProtocolError("exp1.yaml", "staircase.n_down", "must be an integer ≥ 1"))
    'exp1.yaml: staircase.n_down: must be an integer ≥ 1'
    """

    def __init__(self, file: str, where: str, message: str) -> None:
        self.file = str(file)
        self.where = where
        self.message = message
        super().__init__(f"{self.file}: {where}: {message}" if where else f"{self.file}: {message}")


class ProcedureError(MaskingLabError, ValueError):
    """Invalid settings of an adaptive procedure (staircase, QUEST+, functional ramp), or a
    response given to a finished track.

    The common base of every procedure's errors: catch it to handle any of them.

    Examples
    --------
    >>> issubclass(StaircaseError, ProcedureError), issubclass(ProcedureError, StaircaseError)
    (True, False)
    """


class StaircaseError(ProcedureError):
    """Invalid staircase settings (steps, stop rule, down/up ratio) or a response given to a
    finished staircase; a :class:`ProcedureError` like every other procedure's."""


class DeviceError(MaskingLabError):
    """The device failed: unplugged, timed out, sent garbage, or refused a command."""


class DeviceTimeModeError(DeviceError):
    """The device runs in the other time mode (virtual or real) than the session clock.

    Attributes
    ----------
    device_virtual : bool
        True if the device reported virtual time (HELLO ``vt=1``).
    """

    def __init__(self, message: str, *, device_virtual: bool) -> None:
        super().__init__(message)
        self.device_virtual = device_virtual


class SafetyLimitError(DeviceError):
    """A requested amplitude exceeds the device's configured limit; nothing was played."""


class ResponderError(MaskingLabError):
    """The participant's terminal or window failed (not a terminal, closed, no display).

    Not a :class:`DeviceError` (the rig is fine), but handled alike: the session zeroes the
    outputs, logs a ``responder`` fault and exits 3, and can be resumed.
    """


class LogError(MaskingLabError):
    """A session log is unreadable, truncated or inconsistent with its protocol."""


class LogLockedError(LogError):
    """Another process (``run`` or ``resume``) holds the session log's lock."""


class LogWriteError(LogError):
    """Writing or syncing a session-log record failed (disk full, I/O error)."""


class CalibrationError(MaskingLabError):
    """A participant's calibration (unmasked ALs) is missing or incomplete."""


class AnalysisError(MaskingLabError):
    """The data cannot support the requested analysis (missing cells, one participant, ...)."""


class OutputFolderError(MaskingLabError):
    """An output folder cannot be replaced safely (a file, holds inputs or foreign files)."""


class SolverError(MaskingLabError, ValueError):
    """The inverse-rendering problem is ill-posed for the given parameters or targets."""


# Device faults (added with the device layer). Each is a DeviceError, so callers that only care
# that "the device failed" can catch that; the runner records the subclass name in its log.


class DeviceTimeoutError(DeviceError):
    """The device stopped answering: no reply (or no end-of-trial report) within its timeout."""


class DeviceDisconnectedError(DeviceError):
    """The serial link went away (cable unplugged, board reset, port closed by the other side)."""


class DeviceProtocolError(DeviceError):
    """The device sent garbage or corrupted frames, or speaks another protocol version."""


class DeviceFaultError(DeviceError):
    """The device reported a fault of its own (watchdog trip, corrupted command) and zeroed."""


class DeviceConfigError(ProtocolError):
    """A device (rig) config file is malformed; the message names the file and the key."""
