"""Scenes: the shipped files, the geometry and texture profiles, and malformed files."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from masking_lab.core.errors import ProtocolError
from masking_lab.rendering.scene import (
    SHAPES,
    GeometrySpec,
    PathSpec,
    Scene,
    TextureSpec,
    load_scene,
)

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "protocols" / "scenes"
TEXTURES = {"smooth": ("MV270", 6.0), "rough": ("MV180", 12.0), "coarse": ("MV120am40", 12.0)}


def test_every_geometry_texture_combination_ships():
    names = {p.stem for p in SCENES.glob("*.yaml")}
    assert names == {f"{g}_{t}" for g in SHAPES for t in TEXTURES}
    for g in SHAPES:
        for t, (stimulus, level) in TEXTURES.items():
            scene = load_scene(SCENES / f"{g}_{t}.yaml")
            assert scene.name == f"{g}_{t}" and len(scene.sha256) == 64
            assert scene.geometry.shape == g and scene.geometry.stimulus == "EV270"
            assert scene.geometry.perceived_db_sl == (0.0, 10.0)  # paper: 0-10 dB SL
            assert scene.texture.name == t
            assert (scene.texture.stimulus, scene.texture.perceived_db_sl) == (stimulus, level)
            # The cue crosses the whole path in one 1.8 s presentation at 51 mm/s.
            assert scene.path.duration_s == pytest.approx(1.8)
            assert scene.stimulus_pairs() == [(stimulus, "EV270")]


def _numeric_gradient(geometry: GeometrySpec, x: np.ndarray) -> np.ndarray:
    return np.gradient(geometry.height_profile_mm(x), x)


@pytest.mark.parametrize("shape", SHAPES)
def test_all_shapes_share_height_and_steepest_inclination(shape):
    geo = GeometrySpec(shape, position_mm=45.9, height_mm=2.0, max_inclination=0.25)
    x = np.linspace(0.0, 91.8, 200_001)
    h = geo.height_profile_mm(x)
    grad = _numeric_gradient(geo, x)
    assert np.max(np.abs(h)) == pytest.approx(2.0, rel=1e-6)
    assert np.max(np.abs(grad)) == pytest.approx(0.25, rel=1e-3)
    # The analytic gradient agrees with finite differences away from the slopes' kink.
    ok = np.abs(x - 45.9) > 0.01
    np.testing.assert_allclose(geo.gradient(x)[ok], grad[ok], atol=1e-4)


def test_gradient_mapping_gives_distinct_profiles():
    x = np.linspace(0.0, 91.8, 919)
    profiles = {}
    for shape, pos in (("bump", 45.9), ("hole", 45.9), ("ascending", 68.85), ("descending", 22.95)):
        profiles[shape] = GeometrySpec(shape, position_mm=pos).target_db_sl(x)
    bump, hole = profiles["bump"], profiles["hole"]
    # Uphill feels stronger: a bump rises to 10 before its centre and drops to 0 after it.
    assert bump[x < 45.9].max() == pytest.approx(10.0, abs=1e-3)
    assert bump[x > 45.9].min() == pytest.approx(0.0, abs=1e-3)
    assert x[np.argmax(bump)] < 45.9 < x[np.argmin(bump)]
    np.testing.assert_allclose(hole, 10.0 - bump, atol=1e-12)  # mirror image about 5 dB SL
    assert profiles["ascending"].min() == pytest.approx(5.0) and profiles["ascending"].max() > 9.9
    assert profiles["descending"].max() == pytest.approx(5.0) and profiles["descending"].min() < 0.1
    # Level ground sits mid-range; the four profiles differ pairwise.
    assert bump[0] == pytest.approx(5.0, abs=1e-6)
    for a in profiles:
        for b in profiles:
            if a < b:
                assert np.max(np.abs(profiles[a] - profiles[b])) > 4.0


def test_texture_is_constant_and_single_channel_scenes_pass_through():
    tex = TextureSpec("rough", "MV180", 12.0)
    path = PathSpec(length_mm=10.0, n_points=11)
    scene = Scene("t", path, None, tex)
    x, mv, ev = scene.targets()
    assert np.all(mv == 12.0) and np.all(ev == -math.inf) and x[-1] == 10.0
    assert scene.single_channel and scene.stimulus_pairs() == []
    geo_only = Scene("g", path, GeometrySpec("bump", position_mm=5.0), None)
    assert geo_only.single_channel and np.all(geo_only.targets()[1] == -math.inf)
    with pytest.raises(ProtocolError, match="needs `geometry:`, `texture:` or both"):
        Scene("none", path, None, None)


GOOD = """\
schema_version: 1
scene: demo
path: {length_mm: 50, n_points: 101, speed_mm_s: 51}
geometry: {shape: hole, position_mm: 25}
texture: {name: smooth, stimulus: MV270, perceived_db_sl: 6}
"""


def _write(tmp_path, text, name="scene.yaml"):
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def test_defaults_fill_in(tmp_path):
    scene = load_scene(_write(tmp_path, GOOD))
    assert scene.geometry.stimulus == "EV270" and scene.geometry.perceived_db_sl == (0.0, 10.0)
    assert scene.path.n_points == 101 and scene.source.endswith("scene.yaml")
    texture_only = load_scene(
        _write(tmp_path, GOOD.replace("geometry: {shape: hole, position_mm: 25}", "geometry: null"))
    )
    assert texture_only.geometry is None and texture_only.single_channel


@pytest.mark.parametrize(
    "old, new, where, message",
    [
        ("scene: demo\n", "", "(top level)", "'scene' is a required property"),
        ("shape: hole", "shape: ridge", "geometry.shape", "must be one of"),
        ("stimulus: MV270", "stimulus: EV270", "texture.stimulus", "texture is rendered by MV"),
        ("shape: hole,", "shape: hole, stimulus: MV180,", "geometry.stimulus", "rendered by EV"),
        ("stimulus: MV270", "stimulus: vib270", "texture.stimulus", "is not a stimulus name"),
        ("position_mm: 25", "position_mm: 80", "geometry.position_mm", "off the 50 mm path"),
        ("position_mm: 25", "position_mm: 25, perceived_db_sl: [10, 0]", "perceived", "lo < hi"),
        ("n_points: 101", "n_points: 1", "path.n_points", "must be ≥ 2, got 1"),
        ("n_points: 101", "n_points: 101, width: 3", "path", "known keys"),
        ("schema_version: 1", "schema_version: 2", "schema_version", "1 was expected"),
    ],
)
def test_malformed_scenes_name_the_key(tmp_path, old, new, where, message):
    text = GOOD.replace(old, new)
    assert text != GOOD
    with pytest.raises(ProtocolError) as info:
        load_scene(_write(tmp_path, text))
    assert str(tmp_path / "scene.yaml") in str(info.value)
    assert where in info.value.where
    assert message in info.value.message


def test_scene_without_channels_is_refused(tmp_path):
    text = GOOD.replace("geometry: {shape: hole, position_mm: 25}\n", "").replace(
        "texture: {name: smooth, stimulus: MV270, perceived_db_sl: 6}\n", ""
    )
    with pytest.raises(ProtocolError, match="is not valid under any of the given schemas"):
        load_scene(_write(tmp_path, text))
    both_null = GOOD.replace("{shape: hole, position_mm: 25}", "null").replace(
        "{name: smooth, stimulus: MV270, perceived_db_sl: 6}", "null"
    )
    with pytest.raises(ProtocolError, match="needs `geometry:`, `texture:` or both"):
        load_scene(_write(tmp_path, both_null))


def test_unreadable_and_malformed_files(tmp_path):
    with pytest.raises(ProtocolError, match="cannot read the scene"):
        load_scene(tmp_path / "missing.yaml")
    with pytest.raises(ProtocolError) as info:
        load_scene(_write(tmp_path, "scene: [unclosed\n"))
    assert info.value.where.startswith("line 2") and "malformed YAML" in info.value.message
    with pytest.raises(ProtocolError, match="a scene is a YAML mapping"):
        load_scene(_write(tmp_path, "- just\n- a list\n"))
