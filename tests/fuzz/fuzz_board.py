"""Hostile boards (issue 21.9): a whole ``run`` against a scripted device on a real pty that
answers like the firmware until one reply carries a number no board may send.

The changes: a HELLO number that is non-finite, negative, zero or 5,000 digits long; a TIME
that is non-finite, negative, beyond the device clock's range or huge; and, at the first,
second or third trial, a DONE whose onsets are huge (±1e308), non-finite, out of order,
collapsed to one value (as precision loss does far from zero), 1e9 s late or early, whose end
precedes its last onset or lies far beyond it, whose played amplitude is non-finite, negative
or far from the request, or that answers another trial's sequence number.

The oracle: ``run`` ends in a clean device fault (exit 3), the log (if any) holds exactly the
trials played before the hostile reply (nothing of the hostile trial is logged as played), and
nothing non-finite reaches the log. Anything else is a finding: a traceback, a hang, a
non-finite log value, or a *silently wrong* result (another exit code, or more trials logged).
"""

from __future__ import annotations

import json
import random
import re
import shutil
import sys
from pathlib import Path

from fuzz_corpus import BASELINE, Outcome, non_finite_files, run_command

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: hardening_support

from hardening_support import QUICK_RIG, ScriptedPeer, raw_frame, standard

from masking_lab.device import protocol as proto

HELLO_FIELDS = ("proto", "bits_ev", "bits_mv", "fsv_ev", "fsv_mv", "max_ev", "max_mv", "fs")
HELLO_VALUES = ("nan", "inf", "-inf", "1e999", "-1", "0", "-1e308", "9" * 5000)
TIME_VALUES = ("nan", "inf", "-inf", "1e999", "-1", "-1e-9", "1e308", "9" * 5000, "1e18", "1e15")
DONE_CHANGES = (
    "huge",
    "non_finite",
    "out_of_order",
    "collapsed",
    "late",
    "early",
    "end_before",
    "end_far",
    "amp_non_finite",
    "amp_negative",
    "amp_off",
    "other_seq",
)
BOARD_CHANGES = ("hello", "time", *DONE_CHANGES)


def _field(body: str, key: str, value: str) -> str:
    """``body`` with ``key=...`` set to ``value`` (the raw text: any number a board may send)."""
    return re.sub(rf"(?<= ){key}=[^ ]*", f"{key}={value}", body, count=1)


def _done_body(body: str, change: str, rng: random.Random) -> str:
    on = [float(v) for v in re.search(r" on=([^ ]*)", body).group(1).split(",")]  # type: ignore[union-attr]
    end = float(re.search(r" end=([^ ]*)", body).group(1))  # type: ignore[union-attr]
    k = rng.randrange(len(on))
    text = [repr(v) for v in on]
    if change == "huge":
        text[k] = rng.choice(["1e308", "-1e308", "1.7976931348623157e308"])
    elif change == "non_finite":
        text[k] = rng.choice(["nan", "inf", "-inf", "1e999"])
    elif change == "out_of_order":
        text[0], text[-1] = text[-1], text[0]
    elif change == "collapsed":
        # far from zero, three onsets 0.4 s apart are one double: what precision loss makes
        text = [repr(1e17)] * len(on)
    elif change == "late":
        text = [repr(v + 1e9) for v in on]
    elif change == "early":
        text = [repr(v - rng.choice([1.0, 1e9])) for v in on]
    elif change == "end_before":
        body = _field(body, "end", repr(on[-1] - 0.05))
    elif change == "end_far":
        body = _field(body, "end", rng.choice([repr(end + 1e9), "1e308", "nan"]))
    elif change == "amp_non_finite":
        body = _field(body, rng.choice(["tamp", "mamp"]), rng.choice(["nan", "inf", "-inf"]))
    elif change == "amp_negative":
        body = _field(body, "tamp", "-0.5")
    elif change == "amp_off":
        body = _field(body, "tamp", rng.choice(["1e308", "9.5", "1e-9"]))
    elif change == "other_seq":
        seq = int(re.search(r" seq=(\d+)", body).group(1))  # type: ignore[union-attr]
        body = _field(body, "seq", str((seq + 7) % 65536))
    return _field(body, "on", ",".join(text))


def _board(change: str, at: int, rng: random.Random):  # type: ignore[no-untyped-def]
    """The peer's answer function: the firmware's, but hostile once as ``change`` says."""
    plays = [0]
    value = rng.choice(HELLO_VALUES if change == "hello" else TIME_VALUES)
    hello_key = rng.choice(HELLO_FIELDS)

    def respond(frame: proto.Frame, events: list[int]) -> list[bytes] | None:
        out = standard(frame, events)
        if change == "hello" and frame.name == "HELLO":
            body = out[0][: out[0].rindex(b"*")].decode("ascii")
            return [raw_frame(_field(body, hello_key, value))]
        if change == "time" and frame.name == "TIME":
            return [raw_frame(f"{frame.seq} OK t={value}")]
        if change in DONE_CHANGES and frame.name == "PLAY":
            plays[0] += 1
            if plays[0] - 1 == at:
                body = out[-1][: out[-1].rindex(b"*")].decode("ascii")
                return [*out[:-1], raw_frame(_done_body(body, change, rng))]
        return out

    return respond


def board_trial(
    rng: random.Random, work: Path, timeout_s: float, change: str | None = None
) -> tuple[list[Outcome], bool]:
    """One hostile board through ``run``: (outcomes, whether the run ended with exit 0 — for a
    hostile board never right). ``change`` forces one (``"none"``: an honest board, which the
    oracle must call *wrong*, as a check that it can fail)."""
    change = change or rng.choice(BOARD_CHANGES)
    at = rng.randrange(3) if change in DONE_CHANGES else 0
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    (work / "rig.yaml").write_text(QUICK_RIG, encoding="utf-8")
    (work / "base.yaml").write_bytes(BASELINE)
    peer = ScriptedPeer(_board(change, at, rng))
    try:
        argv = [
            *("run", str(work / "base.yaml"), "--participant", "S01"),
            *("--data", str(work / "data"), "--device", f"serial:{peer.port}"),
            *("--device-config", str(work / "rig.yaml"), "--responder", "sim", "--seed", "1"),
            "--no-progress",
        ]
        status, code, detail = run_command(argv, timeout_s)
    finally:
        peer.close()
    what = f"{change} (at trial {at + 1})" if change in DONE_CHANGES else change
    if status == "clean":
        logs = sorted((work / "data").rglob("*.jsonl"))
        played = [
            line
            for log in logs
            for line in log.read_text(encoding="utf-8", errors="replace").splitlines()
            if '"record":"trial"' in line
        ]
        found = non_finite_files(work / "data", {}) if logs else []
        if found:
            status, detail = "non_finite", ", ".join(found)
        elif code != 3:
            status, detail = "wrong", f"{what}: run exit {code}, not a device fault (3)\n{detail}"
        elif len(played) != at:
            last = json.loads(played[-1]) if played else {}
            status = "wrong"
            detail = f"{what}: {len(played)} trials logged, {at} played before it; last {last}"
    return [Outcome(status, ("run", "board", what), code, detail)], code == 0


__all__ = ["BOARD_CHANGES", "board_trial"]
