"""Generators for the classes of issue 21 (the campaign's new kinds), each with its oracle.

- ``log_hostile``: a small simulated study whose logs get one hostile change (a 5,000-digit
  integer, CRLF, a byte-order mark, NaN/Infinity/1e999 levels, a future schema version, a byte
  copy deep in a subfolder, a copy taken mid-session, a 2 GB sparse file, a protocol completed
  twice, or the generic mutators) and go through ``validate`` and ``analyze``. Changes that must
  not change the answer (CRLF, BOM, copies, an oversized stray file) are checked against the
  intact study's ``thresholds.csv``: any difference is a *silently wrong* result; a non-finite
  level must leave its set out of the statistics.
- ``csv_hostile``: shifts tables with a column twice, levels a few ulps apart, CRLF, a BOM,
  hostile numbers, through ``validate`` and ``fit``.
- ``*_schema``: documents drawn from the ground-truth, scene, calibration and protocol schemas
  (:mod:`fuzz_schema`); what ``validate`` accepts must run (``run``, ``render``): a refusal
  there is a *validate gap*.

Outcomes use :class:`fuzz_corpus.Outcome` kinds, plus ``wrong`` and ``validate_gap``.
"""

from __future__ import annotations

import contextlib
import io
import json
import random
import re
import shutil
from pathlib import Path

import yaml
from fuzz_corpus import (
    BASELINE,
    PROTOCOL,
    Outcome,
    RandomPicker,
    mutate,
    non_finite_files,
    prepare,
    run_command,
    snapshot,
)
from fuzz_schema import draw, schema

from masking_lab.formats.resources import shipped

HOSTILE_KINDS = (
    "log_hostile",
    "csv_hostile",
    "truth_schema",
    "scene_schema",
    "calibration_schema",
    "protocol_schema",
)
NEUTRAL_LOG = ("crlf", "bom", "deep_copy", "prefix_copy", "oversized")
LOG_CHANGES = (*NEUTRAL_LOG, "big_int", "non_finite", "future_schema", "twice", "mutate")

_STUDY: dict[str, object] = {}


def _study(root: Path) -> tuple[Path, bytes]:
    """A two-participant study (baseline and experiment 1) and its intact thresholds.csv."""
    if "data" not in _STUDY:
        from masking_lab.simulation.synthetic_logs import simulate_study

        data = root / "study"
        shutil.rmtree(data, ignore_errors=True)
        simulate_study(
            data,
            n_participants=2,
            seed=11,
            protocols=["baseline", "experiment1"],
            baseline_start_above_db=10.0,
        )
        out = root / "study_out"
        status, code, detail = run_command(_analyze_argv(data, out), 600)
        assert status == "clean" and code == 0, detail
        _STUDY["data"] = data
        _STUDY["reference"] = (out / "thresholds.csv").read_bytes()
    return _STUDY["data"], _STUDY["reference"]  # type: ignore[return-value]


def _analyze_argv(data: Path, out: Path) -> list[str]:
    return ["analyze", str(data), "--out", str(out), "--n-boot", "100", "--quiet"]


def _log_change(data: Path, change: str, rng: random.Random) -> Path:
    """Apply ``change`` to the study copy in ``data``; return the file validate checks."""
    logs = sorted(data.rglob("*.jsonl"))
    log = rng.choice(logs)
    raw = log.read_bytes()
    lines = raw.split(b"\n")
    if change == "crlf":
        log.write_bytes(raw.replace(b"\n", b"\r\n"))
    elif change == "bom":
        log.write_bytes(b"\xef\xbb\xbf" + raw)
    elif change == "deep_copy":
        deep = data / "backup" / "2024" / "old"
        deep.mkdir(parents=True)
        log = Path(shutil.copy(log, deep / log.name))
    elif change == "prefix_copy":
        copy = log.with_name("copy_" + log.name)
        copy.write_bytes(b"\n".join(lines[: rng.randint(1, len(lines) - 2)]) + b"\n")
        log = copy
    elif change == "oversized":
        log = data / "stray.jsonl"
        with open(log, "wb") as fh:
            fh.truncate(2 * 1024**3)
    elif change == "big_int":
        i = rng.randrange(len(lines) - 1)
        digits = b"9" * rng.choice([100, 4301, 5000, 20000])
        field = rb'("(?:seq|trial_index|seed|n_trials)":)\d+'
        lines[i] = re.sub(field, rb"\g<1>" + digits, lines[i], count=1)
        log.write_bytes(b"\n".join(lines))
    elif change == "non_finite":
        trials = [i for i, ln in enumerate(lines) if b'"record":"trial"' in ln]
        if trials:
            i = rng.choice(trials)
            token = rng.choice([b"NaN", b"Infinity", b"-Infinity", b"1e999", b"-1e400"])
            level = rb'("level_db_(?:sl|v)":)[-0-9.e]+'
            lines[i] = re.sub(level, rb"\g<1>" + token, lines[i], count=1)
        log.write_bytes(b"\n".join(lines))
    elif change == "future_schema":
        log.write_bytes(raw.replace(b'"schema_version":1', b'"schema_version":2', 1))
    elif change == "twice":
        head = json.loads(lines[0])
        head["session_id"] = f"{head.get('session_id')}-again"
        head["created_utc"] = "2031-01-01T00:00:00Z"
        log = log.with_name("again_" + log.name)
        log.write_bytes(b"\n".join([json.dumps(head).encode(), *lines[1:]]))
    else:
        log.write_bytes(mutate(raw, RandomPicker(rng), rng.randint(1, 2)))
    return log


def _log_trial(rng: random.Random, work: Path, timeout_s: float) -> tuple[list[Outcome], bool]:
    data0, reference = _study(work.parent)
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    data = work / "data"
    shutil.copytree(data0, data)
    change = rng.choice(LOG_CHANGES)
    target = _log_change(data, change, rng)
    outcomes = []
    status, code, detail = run_command(["validate", str(target)], timeout_s)
    outcomes.append(Outcome(status, ("validate", change), code, detail))
    out = work / "out"
    argv = _analyze_argv(data, out)
    status, code, detail = run_command(argv, timeout_s * 3)
    if status == "clean":
        found = non_finite_files(out, {}) if out.is_dir() else []
        if found:
            status, detail = "non_finite", ", ".join(found)
        elif change in NEUTRAL_LOG and code != 0:
            status, detail = "wrong", f"{change}: analyze exit {code}"
        elif change in NEUTRAL_LOG and (out / "thresholds.csv").read_bytes() != reference:
            status, detail = "wrong", f"{change}: thresholds.csv differs from the intact study"
        elif change == "non_finite" and code == 0 and not _refused_set(out):
            status, detail = "wrong", "a non-finite level was not refused"
    outcomes.append(Outcome(status, ("analyze", change), code, detail))
    return outcomes, code == 0


def _refused_set(out: Path) -> bool:
    text = (out / "thresholds.csv").read_text(encoding="utf-8")
    return "non-finite" in text or "no completed" in text or "invalid" in text


def _csv_trial(rng: random.Random, work: Path, timeout_s: float) -> tuple[list[Outcome], bool]:
    text = shipped("data_schema", "shifts.csv").read_text(encoding="utf-8")
    lines = text.splitlines()
    header_at = next(i for i, ln in enumerate(lines) if ln and not ln.startswith("#"))
    change = rng.choice(["dup_column", "ulps", "crlf", "bom", "numbers", "mutate"])
    if change == "dup_column":
        cols = lines[header_at].split(",")
        k = rng.randrange(len(cols))
        lines[header_at] += "," + cols[k]
        lines[header_at + 1 :] = [
            ln + "," + (ln.split(",")[k] if ln and not ln.startswith("#") else "")
            for ln in lines[header_at + 1 :]
        ]
    elif change == "ulps":
        row = rng.randrange(header_at + 1, len(lines))
        fields = lines[row].split(",")
        cols = lines[header_at].split(",")
        j = cols.index("masker_level_db_sl")
        x = float(fields[j])
        fields[j] = repr(x + rng.choice([1e-12, 1e-9, 1e-7, 2e-6]) * max(1.0, abs(x)))
        lines[row] = ",".join(fields)
    elif change == "numbers":
        row = rng.randrange(header_at + 1, len(lines))
        fields = lines[row].split(",")
        j = rng.randrange(len(fields))
        fields[j] = rng.choice(["nan", "1e308", "-1e-320", "9" * 5000, "1e999", "0x10", "١٢"])
        lines[row] = ",".join(fields)
    body = "\n".join(lines) + "\n"
    raw = body.encode()
    if change == "crlf":
        raw = body.replace("\n", "\r\n").encode()
    elif change == "bom":
        raw = b"\xef\xbb\xbf" + raw
    elif change == "mutate":
        raw = mutate(raw, RandomPicker(rng), rng.randint(1, 2))
    file = prepare(work, "shifts_csv", raw)
    return _validate_then(
        "csv_hostile",
        file,
        [
            *("fit", str(file), "--out", str(work / "out"), "--figures", "none", "--quiet"),
            *("--uncertainty", "asymptotic"),
        ],
        work,
        timeout_s,
        gap_is_finding=False,
    )


_SCHEMA_OF = {
    "truth_schema": ("ground_truth", "ground_truth", "truth.yaml"),
    "scene_schema": ("scene", "scene", "scene.yaml"),
    "calibration_schema": ("calibration", "calibration", "data/S01/calibration.json"),
    "protocol_schema": ("protocol", "protocol", "protocol.yaml"),
}


def _schema_trial(
    kind: str, rng: random.Random, work: Path, timeout_s: float
) -> tuple[list[Outcome], bool]:
    name, file_kind, _ = _SCHEMA_OF[kind]
    doc = draw(schema(name), rng)
    if kind == "protocol_schema" and rng.random() < 0.7:
        # Whole drawn protocols rarely hang together (sets need maskers the schema cannot
        # require); mostly keep the seed and draw one block of it from its schema instead.
        whole = schema("protocol")
        doc = yaml.safe_load(PROTOCOL)
        block = rng.choice(["staircase", "timing", "procedure", "order"])
        doc[block] = draw(
            whole["$defs"][block] if block in whole["$defs"] else whole["properties"][block],
            rng,
            whole,
        )
    # The seed protocol plays EV270 masked by MV120 (the baseline: MV120): a drawn file must
    # know them, or run refuses it for a reason no single file's validation can see.
    if kind == "calibration_schema":
        doc["participant"] = "S01"
        for stimulus in ("EV270", "MV120"):
            doc["unmasked_al_db_v"].setdefault(stimulus, rng.uniform(-60.0, 0.0))
    if kind == "truth_schema":
        for stimulus in ("EV270", "MV120"):
            doc["unmasked_al_db_v"].setdefault(stimulus, rng.uniform(-60.0, 0.0))
    raw = (
        json.dumps(doc, indent=1).encode()
        if name == "calibration"
        else yaml.safe_dump(doc, sort_keys=False).encode()
    )
    file = prepare(work, file_kind, raw)
    run = ["run", "--participant", "S01", "--data", str(work / "data"), "--device", "sim"]
    run += ["--responder", "sim", "--seed", "1", "--no-progress"]
    using = {
        "truth_schema": [*run, str(work / "base.yaml"), "--ground-truth", str(file)],
        "scene_schema": [
            *("render", str(file), "--params", str(work / "seed_params.json")),
            *("--out", str(work / "out"), "--no-figure"),
        ],
        "calibration_schema": [*run, str(work / "protocol_seed.yaml")],
        "protocol_schema": [*run, str(file)],
    }[kind]
    # validate checks a protocol for the participant run will use (issue 21.2): the same data.
    same_data = ["--data", str(work / "data"), "--participant", "S01"]
    checks = {
        "protocol_schema": [str(file), *same_data],
        "calibration_schema": [str(file), str(work / "protocol_seed.yaml"), *same_data],
    }.get(kind, [str(file)])
    return _validate_then(kind, file, using, work, timeout_s, gap_is_finding=True, checks=checks)


# render's answer for a scene playing a pair the (seed) parameters lack: a fact about the two
# files together, which validating the scene alone cannot know; render writes the protocols
# that measure the pair, as designed.
# A calibration whose ALs put a protocol's level below what the rig's converter and attenuator
# steps can play ("refused before the first trial") is no longer cross-file: validate with
# --data/--participant runs that same check. ALs (calibration) plus sensation levels (protocol)
# beyond the rig's drive limit refuse every set, so run exits 2 saying so.
_CROSS_FILE = ("Measure the pair", "every set was refused")


def _cross_file(detail: str) -> bool:
    return any(reason in detail for reason in _CROSS_FILE)


def _validate_then(
    kind: str,
    file: Path,
    using: list[str],
    work: Path,
    timeout_s: float,
    *,
    gap_is_finding: bool,
    checks: list[str] | None = None,
) -> tuple[list[Outcome], bool]:
    """``validate`` the file (``checks``: validate's arguments, default the file alone); if it
    passes, the command that uses it must not refuse it."""
    status, code, detail = run_command(["validate", *(checks or [str(file)])], timeout_s)
    outcomes = [Outcome(status, ("validate", kind), code, detail)]
    accepted = status == "clean" and code == 0
    before = snapshot(work)
    status, code, detail = run_command(using, timeout_s)
    if status == "clean":
        found = non_finite_files(work, before)
        if found:
            status, detail = "non_finite", ", ".join(found)
        elif accepted and gap_is_finding and code == 2 and not _cross_file(detail):
            status, detail = "validate_gap", f"validate accepted it, {using[0]} said: {detail}"
    outcomes.append(Outcome(status, (using[0], kind), code, detail))
    return outcomes, accepted


def hostile_trial(
    kind: str, rng: random.Random, work: Path, timeout_s: float
) -> tuple[list[Outcome], bool]:
    """One input of a new kind through its commands: (outcomes, whether it was accepted)."""
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        if kind == "log_hostile":
            return _log_trial(rng, work, timeout_s)
        if kind == "csv_hostile":
            return _csv_trial(rng, work, timeout_s)
        return _schema_trial(kind, rng, work, timeout_s)


__all__ = ["BASELINE", "HOSTILE_KINDS", "PROTOCOL", "hostile_trial"]
