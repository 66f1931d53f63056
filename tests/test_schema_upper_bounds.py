"""Every number a protocol, rig config, scene, calibration or ground truth holds has an upper
bound in its schema (issue 21.3: ``stimulus_s: 1e300`` passed validate), and the bounds that
stand for a limit elsewhere (the firmware's 60 s trial, the scene's point cap) agree with it."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest

from masking_lab.commands.cli import main
from masking_lab.formats.protocol import MAX_TRIAL_S
from masking_lab.formats.resources import shipped
from masking_lab.rendering.scene import MAX_POINTS

ROOT = Path(__file__).resolve().parents[1]
SCHEMAS = ("protocol", "usertest", "device_config", "scene", "calibration", "ground_truth")
# A definition no field refers to (kept for older tools reading the schema).
UNUSED = {"protocol.$defs.db"}


def _schema(name: str) -> dict[str, Any]:
    return json.loads(shipped("data_schema", f"{name}.schema.json").read_text(encoding="utf-8"))


def _unbounded(s: Any, path: str) -> list[str]:
    if not isinstance(s, dict) or "$ref" in s or "enum" in s or "const" in s:
        return []
    kinds = s.get("type") if isinstance(s.get("type"), list) else [s.get("type")]
    found = []
    if {"number", "integer"} & set(kinds) and "maximum" not in s and "exclusiveMaximum" not in s:
        found.append(path)
    for key in ("properties", "$defs"):
        for name, sub in s.get(key, {}).items():
            found += _unbounded(sub, f"{path}.{'$defs.' if key == '$defs' else ''}{name}")
    for key in ("oneOf", "anyOf", "allOf"):
        for sub in s.get(key, []):
            found += _unbounded(sub, path)
    for key in ("items", "additionalProperties"):
        found += _unbounded(s.get(key), f"{path}[]")
    return found


@pytest.mark.parametrize("name", SCHEMAS)
def test_every_number_in_the_schema_has_an_upper_bound(name):
    assert [p for p in _unbounded(_schema(name), name) if p not in UNUSED] == []


def test_the_unbounded_walker_finds_a_missing_bound():
    doc = {"properties": {"t_s": {"type": "number", "minimum": 0}}}
    assert _unbounded(doc, "x") == ["x.t_s"]


def test_interval_bounds_match_the_firmware_trial_limit():
    header = (ROOT / "firmware" / "core" / "trial.h").read_text(encoding="utf-8")
    us = re.search(r"#define TRIAL_MAX_DURATION_US \((\d+)LL \* (\d+)LL\)", header)
    assert us is not None
    assert int(us[1]) * int(us[2]) / 1e6 == MAX_TRIAL_S
    timing = _schema("protocol")["$defs"]["timing"]["properties"]
    usertest = _schema("usertest")["properties"]["timing"]["properties"]
    for part in ("stimulus_s", "gap_s", "lead_in_s"):
        assert timing[part]["maximum"] == MAX_TRIAL_S
        assert usertest[part]["maximum"] == MAX_TRIAL_S


def test_scene_point_cap_matches_the_code():
    assert _schema("scene")["properties"]["path"]["properties"]["n_points"]["maximum"] == MAX_POINTS


def _protocol(tmp_path: Path, old: str, new: str) -> Path:
    text = shipped("protocols", "baseline.yaml").read_text(encoding="utf-8")
    assert old in text
    path = tmp_path / "p.yaml"
    path.write_text(text.replace(old, new, 1), encoding="utf-8")
    return path


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("stimulus_s: 1.8", "stimulus_s: 1.0e+300", "greater than the maximum of 60"),
        ("gap_s: 0.6", "gap_s: 61", "greater than the maximum of 60"),
        ("rest_between_sets_s: 300", "rest_between_sets_s: 1.0e+9", "maximum of 3600"),
        ("stimulus_s: 1.8", "stimulus_s: 20", "over the 60 s a device plays in one trial"),
    ],
)
def test_validate_refuses_timing_beyond_its_limit_naming_it(tmp_path, capsys, old, new, message):
    assert main(["validate", str(_protocol(tmp_path, old, new))]) == 1
    out = capsys.readouterr()
    assert message in out.out + out.err and "timing" in out.out + out.err


def test_a_trial_of_exactly_the_limit_validates(tmp_path):
    # 1.2 + 3 x 19.2 + 2 x 0.6 = 60.0 s: the bound is inclusive, as the firmware's.
    assert main(["validate", str(_protocol(tmp_path, "stimulus_s: 1.8", "stimulus_s: 19.2"))]) == 0


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("repeats: 5", "repeats: 1000000", "must be ≤ 100"),
        ("stimulus_s: 1.8", "stimulus_s: 30", "over the 60 s a device plays in one trial"),
    ],
)
def test_usertest_counts_and_trial_length_are_bounded(tmp_path, capsys, old, new, message):
    folder = tmp_path / "ut"
    folder.mkdir()
    text = shipped("protocols", "usertest.yaml").read_text(encoding="utf-8")
    assert old in text
    (folder / "usertest.yaml").write_text(text.replace(old, new, 1), encoding="utf-8")
    for scene in shipped("protocols", "scenes").iterdir():
        if scene.suffix == ".yaml":
            (folder / "scenes").mkdir(exist_ok=True)
            (folder / "scenes" / scene.name).write_bytes(scene.read_bytes())
    assert main(["validate", str(folder / "usertest.yaml")]) == 1
    assert message in capsys.readouterr().err
