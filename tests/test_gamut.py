"""The perceptual gamut (issue 19 items 1 and 5): exact pieces, agreement with the solver and with
a brute-force search of the input box, stable at b·d ≥ 1 and within ulps of 1."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from masking_lab.core.errors import SolverError
from masking_lab.rendering.gamut import gamut_for_targets, perceptual_gamut
from masking_lab.rendering.ramp_inverse import MAX_INTERCEPT_DB, MAX_SLOPE, Reason
from masking_lab.rendering.solver import MutualMasking, forward

ULP_BELOW_1 = 1.0 - 2.0**-53
slopes = st.one_of(
    st.floats(0.0, 3.0),
    st.sampled_from([0.0, 1e-300, 0.5, 1.0, ULP_BELOW_1, 1.0 + 2.0**-52, 2.0, MAX_SLOPE]),
)
intercepts = st.one_of(
    st.floats(-30.0, 30.0), st.sampled_from([-MAX_INTERCEPT_DB, 0.0, MAX_INTERCEPT_DB])
)
ratings = st.floats(1.0, 60.0)


def in_box_answer(mm: MutualMasking, m_p: float, e_p: float, box_m, box_e) -> bool | None:
    """Whether the solver answers (m_p, e_p) with inputs inside the box; None if it cannot say."""
    p = mm.solve_point(m_p, e_p)
    if p.reason == Reason.ILL_CONDITIONED:
        return None
    slack = 1e-9 * (1 + abs(box_m[1]) + abs(box_e[1]))
    for m_i, e_i, _ in p.solutions:
        if (
            box_m[0] - slack <= m_i <= box_m[1] + slack
            and box_e[0] - slack <= e_i <= box_e[1] + slack
        ):
            return True
    return False


@settings(derandomize=True, max_examples=400, deadline=None)
@given(
    intercepts,
    slopes,
    intercepts,
    slopes,
    ratings,
    ratings,
    st.lists(st.tuples(st.floats(-80, 80), st.floats(-80, 80)), min_size=8, max_size=8),
)
def test_inside_the_gamut_solves_within_the_ratings_and_outside_does_not(
    a, b, c, d, max_m, max_e, targets
):
    mm = MutualMasking(a, b, c, d)
    g = perceptual_gamut(mm, max_m, max_e)
    scale = 1 + abs(a) + abs(c) + (1 + b + d) * 100
    margin = 1e-6 * scale
    for m_p, e_p in targets:
        dist = float(g.distance_db(m_p, e_p))
        around = g.distance_db(
            [m_p - margin, m_p + margin, m_p, m_p], [e_p, e_p, e_p - margin, e_p + margin]
        )
        answer = in_box_answer(mm, m_p, e_p, g.mv_box_db_sl, g.ev_box_db_sl)
        if answer is None:
            continue
        if dist == 0 and np.all(around == 0):  # well inside
            assert answer, (m_p, e_p)
        elif dist > margin:  # well outside
            assert not answer, (m_p, e_p)


@settings(derandomize=True, max_examples=150, deadline=None)
@given(intercepts, slopes, intercepts, slopes, ratings, ratings, st.floats(-20.0, 0.0))
def test_gamut_agrees_with_a_brute_force_search_of_the_input_box(a, b, c, d, max_m, max_e, floor):
    mm = MutualMasking(a, b, c, d)
    g = perceptual_gamut(mm, max_m, max_e, floor_mv_db_sl=floor, floor_ev_db_sl=floor)
    n = 161
    mi, ei = np.meshgrid(np.linspace(floor, max_m, n), np.linspace(floor, max_e, n))
    mp, ep = forward(mm, mi.ravel(), ei.ravel())
    scale = 1 + abs(a) + abs(c) + (1 + b + d) * (abs(floor) + max(max_m, max_e))
    # 1. Every pair the box can produce is in the computed gamut.
    assert float(g.distance_db(mp, ep).max()) <= 1e-9 * scale
    # 2. Every vertex is produced by some input in the box, and nothing is non-finite.
    for piece in g.pieces:
        assert np.isfinite(piece.vertices).all()
        (m0, m1), (e0, e1) = piece.mv_input_db_sl, piece.ev_input_db_sl
        assert floor <= m0 <= m1 <= max_m and floor <= e0 <= e1 <= max_e
    # 3. Targets: inside → brute force comes within the grid's reach; outside → never closer
    #    than the computed distance.
    reach = (1 + max(b, d)) * (max_m - floor + max_e - floor) / (n - 1)
    rng = np.random.default_rng(0)
    lo = np.array([mp.min(), ep.min()]) - 10
    hi = np.array([mp.max(), ep.max()]) + 10
    targets = rng.uniform(lo, hi, size=(40, 2))
    # One call for the 40 targets (the scalar form is exercised in the test above).
    dists = g.distance_db(targets[:, 0], targets[:, 1])
    for (tm, te), dist in zip(targets, dists.tolist(), strict=True):
        brute = float(np.hypot(mp - tm, ep - te).min())
        if dist == 0:
            assert brute <= reach * (1 + 1e-9) + 1e-9 * scale
        else:
            assert brute >= dist - 1e-9 * scale


def test_paper_pair_is_one_polygon_whose_vertices_are_images_of_the_box():
    mm = MutualMasking(-2.0, 0.5, -1.0, 0.4)  # both knees inside the box
    g = perceptual_gamut(mm, 30.0, 30.0)
    assert [p.case for p in g.pieces] == [1, 3, 2, 4]
    # Corners and the four knee crossings (m_i = 2.5, e_i = 4): eight vertices, exact.
    expected = [
        forward(mm, m, e)
        for m, e in [(0, 0), (2.5, 0), (30, 0), (30, 4), (30, 30), (2.5, 30), (0, 30), (0, 4)]
    ]
    assert g.outline.tolist() == [[float(m), float(e)] for m, e in expected]
    assert not g.folded


def test_folded_pair_is_a_union_of_pieces_with_the_both_ramps_piece_reversed():
    mm = MutualMasking(-2.0, 2.0, -2.0, 1.0)  # b·d = 2
    g = perceptual_gamut(mm, 20.0, 20.0)
    assert g.folded and g.outline is None
    four = next(p for p in g.pieces if p.case == 4)
    v = four.vertices
    area2 = sum(v[i - 1][0] * v[i][1] - v[i][0] * v[i - 1][1] for i in range(4))
    assert area2 > 0  # counter-clockwise after the reversal
    # A target with two answers in the box lies in two pieces at once, one per answer.
    assert g.cases_at(1.0, 0.5) == [1, 4]
    assert sorted(s[2] for s in mm.solve_point(1.0, 0.5).solutions) == [1, 4]


def test_bd_within_ulps_of_one_is_finite_and_collapses_the_both_ramps_piece():
    for d in (ULP_BELOW_1, 1.0, 1.0 + 2.0**-52):
        g = perceptual_gamut(MutualMasking(-3.0, 1.0, -3.0, d), 30.0, 30.0)
        four = next(p for p in g.pieces if p.case == 4)
        assert np.isfinite(four.vertices).all()
        v = four.vertices
        area2 = abs(sum(v[i - 1][0] * v[i][1] - v[i][0] * v[i - 1][1] for i in range(4)))
        assert area2 <= 1e-12  # a segment up to rounding: one line of targets
        assert g.contains(0.0, 0.0)


def test_slopes_and_intercepts_at_their_bounds():
    for a, b, c, d in [
        (MAX_INTERCEPT_DB, MAX_SLOPE, -MAX_INTERCEPT_DB, MAX_SLOPE),
        (-MAX_INTERCEPT_DB, 1e-300, MAX_INTERCEPT_DB, 0.0),
        (0.0, MAX_SLOPE, 0.0, 1e-300),
    ]:
        g = perceptual_gamut(MutualMasking(a, b, c, d), 30.0, 30.0)
        for p in g.pieces:
            assert np.isfinite(p.vertices).all()


def test_bounds_must_be_finite_and_ordered():
    mm = MutualMasking(0.0, 0.5, 0.0, 0.5)
    with pytest.raises(SolverError, match="max_mv_db_sl must be a finite"):
        perceptual_gamut(mm, math.inf, 30.0)
    with pytest.raises(SolverError, match=r"floor .* is above the rated maximum"):
        perceptual_gamut(mm, 30.0, 30.0, floor_ev_db_sl=40.0)
    # Was possible through --max-mv-db-sl 1e308: vertices of inf, then a JSON traceback.
    with pytest.raises(SolverError, match="beyond the solver's range"):
        perceptual_gamut(mm, 1e308, 30.0)


def test_gamut_for_targets_lowers_the_floor_to_the_lowest_target():
    mm = MutualMasking(0.0, 0.5, 0.0, 0.5)
    g = gamut_for_targets(mm, 30.0, 30.0, [-7.0, 3.0, -np.inf], [np.nan, 2.0])
    assert g.mv_box_db_sl == (-7.0, 30.0) and g.ev_box_db_sl == (0.0, 30.0)


def test_gamut_command_prints_the_vertices_and_writes_json_and_figure(tmp_path, capsys):
    import json

    from test_render import write_params

    from masking_lab.commands.cli import main
    from masking_lab.formats.masking_params import read_masking_params
    from masking_lab.rendering.solver import pair_from_params

    params = write_params(tmp_path / "p.json")
    out = tmp_path / "g"
    assert main(["gamut", "--params", params, "--mv", "MV180", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    pair = pair_from_params(read_masking_params(params), mv="MV180", ev="EV270")
    g = perceptual_gamut(pair, 30.0, 30.0)  # the reference rig's ratings
    for m, e in g.outline:
        assert f"({m:.6g}, {e:.6g})" in text
    doc = json.loads((out / "gamut.json").read_text())
    assert doc["outline"] == g.outline.tolist() and not doc["folded"]
    assert (out / "gamut.png").read_bytes()[:4] == b"\x89PNG"
    # Capped at the fitted masker ranges (5–25 dB SL in the test parameters).
    args = ["gamut", "--params", params, "--mv", "MV180", "--out", str(out), "--no-figure"]
    assert main([*args, "--fitted-range-only"]) == 0
    assert "capped at the fitted masker ranges" in capsys.readouterr().out
    doc = json.loads((out / "gamut.json").read_text())
    assert doc["mv_input_box_db_sl"] == [0.0, 25.0] and doc["ev_input_box_db_sl"] == [0.0, 25.0]
    # A folded pair is printed as its pieces; bad input is a clean error.
    folded = write_params(tmp_path / "f.json", ramps={"MV180": ((1.0, 2.0), (-1.0, 1.0))})
    assert main(["gamut", "--params", folded, "--out", str(out), "--no-figure"]) == 0
    text = capsys.readouterr().out
    assert "b·d ≥ 1, the union of these pieces" in text and "case 4:" in text
    assert json.loads((out / "gamut.json").read_text())["outline"] is None
    assert main(["gamut", "--params", params, "--mv", "MV999", "--out", str(out)]) == 2
    assert "MV999" in capsys.readouterr().err
    assert main(["gamut", "--params", params, "--out", str(out)]) == 2
    assert "say which MV stimulus" in capsys.readouterr().err
