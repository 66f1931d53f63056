"""Joint uncertainty in masking_params.json (issue 19 item 3): the export's bootstrap draws and
intercept–slope covariance, their schema, and the rendering's intervals drawn from them."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from params_support import masking_entry
from test_render import ROOT

from masking_lab.analysis.functional import RampPosterior, group_ramps
from masking_lab.commands.cli import main
from masking_lab.formats.masking_params import (
    MaskingParamsError,
    draws_field,
    load_masking_params,
    masking_params_json,
    read_masking_params,
    write_masking_params,
)
from masking_lab.rendering.pair import MutualMasking
from masking_lab.rendering.render import render_scene
from masking_lab.rendering.scene import GeometrySpec, PathSpec, Scene, TextureSpec
from masking_lab.rendering.uncertainty import pair_spread, perceived_intervals

SCENE_FILE = ROOT / "protocols" / "scenes" / "bump_rough.yaml"
A, B, C, D = 1.304, 1.062, -5.927, 0.658  # MV180 by EV270 (a, b); EV270 by MV180 (c, d)
SA, SB = 3.0, 0.15  # standard errors of a (dB) and b (dB/dB)


def _doc(mv_entry: dict, ev_entry: dict) -> dict:
    return {
        "schema_version": 1,
        "software_version": "test",
        "created_utc": "2024-01-01T00:00:00Z",
        "provenance": {"source": "fit", "inputs": [], "settings": {}},
        "functions": [mv_entry, ev_entry],
    }


def _correlated_draws(n: int = 200, centre_db_sl: float = 20.0, seed: int = 1):
    """(a, b) pairs whose shift at ``centre_db_sl`` hardly varies: a strongly negative
    intercept–slope correlation, as a fitted ramp's replicates have."""
    rng = np.random.default_rng(seed)
    b = B + SB * rng.standard_normal(n)
    a = A - centre_db_sl * (b - B) + 0.05 * rng.standard_normal(n)
    return list(zip(a.tolist(), b.tolist(), strict=True))


def _params(tmp_path: Path, *, draws=None, cov=None, name="p.json") -> Path:
    mv = masking_entry("MV180", "EV270", A, B)
    mv.update(intercept_se_db=SA, slope_se=SB, uncertainty="bootstrap", ci_level=0.95)
    if draws is not None:
        mv["draws"] = draws_field("bootstrap", 7, 2000, draws)
    if cov is not None:
        mv["intercept_slope_cov"] = cov
    ev = masking_entry("EV270", "MV180", C, D)
    ev.update(intercept_se_db=0.5, slope_se=0.02)
    path = tmp_path / name
    write_masking_params(path, _doc(mv, ev))
    return path


def _rendering():
    scene = Scene("bump", PathSpec(), GeometrySpec("bump"), TextureSpec("rough", "MV180", 12.0))
    pair = MutualMasking(A, B, C, D, mv="MV180", ev="EV270")
    return render_scene(scene, pair)


# -- the file -----------------------------------------------------------------------------------


def test_draws_round_trip_through_the_file_small_and_byte_stable(tmp_path):
    draws = _correlated_draws(300)
    path = _params(tmp_path, draws=draws)
    entry = load_masking_params(path)[("MV180", "EV270")]
    stored = entry.extra["draws"]
    assert stored["method"] == "bootstrap" and stored["seed"] == 7
    assert stored["n_replicates"] == 2000
    # The first 200, rounded to 4 decimals, in order and paired.
    assert len(stored["intercept_db"]) == len(stored["slope"]) == 200
    assert stored["intercept_db"] == [round(a, 4) for a, _ in draws[:200]]
    assert stored["slope"] == [round(b, 4) for _, b in draws[:200]]
    spread = pair_spread(read_masking_params(path), mv="MV180", ev="EV270")
    assert spread.ab_draws == tuple(zip(stored["intercept_db"], stored["slope"], strict=True))
    assert spread.methods() == ("bootstrap draws", "parametric fallback")
    # Re-writing what was read gives the same bytes; each draws array is one line.
    text = path.read_text()
    assert masking_params_json(read_masking_params(path)) == text
    assert sum('"intercept_db": [' in line for line in text.splitlines()) == 1
    assert len(text) < 6000


def test_fit_exports_seeded_bootstrap_draws_and_covariance(tmp_path):
    from test_fit_cli import _fit, _participant_table

    table = _participant_table(tmp_path)
    _, out = _fit(tmp_path, table, "--n-boot", "300", "--figures", "none", "--seed", "3")
    doc = json.loads((out / "masking_params.json").read_text())
    for f in doc["functions"]:
        d = f["draws"]
        assert d["method"] == "bootstrap" and d["seed"] == 3 and d["n_replicates"] == 300
        a, b = np.array(d["intercept_db"]), np.array(d["slope"])
        assert a.size == b.size == 200 and np.isfinite(a).all() and (b >= 0).all()
        # They are replicates of the bootstrap the exported SEs come from.
        assert np.std(a, ddof=1) == pytest.approx(f["intercept_se_db"], rel=0.25)
        assert np.std(b, ddof=1) == pytest.approx(f["slope_se"], rel=0.25)
        # A ramp's intercept and slope trade off: negative covariance, a valid correlation.
        rho = f["intercept_slope_cov"] / (f["intercept_se_db"] * f["slope_se"])
        assert -1.0 <= rho < 0.0
    # Another seed, other draws.
    _, other = _fit(tmp_path, table, "--n-boot", "300", "--figures", "none", name="o")
    first = json.loads((other / "masking_params.json").read_text())["functions"][0]["draws"]
    assert first["seed"] == 0 and first["slope"] != doc["functions"][0]["draws"]["slope"]


def test_functional_random_effects_carry_a_covariance():
    post = [
        RampPosterior(f"P{i}", "EV270", "MV120", -7.0 + i, 1.0, (-9.0, -5.0), 0.7, 0.05,
                      (0.6, 0.8), rho, 87, (5.0, 15.0, 25.0), "completed")
        for i, rho in enumerate((-0.9, -0.7))
    ]  # fmt: skip
    re = next(g for g in group_ramps(post) if g.estimate == "random_effects")
    assert re.intercept_slope_cov == pytest.approx(-0.8 * re.intercept_se_db * re.slope_se)


def _bad(tmp_path, change):
    path = _params(tmp_path, draws=_correlated_draws(50))
    doc = json.loads(path.read_text())
    change(doc["functions"][0]["draws"])
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc, allow_nan=True))
    with pytest.raises(MaskingParamsError) as err:
        read_masking_params(bad)
    return str(err.value)


@pytest.mark.parametrize(
    ("change", "field", "words"),
    [
        (lambda d: d["intercept_db"].__setitem__(3, math.nan), "draws.intercept_db", "number"),
        (lambda d: d["slope"].__setitem__(0, math.inf), "draws.slope", "number"),
        (lambda d: d["slope"].__setitem__(0, -0.5), "draws.slope", "≥ 0"),
        (lambda d: d["intercept_db"].__setitem__(0, 1e6), "draws.intercept_db", "≤ 500"),
        (
            lambda d: d.update(intercept_db=[1.0] * 201, slope=[1.0] * 201),
            "draws.",
            "at most 200 items, got 201",
        ),
        (lambda d: d["slope"].pop(), "draws", "joint pairs"),
        (lambda d: d.pop("seed"), "draws", "seed"),
    ],
    ids=["nan", "inf", "negative-slope", "huge-intercept", "oversized", "unpaired", "no-seed"],
)
def test_schema_refuses_bad_draws_naming_the_field(tmp_path, change, field, words):
    message = _bad(tmp_path, change)
    assert f"functions[0].{field}" in message and words in message
    assert "Traceback" not in message


def test_render_refuses_a_file_with_bad_draws_cleanly(tmp_path, capsys):
    path = _params(tmp_path, draws=_correlated_draws(50))
    doc = json.loads(path.read_text())
    doc["functions"][0]["draws"]["slope"][2] = math.nan
    path.write_text(json.dumps(doc, allow_nan=True))
    args = ["render", str(SCENE_FILE), "--params", str(path), "--out", str(tmp_path / "o")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "functions[0].draws.slope" in err and "Traceback" not in err


def test_draws_field_keeps_only_finite_bounded_draws():
    assert draws_field("bootstrap", 0, 5, [(math.nan, 1.0), (0.0, -1.0), (1e9, 1.0)]) is None
    kept = draws_field("posterior", None, 2, [(1.0, 0.5), (2.0, math.inf), (3.0, 0.25)])
    assert kept == {
        "method": "posterior",
        "seed": None,
        "n_replicates": 2,
        "intercept_db": [1.0, 3.0],
        "slope": [0.5, 0.25],
    }


# -- the rendering ------------------------------------------------------------------------------


def _widths(u):
    return u.mv_hi - u.mv_lo


def test_correlated_draws_give_narrower_intervals_than_independent_normals(tmp_path):
    r = _rendering()
    active = (A + B * r.ev_input_db_sl) > 0  # where the MV ramp masks at all
    assert active.sum() > 20
    joint = perceived_intervals(
        r, pair_spread(read_masking_params(_params(tmp_path, draws=_correlated_draws())),
                       mv="MV180", ev="EV270"),
    )  # fmt: skip
    fallback = perceived_intervals(
        r, pair_spread(read_masking_params(_params(tmp_path, name="old.json")), mv="MV180",
                       ev="EV270"),
    )  # fmt: skip
    # Same SEs: the independent normals spread a + b·e far wider than the trade-off allows.
    wj, wf = _widths(joint)[active], _widths(fallback)[active]
    assert np.median(wj) < 0.5 * np.median(wf)
    assert np.mean(wj < wf) > 0.9
    # The interval is the stored draws' own: at each point, the central 95 % of the 200
    # (a, b) pairs pushed through the model lies within the band.
    draws = np.array(_correlated_draws())
    e = r.ev_input_db_sl[active]
    felt = r.mv_input_db_sl[active] - np.maximum(0.0, draws[:, :1] + draws[:, 1:] * e)
    lo, hi = np.percentile(felt, [2.5, 97.5], axis=0)
    assert np.allclose(joint.mv_lo[active], lo, atol=2e-3)
    assert np.allclose(joint.mv_hi[active], hi, atol=2e-3)
    assert dict(joint.method_by_function) == {
        "MV180 by EV270": "bootstrap draws",
        "EV270 by MV180": "parametric fallback",
    }
    assert "bootstrap draws" in joint.method and "parametric fallback" in joint.method


def test_covariance_alone_also_narrows_the_intervals(tmp_path):
    r = _rendering()
    active = (A + B * r.ev_input_db_sl) > 0
    draws = np.array(_correlated_draws(2000))
    cov = float(np.cov(draws[:, 0], draws[:, 1])[0, 1])
    with_cov = perceived_intervals(
        r, pair_spread(read_masking_params(_params(tmp_path, cov=cov)), mv="MV180", ev="EV270")
    )
    old = perceived_intervals(
        r, pair_spread(read_masking_params(_params(tmp_path, name="o.json")), mv="MV180",
                       ev="EV270"),
    )  # fmt: skip
    assert np.median(_widths(with_cov)[active]) < 0.5 * np.median(_widths(old)[active])
    assert dict(with_cov.method_by_function)["MV180 by EV270"] == "covariance"
    assert "correlation -1.00" in with_cov.method or "correlation -0.99" in with_cov.method


def test_render_names_the_method_for_new_and_old_files(tmp_path, capsys):
    new = _params(tmp_path, draws=_correlated_draws(), name="new.json")
    old = _params(tmp_path, name="old.json")
    for params, words in ((new, "MV180 by EV270 bootstrap draws"), (old, "parametric fallback")):
        out = tmp_path / params.stem
        args = ["render", str(SCENE_FILE), "--params", str(params), "--out", str(out)]
        assert main([*args, "--no-figure"]) == 0
        assert words in capsys.readouterr().out
        u = json.loads((out / "summary.json").read_text())["uncertainty"]
        assert words.split(" ", 3)[-1] in u["method"]
        assert u["method_by_function"]["EV270 by MV180"] == "parametric fallback"


def test_posterior_draws_are_named_as_such(tmp_path):
    path = _params(tmp_path, draws=_correlated_draws(40))
    doc = json.loads(path.read_text())
    doc["functions"][0]["draws"]["method"] = "posterior"
    doc["functions"][1]["intercept_slope_cov"] = -0.009
    spread = pair_spread(doc, mv="MV180", ev="EV270")
    assert spread.methods() == ("posterior draws", "covariance")
    u = perceived_intervals(_rendering(), spread, n_draws=100)
    assert "posterior draws (40 stored" in u.method and "correlation -0.90" in u.method
    assert np.isfinite(u.mv_lo).all() and np.isfinite(u.ev_hi).all()
