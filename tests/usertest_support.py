"""Helpers shared by the user-test runner and analysis tests (no tests here).

Small user-test protocols pointing at the shipped object scenes, masking parameters and ground
truths written by hand (from the paper's Table 2 ramps), and the user-test records of a log
without their times.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import yaml
from params_support import masking_entry

from masking_lab.formats.masking_params import write_masking_params
from masking_lab.formats.resources import shipped

REPO = Path(__file__).resolve().parents[1]
SCENES = REPO / "protocols" / "scenes"
USERTEST = REPO / "protocols" / "usertest.yaml"

# (a, b) of MV masked by EV270 and (c, d) of EV270 masked by MV: the shipped ground truth's
# ramps (paper Table 2 fits; coarse assumed like MV120), typed here by hand.
RAMPS = {
    "MV270": ((1.480, 1.113), (-2.240, 0.602)),
    "MV180": ((1.304, 1.062), (-5.927, 0.658)),
    "MV120am40": ((-0.387, 0.939), (-7.442, 0.711)),
}

# Fields that depend on when (or through which process) a trial ran, not on what it was;
# "seq" is the record's line number, which a resume's fault and resume records shift.
TIME_FIELDS = {"t_s", "planned_onsets_s", "actual_onsets_s", "seq"}

TINY_TIMING = {
    "lead_in_s": 0.02,
    "stimulus_s": 0.05,
    "gap_s": 0.02,
    "n_presentations": 3,
    "inter_trial_s": 0.0,
    "response_timeout_s": None,
}


def write_usertest(
    folder: Path,
    *,
    name: str = "usertest.yaml",
    repeats: int = 1,
    tracking: str = "cue",
    geometries: list[str] | None = None,
    textures: list[str] | None = None,
    conditions: list[str] | None = None,
    timing: dict[str, Any] | None = None,
    randomize: bool = True,
) -> Path:
    """The shipped user-test protocol with changes, its scenes read from the shipped folder."""
    data = yaml.safe_load(USERTEST.read_text(encoding="utf-8"))
    data["scenes_dir"] = str(SCENES)
    data["repeats"] = repeats
    data["tracking"] = tracking
    data["order"] = {"randomize": randomize}
    if geometries is not None:
        data["geometries"] = geometries
    if textures is not None:
        data["textures"] = textures
    if conditions is not None:
        data["conditions"] = conditions
    if timing is not None:
        data["timing"] = {**data["timing"], **timing}
    path = folder / name
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def write_params(path: Path, ramps: dict = RAMPS, drop: tuple[tuple[str, str], ...] = ()) -> Path:
    """A masking_params.json with both directions of every pair in ``ramps`` minus ``drop``."""
    functions = []
    for mv, ((a, b), (c, d)) in ramps.items():
        functions += [masking_entry(mv, "EV270", a, b), masking_entry("EV270", mv, c, d)]
    functions = [f for f in functions if (f["target"], f["masker"]) not in drop]
    doc = {
        "schema_version": 1,
        "software_version": "test",
        "created_utc": "2024-01-01T00:00:00Z",
        "provenance": {"source": "fit", "inputs": [], "settings": {}},
        "functions": functions,
    }
    write_masking_params(path, doc)
    return path


def write_ground_truth(path: Path, shift_db: float = 0.0) -> Path:
    """The shipped ground truth with every unmasked AL moved by ``shift_db`` dB.

    A rig with 20 dB more amplifier gain (``shift_db=-20``) reaches the compensated levels of
    every object within the reference rig's drive limits.
    """
    data = yaml.safe_load(
        shipped("protocols", "simulation/ground_truth.yaml").read_text(encoding="utf-8")
    )
    data["unmasked_al_db_v"] = {k: v + shift_db for k, v in data["unmasked_al_db_v"].items()}
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def write_rig(folder: Path, *, max_level_db_sl: float | None = None, **drive_v: float) -> Path:
    """The reference rig's config with other limits (drive_v: ``EV=5.0``, ``MV=10.0``)."""
    data = yaml.safe_load(shipped("protocols", "devices/default.yaml").read_text(encoding="utf-8"))
    for ch, spec in data["channels"].items():
        if max_level_db_sl is not None:
            spec["max_level_db_sl"] = max_level_db_sl
        if ch in drive_v:
            spec["max_drive_v"] = drive_v[ch]
    path = folder / "rig.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def write_calibration(data_dir: Path, participant: str, als: dict[str, float]) -> Path:
    """A calibration file written by hand."""
    path = data_dir / participant / "calibration.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    record = {"participant": participant, "unmasked_al_db_v": als, "sources": ["by hand"]}
    path.write_text(json.dumps(record), encoding="utf-8")
    return path


def records(path: Path) -> list[dict[str, Any]]:
    """Every complete record of a log, header first."""
    text = Path(path).read_text(encoding="utf-8")
    return [json.loads(line) for line in text.splitlines(keepends=True) if line.endswith("\n")]


def trials(recs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [r for r in recs if r["record"] == "usertest_trial"]


def timeless(recs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """User-test trial records without their times, for comparing runs."""
    return [{k: v for k, v in r.items() if k not in TIME_FIELDS} for r in trials(recs)]


def of_kind(recs: list[dict[str, Any]], kind: str) -> list[dict[str, Any]]:
    return [r for r in recs if r["record"] == kind]
