"""The fuzz engine shared by the seeded suite (``tests/fuzz/test_fuzz_*.py``) and the longer
campaign (``tests/fuzz/campaign.py``): seed files of every kind, mutators, and a runner that
calls the real commands and classifies what happened.

An outcome is *clean* when the command ends with an exit code (0, 1, 2, 3) or an argparse usage
error; a *traceback* when any other exception escapes ``masking_lab.commands.cli.main``; a
*hang* when it runs past its CPU-time limit (SIGPROF; a wall-clock bound ten times longer
catches a run stuck waiting); *non-finite* when a file it wrote holds NaN
or an infinity (a ``NaN``/``Infinity`` token in JSON, a ``nan``/``inf`` field in CSV).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shutil
import signal
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from masking_lab.formats.resources import shipped

# ------------------------------------------------------------------------------ seeds

PROTOCOL = b"""\
schema_version: 1
experiment: pilot
kind: masked
target: EV270
staircase:
  start_level_db: 10
  step_sizes_db: [4, 2]
  n_reversals: 3
  n_reversals_averaged: 2
  max_trials: 30
timing: {stimulus_s: 0.2, gap_s: 0.1, lead_in_s: 0.1, inter_trial_s: 0.1}
order: {randomize: false}
sets:
  - {id: a, masker: MV120, masker_level_db_sl: 5}
  - {id: b, masker: MV120, masker_level_db_sl: 10}
"""
BASELINE = (
    PROTOCOL.replace(b"kind: masked", b"kind: baseline")
    .replace(b"target: EV270\n", b"")
    .replace(b"start_level_db: 10", b"start_level_db: 0")
    .split(b"sets:")[0]
    + b"sets:\n  - {id: MV120, target: MV120}\n"
)
CALIBRATION = json.dumps(
    {
        "participant": "S01",
        "unmasked_al_db_v": {"EV270": -18.0, "MV120": -26.0, "MV180": -30.0},
        "sources": ["by hand"],
    },
    indent=2,
).encode()


def seed(kind: str) -> bytes:
    """The valid file each mutation of ``kind`` starts from."""
    if kind == "protocol":
        return PROTOCOL
    if kind == "calibration":
        return CALIBRATION
    if kind in ("masking_params", "session_log"):
        return _generated(kind)
    path = {
        "usertest": "usertest.yaml",
        "rig": "devices/default.yaml",
        "ground_truth": "simulation/ground_truth.yaml",
        "scene": "scenes/bump_rough.yaml",
    }.get(kind)
    if path is not None:
        return shipped("protocols", path).read_bytes()
    if kind == "shifts_csv":
        return shipped("data_schema", "shifts.csv").read_bytes()
    raise KeyError(kind)


KINDS = (
    "protocol",
    "usertest",
    "rig",
    "ground_truth",
    "scene",
    "calibration",
    "masking_params",
    "shifts_csv",
    "session_log",
)

_GENERATED: dict[str, bytes] = {}


def _generated(kind: str) -> bytes:
    """masking_params.json from `fit` of the paper's shifts; a sim baseline's session log."""
    if kind not in _GENERATED:
        from masking_lab.commands.cli import main

        work = Path(os.environ.get("TMPDIR", "/tmp")) / f"masking-fuzz-seed-{os.getpid()}"
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        (work / "base.yaml").write_bytes(BASELINE)
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            main(
                [
                    "fit",
                    str(shipped("data_schema", "shifts.csv")),
                    "--out",
                    str(work / "fit"),
                    "--figures",
                    "none",
                    "--quiet",
                    "--uncertainty",
                    "asymptotic",
                ]
            )
            main(
                [
                    "run",
                    str(work / "base.yaml"),
                    "--participant",
                    "S01",
                    "--data",
                    str(work / "data"),
                    "--device",
                    "sim",
                    "--responder",
                    "sim",
                    "--seed",
                    "5",
                    "--no-progress",
                ]
            )
        _GENERATED["masking_params"] = (work / "fit" / "masking_params.json").read_bytes()
        log = next((work / "data" / "S01").glob("*.jsonl")).read_bytes()
        # An interrupted session (cut after its first records), so `resume` has work to do.
        lines = log.splitlines(keepends=True)
        _GENERATED["session_log"] = b"".join(lines[: max(2, len(lines) // 2)])
        shutil.rmtree(work, ignore_errors=True)
    return _GENERATED[kind]


# ------------------------------------------------------------------------------ mutators


class Picker(Protocol):
    """Where a mutation's choices come from (``random.Random`` or hypothesis' ``data``)."""

    def int(self, lo: int, hi: int) -> int: ...  # inclusive bounds


class RandomPicker:
    """A :class:`Picker` over ``random.Random`` (the campaign)."""

    def __init__(self, rng) -> None:  # type: ignore[no-untyped-def]
        self.rng = rng

    def int(self, lo: int, hi: int) -> int:
        return self.rng.randint(lo, hi)


def _choice(p: Picker, items: Sequence):  # type: ignore[no-untyped-def]
    return items[p.int(0, len(items) - 1)]


_NUMBER = re.compile(rb"(?<![\w.])-?\d+(?:\.\d+)?(?![\w.])")
NASTY_NUMBERS = (
    b".nan",
    b".inf",
    b"-.inf",
    b"NaN",
    b"Infinity",
    b"-Infinity",
    b"1e999",
    b"1.0e+999",
    b"-1.0e+400",
    b"1e-400",
    b"9" * 400,
    b"-0",
    b"0x1F",
    b"1_000",
    b"1e308",
    b"-1e308",
    b"4.9e-324",
    b"null",
    b"true",
    b'"12"',
    b"[]",
    b"{}",
    b"0",
    b"-1",
    b"1e6",
    b"2147483648",
)
NASTY_TEXT = (
    "\x00",
    "\x1b[2J",
    "\ufeff",
    "é",
    "\udcff",
    "*",
    "&a",
    "*a",
    "!!python/object:os.system",
    "<<: *a",
    "{",
    "[",
    "'",
    '"',
    "\\",
    ": ",
    "- ",
    "#",
    "\t",
    "\r",
    "\n",
    "a" * 300,
    "\u2028",
    "%YAML 1.1\n---",
    "...",
    "--- |",
    "? ",
    "!!binary aGk=",
    "2020-01-01",
)


def m_flip_byte(data: bytes, p: Picker) -> bytes:
    if not data:
        return b"\xff"
    i = p.int(0, len(data) - 1)
    return data[:i] + bytes([p.int(0, 255)]) + data[i + 1 :]


def m_insert_text(data: bytes, p: Picker) -> bytes:
    i = p.int(0, len(data))
    junk = _choice(p, NASTY_TEXT).encode("utf-8", "surrogateescape")
    return data[:i] + junk + data[i:]


def m_raw_bytes(data: bytes, p: Picker) -> bytes:
    i = p.int(0, len(data))
    junk = bytes(p.int(0, 255) for _ in range(p.int(1, 6)))
    return data[:i] + junk + data[i:]


def m_delete_range(data: bytes, p: Picker) -> bytes:
    if not data:
        return data
    i = p.int(0, len(data) - 1)
    return data[:i] + data[i + p.int(1, 40) :]


def m_truncate(data: bytes, p: Picker) -> bytes:
    return data[: p.int(0, len(data))]


def m_number(data: bytes, p: Picker) -> bytes:
    spans = [m.span() for m in _NUMBER.finditer(data)]
    if not spans:
        return m_insert_text(data, p)
    a, b = _choice(p, spans)
    return data[:a] + _choice(p, NASTY_NUMBERS) + data[b:]


def _lines(data: bytes) -> list[bytes]:
    return data.splitlines(keepends=True) or [b""]


def m_duplicate_line(data: bytes, p: Picker) -> bytes:
    lines = _lines(data)
    i = p.int(0, len(lines) - 1)
    return b"".join([*lines[: i + 1], lines[i], *lines[i + 1 :]])


def m_swap_lines(data: bytes, p: Picker) -> bytes:
    lines = _lines(data)
    i, j = p.int(0, len(lines) - 1), p.int(0, len(lines) - 1)
    lines[i], lines[j] = lines[j], lines[i]
    return b"".join(lines)


def m_delete_line(data: bytes, p: Picker) -> bytes:
    lines = _lines(data)
    del lines[p.int(0, len(lines) - 1)]
    return b"".join(lines)


def m_alias_bomb(data: bytes, p: Picker) -> bytes:
    width, depth = p.int(2, 9), p.int(3, 12)
    rows = ["b0: &b0 [" + ", ".join(['"lol"'] * width) + "]"]
    rows += [f"b{i}: &b{i} [" + ", ".join([f"*b{i - 1}"] * width) + "]" for i in range(1, depth)]
    return data.rstrip(b"\n") + b"\n" + "\n".join(rows).encode() + b"\n"


def m_deep_nesting(data: bytes, p: Picker) -> bytes:
    n = p.int(30, 20000)
    opener, closer = _choice(p, ((b"[", b"]"), (b"{a: ", b"}"), (b'{"a": ', b"}")))
    i = p.int(0, len(data))
    return data[:i] + opener * n + b"1" + closer * n + data[i:]


def m_huge(data: bytes, p: Picker) -> bytes:
    i = p.int(0, len(data))
    return data[:i] + b"x" * p.int(10_000, 5_000_000) + data[i:]


def m_json_value(data: bytes, p: Picker) -> bytes:
    """Replace a JSON/YAML scalar after a colon with a hostile one."""
    spans = [m.span(1) for m in re.finditer(rb":\s*([^,\n{}\[\]]+)", data)]
    if not spans:
        return m_number(data, p)
    a, b = _choice(p, spans)
    return data[:a] + _choice(p, (*NASTY_NUMBERS, b'"\\u0000"', b'"../../etc/passwd"')) + data[b:]


MUTATORS: tuple[Callable[[bytes, Picker], bytes], ...] = (
    m_flip_byte,
    m_insert_text,
    m_raw_bytes,
    m_delete_range,
    m_truncate,
    m_number,
    m_number,
    m_json_value,
    m_duplicate_line,
    m_swap_lines,
    m_delete_line,
    m_alias_bomb,
    m_deep_nesting,
    m_huge,
)


def mutate(data: bytes, p: Picker, n: int) -> bytes:
    """Apply ``n`` mutators drawn by ``p`` in turn."""
    for _ in range(n):
        data = _choice(p, MUTATORS)(data, p)
    return data


# ------------------------------------------------------------------------------ commands

FILE_NAMES = {
    "protocol": "protocol.yaml",
    "usertest": "usertest.yaml",
    "rig": "rig.yaml",
    "ground_truth": "truth.yaml",
    "scene": "scene.yaml",
    "calibration": "data/S01/calibration.json",
    "masking_params": "masking_params.json",
    "shifts_csv": "shifts.csv",
    "session_log": "data/S01/masked-S01-20260101T000000Z.jsonl",
}
DIRECT = ["--mv-masked-by-ev=1.39,1.09", "--ev-masked-by-mv=-0.4,0.94"]


def commands(kind: str, work: Path, file: Path) -> list[list[str]]:
    """The real commands that read a file of ``kind`` (paths inside ``work``)."""
    run = [
        "run",
        "--participant",
        "S01",
        "--data",
        str(work / "data"),
        "--device",
        "sim",
        "--responder",
        "sim",
        "--seed",
        "1",
        "--no-progress",
    ]
    out = str(work / "out")
    scene = str(work / "seed_scene.yaml")
    params = str(work / "seed_params.json")
    f = str(file)
    table: dict[str, list[list[str]]] = {
        "protocol": [["validate", f], [*run, f]],
        "usertest": [["validate", f]],
        "rig": [
            ["validate", f],
            [
                "solve",
                *DIRECT,
                "--mv-target",
                "12",
                "--ev-target",
                "5",
                "--json",
                "--device-config",
                f,
            ],
            [*run, str(work / "base.yaml"), "--device-config", f],
        ],
        "ground_truth": [["validate", f], [*run, str(work / "base.yaml"), "--ground-truth", f]],
        "scene": [["validate", f], ["render", f, "--params", params, "--out", out, "--no-figure"]],
        "calibration": [["validate", f], [*run, str(work / "protocol_seed.yaml")]],
        "masking_params": [
            ["validate", f],
            [
                "solve",
                "--params",
                f,
                "--mv",
                "MV180",
                "--mv-target",
                "12,0,-inf",
                "--ev-target",
                "5",
                "--json",
            ],
            ["render", scene, "--params", f, "--out", out, "--no-figure"],
        ],
        "shifts_csv": [
            ["validate", f],
            ["fit", f, "--out", out, "--figures", "none", "--quiet", "--uncertainty", "asymptotic"],
        ],
        "session_log": [["validate", f], ["resume", f, "--no-progress"]],
    }
    return table[kind]


def prepare(work: Path, kind: str, data: bytes) -> Path:
    """A fresh work folder holding the mutated file and the valid files its commands need."""
    shutil.rmtree(work, ignore_errors=True)
    (work / "data" / "S01").mkdir(parents=True)
    (work / "base.yaml").write_bytes(BASELINE)
    (work / "protocol_seed.yaml").write_bytes(PROTOCOL)
    (work / "seed_scene.yaml").write_bytes(seed("scene"))
    (work / "seed_params.json").write_bytes(seed("masking_params"))
    if kind != "calibration":
        (work / "data" / "S01" / "calibration.json").write_bytes(CALIBRATION)
    if kind == "usertest":
        shutil.copytree(shipped("protocols", "scenes"), work / "scenes")
    file = work / FILE_NAMES[kind]
    file.write_bytes(data)
    return file


# ------------------------------------------------------------------------------ running


class Hang(BaseException):
    """Raised by SIGALRM in the command's thread (BaseException: no handler swallows it)."""


@dataclass(frozen=True)
class Outcome:
    """What one command did with one input."""

    kind: str  # "clean", "traceback", "hang" or "non_finite"
    argv: tuple[str, ...]
    code: int | None
    detail: str = ""


def run_command(argv: Sequence[str], timeout_s: float) -> tuple[str, int | None, str]:
    """Run ``main(argv)`` in-process: ("clean"|"traceback"|"hang", exit code, detail)."""
    from masking_lab.commands.cli import main

    def alarm(signum, frame):  # type: ignore[no-untyped-def]
        raise Hang

    # The limit is CPU time (ITIMER_PROF), so a busy machine never turns a slow run into a
    # "hang"; a run stuck waiting (no CPU used) is caught by a wall-clock bound ten times longer.
    previous = signal.signal(signal.SIGALRM, alarm)
    previous_prof = signal.signal(signal.SIGPROF, alarm)
    signal.setitimer(signal.ITIMER_PROF, timeout_s)
    signal.setitimer(signal.ITIMER_REAL, 10 * timeout_s)
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(list(argv))
        # The message, for the oracles: its head (a long message cut at its tail lost the
        # reason the oracles look for, e.g. "refused before the first trial").
        return "clean", code, err.getvalue()[:2000]
    except SystemExit as exc:  # argparse usage errors
        return "clean", exc.code if isinstance(exc.code, int) else 2, ""
    except Hang:
        return "hang", None, f"no end within {timeout_s:g} s of CPU ({10 * timeout_s:g} s wall)"
    except BaseException:  # any other escape is the finding
        return "traceback", None, traceback.format_exc(limit=-4)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.setitimer(signal.ITIMER_PROF, 0)
        signal.signal(signal.SIGALRM, previous)
        signal.signal(signal.SIGPROF, previous_prof)


_CSV_BAD = re.compile(r"(?:^|,)\s*[-+]?(?:nan|inf|infinity)\s*(?:,|$)", re.IGNORECASE | re.M)


def snapshot(work: Path) -> dict[Path, bytes]:
    """Every file under ``work`` with its bytes (to tell what a command wrote)."""
    return {p: p.read_bytes() for p in work.rglob("*") if p.is_file()}


def non_finite_files(work: Path, before: dict[Path, bytes]) -> list[str]:
    """Files under ``work`` written by the command that hold NaN or an infinity (for a file
    that existed before, only its new lines count: the input may hold them on purpose)."""
    bad = []
    for path in sorted(work.rglob("*")):
        if not path.is_file() or path.suffix not in (".csv", ".json", ".jsonl"):
            continue
        raw = path.read_bytes()
        if before.get(path) == raw:
            continue
        old = set(before.get(path, b"").splitlines())
        new = [ln for ln in raw.splitlines() if ln not in old]
        text = b"\n".join(new).decode("utf-8", errors="replace")
        if path.suffix == ".csv":
            if _CSV_BAD.search(text):
                bad.append(str(path))
            continue
        whole = [raw.decode("utf-8", "replace")]
        for chunk in text.splitlines() if path.suffix == ".jsonl" else whole:
            try:
                json.loads(chunk, parse_constant=_refuse)
            except _NonFinite:
                bad.append(str(path))
                break
            except ValueError:
                continue  # a torn last line; the reader reports those
    return bad


class _NonFinite(Exception):
    pass


def _refuse(token: str) -> None:
    raise _NonFinite(token)


def trial(kind: str, data: bytes, work: Path, timeout_s: float = 20.0) -> list[Outcome]:
    """Every command of ``kind`` on ``data``; one :class:`Outcome` each."""
    outcomes = []
    for argv in commands(kind, work, work / FILE_NAMES[kind]):
        prepare(work, kind, data)
        before = snapshot(work)
        status, code, detail = run_command(argv, timeout_s)
        if status == "clean":
            found = non_finite_files(work, before)
            if found:
                status, detail = "non_finite", ", ".join(found)
        outcomes.append(Outcome(status, tuple(argv), code, detail))
    return outcomes
