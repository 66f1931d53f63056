"""The masking_lab serial line protocol: framing, checksum, sequence numbers. Pure, no I/O.

One frame is one line of printable ASCII::

    BODY*CCCC\\n

``CCCC`` is the CRC-16/CCITT-FALSE of the BODY bytes (poly 0x1021, init 0xFFFF, no reflection,
no final xor) as four upper-case hex digits. BODY is space-separated tokens:

- command (host → device):  ``<seq> <NAME> [key=value ...]``
- reply (device → host):    ``<seq> OK [key=value ...]`` or ``<seq> ERR <CODE> <free text>``
- event (device → host):    ``!<n> <NAME> [key=value ...]`` (``n`` counts the device's events)

A reply echoes the sequence number of the command it answers; an event's leading ``!`` sets it
apart from replies. The full specification is ``docs/device-protocol.md``.
"""

from __future__ import annotations

import binascii
import itertools
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Literal

PROTOCOL_VERSION = 2
#: Oldest protocol and firmware the host talks to; anything older must be flashed first.
MIN_PROTOCOL = 2
MIN_FIRMWARE = "fw-2.0.0"
SEQ_MODULO = 65536
MAX_FRAME_BYTES = 256  # longest line either side accepts, terminator included
#: ``ERR SIZE`` text a device sends in place of a reply longer than MAX_FRAME_BYTES (the C
#: firmware's FW_SIZE_TEXT); an event that long becomes ``FAULT code=SIZE``.
SIZE_TEXT = "reply longer than 256 bytes not sent"

COMMANDS = ("HELLO", "TIME", "SETUP", "AMP", "PLAY", "STOP", "PING")
EVENTS = ("DONE", "ABORTED", "WATCHDOG", "FAULT", "BOOT")
ERROR_CODES = ("UNKNOWN", "ARGS", "LIMIT", "STATE", "BUSY", "INTERLOCK", "SIZE")

FrameKind = Literal["command", "reply", "event"]

_WORD = re.compile(r"^[A-Z][A-Z0-9_]*$")
_KEY = re.compile(r"^[a-z][a-z0-9_]*$")
# The field names of every trial's frames (PLAY, its OK and DONE): looked up, not matched.
_TRIAL_KEYS = frozenset({"tch", "tcar", "tenv", "tamp", "ti", "mch", "mcar", "menv", "mamp",
                         "stim", "gap", "lead", "n", "at", "tatt", "matt", "start", "seq", "on",
                         "end"})  # fmt: skip
_VALUE = re.compile(r"^[!-~]+$")  # printable, no space
_SEQ = re.compile(r"^(0|[1-9][0-9]{0,4})$")
_HEX4 = re.compile(r"^[0-9A-F]{4}$")
# Numbers on the wire are plain decimals (fmt_number); an exponent is tolerated, but not
# "nan", "inf", "0x10" or "1_000", which Python's float() would take.
_NUMBER = re.compile(r"^[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]{1,3})?$")
_INTEGER = re.compile(r"^(0|[1-9][0-9]{0,9})$")

#: HELLO ranges the host accepts (anything outside is a firmware bug or a foreign device).
MAX_WATCHDOG_MS = 60_000
MAX_SAMPLE_RATE_HZ = 10_000_000.0  # a HELLO's fs beyond 10 MHz is no DAC board's
MAX_LIMIT_V = 1000.0
MAX_ONSETS = 16
#: Largest device time the host accepts, s: 2**53 µs, beyond which a float64 in seconds no
#: longer holds whole microseconds (285 years of uptime: larger is a firmware bug).
MAX_DEVICE_TIME_S = 2.0**53 / 1e6
MAX_BITS = 32
RESET_CAUSES = ("pin", "watchdog", "brownout", "software", "power", "unknown")
CLOCK_SOURCES = ("hse", "hsi", "host")
_BUILD = re.compile(r"^[0-9a-f]{12}$")
# fw-X.Y.Z, an optional pre-release (-rc1: older than X.Y.Z) and build suffix (+stm32, +qemu)
_FW_VERSION = re.compile(
    r"^fw-([0-9]{1,6})\.([0-9]{1,6})\.([0-9]{1,6})(-[0-9A-Za-z.-]+)?(\+[0-9A-Za-z.-]+)?$"
)


class FrameError(ValueError):
    """A line that is not a valid frame (no checksum, bad checksum, bad tokens, too long)."""


@dataclass(frozen=True)
class Frame:
    """One decoded frame.

    Attributes
    ----------
    kind : {"command", "reply", "event"}
        Direction and role of the frame.
    seq : int
        Command sequence number (commands and replies) or device event number (events), 0–65535.
    name : str
        Command name (``PLAY``), ``OK``/``ERR`` for replies, or event name (``DONE``).
    fields : Mapping[str, str]
        ``key=value`` arguments, as text.
    code : str or None
        Error code of an ``ERR`` reply (``LIMIT``, ``ARGS``, ...).
    text : str
        Free text of an ``ERR`` reply.
    """

    kind: FrameKind
    seq: int
    name: str
    fields: Mapping[str, str] = field(default_factory=dict)
    code: str | None = None
    text: str = ""

    @property
    def ok(self) -> bool:
        """True for an ``OK`` reply."""
        return self.kind == "reply" and self.name == "OK"

    def number(self, key: str) -> float:
        """Field ``key`` as a finite float; FrameError if missing or not a number."""
        return _to_number(self._raw(key), self, key)

    def numbers(self, key: str) -> list[float]:
        """Comma-separated field ``key`` as finite floats."""
        return [_to_number(x, self, key, " list") for x in self._raw(key).split(",")]

    def integer(self, key: str, lo: int = 0, hi: int = SEQ_MODULO - 1) -> int:
        """Field ``key`` as a whole number in ``lo..hi`` (no sign, fraction or exponent)."""
        raw = self._raw(key)
        if not _INTEGER.match(raw) or not lo <= int(raw) <= hi:
            raise FrameError(
                f"{self.name} #{self.seq}: {key}={raw[:20]!r} is not a whole number in {lo}..{hi}"
            )
        return int(raw)

    def _raw(self, key: str) -> str:
        raw = self.fields.get(key)
        if raw is None:
            raise FrameError(f"{self.name} frame #{self.seq} lacks field {key!r}")
        return raw


def _to_number(raw: str, frame: Frame, key: str, what: str = "") -> float:
    if _NUMBER.match(raw):  # the common case: a plain decimal (never "nan" or "inf" text)
        value = float(raw)
        if math.isfinite(value):
            return value
    here = f"{frame.name} #{frame.seq}: {key}={raw[:20]!r}"
    if raw.strip("+-").lower() in ("nan", "inf", "infinity"):
        raise FrameError(f"{here} is not finite")
    if not _NUMBER.match(raw):
        raise FrameError(f"{here} is not a number{what}")
    value = float(raw)
    if not math.isfinite(value):
        raise FrameError(f"{here} is not finite")
    return value


# --------------------------------------------------------------------------------------------
# Typed frames: every field the host uses, validated into a value or a FrameError


@dataclass(frozen=True)
class Hello:
    """The device's HELLO reply.

    Attributes
    ----------
    version : int
        Protocol version (whole number).
    max_v : Mapping[str, float]
        The firmware's own peak limits per channel (``"EV"``, ``"MV"``), V, in (0, 1000].
    watchdog_ms : int
        Watchdog period, ms (0: none; at most :data:`MAX_WATCHDOG_MS`).
    virtual : bool
        The device runs in virtual time (``vt=1``).
    interlock_open : bool
        The interlock input is open (``il=open``).
    model, serial_number, firmware : str
        Identity, as reported (``"unknown"``/``"n/a"`` when absent).
    build : str
        Firmware source hash, 12 lower-case hex digits (``""`` before protocol 2).
    clock_source : str
        ``hse``, ``hsi`` (fallback: the crystal did not start) or ``host`` (``""`` before v2).
    reset_cause : str
        Why the board last reset: one of :data:`RESET_CAUSES` (``""`` before v2).
    bits : Mapping[str, int]
        Converter resolution per channel, bits (empty before v2).
    full_scale_v : Mapping[str, float]
        Converter full scale per channel at the amplifier input with no attenuation, peak V.
    attenuation_db : tuple of float
        Attenuator steps the board can switch, dB, ascending, first 0 (``(0.0,)`` without).
    linear_codes : Mapping[str, int]
        Per channel, the largest |code| around mid-scale the output plays without clipping
        (HELLO ``lin=EV,MV``; empty when the board does not report it: the whole converter).
    """

    version: int
    max_v: Mapping[str, float]
    watchdog_ms: int
    virtual: bool
    interlock_open: bool
    model: str
    serial_number: str
    firmware: str
    build: str = ""
    clock_source: str = ""
    reset_cause: str = ""
    bits: Mapping[str, int] = field(default_factory=dict)
    full_scale_v: Mapping[str, float] = field(default_factory=dict)
    attenuation_db: tuple[float, ...] = (0.0,)
    linear_codes: Mapping[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class Done:
    """A ``DONE`` event: PLAY ``seq`` ended; onsets and end (device s), amplitudes played (V)."""

    seq: int
    onsets_s: tuple[float, ...]
    target_v: float
    masker_v: float
    end_s: float = math.nan  # always set by parse_done (``end`` is required)


@dataclass(frozen=True)
class Aborted:
    """An ``ABORTED`` event: PLAY ``seq`` was cut short, ``why`` (a code word or ``"?"``)."""

    seq: int
    why: str


def parse_hello(frame: Frame) -> Hello:
    """Validate a HELLO reply into a :class:`Hello`.

    The protocol-2 fields (``build``, ``clk``, ``rst``, ``bits_*``, ``fsv_*``, ``att``, ``lin``) are
    checked when the reply says ``proto`` ≥ 2; an older reply parses without them so the host can
    say which firmware to flash.

    Raises
    ------
    FrameError
        A missing field, a fractional or negative version or watchdog period, a limit that is
        not in (0, 1000] V, a sample rate ``fs`` not in (0, 10 MHz], ``vt``/``il`` values other
        than ``0``/``1`` and ``open``/``closed``,
        or a protocol-2 field out of range (bits not in 1..32, a full scale not in (0, 1000] V,
        attenuation steps not ascending from 0, an unknown clock source or reset cause, a
        linear range ``lin`` that is not two whole codes within the converters).

    Examples
    --------
    >>> f = decode(encode_ok(1, {"proto": 1, "max_ev": 5.0, "max_mv": 10.0, "wd_ms": 500}))
    >>> parse_hello(f).watchdog_ms
    500
    """
    version = frame.integer("proto", 0, 65535)
    limits = {"EV": frame.number("max_ev"), "MV": frame.number("max_mv")}
    for channel, value in limits.items():
        if not 0 < value <= MAX_LIMIT_V:
            raise FrameError(
                f"HELLO: max_{channel.lower()}={value:g} V: a limit must be > 0 V and ≤ 1000 V"
            )
    watchdog_ms = frame.integer("wd_ms", 0, MAX_WATCHDOG_MS)
    if "fs" in frame.fields:  # the sample rate: the host does not use it, but a board whose
        fs = frame.number("fs")  # own rate is not a positive finite number is broken
        if not 0 < fs <= MAX_SAMPLE_RATE_HZ:
            raise FrameError(
                f"HELLO: fs={fs:g} Hz: a sample rate must be > 0 and ≤ {MAX_SAMPLE_RATE_HZ:g} Hz"
            )
    vt = frame.fields.get("vt", "0")
    il = frame.fields.get("il", "closed")
    if vt not in ("0", "1"):
        raise FrameError(f"HELLO: vt={vt[:20]!r} must be 0 or 1")
    if il not in ("open", "closed"):
        raise FrameError(f"HELLO: il={il[:20]!r} must be open or closed")
    hello = Hello(
        version=version,
        max_v=limits,
        watchdog_ms=watchdog_ms,
        virtual=vt == "1",
        interlock_open=il == "open",
        model=frame.fields.get("model", "unknown"),
        serial_number=frame.fields.get("sn", "n/a"),
        firmware=frame.fields.get("fw", "unknown"),
    )
    if version < 2:
        return hello
    return _hello_v2(frame, hello)


def _hello_v2(frame: Frame, hello: Hello) -> Hello:
    build, clk, rst = (frame._raw(k) for k in ("build", "clk", "rst"))
    if not _BUILD.match(build):
        raise FrameError(f"HELLO: build={build[:20]!r} is not 12 lower-case hex digits")
    if clk not in CLOCK_SOURCES:
        raise FrameError(f"HELLO: clk={clk[:20]!r} is not one of {', '.join(CLOCK_SOURCES)}")
    if rst not in RESET_CAUSES:
        raise FrameError(f"HELLO: rst={rst[:20]!r} is not one of {', '.join(RESET_CAUSES)}")
    bits = {ch: frame.integer(f"bits_{ch.lower()}", 1, MAX_BITS) for ch in ("EV", "MV")}
    fsv = {ch: frame.number(f"fsv_{ch.lower()}") for ch in ("EV", "MV")}
    for ch, value in fsv.items():
        if not 0 < value <= MAX_LIMIT_V:
            raise FrameError(f"HELLO: fsv_{ch.lower()}={value:g} V is not in (0, 1000] V")
    att = tuple(frame.numbers("att"))
    if att[0] != 0 or any(b <= a for a, b in itertools.pairwise(att)) or att[-1] > 200:
        raise FrameError(
            f"HELLO: att={frame._raw('att')[:40]!r} must ascend from 0 dB (at most 200 dB)"
        )
    return replace(
        hello,
        build=build,
        clock_source=clk,
        reset_cause=rst,
        bits=bits,
        full_scale_v=fsv,
        attenuation_db=att,
        linear_codes=_hello_linear(frame, bits),
    )


def _hello_linear(frame: Frame, bits: Mapping[str, int]) -> dict[str, int]:
    """HELLO ``lin=EV,MV``: whole codes in 1..2^(bits−1)−1 per channel; {} when absent."""
    if "lin" not in frame.fields:
        return {}  # firmware before the field: its converter's whole range
    raw = frame._raw("lin")
    try:
        values = [float(v) for v in raw.split(",")]
    except ValueError:
        values = []
    out: dict[str, int] = {}
    for ch, v in zip(("EV", "MV"), values, strict=False):
        top = (1 << (bits[ch] - 1)) - 1
        if math.isfinite(v) and v == int(v) and 1 <= v <= top:
            out[ch] = int(v)
    if len(values) != 2 or len(out) != 2:
        raise FrameError(
            f"HELLO: lin={raw[:40]!r} must be two whole code counts EV,MV, each in "
            f"1..2^(bits-1)-1 ({(1 << (bits['EV'] - 1)) - 1},{(1 << (bits['MV'] - 1)) - 1})"
        )
    return out


def firmware_too_old(version: int, firmware: str) -> str | None:
    """Why a board must be flashed before the host talks to it, or None if it is recent enough.

    Parameters
    ----------
    version : int
        The board's protocol version (HELLO ``proto``).
    firmware : str
        The board's firmware version (HELLO ``fw``), ``fw-X.Y.Z`` compared numerically.

    Examples
    --------
    >>> firmware_too_old(2, "fw-2.0.1") is None, firmware_too_old(2, "fw-2.0.0+stm32") is None
    (True, True)
    >>> firmware_too_old(2, "fw-2.0.0-rc1")
    'firmware fw-2.0.0-rc1 is older than fw-2.0.0'
    >>> firmware_too_old(2, "fw-1.9.10")
    'firmware fw-1.9.10 is older than fw-2.0.0'
    >>> firmware_too_old(1, "fw-2.0.0")
    'protocol version 1 is not 2'
    """
    if version != PROTOCOL_VERSION or version < MIN_PROTOCOL:
        return f"protocol version {version} is not {PROTOCOL_VERSION}"
    match = _FW_VERSION.match(firmware)
    if match is None:
        return f"firmware version {firmware[:30]!r} is not of the form fw-X.Y.Z"
    need_match = _FW_VERSION.match(MIN_FIRMWARE)
    assert need_match is not None
    have, need = (tuple(int(g) for g in m.groups()[:3]) for m in (match, need_match))
    if have < need or (have == need and match.group(4)):  # 2.0.0-rc1 precedes 2.0.0
        return f"firmware {firmware} is older than {MIN_FIRMWARE}"
    return None


def parse_time(frame: Frame) -> float:
    """The device clock of a TIME reply, s (finite, in 0..:data:`MAX_DEVICE_TIME_S`).

    Examples
    --------
    >>> parse_time(decode(encode_ok(2, {"t": 1.25})))
    1.25
    """
    t = frame.number("t")
    if t < 0:
        raise FrameError(f"TIME: t={t:g} s is negative")
    if t > MAX_DEVICE_TIME_S:
        raise FrameError(f"TIME: t={t:g} s is beyond {MAX_DEVICE_TIME_S:.4g} s (2**53 µs)")
    return t


def parse_done(frame: Frame) -> Done:
    """Validate a DONE event into a :class:`Done`.

    Examples
    --------
    >>> f = decode(encode_event(4, "DONE", {"seq": 12, "on": [1.0, 2.0, 3.0], "end": 3.2,
    ...                                      "tamp": 0.5, "mamp": 0.0}))
    >>> parse_done(f).onsets_s
    (1.0, 2.0, 3.0)
    """
    seq = frame.integer("seq")
    onsets = frame.numbers("on")
    if not 1 <= len(onsets) <= MAX_ONSETS:
        raise FrameError(f"DONE: {len(onsets)} onsets (expected 1..{MAX_ONSETS})")
    target, masker = frame.number("tamp"), frame.number("mamp")
    if not (0 <= target <= MAX_LIMIT_V and 0 <= masker <= MAX_LIMIT_V):
        raise FrameError("DONE: a played amplitude is negative or above 1000 V")
    end = frame.number("end")  # protocol 2: when the output stage finished
    for t in (*onsets, end):
        if not 0 <= t <= MAX_DEVICE_TIME_S:
            raise FrameError(f"DONE: time {t:g} s is not in 0..{MAX_DEVICE_TIME_S:.4g} s")
    return Done(seq, tuple(onsets), target, masker, end)


def parse_aborted(frame: Frame) -> Aborted:
    """Validate an ABORTED event into an :class:`Aborted`.

    Examples
    --------
    >>> parse_aborted(decode(encode_event(5, "ABORTED", {"seq": 3, "why": "STOP"}))).why
    'STOP'
    """
    why = frame.fields.get("why", "?")
    if why != "?" and not _WORD.match(why):
        raise FrameError(f"ABORTED: why={why[:20]!r} is not a code word")
    return Aborted(frame.integer("seq"), why)


def check_event(frame: Frame) -> Done | Aborted | None:
    """Validate the fields of any event the host acts on (unknown events pass: newer firmware).

    Returns the parsed DONE or ABORTED event (None for any other), so a caller needs no
    second parse.

    Raises
    ------
    FrameError
        For a DONE, ABORTED, WATCHDOG, FAULT or INTERLOCK event with a missing or malformed
        field.

    Examples
    --------
    >>> check_event(decode(encode_event(1, "WATCHDOG", {"quiet_ms": 510})))
    """
    if frame.name == "DONE":
        return parse_done(frame)
    if frame.name == "ABORTED":
        return parse_aborted(frame)
    if frame.name == "WATCHDOG" and "quiet_ms" in frame.fields:
        frame.integer("quiet_ms", 0, 10**9)
    elif frame.name == "FAULT" and not _WORD.match(frame.fields.get("code", "FRAME")):
        raise FrameError("FAULT: code is not a code word")
    elif frame.name == "INTERLOCK" and frame.fields.get("state") not in ("open", "closed"):
        raise FrameError("INTERLOCK: state must be open or closed")
    return None


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (poly 0x1021, init 0xFFFF); ``b"123456789"`` → 0x29B1."""
    return binascii.crc_hqx(data, 0xFFFF)


def next_seq(seq: int) -> int:
    """The sequence number after ``seq`` (wraps from 65535 to 0)."""
    return (seq + 1) % SEQ_MODULO


def fmt_number(x: float) -> str:
    """A number as frame text: up to 6 decimals (µs for times, µV for amplitudes), no exponent."""
    if not math.isfinite(x):
        raise FrameError(f"cannot send a non-finite number ({x!r})")
    text = f"{x:.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def encode_command(seq: int, name: str, fields: Mapping[str, object] | None = None) -> bytes:
    """Frame a host command, e.g. ``encode_command(7, "PING")`` → ``b"7 PING*XXXX\\n"``."""
    _check_seq(seq)
    if name not in COMMANDS and not _WORD.match(name):
        raise FrameError(f"bad command name {name!r}")
    if name in ("OK", "ERR"):
        raise FrameError("OK and ERR are replies, not commands")
    return _frame(f"{seq} {name}{_fields(fields)}")


def encode_ok(seq: int, fields: Mapping[str, object] | None = None) -> bytes:
    """Frame an ``OK`` reply to command ``seq``."""
    _check_seq(seq)
    return _frame(f"{seq} OK{_fields(fields)}")


def encode_err(seq: int, code: str, text: str) -> bytes:
    """Frame an ``ERR`` reply; ``text`` is made printable ASCII without ``*`` (kept readable)."""
    _check_seq(seq)
    if not _WORD.match(code):
        raise FrameError(f"bad error code {code!r}")
    clean = "".join(c if " " <= c <= "~" and c != "*" else "?" for c in text).strip()
    body = f"{seq} ERR {code} {clean}" if clean else f"{seq} ERR {code}"
    room = MAX_FRAME_BYTES - 6  # "*CCCC\n"
    return _frame(body[:room].rstrip())


def encode_event(number: int, name: str, fields: Mapping[str, object] | None = None) -> bytes:
    """Frame a device event, e.g. ``!3 DONE seq=12 on=...``."""
    _check_seq(number)
    if not _WORD.match(name):
        raise FrameError(f"bad event name {name!r}")
    return _frame(f"!{number} {name}{_fields(fields)}")


def decode(line: bytes) -> Frame:
    """Decode one line (with or without its ``\\n``; ``\\r\\n`` is tolerated).

    Raises
    ------
    FrameError
        If the line is too long, not ASCII, lacks ``*CCCC``, has a wrong CRC or bad tokens.
    """
    if len(line) > MAX_FRAME_BYTES:
        raise FrameError(f"line of {len(line)} bytes is longer than {MAX_FRAME_BYTES}")
    raw = line
    if raw.endswith(b"\n"):
        raw = raw[:-1]
        if raw.endswith(b"\r"):  # CRLF from a terminal-minded peer; a lone CR is not an ending
            raw = raw[:-1]
    star = raw.rfind(b"*")
    if star < 0:
        raise FrameError("no '*' checksum separator: not a frame")
    body, crc_text = raw[:star], raw[star + 1 :]
    try:
        text = body.decode("ascii")
        crc_str = crc_text.decode("ascii")
    except UnicodeDecodeError:
        raise FrameError("non-ASCII bytes in line") from None
    if not _HEX4.match(crc_str):
        raise FrameError(f"checksum {crc_str!r} is not four upper-case hex digits")
    if int(crc_str, 16) != crc16(body):
        raise FrameError(f"bad checksum {crc_str} (computed {crc16(body):04X})")
    if not text or not text.isprintable():  # ASCII here, so: no control characters
        raise FrameError("empty body or control characters in body")
    tokens = text.split(" ")
    if len(tokens) < 2 or "" in tokens[:2]:
        raise FrameError(f"frame {text!r} needs a sequence number and a name")
    head, name = tokens[0], tokens[1]
    kind: FrameKind
    if head.startswith("!"):
        kind, head = "event", head[1:]
    elif name in ("OK", "ERR"):
        kind = "reply"
    else:
        kind = "command"
    if not _SEQ.match(head) or int(head) >= SEQ_MODULO:
        raise FrameError(f"bad sequence number {head!r}")
    if not _WORD.match(name):
        raise FrameError(f"bad frame name {name!r}")
    seq = int(head)
    if kind == "reply" and name == "ERR":
        if len(tokens) < 3 or not _WORD.match(tokens[2]):
            raise FrameError("ERR reply without an error code")
        return Frame(kind, seq, name, {}, tokens[2], " ".join(tokens[3:]))
    fields: dict[str, str] = {}
    for tok in tokens[2:]:
        key, eq, value = tok.partition("=")
        # the body is printable ASCII split at spaces: a value matches _VALUE unless empty
        if not (eq and value and (key in _TRIAL_KEYS or _KEY.match(key))) or key in fields:
            raise FrameError(f"bad field {tok!r} in {name} frame")
        fields[key] = value
    return Frame(kind, seq, name, fields)


def _frame(body: str) -> bytes:
    data = body.encode("ascii")
    out = data + b"*" + f"{crc16(data):04X}".encode("ascii") + b"\n"
    if len(out) > MAX_FRAME_BYTES:
        raise FrameError(f"frame of {len(out)} bytes exceeds {MAX_FRAME_BYTES}: {body[:40]}...")
    return out


def _fields(fields: Mapping[str, object] | None) -> str:
    if not fields:
        return ""
    parts = []
    for key, value in fields.items():
        if key not in _TRIAL_KEYS and not _KEY.match(key):
            raise FrameError(f"bad field name {key!r}")
        if isinstance(value, float):
            parts.append(f"{key}={fmt_number(value)}")  # digits, '-' and '.': always valid
            continue
        if isinstance(value, int):  # a bool as 1 or 0; digits and '-': always valid
            parts.append(f"{key}={int(value)}")
            continue
        if isinstance(value, (list, tuple)):
            text = ",".join(fmt_number(float(v)) for v in value)
        else:
            text = str(value)
        if not _VALUE.match(text) or "*" in text:
            raise FrameError(f"field {key}={text!r} must be printable ASCII without spaces or '*'")
        parts.append(f"{key}={text}")
    return " " + " ".join(parts)


def _check_seq(seq: int) -> None:
    if not (isinstance(seq, int) and 0 <= seq < SEQ_MODULO):
        raise FrameError(f"sequence number must be an int in 0..{SEQ_MODULO - 1}, got {seq!r}")
