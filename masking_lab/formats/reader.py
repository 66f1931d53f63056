"""The one reader every YAML/JSON input file goes through (protocol, rig config, ground truth,
scene, user test, calibration, masking params).

A file from a participant folder, a colleague or a crafted log is untrusted input. This module
turns its bytes into plain data (dicts, lists, str, int, float, bool, None) or a clean error
that names the file, the key path and the line, and never more than a short sanitised excerpt
of the offending input. It refuses, before anything else reads the data:

- files larger than :data:`MAX_BYTES` (read stops one byte past the limit, so ``/dev/zero``
  cannot exhaust memory);
- bytes that are not UTF-8 (the line and column of the first bad byte are named);
- YAML documents whose aliases (``*name``) expand to more than :data:`MAX_NODES` values: an
  alias bomb of a few hundred bytes would otherwise expand to gigabytes wherever the data is
  walked (anchors and merge keys within that budget are fine);
- nesting deeper than :data:`MAX_DEPTH` (deep nesting otherwise raises ``RecursionError``);
- duplicate keys in one mapping (YAML and JSON would silently keep the last), with their line;
- tags that build anything but plain data (``!!python/...``, ``!!binary``, ``!!set``), and
  non-text keys;
- NaN and infinities, and integers too large for a float, where a finite number is meant
  (every number in these files), with the key path and line.

Pure: :func:`parse_yaml`, :func:`parse_json` and :func:`decode_utf8` work on text or bytes;
only :func:`read_limited` and :func:`load_document` touch the file system.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import stat
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from masking_lab.core.errors import ProtocolError

#: Largest input file accepted, bytes (the biggest shipped file is a few kB).
MAX_BYTES = 4 * 1024 * 1024
#: Deepest nesting of mappings and lists accepted (shipped files nest at most 4 deep).
MAX_DEPTH = 32
#: Most values (scalars, mappings, lists) a YAML document may hold with its aliases expanded.
MAX_NODES = 50_000
#: Longest excerpt of user input quoted in an error message, characters.
EXCERPT_CHARS = 40

#: Builds the error a loader raises from (file, where, message); ``ProtocolError`` by default.
ErrorFactory = Callable[[str, str, str], Exception]

_PLAIN_TAGS = frozenset(
    "tag:yaml.org,2002:" + t for t in ("str", "int", "float", "bool", "null", "map", "seq")
)
_MERGE = "tag:yaml.org,2002:merge"


@dataclass(frozen=True)
class Document:
    """A parsed input file.

    Attributes
    ----------
    data : Any
        Plain data: dict, list, str, int, float (finite), bool or None.
    lines : Mapping[str, int]
        Key path (``sets[2].masker``) → 1-based line where it stands.
    sha256 : str
        Hex digest of the file's bytes.
    source : str
        The file's name as given (used in messages).
    """

    data: Any
    lines: Mapping[str, int]
    sha256: str
    source: str


def excerpt(value: object, limit: int = EXCERPT_CHARS) -> str:
    """A short, printable quotation of untrusted input for an error message.

    Control characters and non-ASCII are escaped (``repr`` style) and the result is cut to
    ``limit`` characters, so a message never carries terminal escapes or a whole file.

    Examples
    --------
    >>> print(excerpt("root:x:0:0\\x1b[2J" + "a" * 100))
    'root:x:0:0\\x1b[2Jaaaaaaaaaaaaaaaaaaaaa…
    """
    text = ascii(value)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def where(path: str, lines: Mapping[str, int]) -> str:
    """``path (line N)`` for the nearest enclosing key path that has a known line.

    Examples
    --------
    >>> where("sets[1].masker", {"sets[1]": 7})
    'sets[1].masker (line 7)'
    """
    probe = path
    while probe:
        if probe in lines:
            return f"{path} (line {lines[probe]})"
        parent = probe.rsplit(".", 1)[0] if "." in probe else probe.rsplit("[", 1)[0]
        if parent == probe:
            break
        probe = parent
    return path


def read_limited(
    path: str | Path, *, what: str, error: ErrorFactory = ProtocolError, max_bytes: int = MAX_BYTES
) -> bytes:
    """Read at most ``max_bytes`` of ``path``; a larger file, a directory or an OS error is
    refused with ``error(file, "", message)``.

    Examples
    --------
    >>> read_limited("/nonexistent.yaml", what="protocol")  # doctest: +IGNORE_EXCEPTION_DETAIL
    Traceback (most recent call last):
    ProtocolError: /nonexistent.yaml: cannot read the protocol (No such file or directory)
    """
    p = Path(path)
    try:
        # O_NONBLOCK: opening a FIFO must not wait for a writer; only regular files are read.
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK)
        with os.fdopen(fd, "rb") as fh:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                raise error(
                    str(p),
                    "",
                    "not a regular file (a device, FIFO or folder); "
                    f"give the path of the {what} itself",
                )
            raw = fh.read(max_bytes + 1)
    except OSError as exc:
        raise error(
            str(p),
            "",
            f"cannot read the {what} ({exc.strerror or type(exc).__name__}); check the path",
        ) from exc
    if len(raw) > max_bytes:
        raise error(
            str(p),
            "",
            f"the file is larger than {max_bytes // 1024} kB: not a {what} this command reads; "
            "check the path",
        )
    return raw


def decode_utf8(raw: bytes, source: str, *, error: ErrorFactory = ProtocolError) -> str:
    """Strict UTF-8 decoding (a leading byte-order mark is dropped).

    Raises ``error`` naming the line and column of the first byte that is not UTF-8.

    Examples
    --------
    >>> decode_utf8("level: 3 dB".encode(), "p.yaml")
    'level: 3 dB'
    """
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        column = exc.start - (raw.rfind(b"\n", 0, exc.start) + 1) + 1
        raise error(
            source,
            f"line {line}, column {column}",
            f"byte 0x{raw[exc.start]:02x} is not UTF-8 text; save the file as UTF-8",
        ) from None
    return text[1:] if text.startswith("\ufeff") else text


# --------------------------------------------------------------------------------------------
# YAML


class _Refused(Exception):
    def __init__(self, mark: yaml.Mark | None, message: str) -> None:
        super().__init__(message)
        self.mark = mark
        self.message = message


class _PlainLoader(yaml.SafeLoader):
    """SafeLoader with a depth limit, a cap on what aliases expand to, and dates left as text."""

    # PyYAML's stubs declare this table an instance attribute; it is a class-level one here too
    yaml_implicit_resolvers: dict[Any, list[Any]] = {  # noqa: RUF012
        first: [(tag, rx) for tag, rx in resolvers if tag != "tag:yaml.org,2002:timestamp"]
        for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
    }

    def __init__(self, stream: str, max_depth: int, max_nodes: int) -> None:
        super().__init__(stream)
        self._depth = 0
        self._max_depth = max_depth
        self._budget = max_nodes
        self._max_nodes = max_nodes

    def compose_node(self, parent: Any, index: Any) -> Any:
        mark = self.peek_event().start_mark
        if self.check_event(yaml.AliasEvent):
            node = super().compose_node(parent, index)
            # An alias is a reference; whatever walks the data later walks it in full, so it
            # costs what its expansion holds (a few hundred bytes can expand to gigabytes).
            if node is not None:
                self._spend(_expanded_size(node, self._budget + 1), mark)
            return node
        self._spend(1, mark)
        self._depth += 1
        if self._depth > self._max_depth:
            raise _Refused(mark, f"nested more than {self._max_depth} levels deep; flatten it")
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def _spend(self, n: int, mark: yaml.Mark) -> None:
        self._budget -= n
        if self._budget < 0:
            raise _Refused(
                mark,
                f"the document expands to more than {self._max_nodes} values (YAML aliases "
                "*name repeat what they name); write the values out or use fewer aliases",
            )


def _expanded_size(node: yaml.Node, cap: int) -> int:
    """Number of nodes ``node`` stands for with every alias expanded, counted up to ``cap``."""
    count, stack = 0, [node]
    while stack and count < cap:
        item = stack.pop()
        count += 1
        if isinstance(item, yaml.MappingNode):
            for key, value in item.value:
                stack.extend((key, value))
        elif isinstance(item, yaml.SequenceNode):
            stack.extend(item.value)
    return count


def parse_yaml(
    text: str,
    source: str,
    *,
    error: ErrorFactory = ProtocolError,
    max_depth: int = MAX_DEPTH,
    max_nodes: int = MAX_NODES,
) -> tuple[Any, dict[str, int]]:
    """Parse one YAML document into plain data and a key-path → line map.

    Raises
    ------
    Exception
        ``error(source, where, message)`` for malformed YAML, alias bombs, deep nesting, tags
        that build objects, non-text or duplicate keys, and non-finite numbers.

    Examples
    --------
    >>> parse_yaml("a: 1\\nb: [2, 3]\\n", "x.yaml")
    ({'a': 1, 'b': [2, 3]}, {'(top level)': 1, 'a': 1, 'b': 2, 'b[0]': 2, 'b[1]': 2})
    """
    loader: _PlainLoader | None = None
    try:
        loader = _PlainLoader(text, max_depth, max_nodes)  # checks for control characters
        node = loader.get_single_node()
        if node is not None:
            lines, problem = _walk_yaml(node)
            if problem is not None:
                raise error(source, problem[0], problem[1])
        else:
            lines = {}
        data = loader.construct_document(node) if node is not None else None
    except _Refused as exc:
        raise error(source, _mark(exc.mark), exc.message) from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        what = excerpt(exc.problem or type(exc).__name__, 120).strip("'\"")
        raise error(source, _mark(mark), f"malformed YAML: {what}; fix the syntax there") from None
    except yaml.reader.ReaderError as exc:
        line = text.count("\n", 0, exc.position) + 1
        raise error(
            source,
            f"line {line}",
            f"character U+{exc.character:04X} is not allowed in YAML (a control character); "
            "delete it",
        ) from None
    except yaml.YAMLError as exc:
        raise error(source, "", f"malformed YAML ({type(exc).__name__})") from None
    except (ValueError, OverflowError, RecursionError) as exc:
        # int('9' * 5000) in the constructor: Python refuses to convert so many digits.
        raise error(source, "", f"a value cannot be read ({excerpt(str(exc), 80)})") from None
    finally:
        if loader is not None:
            loader.dispose()
    _refuse_non_finite(data, lines, source, error)
    return data, lines


def _mark(mark: yaml.Mark | None) -> str:
    return f"line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""


def _walk_yaml(root: yaml.Node) -> tuple[dict[str, int], tuple[str, str] | None]:
    """Line map of every key path, and the first problem (where, message), iteratively."""
    lines: dict[str, int] = {}
    stack: list[tuple[yaml.Node, str]] = [(root, "")]
    while stack:
        node, path = stack.pop()
        line = node.start_mark.line + 1
        lines.setdefault(path or "(top level)", line)
        if node.tag not in _PLAIN_TAGS:
            return lines, (
                f"{path or '(top level)'} (line {line})",
                f"tag {excerpt(node.tag)} is not allowed: only plain text, numbers, true/false, "
                "null, mappings and lists",
            )
        if isinstance(node, yaml.MappingNode):
            seen: set[str] = set()
            children = []
            for key_node, value_node in node.value:
                key_line = key_node.start_mark.line + 1
                if key_node.tag == _MERGE:
                    continue  # `<<: *base`: the named mapping was checked where it stands
                if not isinstance(key_node, yaml.ScalarNode) or key_node.tag != (
                    "tag:yaml.org,2002:str"
                ):
                    shown = key_node.value if isinstance(key_node, yaml.ScalarNode) else "?"
                    return lines, (
                        f"{path or '(top level)'} (line {key_line})",
                        f"key {excerpt(shown)} is not text (YAML reads it as a number, "
                        "true/false or null); put it in quotes or rename it",
                    )
                key = key_node.value
                child = f"{path}.{key}" if path else key
                if key in seen:
                    return lines, (
                        f"{child} (line {key_line})",
                        "this key appears twice in the same mapping; YAML would silently keep "
                        "the last one. Delete or rename one of them",
                    )
                seen.add(key)
                lines[child] = key_line
                children.append((value_node, child))
            stack.extend(reversed(children))
        elif isinstance(node, yaml.SequenceNode):
            stack.extend(
                (item, f"{path}[{i}]") for i, item in reversed(list(enumerate(node.value)))
            )
    return lines, None


# --------------------------------------------------------------------------------------------
# JSON

_JSON_TOKEN = re.compile(r'"(?:[^"\\\n]|\\.)*"|[{}\[\],:]|[^\s{}\[\],:"]+')


def parse_json(
    text: str, source: str, *, error: ErrorFactory = ProtocolError, max_depth: int = MAX_DEPTH
) -> tuple[Any, dict[str, int]]:
    """Parse a JSON document into plain data and a key-path → line map.

    Raises ``error(source, where, message)`` for malformed JSON, deep nesting, duplicate keys
    and non-finite numbers (``NaN``, ``Infinity``, ``1e999``).

    Examples
    --------
    >>> parse_json('{"a": [1, 2]}', "x.json")[0]
    {'a': [1, 2]}
    """
    lines, problem = _scan_json(text, max_depth)
    if problem is not None and problem[1].startswith("nested"):
        raise error(source, problem[0], problem[1])
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise error(
            source,
            f"line {exc.lineno}",
            f"not valid JSON ({exc.msg} at column {exc.colno}); is the file truncated?",
        ) from None
    except (ValueError, RecursionError) as exc:
        raise error(source, "", f"a value cannot be read ({excerpt(str(exc), 80)})") from None
    if problem is not None:
        raise error(source, problem[0], problem[1])
    _refuse_non_finite(data, lines, source, error)
    return data, lines


def _scan_json(text: str, max_depth: int) -> tuple[dict[str, int], tuple[str, str] | None]:
    """Key-path → line map, the depth check and duplicate keys, without recursion."""
    lines: dict[str, int] = {}
    # Frames: [is_object, path, expecting_key, current key or index, keys seen]
    stack: list[list[Any]] = []
    line, pos = 1, 0

    def value_path() -> str:
        if not stack:
            return ""
        is_obj, path, _, cur, _ = stack[-1]
        if is_obj:
            return f"{path}.{cur}" if path else str(cur)
        return f"{path}[{cur}]"

    for m in _JSON_TOKEN.finditer(text):
        line += text.count("\n", pos, m.start())
        pos = m.start()
        tok = m.group()
        top = stack[-1] if stack else None
        if tok in "{[":
            path = value_path()
            lines.setdefault(path or "(top level)", line)
            stack.append([tok == "{", path, tok == "{", 0, set()])
            if len(stack) > max_depth:
                return lines, (f"line {line}", f"nested more than {max_depth} levels deep")
        elif tok in "}]":
            if stack:
                stack.pop()
        elif tok == ":":
            if top is not None and top[0]:
                top[2] = False
        elif tok == ",":
            if top is not None:
                if top[0]:
                    top[2] = True
                else:
                    top[3] += 1
        elif top is not None and top[0] and top[2] and tok.startswith('"'):
            try:
                key = json.loads(tok)
            except ValueError:
                continue  # json.loads of the whole text reports it
            child = f"{top[1]}.{key}" if top[1] else str(key)
            if key in top[4]:
                return lines, (
                    f"{child} (line {line})",
                    "this key appears twice in the same object; JSON readers would silently "
                    "keep the last one. Delete or rename one of them",
                )
            top[4].add(key)
            top[3] = key
            lines[child] = line
        else:
            lines.setdefault(value_path() or "(top level)", line)
    return lines, None


# --------------------------------------------------------------------------------------------
# Both


def non_finite(value: Any, path: str = "") -> Iterator[tuple[str, object]]:
    """Key paths of NaN, ±inf and integers beyond float range in plain data, iteratively.

    Examples
    --------
    >>> list(non_finite({"a": [1.0, float("nan")]}))
    [('a[1]', nan)]
    """
    stack: list[tuple[Any, str]] = [(value, path)]
    while stack:
        item, here = stack.pop()
        too_big = isinstance(item, int) and not isinstance(item, bool) and abs(item) > 1e308
        if too_big or (isinstance(item, float) and not math.isfinite(item)):
            yield here or "(top level)", item
        elif isinstance(item, Mapping):
            stack.extend(
                (v, f"{here}.{k}" if here else str(k)) for k, v in reversed(list(item.items()))
            )
        elif isinstance(item, list | tuple):
            stack.extend((v, f"{here}[{i}]") for i, v in reversed(list(enumerate(item))))


def _refuse_non_finite(
    data: Any, lines: Mapping[str, int], source: str, error: ErrorFactory
) -> None:
    for path, value in non_finite(data):
        shown = excerpt(value) if isinstance(value, float) else f"a {len(str(value))}-digit number"
        raise error(
            source,
            where(path, lines),
            f"{shown} is not a finite number; write a plain number (e.g. 1.8)",
        )


def parse_document(
    raw: bytes,
    source: str,
    *,
    fmt: str = "yaml",
    error: ErrorFactory = ProtocolError,
    max_depth: int = MAX_DEPTH,
) -> Document:
    """Decode and parse bytes already read (``fmt`` is ``"yaml"`` or ``"json"``).

    Examples
    --------
    >>> parse_document(b"kind: masked\\n", "p.yaml").data
    {'kind': 'masked'}
    """
    text = decode_utf8(raw, source, error=error)
    parse = parse_json if fmt == "json" else parse_yaml
    data, lines = parse(text, source, error=error, max_depth=max_depth)
    return Document(data, lines, hashlib.sha256(raw).hexdigest(), source)


def syntax_of(path: str | Path) -> str:
    """The syntax :func:`load_document` reads a file in by default: ``"json"`` for a ``.json``
    suffix (any case), else ``"yaml"``.

    Examples
    --------
    >>> syntax_of("truth.JSON"), syntax_of("protocol.yaml")
    ('json', 'yaml')
    """
    return "json" if Path(path).suffix.lower() == ".json" else "yaml"


def load_document(
    path: str | Path,
    *,
    what: str,
    fmt: str | None = None,
    error: ErrorFactory = ProtocolError,
    max_bytes: int = MAX_BYTES,
) -> Document:
    """Read and parse one input file through every limit above.

    Parameters
    ----------
    path : str or Path
        The file.
    what : str
        What the file is, for messages ("protocol", "rig config").
    fmt : {"yaml", "json"}, optional
        Syntax; by default JSON for a ``.json`` suffix, else YAML.
    error : callable
        Builds the loader's error type from (file, where, message).
    max_bytes : int
        Size limit, bytes.

    Examples
    --------
    >>> from masking_lab.formats.resources import shipped
    >>> load_document(shipped("protocols", "baseline.yaml"), what="protocol").data["kind"]
    'baseline'
    """
    p = Path(path)
    raw = read_limited(p, what=what, error=error, max_bytes=max_bytes)
    return parse_document(raw, str(p), fmt=fmt or syntax_of(p), error=error)
