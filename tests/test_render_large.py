"""A scene of the schema's largest size renders (issue 21 campaign, seed 52: a drawn scene of
100,000 points took > 20 s of CPU in ``render``). The time went to numpy's NaN-percentile, which
loops in Python per point once a NaN is present, and to the gamut's scale search projecting every
point; both are now vectorised. These tests pin that the fast paths give numpy's answers
exactly; the largest scene renders through the CLI (its speed is not asserted here)."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from test_render import write_params

from masking_lab.commands.cli import main
from masking_lab.rendering.gamut import perceptual_gamut
from masking_lab.rendering.pair import MutualMasking
from masking_lab.rendering.scene import MAX_POINTS
from masking_lab.rendering.uncertainty import _nan_percentile


@pytest.mark.parametrize("seed", range(6))
def test_nan_percentile_matches_numpy_with_nans_and_all_nan_columns(seed):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(2, 37, 23)) * 10.0 ** rng.integers(-3, 4)
    x[rng.random(x.shape) < 0.3] = np.nan
    x[:, :, 0] = np.nan  # a point with no answer in any draw
    x[:, 3, :] = np.round(x[:, 3, :], 1)  # ties
    for axis in (0, 1, 2):
        for q in ([5.0, 95.0], [2.5, 97.5], [50.0]):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                expected = np.nanpercentile(x, q, axis=axis)
            np.testing.assert_array_equal(_nan_percentile(x, q, axis=axis), expected)


@pytest.mark.parametrize(
    "pair",
    [
        MutualMasking(0.0, 0.0, 0.0, 0.0),
        MutualMasking(1.3, 1.06, -5.9, 0.66),
        MutualMasking(-2.0, 2.0, -2.0, 1.0),
    ],
    ids=["none", "bd<1", "bd>1"],
)
def test_contains_agrees_with_the_distance_to_the_gamut(pair):
    g = perceptual_gamut(pair, 30.0, 25.0)
    rng = np.random.default_rng(3)
    m, e = rng.uniform(-20, 60, 4000), rng.uniform(-20, 60, 4000)
    m[:5], e[5:10] = np.nan, np.inf
    for tol in (0.0, 1e-9, 0.5):
        expected = g.distance_db(m, e) <= tol
        got = g.contains(m, e, tol_db=tol)
        assert got.tolist() == expected.tolist()
        assert 0 < got.sum() < got.size  # both sides exercised


def test_a_scene_of_the_largest_size_renders_with_intervals(tmp_path):
    scene = tmp_path / "big.yaml"
    scene.write_text(
        "schema_version: 1\nscene: big\n"
        f"path: {{length_mm: 10000, n_points: {MAX_POINTS}, speed_mm_s: 0.1}}\n"
        "geometry: {shape: bump, height_mm: 1000, max_inclination: 0.001, position_mm: 0,\n"
        "           perceived_db_sl: [-100, 100]}\n"
        "texture: {name: rough, stimulus: MV180, perceived_db_sl: 100}\n",
        encoding="utf-8",
    )
    params = write_params(tmp_path / "masking_params.json")
    out = tmp_path / "out"
    argv = ["render", str(scene), "--params", params, "--out", str(out), "--no-figure"]
    assert main([*argv, "--gamut-map", "scale", "--uncertainty-draws", "40"]) in (0, 1)
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    assert summary["n_points"] == MAX_POINTS
