"""Helpers shared by the session-runner tests (no tests here).

Small protocols written to tmp folders, reading and validating session logs, comparing trial
records without their times, and running the CLI in a subprocess.
"""

from __future__ import annotations

import functools
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import jsonschema
import yaml

from masking_lab.formats.resources import shipped
from masking_lab.formats.schemas import load_schema, schema_errors

REPO = Path(__file__).resolve().parents[1]

# Fields that depend on when (or through which process) a trial ran, not on what it was;
# "seq" is the record's line number, which a resume's fault and resume records shift.
TIME_FIELDS = {"planned_onsets_s", "actual_onsets_s", "device_extra", "t_s", "seq"}

FAST_TIMING = {
    "stimulus_s": 0.05,
    "gap_s": 0.02,
    "lead_in_s": 0.02,
    "inter_trial_s": 0.0,
    "response_timeout_s": None,
    "rest_between_sets_s": 0.0,
}


def write_protocol(
    folder: Path,
    *,
    kind: str = "masked",
    sets: list[dict[str, Any]] | None = None,
    name: str = "proto.yaml",
    experiment: str = "exp",
    staircase: dict[str, Any] | None = None,
    timing: dict[str, Any] | None = None,
    randomize: bool = True,
) -> Path:
    """A small protocol: few reversals so a set takes ~20 trials."""
    if sets is None:
        sets = (
            [{"id": "EV", "target": "EV270"}, {"id": "MV", "target": "MV120"}]
            if kind == "baseline"
            else [
                {"id": "A10", "masker": "MV120", "masker_level_db_sl": 10},
                {"id": "A20", "masker": "MV120", "masker_level_db_sl": 20},
            ]
        )
    sc = {
        "start_level_db": 0 if kind == "baseline" else 10,
        "step_sizes_db": [4, 2],
        "down_up_ratio": 1.0,
        "n_up": 1,
        "n_down": 3,
        "n_reversals": 5,
        "n_reversals_averaged": 4,
        "initial_one_down_one_up": False,
        "min_level_db": -60 if kind == "baseline" else -20,
        "max_level_db": None if kind == "baseline" else 40,
        "bound_policy": "clamp",
        "max_bound_hits": 3,
        "max_trials": 80,
    }
    sc.update(staircase or {})
    data: dict[str, Any] = {
        "schema_version": 1,
        "experiment": experiment,
        "description": "test protocol",
        "kind": kind,
    }
    if kind == "masked":
        data["target"] = "EV270"
    data.update(
        {
            "staircase": sc,
            "timing": {**FAST_TIMING, **(timing or {})},
            "order": {"randomize": randomize},
            "sets": sets,
        }
    )
    path = folder / name
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def write_calibration(data_dir: Path, participant: str, als: dict[str, float]) -> Path:
    """A calibration file written by hand (not by the code under test)."""
    path = data_dir / participant / "calibration.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    record = {"participant": participant, "unmasked_al_db_v": als, "sources": ["by hand"]}
    path.write_text(json.dumps(record), encoding="utf-8")
    return path


def write_device_config(folder: Path, **changes: Any) -> Path:
    """The reference rig's config with ``channels.EV.max_drive_v=...`` style changes."""
    text = shipped("protocols", "devices/default.yaml").read_text(encoding="utf-8")
    data = yaml.safe_load(text)
    for dotted, value in changes.items():
        node = data
        *parents, leaf = dotted.split("__")
        for key in parents:
            node = node.setdefault(key, {})
        node[leaf] = value
    path = folder / "rig.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def records(path: Path) -> list[dict[str, Any]]:
    """Every complete record of a log, header first."""
    text = Path(path).read_text(encoding="utf-8")
    return [json.loads(line) for line in text.splitlines(keepends=True) if line.endswith("\n")]


@functools.cache
def _log_validator() -> Any:
    schema = load_schema("session_log")
    return jsonschema.validators.validator_for(schema)(schema)


def assert_valid_log(path: Path) -> list[dict[str, Any]]:
    """Every line of the log validates against data_schema/session_log.schema.json."""
    recs = records(path)
    assert recs and recs[0]["record"] == "header"
    validator = _log_validator()
    for i, rec in enumerate(recs, start=1):
        if not validator.is_valid(rec):  # the slow, detailed path only for a bad record
            errors = schema_errors(rec, "session_log")
            assert not errors, f"{path} line {i} ({rec.get('record')}): {errors[0].message[:300]}"
    return recs


def trials(recs: list[dict[str, Any]], set_id: str | None = None) -> list[dict[str, Any]]:
    return [r for r in recs if r["record"] == "trial" and (set_id is None or r["set_id"] == set_id)]


def timeless(recs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Trial records without their times, for comparing runs."""
    return [{k: v for k, v in r.items() if k not in TIME_FIELDS} for r in trials(recs)]


def of_kind(recs: list[dict[str, Any]], kind: str) -> list[dict[str, Any]]:
    return [r for r in recs if r["record"] == kind]


def cli(*args: str, cwd: Path | None = None, timeout: float = 60) -> subprocess.CompletedProcess:
    """Run ``python -m masking_lab.commands.cli ARGS`` to completion."""
    return subprocess.run(
        [sys.executable, "-m", "masking_lab.commands.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=cwd,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )


def cli_popen(*args: str, cwd: Path | None = None) -> subprocess.Popen:
    """Start ``python -m masking_lab.commands.cli ARGS`` without waiting."""
    return subprocess.Popen(
        [sys.executable, "-m", "masking_lab.commands.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=cwd,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )


def only_log(data_dir: Path, participant: str = "S01", experiment: str = "exp") -> Path:
    logs = sorted((data_dir / participant).glob(f"{experiment}-{participant}-*.jsonl"))
    assert len(logs) == 1, logs
    return logs[0]
