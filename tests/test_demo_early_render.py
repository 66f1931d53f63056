"""The demo renders its scene from the export the analysis hands over before writing it
(``run_analyze(on_params=...)``): the same bytes as analysing first and rendering after."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from masking_lab.analysis.batch import run_analyze
from masking_lab.analysis.settings import AnalysisSettings
from masking_lab.demo import _render, _SceneRender
from masking_lab.formats.masking_params import MaskingParamsError
from masking_lab.simulation.synthetic_logs import simulate_study

SETTINGS = AnalysisSettings(seed=3, n_boot=100, pf_boot=50)


def _files(folder: Path) -> dict[str, bytes]:
    return {
        p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()
    }


@pytest.fixture(scope="module")
def analysed(tmp_path_factory):
    """A small simulated study, analysed without the hook (``analysis``) and with it."""
    root = tmp_path_factory.mktemp("early")
    simulate_study(root / "data", n_participants=4, seed=11, baseline_start_above_db=10.0)
    run_analyze(root / "data", root / "plain", SETTINGS)
    handed: list[str] = []
    run_analyze(root / "data", root / "analysis", SETTINGS, on_params=handed.append)
    return root, handed


def test_the_hook_hears_the_export_once_and_changes_no_output(analysed):
    root, handed = analysed
    assert len(handed) == 1
    assert handed[0].encode("utf-8") == (root / "analysis" / "masking_params.json").read_bytes()
    plain, hooked = _files(root / "plain"), _files(root / "analysis")
    assert sorted(plain) == sorted(hooked)
    assert [n for n in plain if plain[n] != hooked[n]] == []


def test_the_scene_rendered_in_a_worker_from_the_text_is_the_scene_from_the_file(analysed):
    root, handed = analysed
    from_file = _render(root)
    shutil.move(root / "render", root / "render_from_file")
    scene = _SceneRender(root)
    try:
        scene.start(handed[0])
        assert scene.pending is not None  # rendered in the worker, not here
        from_text = scene.result()
    finally:
        scene.close()
    assert json.dumps(from_text, sort_keys=True) == json.dumps(from_file, sort_keys=True)
    assert _files(root / "render") == _files(root / "render_from_file")
    assert {Path(p).name for p in from_text["files"]} >= {"points.csv", "figure4.png"}


def test_without_the_text_the_scene_is_rendered_from_the_written_file(analysed, tmp_path):
    root, _ = analysed
    (tmp_path / "analysis").mkdir()
    shutil.copy(root / "analysis" / "masking_params.json", tmp_path / "analysis")
    scene = _SceneRender(tmp_path)
    try:
        summary = scene.result()
    finally:
        scene.close()
    assert [Path(p).parent for p in summary["files"]] == [tmp_path / "render"] * 4
    assert _files(tmp_path / "render") == _files(root / "render_from_file")


def test_a_broken_export_text_is_refused_as_the_file_would_be(analysed, tmp_path):
    _, handed = analysed
    doc = json.loads(handed[0])
    del doc["functions"]
    with pytest.raises(MaskingParamsError):
        _render(tmp_path, json.dumps(doc))


def test_a_failed_analysis_leaves_no_scene_behind(analysed, tmp_path):
    _, handed = analysed
    scene = _SceneRender(tmp_path)
    scene.start(handed[0])
    scene.close(discard=True)  # waits for the worker, then removes what it wrote
    assert not (tmp_path / "render").exists()
