"""Reading a session log's bytes safely: a size limit, hostile numbers, schema versions.

A log handed to ``analyze``, ``validate`` or ``resume`` may come from a colleague, a copy or an
attacker. Before anything parses it:

- its size is checked from ``fstat`` before a byte is read, and the read stops one byte past
  :data:`MAX_LOG_BYTES` (a file that grows, a sparse 2 GB file or ``/dev/zero`` cannot exhaust
  memory; a real session log is a few MB at most);
- a UTF-8 byte-order mark at the start is dropped and CRLF line ends are read like LF (a log
  opened and saved on Windows stays a log);

and while each line is decoded (:func:`loads_record`):

- an integer longer than :data:`MAX_INT_DIGITS` digits is refused (a 5,000-digit integer would
  otherwise trip Python's int-conversion limit, or overflow every float conversion after it);
- NaN, ±Infinity and floats that overflow to infinity (``1e999``) are *noted*, so the reader can
  refuse the record's set: a non-finite level is never averaged into a threshold.

:func:`check_schema_version` refuses a log written in a newer format than this version reads.
Only :func:`read_log_bytes` touches the file system.
"""

from __future__ import annotations

import json
import math
import os
import stat
from pathlib import Path
from typing import Any

import msgspec

from masking_lab.core.errors import LogError

__all__ = [
    "LOG_SCHEMA_VERSION",
    "MAX_INT_DIGITS",
    "MAX_LOG_BYTES",
    "BadNumber",
    "check_schema_version",
    "loads_record",
    "read_log_bytes",
    "strip_bom",
]

#: The session-log format this version writes and reads (``header.schema_version``).
LOG_SCHEMA_VERSION = 1
#: Largest session log read, bytes (a 3-hour real-time session is about 2 MB).
MAX_LOG_BYTES = 128 * 1024 * 1024
#: Most digits of an integer in a log record (seeds are at most 39 digits).
MAX_INT_DIGITS = 64
_BOM = b"\xef\xbb\xbf"


class BadNumber(ValueError):
    """A number in a log line that no log value can be (an integer too long to read)."""


def read_log_bytes(path: str | Path, *, max_bytes: int = MAX_LOG_BYTES) -> bytes:
    """The bytes of the log at ``path``, refusing a file larger than ``max_bytes``.

    The size is checked before reading; the read itself stops one byte past the limit.

    Raises
    ------
    LogError
        Missing, unreadable, not a regular file, or larger than the limit (naming both sizes).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "log.jsonl"
    >>> _ = p.write_bytes(b'{"record":"header"}\\n')
    >>> read_log_bytes(p)
    b'{"record":"header"}\\n'
    >>> read_log_bytes(p, max_bytes=4)
    Traceback (most recent call last):
    ...
    masking_lab.core.errors.LogError: ...: 20 bytes, more than the 4 bytes a session log ...
    """
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | os.O_CLOEXEC)
    except OSError as exc:
        raise LogError(f"{p}: cannot read session log ({exc.strerror or exc})") from exc
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise LogError(f"{p}: not a regular file; give a session log (*.jsonl)")
        if st.st_size > max_bytes:
            raise _too_large(p, st.st_size, max_bytes)
        chunks: list[bytes] = []
        total = 0
        while total <= max_bytes:
            chunk = os.read(fd, min(1 << 20, max_bytes + 1 - total))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
        if total > max_bytes:  # the file grew while being read
            raise _too_large(p, total, max_bytes)
        return b"".join(chunks)
    except OSError as exc:
        raise LogError(f"{p}: cannot read session log ({exc.strerror or exc})") from exc
    finally:
        os.close(fd)


def _too_large(p: Path, size: int, limit: int) -> LogError:
    return LogError(
        f"{p}: {size:,} bytes, more than the {limit:,} bytes a session log may have; a session "
        "log is a few MB at most: is this the right file?"
    )


def strip_bom(raw: bytes) -> bytes:
    """``raw`` without a leading UTF-8 byte-order mark.

    Examples
    --------
    >>> strip_bom(b'\\xef\\xbb\\xbf{"record":"header"}')
    b'{"record":"header"}'
    """
    return raw[len(_BOM) :] if raw.startswith(_BOM) else raw


def _parse_int(text: str) -> int:
    digits = len(text.lstrip("-"))
    if digits > MAX_INT_DIGITS:
        raise BadNumber(f"an integer of {digits} digits (at most {MAX_INT_DIGITS} in a log record)")
    return int(text)


# The fast decoder of a line that can hold neither a non-finite number (no ``NaN`` or
# ``Infinity``; msgspec refuses an overflowing float), nor an integer too long (no run of more
# than MAX_INT_DIGITS digits), nor nesting near the recursion limit (fewer than _FAST_OPEN
# brackets): msgspec's values are then json.loads' values (the same types, numbers, key order,
# last duplicate kept). Anything it refuses goes the exact way below.
_FAST = msgspec.json.Decoder()
_FAST_OPEN = 256
# A run of digits found as a run of b"0" in the line's UTF-8 bytes with 1-9 mapped to 0: a
# byte table (a quarter of the time of str.translate's dict, a third of a line's decode). Only
# ASCII digits encode to those bytes; "surrogatepass" so that no str can make it raise.
_DIGITS_AS_ZERO = bytes.maketrans(b"123456789", b"000000000")
_LONG_DIGITS = b"0" * (MAX_INT_DIGITS + 1)


def loads_record(text: str) -> tuple[Any, str | None]:
    """One JSON line decoded, and the first non-finite number in it (or None).

    A plain line is decoded by msgspec (a fifth of the time), any other by :func:`json.loads`
    with number hooks: the same value, the same errors.

    Returns
    -------
    value : Any
        The decoded JSON (NaN and infinities kept as floats, for the caller to refuse).
    non_finite : str or None
        The first non-finite number's text (``NaN``, ``-Infinity``, ``1e999``), if any.

    Raises
    ------
    json.JSONDecodeError
        Not JSON.
    BadNumber
        An integer longer than :data:`MAX_INT_DIGITS` digits.
    RecursionError
        Nested too deeply.

    Examples
    --------
    >>> loads_record('{"level_db_sl": 1e999}')
    ({'level_db_sl': inf}, '1e999')
    >>> loads_record('{"a": NaN, "b": 1}')
    ({'a': nan, 'b': 1}, 'NaN')
    """
    if (
        "NaN" not in text
        and "Infinity" not in text
        and text.count("[") + text.count("{") < _FAST_OPEN
        and _LONG_DIGITS not in text.encode("utf-8", "surrogatepass").translate(_DIGITS_AS_ZERO)
    ):
        try:
            return _FAST.decode(text), None
        except Exception:  # not JSON, an overflowing float, too deep: decoded as below
            pass
    seen: list[str] = []

    def constant(name: str) -> float:
        seen.append(name)
        return float(name.replace("Infinity", "inf"))

    def number(s: str) -> float:
        value = float(s)
        if not math.isfinite(value):
            seen.append(s)
        return value

    value = json.loads(text, parse_int=_parse_int, parse_float=number, parse_constant=constant)
    return value, (seen[0] if seen else None)


def check_schema_version(header: Any, path: str | Path) -> None:
    """Refuse a log whose header names a schema version this version does not read.

    A header without ``schema_version`` (written before it existed) is read.

    Raises
    ------
    LogError
        Naming the version found and the one read, and what to do.

    Examples
    --------
    >>> check_schema_version({"schema_version": 1}, "a.jsonl")
    >>> check_schema_version({"schema_version": 2}, "a.jsonl")
    Traceback (most recent call last):
    ...
    masking_lab.core.errors.LogError: a.jsonl: line 1: session-log schema version 2, ...
    """
    version = header.get("schema_version") if hasattr(header, "get") else None
    if version is None or (version == LOG_SCHEMA_VERSION and type(version) is int):
        return
    if type(version) is int and version > LOG_SCHEMA_VERSION:
        raise LogError(
            f"{path}: line 1: session-log schema version {version}, but this masking-lab reads "
            f"version {LOG_SCHEMA_VERSION}; the log was written by a newer masking-lab: analyse "
            "it with that version (or update this one)"
        )
    shown = json.dumps(version)[:40] if _jsonable(version) else type(version).__name__
    raise LogError(
        f"{path}: line 1: session-log schema_version {shown} is not a version this masking-lab "
        f"knows (it reads {LOG_SCHEMA_VERSION}); the header was edited or written by other "
        "software"
    )


def _jsonable(value: Any) -> bool:
    try:
        json.dumps(value)
    except (TypeError, ValueError):
        return False
    return True
