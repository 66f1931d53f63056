"""Uncertainty carried to the finger (issue 19 item 3): intervals from the exported standard
errors, the two per-point flags, columns, summary and CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from test_render import ROOT, write_params

from masking_lab.commands.cli import main
from masking_lab.core.errors import SolverError
from masking_lab.rendering.pair import MutualMasking
from masking_lab.rendering.render import render_scene
from masking_lab.rendering.scene import GeometrySpec, PathSpec, Scene, TextureSpec
from masking_lab.rendering.uncertainty import PairSpread, pair_spread, perceived_intervals

SCENE = Scene("bump_rough", PathSpec(), GeometrySpec("bump"), TextureSpec("rough", "MV180", 12.0))
PAIR = MutualMasking(
    1.304,
    1.062,
    -5.927,
    0.658,
    mv="MV180",
    ev="EV270",
    f_fitted_range_db_sl=(5.0, 25.0),
    g_fitted_range_db_sl=(5.0, 25.0),
)


def test_exact_parameters_give_zero_width_intervals_at_the_targets():
    r = render_scene(SCENE, PAIR)
    u = perceived_intervals(r, PairSpread(0.0, 0.0, 0.0, 0.0), n_draws=20)
    assert np.allclose(u.mv_lo, 12.0) and np.allclose(u.mv_hi, 12.0)
    assert np.allclose(u.ev_lo, r.ev_target_db_sl) and np.allclose(u.ev_hi, u.ev_lo)
    # Compensation is better wherever masking is at work, and never worse.
    assert not u.not_better[np.abs(r.ev_perceived_uncomp_db_sl - r.ev_target_db_sl) > 0.1].any()


def test_wider_standard_errors_give_wider_bands_and_more_doubtful_points():
    r = render_scene(SCENE, PAIR)
    narrow = perceived_intervals(r, PairSpread(0.1, 0.005, 0.1, 0.005))
    wide = perceived_intervals(r, PairSpread(2.0, 0.1, 2.0, 0.1))
    assert np.all(wide.mv_hi - wide.mv_lo >= narrow.mv_hi - narrow.mv_lo - 1e-9)
    assert wide.not_better.sum() > narrow.not_better.sum()
    assert np.all(
        (narrow.ev_lo <= r.ev_target_db_sl + 0.5) & (narrow.ev_hi >= r.ev_target_db_sl - 0.5)
    )
    # Seeded: the same rendering gives the same intervals.
    again = perceived_intervals(r, PairSpread(2.0, 0.1, 2.0, 0.1))
    assert np.array_equal(again.mv_lo, wide.mv_lo)


def test_points_relying_on_a_ramp_beyond_its_fitted_range_are_flagged():
    r = render_scene(SCENE, PAIR)
    u = perceived_intervals(r, PairSpread(0.1, 0.01, 0.1, 0.01))
    expected = (r.mv_input_db_sl > 25.0) | (r.ev_input_db_sl > 25.0)
    assert expected.any() and np.array_equal(u.beyond_fitted, expected)


def test_spread_from_the_interval_when_no_standard_error():
    doc = {
        "functions": [
            {"target": "MV180", "masker": "EV270", "intercept_se_db": 0.5, "slope_se": 0.02},
            {
                "target": "EV270",
                "masker": "MV180",
                "intercept_ci_db": [-8.96, -5.04],
                "slope_ci": None,
                "ci_level": 0.95,
                "intercept_se_db": None,
                "slope_se": None,
            },
        ]
    }
    s = pair_spread(doc, mv="MV180", ev="EV270")
    assert (s.a_sd_db, s.b_sd) == (0.5, 0.02)
    assert s.c_sd_db == pytest.approx(1.0, rel=1e-3) and s.d_sd == 0.0
    with pytest.raises(SolverError, match="no masking function for MV120"):
        pair_spread(doc, mv="MV120", ev="EV270")


def test_bad_draw_settings_are_refused():
    r = render_scene(SCENE, PAIR)
    with pytest.raises(SolverError, match="at least 20 draws"):
        perceived_intervals(r, PairSpread(0, 0, 0, 0), n_draws=5)
    with pytest.raises(SolverError, match="level must be in"):
        perceived_intervals(r, PairSpread(0, 0, 0, 0), level=1.5)


def test_render_writes_interval_columns_flags_and_counts(tmp_path, capsys):
    params = write_params(tmp_path / "p.json")
    scene = str(ROOT / "protocols" / "scenes" / "bump_rough.yaml")
    out = tmp_path / "o"
    assert main(["render", scene, "--params", params, "--out", str(out), "--no-figure"]) == 0
    text = capsys.readouterr().out
    assert "parametric fallback" in text and "compensation not better than none at" in text
    table = pd.read_csv(out / "points.csv")
    for ch in ("mv", "ev"):
        assert (table[f"{ch}_perceived_lo_db_sl"] <= table[f"{ch}_perceived_db_sl"] + 1e-9).all()
        assert (table[f"{ch}_perceived_hi_db_sl"] >= table[f"{ch}_perceived_db_sl"] - 1e-9).all()
    summary = json.loads((out / "summary.json").read_text())
    u = summary["uncertainty"]
    assert u["points_compensation_not_better"] == int(table["compensation_not_better"].sum())
    assert u["points_beyond_fitted_range"] == int(table["beyond_fitted_range"].sum())
    assert "parametric" in u["method"]
    # Restricted to the fitted range, no point relies on an extrapolated ramp.
    out2 = tmp_path / "o2"
    args = ["render", scene, "--params", params, "--out", str(out2), "--no-figure"]
    assert main([*args, "--fitted-range-only"]) == 0
    capsys.readouterr()
    summary = json.loads((out2 / "summary.json").read_text())
    assert summary["uncertainty"]["points_beyond_fitted_range"] == 0
    assert summary["gamut"]["mv_input_box_db_sl"][1] <= 25.0
    assert main([*args, "--uncertainty-draws", "3"]) == 2
    assert "at least 20 draws" in capsys.readouterr().err


def test_absurd_standard_errors_give_no_band_rather_than_a_traceback(tmp_path, capsys):
    doc = json.loads(Path(write_params(tmp_path / "p.json")).read_text())
    for f in doc["functions"]:
        f["intercept_se_db"], f["slope_se"] = 1e308, 1e300
    (tmp_path / "p.json").write_text(json.dumps(doc))
    scene = str(ROOT / "protocols" / "scenes" / "bump_rough.yaml")
    args = ["render", scene, "--params", str(tmp_path / "p.json"), "--out", str(tmp_path / "o")]
    assert main(args) == 0
    capsys.readouterr()
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())  # strict JSON
    assert summary["uncertainty"]["points_compensation_not_better"] == summary["n_points"]
