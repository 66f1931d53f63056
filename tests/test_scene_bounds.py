"""Scene values bounded by the schema (issue 21 item 3): every scene `validate` accepts renders,
with finite outputs, and the extremes that once overflowed (1e300, 1e-300, denormals) are
refused naming the field."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from masking_lab.core.errors import ProtocolError
from masking_lab.rendering.outputs import check_outputs_finite
from masking_lab.rendering.render import render_scene
from masking_lab.rendering.scene import parse_scene
from masking_lab.rendering.solver import MutualMasking

EXTREMES = [1e300, -1e300, 1e-300, 5e-324, -5e-324, 0.0, 1e-3, 0.1, 100.0, 1000.0, 1e4, 1e6]
numbers = st.one_of(st.sampled_from(EXTREMES), st.floats(-1e4, 1e4), st.floats(0.001, 200.0))
PAIR = MutualMasking(1.304, 1.062, -5.927, 0.658, mv="MV180", ev="EV270")


@st.composite
def scenes(draw):
    doc = {"schema_version": 1, "scene": "fuzz"}
    path = {}
    for key in ("length_mm", "speed_mm_s"):
        if draw(st.booleans()):
            path[key] = draw(numbers)
    path["n_points"] = draw(st.sampled_from([2, 3, 50]))
    doc["path"] = path
    geometry = {"shape": draw(st.sampled_from(["bump", "hole", "ascending", "descending"]))}
    for key in ("position_mm", "height_mm", "max_inclination"):
        if draw(st.booleans()):
            geometry[key] = draw(numbers)
    if draw(st.booleans()):
        geometry["perceived_db_sl"] = sorted([draw(numbers), draw(numbers)])
    doc["geometry"] = geometry
    if draw(st.booleans()):
        doc["texture"] = {"name": "t", "stimulus": "MV180", "perceived_db_sl": draw(numbers)}
    return doc


@settings(derandomize=True, max_examples=400, deadline=None)
@given(scenes())
def test_every_accepted_scene_renders_with_finite_outputs(doc):
    try:
        scene = parse_scene(doc, "fuzz.yaml")
    except ProtocolError:
        return  # refused with a message: fine
    pair = PAIR if scene.texture is not None else None
    for strategy in ("none", "clip"):
        r = render_scene(scene, pair, max_mv_db_sl=30.0, max_ev_db_sl=30.0, gamut_map=strategy)
        check_outputs_finite(r)
        x, mv_t, ev_t = scene.targets()
        assert np.isfinite(x).all() and np.isfinite(r.t_s).all()
        for t in (mv_t, ev_t):
            assert (np.isfinite(t) | (t == -np.inf)).all()


@pytest.mark.parametrize(
    ("where", "value", "message"),
    [
        (("geometry", "height_mm"), 1e300, r"geometry\.height_mm: must be ≤ 1000"),
        (("geometry", "height_mm"), 5e-324, r"geometry\.height_mm: must be ≥ 0\.001"),
        (("geometry", "max_inclination"), 1e-300, r"max_inclination: must be ≥ 0\.001"),
        (("path", "speed_mm_s"), 1e-300, r"path\.speed_mm_s: must be ≥ 0\.1"),
        (("path", "length_mm"), 1e300, r"path\.length_mm: must be ≤ 10000"),
        (("texture", "perceived_db_sl"), 1e300, r"texture\.perceived_db_sl: must be ≤ 100"),
    ],
)
def test_extremes_that_overflowed_are_refused_naming_the_field(where, value, message):
    # Were: OverflowError tracebacks, or NaN targets blamed on "b·d ≥ 1".
    doc = {
        "schema_version": 1,
        "scene": "x",
        "path": {},
        "geometry": {"shape": "bump"},
        "texture": {"name": "t", "stimulus": "MV180", "perceived_db_sl": 12.0},
    }
    doc[where[0]][where[1]] = value
    with pytest.raises(ProtocolError, match=message):
        parse_scene(doc, "s.yaml")


def test_a_denormal_level_is_accepted_and_renders():
    doc = {
        "schema_version": 1,
        "scene": "x",
        "geometry": {"shape": "bump", "perceived_db_sl": [0.0, 5e-324]},
        "texture": {"name": "t", "stimulus": "MV180", "perceived_db_sl": 5e-324},
    }
    r = render_scene(parse_scene(doc, "s.yaml"), PAIR, max_mv_db_sl=30.0, max_ev_db_sl=30.0)
    check_outputs_finite(r)
    assert np.isfinite(r.mv_input_db_sl).all()
