"""Gamut mapping (issue 19 items 2 and 5): every strategy ends with finite inputs within the
ratings, on random parameter sets including b·d ≥ 1 and b·d within ulps of 1; metrics."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from masking_lab.core.errors import SolverError
from masking_lab.rendering.gamut import gamut_for_targets, perceptual_gamut
from masking_lab.rendering.mapping import (
    STRATEGIES,
    map_targets,
    mapping_metrics,
    playable_inputs,
)
from masking_lab.rendering.ramp_inverse import MAX_INTERCEPT_DB, MAX_SLOPE
from masking_lab.rendering.render import compare_strategies, render_scene
from masking_lab.rendering.scene import GeometrySpec, PathSpec, Scene, TextureSpec
from masking_lab.rendering.solver import MutualMasking, Status, forward, solve

slopes = st.one_of(
    st.floats(0.0, 3.0),
    st.sampled_from([0.0, 1e-300, 1.0, 1.0 - 2.0**-53, 1.0 + 2.0**-52, MAX_SLOPE]),
)
intercepts = st.one_of(
    st.floats(-30.0, 30.0), st.sampled_from([-MAX_INTERCEPT_DB, 0.0, MAX_INTERCEPT_DB])
)


@settings(derandomize=True, max_examples=120, deadline=None)
@given(
    intercepts,
    slopes,
    intercepts,
    slopes,
    st.floats(1.0, 60.0),
    st.floats(1.0, 60.0),
    st.floats(-10.0, 40.0),
    st.floats(-10.0, 40.0),
    st.floats(0.0, 40.0),
    st.sampled_from(STRATEGIES[:3]),
)
def test_mapping_never_gives_non_finite_or_out_of_rating_inputs(
    a, b, c, d, max_m, max_e, texture, lo, span, strategy
):
    mm = MutualMasking(a, b, c, d)
    n = 60
    mv_t = np.full(n, texture)
    ev_t = lo + span * 0.5 * (1 + np.sin(np.linspace(0, 2 * np.pi, n)))
    g = gamut_for_targets(mm, max_m, max_e, mv_t, ev_t)
    m, e, gain = map_targets(g, mv_t, ev_t, strategy)
    assert np.isfinite(m).all() and np.isfinite(e).all() and 0.0 <= gain <= 1.0
    sol = solve(mm, m, e)
    several = sol.status == Status.MULTIPLE
    mi, ei, edge = playable_inputs(g, m, e, sol.mv_input_db_sl, sol.ev_input_db_sl, several)
    placed = ~several
    assert np.isfinite(mi[placed]).all() and np.isfinite(ei[placed]).all()
    (m_lo, m_hi), (e_lo, e_hi) = g.mv_box_db_sl, g.ev_box_db_sl
    assert ((mi[placed] >= m_lo) & (mi[placed] <= m_hi)).all()
    assert ((ei[placed] >= e_lo) & (ei[placed] <= e_hi)).all()
    # The solver's inputs give the mapped target back; the edge's are the nearest edge point.
    fm, fe = forward(mm, mi, ei)
    solved = placed & ~edge
    assert np.allclose(fm[solved], m[solved], atol=1e-6)
    assert np.allclose(fe[solved], e[solved], atol=1e-6)
    assert float(g.distance_db(fm[placed], fe[placed]).max(initial=0.0)) <= 1e-6 * (
        1 + abs(a) + abs(c) + (1 + b + d) * 100
    )


def test_single_channel_scene_is_clipped_on_its_own_channel():
    scene = Scene(
        "bump", PathSpec(n_points=51), GeometrySpec("bump", perceived_db_sl=(0, 40)), None
    )
    r = render_scene(scene, None, max_mv_db_sl=30.0, max_ev_db_sl=30.0, gamut_map="clip")
    assert np.all(r.mv_input_db_sl == -np.inf)
    assert r.ev_input_db_sl.max() == 30.0 and np.isfinite(r.ev_input_db_sl).all()
    scaled = render_scene(scene, None, max_mv_db_sl=30.0, max_ev_db_sl=30.0, gamut_map="scale")
    assert scaled.gain == pytest.approx(30.0 / scene.targets()[2].max())


def test_mapping_needs_ratings_and_a_known_strategy():
    scene = Scene("bump", PathSpec(n_points=11), GeometrySpec("bump"), None)
    with pytest.raises(SolverError, match="needs both channels' rated maxima"):
        render_scene(scene, None, gamut_map="clip")
    g = perceptual_gamut(MutualMasking(0, 0, 0, 0), 30.0, 30.0)
    with pytest.raises(SolverError, match="unknown gamut mapping 'squash'"):
        map_targets(g, np.zeros(2), np.zeros(2), "squash")


def test_strategies_trade_level_against_profile_on_the_paper_scene():
    scene = Scene(
        "bump_rough", PathSpec(), GeometrySpec("bump"), TextureSpec("rough", "MV180", 12.0)
    )
    pair = MutualMasking(1.304, 1.062, -5.927, 0.658, mv="MV180", ev="EV270")
    t = compare_strategies(scene, pair, 30.0, 30.0)
    for s in ("clip", "scale", "compress"):
        assert t[s]["share_within_ratings"] == 1.0
        assert t[s]["rms_error_db"] < t["none"]["rms_error_db"]
    assert t["none"]["share_within_ratings"] < 0.1
    # scale keeps both profiles exactly and pays in level; clip is closest point by point.
    assert t["scale"]["geometry_correlation"] == pytest.approx(1.0)
    assert t["scale"]["texture_sd_db"] == pytest.approx(0.0, abs=1e-9)
    assert t["clip"]["rms_error_db"] < t["scale"]["rms_error_db"]
    assert t["compress"]["geometry_correlation"] > 0.95


def test_metrics_of_a_perfect_rendering():
    x = np.linspace(0, 1, 5)
    ev = np.array([0.0, 5.0, 10.0, 5.0, 0.0])
    out = mapping_metrics(x, np.full(5, 6.0), ev, np.full(5, 6.0), ev, np.ones(5, bool))
    assert out["rms_error_db"] == 0.0 and out["share_at_target"] == 1.0
    assert out["geometry_correlation"] == 1.0 and out["texture_sd_db"] == 0.0
    # A point with no input has no level: counted, never a NaN in the numbers.
    got = ev.copy()
    got[2] = np.nan
    out = mapping_metrics(x, np.full(5, 6.0), ev, np.full(5, 6.0), got, np.ones(5, bool))
    assert out["points_without_a_level"] == 1 and out["share_at_target"] == 0.8


def test_demo_scene_renders_within_the_ratings_and_the_summary_shows_the_trade(tmp_path):
    from test_render import write_params

    from masking_lab import demo, demo_summary

    (tmp_path / "analysis").mkdir()
    write_params(tmp_path / "analysis" / "masking_params.json")
    summary = demo._render(tmp_path)
    written = json.loads((tmp_path / "render" / "summary.json").read_text())
    assert written["gamut_mapping"]["strategies"] == summary["gamut_mapping"]["strategies"]
    gm = summary["gamut_mapping"]
    assert gm["strategy"] == "clip" and gm["as_played"]["share_within_ratings"] == 1.0
    for ch in summary["channels"].values():
        assert ch["points_above_rating"] == 0
    rows = demo_summary._mapping(summary)
    assert rows["mapping"] == "clip" and [r[0] for r in rows["strategies"]] == list(STRATEGIES)
    none = rows["strategies"][-1]
    assert none[5] < 0.1  # played as designed, most points would need more than the rig has


def test_compress_leaves_points_below_the_knee_and_keeps_order_along_a_ray():
    g = perceptual_gamut(MutualMasking(0.0, 0.0, 0.0, 0.0), 30.0, 30.0)  # the box itself
    # Along the diagonal the edge is at 30 dB SL: below 0.7 of it nothing moves.
    levels = np.array([3.0, 10.0, 20.0, 21.0, 25.0, 30.0, 45.0, 90.0])
    m, e, gain = map_targets(g, levels, levels, "compress")
    assert gain == 1.0
    assert np.allclose(m[:3], levels[:3], atol=1e-6) and np.allclose(m, e)
    assert np.all(np.diff(m) > 0)  # order kept: the profile's contrast survives
    assert np.all(m < 30.0) and np.all(g.contains(m, e))
    clipped, _, _ = map_targets(g, levels, levels, "clip")
    assert np.array_equal(clipped[-3:], [30.0, 30.0, 30.0])  # clip flattens what compress keeps


def test_metrics_stay_json_ready_for_absurd_levels():
    x = np.linspace(0, 1, 4)
    big = np.array([0.0, 1e300, -1e300, 5.0])
    out = mapping_metrics(x, np.full(4, 6.0), big, np.full(4, 6.0), -big, np.ones(4, bool))
    json.dumps(out, allow_nan=False)  # no inf or NaN reaches a summary
    # Errors 0 (MV, 4 points) and 0, 2e300, 2e300, 10 dB (EV): no overflow in the RMS.
    assert out["rms_error_db"] == pytest.approx(1e300, rel=1e-9)
    assert out["max_error_db"] == 2e300
