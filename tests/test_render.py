"""`masking-lab render` and masking_lab.rendering.render: outputs per scene, pass-through, missing
pairs."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from params_support import masking_entry

from masking_lab.commands.cli import main
from masking_lab.core.errors import SolverError
from masking_lab.formats.masking_params import write_masking_params
from masking_lab.formats.protocol import load_protocol
from masking_lab.rendering.outputs import POINT_COLUMNS, measurement_protocol, write_rendering
from masking_lab.rendering.render import render_scene, runs_mm
from masking_lab.rendering.scene import GeometrySpec, PathSpec, Scene, TextureSpec, load_scene
from masking_lab.rendering.solver import MutualMasking, PairProblem

ROOT = Path(__file__).resolve().parents[1]
SCENES = sorted((ROOT / "protocols" / "scenes").glob("*.yaml"))
# Enough parameter draws for the interval columns to be computed and written; their widths are
# tested in test_uncertainty.py, not here (the default, 200, was most of a render's time).
DRAWS = ["--uncertainty-draws", "20"]

# Ground-truth ramps (paper Table 2 fits; coarse assumed like MV120): (a, b) for MV by EV and
# (c, d) for EV by MV.
RAMPS = {
    "MV270": ((1.480, 1.113), (-2.240, 0.602)),
    "MV180": ((1.304, 1.062), (-5.927, 0.658)),
    "MV120am40": ((-0.387, 0.939), (-7.442, 0.711)),
}


def write_params(path: Path, ramps=RAMPS, extra=()) -> str:
    functions = list(extra)
    for mv, ((a, b), (c, d)) in ramps.items():
        functions += [masking_entry(mv, "EV270", a, b), masking_entry("EV270", mv, c, d)]
    doc = {
        "schema_version": 1,
        "software_version": "test",
        "created_utc": "2024-01-01T00:00:00Z",
        "provenance": {"source": "fit", "inputs": [], "settings": {}},
        "functions": functions,
    }
    write_masking_params(path, doc)
    return str(path)


@pytest.fixture(scope="module")
def params(tmp_path_factory):
    return write_params(tmp_path_factory.mktemp("params") / "masking_params.json")


@pytest.mark.parametrize("scene_file", SCENES, ids=lambda p: p.stem)
def test_render_writes_outputs_for_every_shipped_scene(scene_file, params, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["render", str(scene_file), "--params", params, "--out", str(out), *DRAWS]) == 0
    assert "wrote" in capsys.readouterr().out
    table = pd.read_csv(out / "points.csv")
    # The fixed columns, then the uncertainty intervals and flags (test_uncertainty.py).
    assert tuple(table.columns)[: len(POINT_COLUMNS)] == POINT_COLUMNS
    assert "compensation_not_better" in table.columns
    scene = load_scene(scene_file)
    assert len(table) == scene.path.n_points
    (a, b), (c, d) = RAMPS[scene.texture.stimulus]
    mv_t, ev_t = table["mv_target_db_sl"], table["ev_target_db_sl"]
    # With compensation the participant feels the targets (Eq. 3-4 on the written inputs).
    m_i, e_i = table["mv_input_db_sl"], table["ev_input_db_sl"]
    assert np.allclose(m_i - np.maximum(0, a + b * e_i), mv_t, atol=1e-9)
    assert np.allclose(e_i - np.maximum(0, c + d * m_i), ev_t, atol=1e-9)
    assert np.allclose(table["mv_perceived_db_sl"], mv_t, atol=1e-9)
    # Without it, each target is lowered by the other's masking at its target level.
    assert np.allclose(table["mv_perceived_uncomp_db_sl"], mv_t - np.maximum(0, a + b * ev_t))
    assert np.allclose(table["ev_perceived_uncomp_db_sl"], ev_t - np.maximum(0, c + d * mv_t))
    assert set(table["status"]) == {"unique"}
    png = (out / "figure4.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scene"] == scene.name and summary["status_counts"]["unique"] == len(table)
    assert summary["masking"]["b"] == b and summary["masking"]["d"] == d


def test_bump_rough_needs_more_than_the_reference_rig_rates(params, tmp_path, capsys):
    out = tmp_path / "br"
    scene = str(ROOT / "protocols" / "scenes" / "bump_rough.yaml")
    args = ["render", scene, "--params", params, "--out", str(out), "--no-figure", *DRAWS]
    assert main([*args, "--gamut-map", "none"]) == 0
    text = capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    mv = summary["channels"]["MV"]
    # Reference rig: 30 dB SL per channel (protocols/devices/default.yaml).
    assert mv["max_rated_db_sl"] == 30.0 and mv["points_above_rating"] > 0
    table = pd.read_csv(out / "points.csv")
    above = table["mv_input_db_sl"] > 30.0
    assert above.sum() == mv["points_above_rating"]  # flagged exactly where needed ...
    assert (table["mv_exceeds_rating"] == above.astype(int)).all()
    assert table["mv_input_db_sl"].max() > 30.0  # ... and not clipped
    assert "need more than the rated 30 dB SL" in text and "(extrapolated)" in text
    assert not (out / "figure4.png").exists()
    # Compensation makes the inputs mask beyond the 5-25 dB SL the ramps were fitted on.
    assert mv["points_beyond_fitted_range"] == int((table["mv_input_db_sl"] > 25.0).sum())
    # Uncompensated, the texture all but vanishes where EV climbs (paper Figure 8b).
    assert (
        table["mv_perceived_uncomp_db_sl"].min()
        < 1.0
        < 11.0
        < mv["uncompensated"]["max_abs_error_db"]
    )
    assert mv["compensated"]["points_not_felt"] == 0
    assert summary["gamut_mapping"]["as_played"]["share_within_ratings"] < 0.2
    out2 = tmp_path / "br2"
    args = ["render", scene, "--params", params, "--out", str(out2), "--no-figure", *DRAWS]
    assert main([*args, "--max-mv-db-sl", "100", "--max-ev-db-sl", "100"]) == 0
    capsys.readouterr()
    assert (
        json.loads((out2 / "summary.json").read_text())["channels"]["MV"]["points_above_rating"]
        == 0
    )


def test_single_channel_scene_passes_through_without_parameters(tmp_path, capsys):
    scene_file = tmp_path / "smooth_only.yaml"
    scene_file.write_text(
        "schema_version: 1\nscene: smooth_only\n"
        "texture: {name: smooth, stimulus: MV270, perceived_db_sl: 6}\n"
    )
    out = tmp_path / "out"
    assert main(["render", str(scene_file), "--out", str(out)]) == 0
    assert "passed straight through" in capsys.readouterr().out
    table = pd.read_csv(out / "points.csv")
    assert (table["mv_input_db_sl"] == 6.0).all() and (table["mv_perceived_db_sl"] == 6.0).all()
    assert table["ev_input_db_sl"].isna().all()  # a silent channel: an empty field
    summary = json.loads((out / "summary.json").read_text())
    assert summary["single_channel"] and summary["masking"] is None
    assert list(summary["channels"]) == ["MV"]
    assert not list(out.glob("measure_*.yaml"))


def test_missing_pair_writes_the_protocol_that_measures_just_it(tmp_path, capsys):
    partial = write_params(
        tmp_path / "partial.json",
        ramps={"MV180": RAMPS["MV180"]},
        extra=[masking_entry("MV120am40", "EV270", None, None, "insufficient_data")],
    )
    out = tmp_path / "out"
    scene = str(ROOT / "protocols" / "scenes" / "hole_coarse.yaml")
    assert main(["render", scene, "--params", partial, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "MV120am40 masked by EV270: status 'insufficient_data'" in err
    assert "EV270 masked by MV120am40: no entry" in err
    # One protocol per masking direction, so `analyze` never sees one frequency level in two
    # pairs of one experiment.
    for target, masker in (("EV270", "MV120am40"), ("MV120am40", "EV270")):
        written = out / f"measure_{target}_by_{masker}.yaml"
        assert str(written) in err and not (out / "points.csv").exists()
        assert written.read_text().startswith("# Written by masking-lab render:")
        protocol = load_protocol(written)
        assert protocol.kind == "masked" and protocol.experiment == written.stem
        assert sorted(
            (s.target.name, s.masker.name, s.masker_level_db_sl) for s in protocol.sets
        ) == [(target, masker, float(lv)) for lv in (5, 10, 15, 20, 25)]
        sc = protocol.sets[0].staircase
        assert (sc.n_up, sc.n_down, sc.n_reversals, sc.n_reversals_averaged) == (1, 3, 11, 8)
        assert main(["validate", str(written)]) == 0


def test_two_channel_scene_without_params_writes_the_protocol(tmp_path, capsys):
    out = tmp_path / "out"
    scene = str(ROOT / "protocols" / "scenes" / "bump_rough.yaml")
    assert main(["render", scene, "--out", str(out)]) == 2
    assert "pass --params masking_params.json" in capsys.readouterr().err
    for name in ("measure_EV270_by_MV180.yaml", "measure_MV180_by_EV270.yaml"):
        protocol = load_protocol(out / name)
        assert protocol.stimuli() == {"EV270", "MV180"} and len(protocol.sets) == 5


def test_only_the_scene_pair_is_loaded(tmp_path, capsys):
    # An unusable entry for another pair does not stop a scene that does not use it.
    params = write_params(
        tmp_path / "p.json",
        ramps={"MV180": RAMPS["MV180"]},
        extra=[masking_entry("MV120am40", "EV270", None, None, "insufficient_data")],
    )
    scene = str(ROOT / "protocols" / "scenes" / "bump_rough.yaml")
    assert (
        main(["render", scene, "--params", params, "--out", str(tmp_path / "o"), "--no-figure"])
        == 0
    )
    capsys.readouterr()


def test_folded_pair_is_reported_per_point_and_exits_1(tmp_path, capsys):
    params = write_params(tmp_path / "p.json", ramps={"MV180": ((1.0, 2.0), (-1.0, 1.0))})
    scene = str(ROOT / "protocols" / "scenes" / "bump_rough.yaml")
    out = tmp_path / "o"
    assert main(["render", scene, "--params", params, "--out", str(out), "--no-figure"]) == 1
    assert "no unique compensated input" in capsys.readouterr().out
    table = pd.read_csv(out / "points.csv")
    not_unique = table["status"] != "unique"
    assert not_unique.any()
    assert table.loc[not_unique, "mv_input_db_sl"].isna().all()  # no silent pair
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status_counts"]["unique"] + summary["status_counts"]["none"] + summary[
        "status_counts"
    ]["multiple"] == len(table)


def test_bad_scene_or_params_exit_2(tmp_path, capsys):
    assert main(["render", str(tmp_path / "nope.yaml"), "--out", str(tmp_path)]) == 2
    assert "cannot read the scene" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    scene = str(ROOT / "protocols" / "scenes" / "bump_rough.yaml")
    assert main(["render", scene, "--params", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "not valid JSON" in capsys.readouterr().err


def _tiny_scene():
    return Scene(
        "tiny",
        PathSpec(length_mm=10.0, n_points=21),
        GeometrySpec("bump", position_mm=5.0, height_mm=1.0, max_inclination=0.5),
        TextureSpec("rough", "MV180", 12.0),
    )


def test_render_scene_refuses_a_wrong_or_missing_pair():
    scene = _tiny_scene()
    with pytest.raises(SolverError, match="needs their masking functions"):
        render_scene(scene, None)
    with pytest.raises(SolverError, match="for MV270 with EV270"):
        render_scene(scene, MutualMasking(1, 1, -6, 0.6, mv="MV270", ev="EV270"))


def test_render_scene_arrays_and_ideal_passthrough():
    scene = _tiny_scene()
    none = MutualMasking(0.0, 0.0, 0.0, 0.0, mv="MV180", ev="EV270")
    r = render_scene(scene, none)
    np.testing.assert_array_equal(r.mv_input_db_sl, r.mv_target_db_sl)
    np.testing.assert_array_equal(r.ev_perceived_uncomp_db_sl, r.ev_target_db_sl)
    np.testing.assert_allclose(r.t_s, r.x_mm / 51.0)
    assert r.inputs(False)[0] is r.mv_target_db_sl and r.perceived(True)[1] is r.ev_perceived_db_sl


def test_a_rendering_cannot_disagree_with_itself():
    # Targets and inputs are the solution's arrays; what is felt is input − masked AL, also
    # after the inputs are replaced by what a device played.
    pair = MutualMasking(a_db=-2.0, b=0.5, c_db=-1.0, d=0.4, mv="MV180", ev="EV270")
    r = render_scene(_tiny_scene(), pair)
    assert r.mv_input_db_sl is r.solution.mv_input_db_sl
    assert r.ev_target_db_sl is r.solution.ev_target_db_sl
    finite = np.isfinite(r.ev_input_db_sl)
    assert finite.any()
    played_ev = np.where(finite, r.ev_input_db_sl - 2.5, r.ev_input_db_sl)
    played = r.with_inputs(r.mv_input_db_sl, played_ev)
    np.testing.assert_array_equal(played.ev_input_db_sl, played_ev)
    np.testing.assert_allclose(
        played.ev_perceived_db_sl[finite], r.ev_perceived_db_sl[finite] - 2.5, atol=1e-12
    )
    np.testing.assert_array_equal(played.mv_perceived_db_sl, r.mv_perceived_db_sl)
    # The solver's verdicts and the uncompensated side stay those of the rendering.
    np.testing.assert_array_equal(played.solution.status, r.solution.status)
    np.testing.assert_array_equal(played.ev_perceived_uncomp_db_sl, r.ev_perceived_uncomp_db_sl)
    np.testing.assert_array_equal(r.ev_perceived_db_sl, r.ev_input_db_sl - r.ev_masked_al_db_sl)


def test_write_rendering_is_complete_and_json_is_strict(tmp_path):
    scene = Scene(
        "g", PathSpec(length_mm=10.0, n_points=5), GeometrySpec("hole", position_mm=5.0), None
    )
    r = render_scene(scene, None, max_ev_db_sl=8.0)
    paths = write_rendering(r, tmp_path, figure=True)
    assert sorted(p.name for p in paths) == ["figure4.png", "points.csv", "summary.json"]
    summary = json.loads((tmp_path / "summary.json").read_text())  # strict: no NaN/Infinity
    assert summary["channels"]["EV"]["max_rated_db_sl"] == 8.0
    text = (tmp_path / "points.csv").read_text()
    # No non-finite number in the file: the silent MV channel is an empty field.
    assert "inf" not in text.lower() and "nan" not in text.lower() and ",," in text


def test_figure4_drawn_in_a_worker_is_the_same_file(tmp_path):
    pair = MutualMasking(a_db=-2.0, b=0.5, c_db=-1.0, d=0.4, mv="MV180", ev="EV270")
    r = render_scene(_tiny_scene(), pair, max_mv_db_sl=30.0, max_ev_db_sl=30.0, gamut_map="clip")
    here = write_rendering(r, tmp_path / "here")
    worker = write_rendering(r, tmp_path / "worker", figure_worker=True)
    assert [p.name for p in here] == [p.name for p in worker]
    assert [p.name for p in here] == ["points.csv", "summary.json", "figure4.png", "gamut.png"]
    for a, b in zip(here, worker, strict=True):
        assert a.read_bytes() == b.read_bytes(), a.name


def test_runs_mm():
    x = np.arange(8.0)
    mask = np.array([1, 1, 0, 0, 1, 0, 1, 1], dtype=bool)
    assert runs_mm(mask, x) == [(0.0, 1.0), (4.0, 4.0), (6.0, 7.0)]
    assert runs_mm(np.zeros(3, dtype=bool), x[:3]) == []


def test_measurement_protocol_needs_something_to_measure():
    with pytest.raises(SolverError, match="nothing to measure"):
        measurement_protocol([])
    doc = measurement_protocol([PairProblem("EV270", "MV180", "missing")], levels_db_sl=[7.5])
    assert doc["sets"] == [
        {
            "id": "EV270_by_MV180_7.5",
            "target": "EV270",
            "masker": "MV180",
            "masker_level_db_sl": 7.5,
        }
    ]
    assert math.isclose(doc["timing"]["stimulus_s"], 1.8)


def test_bd_one_ulp_below_one_is_ill_conditioned_and_exits_1(tmp_path, capsys):
    # Was (issue 21): "unique" inputs of ~1e17 dB SL, 52 dB off through the model, exit 0.
    doc = json.loads(Path(write_params(tmp_path / "p.json")).read_text())
    for f in doc["functions"]:
        if (f["target"], f["masker"]) == ("MV180", "EV270"):
            f["intercept_db"], f["slope"] = 1.39, 1.0
        if (f["target"], f["masker"]) == ("EV270", "MV180"):
            f["intercept_db"], f["slope"] = -6.22, 1.0 - 2.0**-53
    (tmp_path / "p.json").write_text(json.dumps(doc))
    scene = str(ROOT / "protocols" / "scenes" / "bump_rough.yaml")
    out = tmp_path / "o"
    args = ["render", scene, "--params", str(tmp_path / "p.json"), "--out", str(out)]
    code = main([*args, "--gamut-map", "none"])
    text = capsys.readouterr().out
    assert code == 1
    assert "ill-conditioned" in text and "b·d ≥ 1" not in text and "b·d=1 − 1.11e-16" in text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status_counts"]["unique"] == 0
    (reason,) = summary["no_answer_reasons"]
    assert reason.startswith("ill-conditioned")
    table = pd.read_csv(out / "points.csv")
    assert table["mv_input_db_sl"].isna().all() and (table["status"] == "none").all()
    # Mapped into the gamut (the default), every point gets inputs within the ratings, found on
    # the gamut's edge where the solver cannot answer; the exit status still says so.
    assert main([*args, "--no-figure"]) == 1
    capsys.readouterr()
    table = pd.read_csv(out / "points.csv")
    for ch in ("mv", "ev"):
        assert table[f"{ch}_input_db_sl"].between(0.0, 30.0).all()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["gamut_mapping"]["points_from_gamut_edge"] > 0


def test_the_output_guard_refuses_a_non_finite_number_and_names_the_point(tmp_path):
    scene = Scene("bump", PathSpec(n_points=5), GeometrySpec("bump"), None, source="s.yaml")
    r = render_scene(scene, None)
    ev = r.ev_input_db_sl.copy()
    ev[2] = np.inf  # as if a defect upstream let an infinite level through
    with pytest.raises(SolverError, match=r"s\.yaml: ev_input_db_sl is inf .* x = 45\.9 mm"):
        write_rendering(r.with_inputs(r.mv_input_db_sl, ev), tmp_path / "o", figure=False)
    assert not (tmp_path / "o").exists()
    write_rendering(r, tmp_path / "o", figure=False)  # −inf for the silent MV is fine


@pytest.mark.parametrize("strategy", ["clip", "scale", "compress"])
def test_gamut_mapping_keeps_every_input_within_the_ratings(params, tmp_path, capsys, strategy):
    out = tmp_path / strategy
    scene = str(ROOT / "protocols" / "scenes" / "bump_rough.yaml")
    args = ["render", scene, "--params", params, "--out", str(out), "--gamut-map", strategy]
    args += DRAWS
    assert main(args) == 0
    text = capsys.readouterr().out
    assert f"gamut mapping {strategy}" in text
    summary = json.loads((out / "summary.json").read_text())
    gm = summary["gamut_mapping"]
    assert gm["strategy"] == strategy and gm["points_moved"] > 0
    # Every strategy's metrics, for the trade; this one's are those of the rendering itself.
    assert set(gm["strategies"]) == {"clip", "scale", "compress", "none"}
    assert gm["strategies"][strategy] == gm["as_played"]
    assert "other mappings" in text
    assert gm["as_played"]["share_within_ratings"] == 1.0
    table = pd.read_csv(out / "points.csv")
    for ch in ("mv", "ev"):
        assert table[f"{ch}_input_db_sl"].notna().all()
        assert (table[f"{ch}_input_db_sl"] <= 30.0).all()
        assert (table[f"{ch}_exceeds_rating"] == 0).all()
        # What is felt is the mapped target, which the intended column keeps apart.
        assert np.allclose(table[f"{ch}_perceived_db_sl"], table[f"{ch}_target_db_sl"], atol=1e-6)
    assert (table["ev_intended_db_sl"] != table["ev_target_db_sl"]).any()
    if strategy == "scale":
        assert 0 < gm["gain"] < 1
        ratio = (
            table["ev_target_db_sl"][table["ev_intended_db_sl"] > 0]
            / table["ev_intended_db_sl"][table["ev_intended_db_sl"] > 0]
        )
        assert np.allclose(ratio, gm["gain"])
        assert gm["as_played"]["geometry_correlation"] == pytest.approx(1.0)
        assert gm["as_played"]["texture_sd_db"] == pytest.approx(0.0, abs=1e-9)
    assert (out / "gamut.png").exists() and summary["gamut"]["outline"]
