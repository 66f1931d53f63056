"""LineBundle draws the AL-shift figure's participant lines with the bytes of one Line2D each."""

from __future__ import annotations

import random

import numpy as np
import pytest

import masking_lab.analysis.line_bundle as line_bundle
from masking_lab.analysis.lab_figures import shift_figure_png


def _shifts(seed: int, n_people: int) -> tuple[list[dict], set]:
    rng = random.Random(seed)
    shifts, flagged = [], set()
    for k in range(n_people):
        p = f"P{k:03d}"
        for mv in ("MV120", "MV180", "MV270"):
            if rng.random() < 0.2:  # missing from this panel
                continue
            for level in rng.sample([5.0, 10.0, 15.0, 20.0, 25.0, 30.0], rng.randint(1, 5)):
                shift = rng.gauss(level / 3, 4.0)
                if rng.random() < 0.03:
                    level = float("nan")  # a level that matches no other
                shifts.append({"participant": p, "mv_stimulus": mv, "pair": f"EV270|{mv}",
                               "masker_level_db_sl": level, "shift_db": shift})  # fmt: skip
                if rng.random() < 0.05:
                    flagged.add((p, f"EV270|{mv}", level))
    return shifts, flagged


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # the mean of a NaN level
@pytest.mark.parametrize(("seed", "n_people"), [(0, 1), (1, 2), (2, 13), (3, 60)])
def test_bundle_draws_the_bytes_of_one_line2d_each(monkeypatch, seed, n_people):
    shifts, flagged = _shifts(seed, n_people)
    bundled = shift_figure_png("e1", shifts, flagged)
    monkeypatch.setattr(line_bundle, "bundle_supported", lambda template: False)
    assert shift_figure_png("e1", shifts, flagged) == bundled


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_first_participant_missing_from_a_panel(monkeypatch):
    shifts, _ = _shifts(4, 8)
    shifts = [s for s in shifts if not (s["participant"] == "P000" and s["mv_stimulus"] == "MV120")]
    bundled = shift_figure_png("e1", shifts)
    monkeypatch.setattr(line_bundle, "bundle_supported", lambda template: False)
    assert shift_figure_png("e1", shifts) == bundled


def test_styles_the_bundle_cannot_stand_for():
    from matplotlib.lines import Line2D

    ok = {"marker": "o", "linestyle": "-", "linewidth": 0.9, "markersize": 3.5, "alpha": 0.7}
    assert line_bundle.bundle_supported(Line2D([], [], **ok))
    for change in ({"linestyle": "--"}, {"marker": ","}, {"markerfacecolor": "white"},
                   {"fillstyle": "left"}, {"markevery": 2}, {"drawstyle": "steps"}):  # fmt: skip
        assert not line_bundle.bundle_supported(Line2D([], [], **{**ok, **change}))


def test_bundle_refuses_an_unsupported_style():
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    ax = Figure().add_subplot()
    with pytest.raises(ValueError, match="draws differently"):
        line_bundle.LineBundle(ax, Line2D([], [], linestyle="--"), [(np.zeros((1, 2)), "C0")])


def test_the_layout_pass_is_told_apart_from_the_real_draw():
    # matplotlib's pre-save layout pass swaps the renderer's draw methods for no-ops: the bundle
    # skips its lines there (they would be walked for nothing) and draws them otherwise.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    renderer = FigureCanvasAgg(Figure()).get_renderer()
    assert not line_bundle._drawing_disabled(renderer)
    with renderer._draw_disabled():
        assert line_bundle._drawing_disabled(renderer)
    assert not line_bundle._drawing_disabled(renderer)


@pytest.mark.parametrize("n_points", [1, 127, 128, 400])
def test_short_and_long_lines_draw_as_line2d_draws_them(n_points):
    # Paths of 128 or more vertices may be simplified by Agg, so the bundle builds them with
    # Path() as Line2D does; shorter ones skip its checks.
    from matplotlib.lines import Line2D

    from masking_lab.formats.png_figure import legible, png_bytes

    x = np.linspace(0.0, 30.0, n_points)
    lines = [(np.column_stack([x, np.sin(x / (k + 1)) * 5 + k]), f"C{k}") for k in range(3)]
    style = {"marker": "o", "linestyle": "-", "linewidth": 0.9, "markersize": 3.5, "alpha": 0.7}

    def draw(bundled: bool) -> bytes:
        with legible() as plt:
            fig, ax = plt.subplots(figsize=(3, 2))
            if bundled:
                line_bundle.LineBundle(ax, Line2D([], [], **style), lines)
            else:
                for xy, color in lines:
                    ax.plot(xy[:, 0], xy[:, 1], color=color, **style)
            return png_bytes(fig)

    assert draw(True) == draw(False)
