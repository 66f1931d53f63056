"""Every figure the package saves is legible at 100 %: every visible text artist is at least
8 pt at the saved size, every drawn axes has labelled axes, titles, labels and legends do not
overlap, and the figures say what the issue asked (target and masker named, n with the right
grammar, chance lines, no '± SE' without bars, the rig's unplayable points marked)."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure
from test_render import write_params
from test_usertest_analysis import header, trial_records, write_log

from masking_lab.analysis.figure_pool import FigurePool
from masking_lab.commands.cli import main
from masking_lab.formats.png_figure import MIN_FONT_PT, small_texts
from masking_lab.simulation.synthetic_logs import simulate_study

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture()
def saved(monkeypatch):
    """Record every figure as it is saved (in this process), with what it shows.

    analyze's summary figures are drawn in this process, not in its figure worker, so that they
    are seen here; the worker draws the same bytes (tests/test_lab_outputs.py)."""
    monkeypatch.setattr(FigurePool, "_add_lane", lambda self: False)
    seen: list[dict] = []
    original = Figure.savefig

    def record(self, *args, **kwargs):
        original(self, *args, **kwargs)  # draws: text extents are final now
        seen.append(_inspect(self))

    monkeypatch.setattr(Figure, "savefig", record)
    return seen


def _inspect(fig: Figure) -> dict:
    renderer = fig.canvas.get_renderer()
    boxes = []
    if fig._suptitle is not None and fig._suptitle.get_text():
        boxes.append(("suptitle", fig._suptitle.get_window_extent(renderer)))
    for k, t in enumerate(fig.texts):
        if t.get_visible() and t.get_text() and t not in (fig._suptitle, fig._supxlabel):
            boxes.append((f"figure text {k}", t.get_window_extent(renderer)))
    if fig._supxlabel is not None and fig._supxlabel.get_text():
        boxes.append(("supxlabel", fig._supxlabel.get_window_extent(renderer)))
    axes = [ax for ax in fig.axes if ax.get_visible()]
    unlabelled = []
    for i, ax in enumerate(axes):
        for name, t in (
            ("title", ax.title),
            ("xlabel", ax.xaxis.label),
            ("ylabel", ax.yaxis.label),
        ):
            if t.get_visible() and t.get_text():
                boxes.append((f"axes{i} {name}", t.get_window_extent(renderer)))
        leg = ax.get_legend()
        if leg is not None:
            boxes.append((f"axes{i} legend", leg.get_window_extent(renderer)))
        has_x = ax.get_xlabel() or any(
            a.get_xlabel() for a in axes if a is not ax and a.get_shared_x_axes().joined(a, ax)
        )
        if not (has_x and ax.get_ylabel()):
            unlabelled.append(ax.get_title())
    overlaps = [
        (a, b)
        for (a, ba), (b, bb) in itertools.combinations(boxes, 2)
        if ba.width > 0 and bb.width > 0 and ba.overlaps(bb)
    ]
    titles = [fig._suptitle.get_text() if fig._suptitle else ""] + [ax.get_title() for ax in axes]
    return {
        "titles": titles,
        "small": small_texts(fig, MIN_FONT_PT),
        "unlabelled": unlabelled,
        "overlaps": overlaps,
        "texts": [t.get_text() for t in fig.findobj(lambda a: hasattr(a, "get_text"))],
        "legend_labels": [
            t.get_text() for ax in axes if ax.get_legend() for t in ax.get_legend().get_texts()
        ],
    }


def _assert_legible(figures: list[dict]) -> None:
    assert figures
    for f in figures:
        assert f["small"] == [], (f["titles"][:2], f["small"][:5])
        assert f["unlabelled"] == [], (f["titles"][:2], f["unlabelled"])
        assert f["overlaps"] == [], (f["titles"][:2], f["overlaps"])


def test_analysis_figures_masking_functions_and_tracks(saved, tmp_path):
    simulate_study(tmp_path / "data", n_participants=2, seed=4, baseline_start_above_db=10.0)
    argv = ["analyze", str(tmp_path / "data"), "--out", str(tmp_path / "out"), "--quiet"]
    assert main([*argv, "--figures", "all", "--n-boot", "200"]) == 0
    _assert_legible(saved)
    masking = [f for f in saved if f["titles"][1].startswith("experiment")]
    assert [f["titles"][1] for f in masking] == [
        "experiment1: EV270 masked by MV120, MV180, MV270",
        "experiment2: MV120, MV180, MV270 masked by EV270",
    ]
    tracks = [f for f in saved if f["titles"][0].startswith("staircase tracks")]
    assert len(tracks) == 6  # 2 participants x 3 sessions, drawn in this process
    assert {"correct", "wrong", "reversal", "AL"} <= set(tracks[0]["texts"])


def test_masking_figure_says_se_only_where_bars_are_drawn(saved, tmp_path):
    table = tmp_path / "means.csv"
    rows = ["target,masker,masker_level_db_sl,shift_db"]
    rows += [f"EV270,MV120,{x},{0.6 * x - 5:.2f}" for x in (5, 10, 15, 20, 25)]
    table.write_text("\n".join(rows) + "\n")
    assert main(["fit", str(table), "--out", str(tmp_path / "out")]) == 0
    (fig,) = saved
    assert not any("SE" in t for t in fig["titles"] + fig["legend_labels"])
    _assert_legible(saved)


def test_figure4_marks_what_the_rig_cannot_play(saved, tmp_path):
    params = write_params(tmp_path / "masking_params.json")
    scene = ROOT / "protocols" / "scenes" / "bump_rough.yaml"
    out = tmp_path / "render"
    args = ["render", str(scene), "--params", params, "--out", str(out), "--gamut-map", "none"]
    assert main(args) == 0
    fig, gamut = saved  # figure 4, then the gamut (Figure 6)
    _assert_legible(saved)
    assert "masked by" in fig["titles"][0]
    assert any("outside the gamut" in t for t in gamut["legend_labels"])
    summary = json.loads((out / "summary.json").read_text())
    over = sum(ch["points_above_rating"] > 0 for ch in summary["channels"].values())
    assert over, "the shipped bump_rough scene needs more than the rig's rating somewhere"
    unplayable = [t for t in fig["legend_labels"] if t.startswith("rig cannot play")]
    assert len(unplayable) == 1 and f"of {summary['n_points']} points" in unplayable[0]
    assert any(t.endswith("perceived if clipped") for t in fig["legend_labels"])


def test_mapped_figure4_shows_bands_and_the_intended_levels(saved, tmp_path):
    params = write_params(tmp_path / "masking_params.json")
    scene = ROOT / "protocols" / "scenes" / "bump_rough.yaml"
    assert main(["render", str(scene), "--params", params, "--out", str(tmp_path / "r")]) == 0
    fig, gamut = saved
    _assert_legible(saved)
    assert "gamut mapping: clip" in fig["titles"][0]
    labels = fig["legend_labels"]
    assert any("95 % interval (masking fits)" in t for t in labels)
    assert any("intended by the scene" in t for t in labels)
    assert any("after gamut mapping" in t for t in gamut["legend_labels"])


def test_figure8a_says_n_draws_chance_and_no_zero_sd_bars(saved, tmp_path):
    data = tmp_path / "data"
    write_log(data / "usertest-A.jsonl", [header("A"), *trial_records("A")])
    assert main(["usertest-report", str(data), "--out", str(tmp_path / "one")]) == 0
    (one,) = saved
    assert "of 1 participant (" in one["titles"][1] and "participants" not in one["titles"][1]
    assert "chance (guessing)" in one["legend_labels"]
    assert "± SD over participants" not in one["legend_labels"]  # no bars with n = 1
    saved.clear()
    for p in ("B", "C"):
        write_log(data / f"usertest-{p}.jsonl", [header(p), *trial_records(p)])
    assert main(["usertest-report", str(data), "--out", str(tmp_path / "three")]) == 0
    (three,) = saved
    assert "of 3 participants (mean ± SD)" in three["titles"][1]
    assert "± SD over participants" in three["legend_labels"]
    _assert_legible([one, three])


def test_plan_figure_is_legible(saved, tmp_path):
    exp1 = ROOT / "protocols" / "experiment1.yaml"
    argv = ["plan", str(exp1), "--replicates", "20", "--out", str(tmp_path)]
    assert main(argv) == 0
    _assert_legible(saved)
    assert np.all([f["titles"][1] for f in saved])


def test_figure8a_notes_clipping(saved, tmp_path):
    data = tmp_path / "data"
    for p in ("A", "B"):
        recs = trial_records(p)
        for r in recs[:2]:  # the first two compensated trials were clipped
            r["clipped"] = {"MV": {"n_ticks": 3, "max_excess_db": 1.5}}
        write_log(data / f"usertest-{p}.jsonl", [header(p), *recs])
    assert main(["usertest-report", str(data), "--out", str(tmp_path / "out")]) == 0
    (fig,) = saved
    assert "compensated: 4 of 8 trials clipped at the rig's limits" in fig["texts"]
    _assert_legible(saved)
    text = (tmp_path / "out" / "report.txt").read_text(encoding="utf-8")
    assert "compensated: 4 of 8 trials were clipped at the rig's limits" in text


def test_track_figures_reused_in_parallel_draw_the_same_pixels(tmp_path, monkeypatch):
    from masking_lab.analysis import track_figures
    from masking_lab.analysis.track_figures import draw_tracks, track_job
    from masking_lab.formats.session_log import read_log

    logs = simulate_study(tmp_path / "data", n_participants=2, seed=8)
    parsed = [read_log(p) for p in logs]
    # Chunks of 3 instead of 8 (the workers fork, so they see it): 9 figures make three
    # chunks on two workers, so one worker reuses its canvases across chunks, as 18 figures
    # did with chunks of 8; every log is drawn, the first two after different neighbours.
    monkeypatch.setattr(track_figures, "_CHUNK", 3)
    order = [parsed[i % len(parsed)] for i in (0, 3, 1, 4, 2, 5, 1, 2, 0)]

    def jobs(folder: Path):
        return [track_job(folder / f"{k:02d}.png", log, {}) for k, log in enumerate(order)]

    serial = draw_tracks(jobs(tmp_path / "serial"), workers=1)
    parallel = draw_tracks(jobs(tmp_path / "parallel"), workers=2)
    assert [p.name for p in serial] == [p.name for p in parallel]
    for a, b in zip(serial, parallel, strict=True):
        assert a.read_bytes() == b.read_bytes(), a.name
    # Same session, different neighbours: identical pixels, so nothing leaks between figures.
    assert serial[0].read_bytes() == serial[8].read_bytes()
    assert serial[2].read_bytes() == serial[6].read_bytes()
    assert serial[0].read_bytes() != serial[2].read_bytes()
