"""What the host makes of the firmware's fault reports: events, aborts and refusals.

Each function turns one frame from the device into the :class:`DeviceError` the session sees,
with a message that names the port and says what to check. The ``kind`` attribute set on a
:class:`DeviceFaultError` is what the runner logs as the fault's kind (``watchdog``,
``device_fault``, ``rebooted``, ``interlock``).
"""

from __future__ import annotations

from masking_lab.core.errors import (
    DeviceDisconnectedError,
    DeviceError,
    DeviceFaultError,
    DeviceProtocolError,
    DeviceTimeoutError,
    SafetyLimitError,
)
from masking_lab.device import protocol as proto

RESUME_HINT = "then `masking-lab resume LOG` to continue the session"
INTERLOCK_CHECK = (
    "check that the HV amplifier is enabled, the E-stop is released and the participant's "
    "grounding wristband is connected"
)


def _fault(message: str, kind: str) -> DeviceFaultError:
    exc = DeviceFaultError(message)
    exc.kind = kind  # type: ignore[attr-defined]  # the runner logs it as the fault's kind
    return exc


def interlock_error(port: str, what: str) -> DeviceFaultError:
    """The interlock is open: the device refuses output until it is closed.

    Parameters
    ----------
    port : str
        Serial port of the device.
    what : str
        When it was noticed (``"at HELLO"``, ``"during PLAY #7"``, ...).
    """
    return _fault(
        f"device on {port} reports its interlock open {what}, so both outputs are held at "
        f"0 V and no stimulus can play: {INTERLOCK_CHECK}; {RESUME_HINT}",
        "interlock",
    )


def event_error(port: str, frame: proto.Frame) -> DeviceError | None:
    """The fault an unsolicited event reports, or None for an event that is no fault."""
    if frame.name == "WATCHDOG":
        return _fault(
            f"device on {port} watchdog tripped: the host was quiet for "
            f"{frame.fields.get('quiet_ms', '?')} ms while an output was on, so the firmware "
            f"zeroed both outputs. Keep the host responsive (or call keepalive()); "
            f"{RESUME_HINT}",
            "watchdog",
        )
    if frame.name == "FAULT":
        return _fault(
            f"device on {port} received a corrupted command (FAULT "
            f"{frame.fields.get('code', '?')}) and zeroed both outputs: check the cable and "
            f"for electrical noise near it; {RESUME_HINT}",
            "device_fault",
        )
    if frame.name == "BOOT":
        return _fault(
            f"device on {port} rebooted (power dip or reset); its outputs are zero and "
            f"its clock restarted: check the power supply, {RESUME_HINT}",
            "rebooted",
        )
    if frame.name == "INTERLOCK" and frame.fields.get("state") == "open":
        return interlock_error(port, "(it opened during the session)")
    return None  # INTERLOCK closed, or an event from a newer firmware: harmless


def abort_error(port: str, seq: int, frame: proto.Frame) -> DeviceError:
    """The error for a trial the firmware aborted; a watchdog abort reads like the trip.

    The firmware aborts the playing trial before it reports the trip itself, so which of
    the two events the host sees first is a race: both must give the same fault.
    """
    why = frame.fields.get("why", "?")
    if why == "WATCHDOG":
        return _fault(
            f"device on {port} watchdog tripped during trial PLAY #{seq}: the host was "
            "quiet too long while an output was on, so the firmware zeroed both outputs. "
            f"Keep the host responsive; {RESUME_HINT}",
            "watchdog",
        )
    if why == "INTERLOCK":
        return interlock_error(port, f"during trial PLAY #{seq}")
    return DeviceFaultError(
        f"device on {port} aborted trial PLAY #{seq} ({why}); outputs zeroed. "
        f"Check the rig, {RESUME_HINT}"
    )


def refusal_error(port: str, name: str, frame: proto.Frame) -> DeviceError:
    """The error for an ``ERR`` reply to command ``name``."""
    text = f"device on {port} refused {name} #{frame.seq}: {frame.code} {frame.text}"
    if frame.code == "LIMIT":
        return SafetyLimitError(
            f"{text}; the firmware's limit is stricter than the host's and it zeroed both "
            "outputs: lower the level or align channels.*.max_drive_v with the firmware"
        )
    if frame.code == "INTERLOCK":
        return interlock_error(port, f"(it refused {name} #{frame.seq})")
    return DeviceError(f"{text}; both outputs were zeroed")


def malformed_error(port: str, what: str, exc: Exception) -> DeviceProtocolError:
    """A frame with a valid checksum but a missing, malformed or out-of-range field.

    Examples
    --------
    >>> str(malformed_error("/dev/ttyACM0", "TIME reply", ValueError("lacks field 't'")))[:44]
    'device on /dev/ttyACM0 sent a malformed TIME'
    """
    return DeviceProtocolError(
        f"device on {port} sent a malformed {what} (an incomplete {what} or a field out of "
        f"range: {exc}): its firmware does not follow "
        f"docs/device-protocol.md; update it, {RESUME_HINT}"
    )


def write_timeout_error(port: str, seconds: float | None) -> DeviceTimeoutError:
    """A write that stayed blocked ``seconds`` s: the board does not read the link.

    Examples
    --------
    >>> "does not read" in str(write_timeout_error("/dev/pts/3", 0.5))
    True
    """
    return DeviceTimeoutError(
        f"device on {port} does not read what the host sends (a write blocked for "
        f"{seconds or 0:.2g} s): check that the board runs masking-lab firmware and is not "
        f"stuck; {RESUME_HINT}"
    )


def no_hello_error(
    port: str, boot_s: float, last_garbage: bytes, baud_rate: int, note: str = ""
) -> DeviceError:
    """No HELLO answer within the handshake's ``boot_s`` s (chatter, or silence).

    Examples
    --------
    >>> "wrong baud rate" in str(no_hello_error("/dev/ttyUSB0", 4.0, b"$GPGGA", 115200))
    True
    """
    if last_garbage:
        return DeviceProtocolError(
            f"device on {port} sends lines that are not masking-lab frames "
            f"(e.g. {last_garbage[:40]!r}) and never answered HELLO in "
            f"{boot_s:.1f} s{note}: wrong device, wrong baud rate "
            f"(serial.baud_rate={baud_rate}) or firmware not flashed"
        )
    return DeviceTimeoutError(
        f"no answer to HELLO from {port} within {boot_s:.1f} s{note}: check that the "
        "board runs masking-lab firmware, its power and cable; a board that resets "
        "when the port opens may need a longer serial.boot_timeout_s"
    )


def garbage_error(port: str, run: int, what: str, line: bytes, why: str) -> DeviceProtocolError:
    """``run`` unframed or corrupted lines in a row while the host waited for ``what``.

    Examples
    --------
    >>> "baud rate" in str(garbage_error("/dev/ttyUSB0", 17, "HELLO", b"x", "no '*'"))
    True
    """
    return DeviceProtocolError(
        f"device on {port} sent {run} unframed or corrupted lines in a row while the host "
        f"waited for {what} (last: {line[:40]!r}, {why}): check the cable, the baud rate "
        f"(serial.baud_rate) and the firmware; {RESUME_HINT}"
    )


def disconnected_error(port: str, doing: str, exc: BaseException) -> DeviceDisconnectedError:
    """The link dropped while the host was ``doing`` something (the firmware zeroes itself).

    Examples
    --------
    >>> str(disconnected_error("/dev/ttyACM0", "reading", OSError("EIO")))[:46]
    'device on /dev/ttyACM0 disconnected while read'
    """
    return DeviceDisconnectedError(
        f"device on {port} disconnected while {doing} ({exc}): the firmware zeroes its "
        f"outputs when the link drops. Reconnect the cable, {RESUME_HINT}"
    )
