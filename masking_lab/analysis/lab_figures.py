"""Per-participant figures (*shell*: draws PNGs): psychometric functions and AL shifts.

* :func:`pf_figure_png` — one participant's sets of one experiment, a panel per set: the
  proportion correct at each level run (marker area grows with the trials there, n printed
  beside it), the fitted psychometric function and its threshold α (dashed) and AL at the
  staircase's target p (dotted);
* :func:`shift_figure_png` — one experiment's AL shifts, a panel per MV stimulus: each
  participant's shift against masker level (thin lines), their mean (thick), outliers circled.

Both use the package's legible style (:mod:`masking_lab.formats.png_figure`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from masking_lab.analysis.psychometric import PFFit, binned, pf_curve
from masking_lab.formats.png_figure import legible, png_bytes

__all__ = ["pf_figure_png", "shift_figure_png", "shift_figure_png_columns"]

_UNIT = {"db_sl": "dB SL", "db_v": "dB re 1 V"}
# A participant's line in the AL-shift figure (widths in points).
_PERSON: dict[str, Any] = {"linewidth": 0.9, "markersize": 3.5, "alpha": 0.7}


def _grid(n: int) -> tuple[int, int]:
    cols = min(4, max(1, n))
    return math.ceil(n / cols), cols


def pf_figure_png(title: str, panels: Sequence[Mapping[str, Any]]) -> bytes:
    """The psychometric functions of one participant's sets, as PNG bytes.

    Parameters
    ----------
    title : str
        Figure title (participant and experiment).
    panels : sequence of mapping
        Per set: ``label`` (str), ``levels_db`` and ``correct`` (the trials), ``unit``
        (``db_sl`` or ``db_v``) and ``fit`` (:class:`~masking_lab.analysis.psychometric.PFFit`).

    Examples
    --------
    >>> from masking_lab.analysis.psychometric import fit_pf
    >>> x = [0.0, 2.0, 4.0] * 10
    >>> r = [False, True, True] * 10
    >>> png = pf_figure_png("P1", [{"label": "A", "levels_db": x, "correct": r,
    ...                            "unit": "db_sl", "fit": fit_pf(x, r, n_boot=0)}])
    >>> png[:4]
    b'\\x89PNG'
    """
    rows, cols = _grid(len(panels))
    with legible(constrained=False) as plt:
        # Fixed margins in inches, not constrained layout: its layout passes took half of the
        # drawing time of a 15-panel figure (2.6 s), and `analyze --figures all` draws one
        # per participant and experiment.
        fig, axes = plt.subplots(rows, cols, squeeze=False, layout="none")
        for ax in axes.ravel()[len(panels) :]:
            ax.set_visible(False)
        for ax, panel in zip(axes.ravel(), panels, strict=False):
            _pf_panel(ax, panel)
        handles, labels = axes.ravel()[0].get_legend_handles_labels()
        legend_cols = min(4, len(labels), cols + (cols > 1))
        legend_h = 0.1 + 0.22 * math.ceil(len(labels) / max(1, legend_cols)) if labels else 0.0
        _pf_margins(fig, rows, cols, legend_h)
        if handles:
            fig.legend(handles, labels, loc="lower center", bbox_to_anchor=(0.5, 0.0),
                       ncols=legend_cols, fontsize=8, frameon=False)  # fmt: skip
        fig.suptitle(title, y=1.0 - 0.1 / fig.get_figheight(), va="top")
        return png_bytes(fig)


# A panel's box and the space around it, inches: the gaps hold its two-line title above and
# its tick labels and x label below (rows), its y label and tick labels (columns).
_AX_W, _AX_H, _GAP_W, _GAP_H = 2.5, 1.75, 0.8, 0.95
_LEFT, _RIGHT, _TOP, _BOTTOM = 0.65, 0.2, 0.9, 0.5


def _pf_margins(fig: Any, rows: int, cols: int, legend_h: float) -> None:
    width = _LEFT + cols * _AX_W + (cols - 1) * _GAP_W + _RIGHT
    height = _TOP + rows * _AX_H + (rows - 1) * _GAP_H + _BOTTOM + legend_h
    fig.set_size_inches(width, height)
    fig.subplots_adjust(
        left=_LEFT / width,
        right=1.0 - _RIGHT / width,
        top=1.0 - _TOP / height,
        bottom=(_BOTTOM + legend_h) / height,
        wspace=_GAP_W / _AX_W,
        hspace=_GAP_H / _AX_H,
    )


def _pf_panel(ax: Any, panel: Mapping[str, Any]) -> None:
    from matplotlib.ticker import MaxNLocator

    fit: PFFit = panel["fit"]
    x, n, k = binned(panel["levels_db"], panel["correct"])
    ax.scatter(
        x, k / n, s=12 + 10 * n, facecolors="white", edgecolors="black", zorder=3,
        label="proportion correct (area ∝ n)",
    )  # fmt: skip
    for xi, ni, pi in zip(x, n, k / n, strict=True):
        ax.annotate(f"{int(ni)}", (xi, pi), textcoords="offset points", xytext=(0, 7),
                    ha="center", fontsize=8)  # fmt: skip
    ax.axhline(fit.guess, color="0.6", lw=0.8, ls=":", label="guess rate")
    th, slope, lapse = fit.threshold_db, fit.slope_per_db, fit.lapse  # all set when fit.ok
    if fit.ok and th is not None and slope is not None and lapse is not None:
        lo, hi = float(x.min()), float(x.max())
        pad = max(1.0, 0.1 * (hi - lo))
        xs = np.linspace(lo - pad, hi + pad, 200)
        ys = pf_curve(xs, th, slope, lapse, fit.guess)
        ax.plot(xs, ys, color="C0", lw=1.6, label="fitted function")
        ax.axvline(fit.threshold_db, color="C3", lw=1.2, ls="--", label="threshold α")
        ax.axvline(fit.al_db, color="C2", lw=1.2, ls=":", label="AL at target p")
        sub = f"α = {fit.threshold_db:.1f}, β = {fit.slope_per_db:.2f}/dB, λ = {fit.lapse:.3f}"
    else:
        sub = "no fit: " + (fit.message or "")[:40]
    # An explicit y skips matplotlib's title placement pass (a bounding-box walk per panel).
    ax.set_title(f"{panel['label']}\n{sub}", fontsize=8.5, y=1.0)
    ax.set_ylim(0.0, 1.08)
    ax.set_yticks([0.0, 0.25, 0.5, 0.75, 1.0])
    ax.xaxis.set_major_locator(MaxNLocator(5))
    ax.set_xlabel(f"level ({_UNIT.get(panel.get('unit', ''), 'dB')})")
    ax.set_ylabel("p(correct)")


def shift_figure_png_columns(
    title: str,
    columns: Mapping[str, Sequence[Any]],
    flagged: set[tuple[str, str, float]] | None = None,
) -> bytes:
    """:func:`shift_figure_png` of shifts given column by column (``columns``: the keys of a
    shift → the values of every shift, in order): what a run hands its figure worker, a list
    per column being a fraction of the memory of a dict per set.

    Examples
    --------
    >>> png = shift_figure_png_columns("e1", {"participant": ["P1"], "mv_stimulus": ["MV120"],
    ...     "pair": ["EV270|MV120"], "masker_level_db_sl": [10.0], "shift_db": [2.0]})
    >>> png[:4]
    b'\\x89PNG'
    """
    names = list(columns)
    shifts = [dict(zip(names, row, strict=True)) for row in zip(*columns.values(), strict=True)]
    return shift_figure_png(title, shifts, flagged)


def shift_figure_png(
    title: str,
    shifts: Sequence[Mapping[str, Any]],
    flagged: set[tuple[str, str, float]] | None = None,
) -> bytes:
    """Individual AL shifts of one experiment, a panel per MV stimulus, as PNG bytes.

    Parameters
    ----------
    title : str
        Figure title.
    shifts : sequence of mapping
        ``participant``, ``mv_stimulus``, ``pair``, ``masker_level_db_sl`` (dB SL) and
        ``shift_db`` (dB) per completed set.
    flagged : set of (participant, pair, level), optional
        Outliers to circle.

    Examples
    --------
    >>> png = shift_figure_png("e1", [{"participant": "P1", "mv_stimulus": "MV120",
    ...     "pair": "EV270|MV120", "masker_level_db_sl": 10.0, "shift_db": 2.0}])
    >>> png[:4]
    b'\\x89PNG'
    """
    from matplotlib.lines import Line2D  # here: the main process imports this module

    from masking_lab.analysis.line_bundle import LineBundle, bundle_supported

    flagged = flagged or set()
    levels = sorted({str(s["mv_stimulus"]) for s in shifts})
    rows, cols = _grid(len(levels))
    people = sorted({str(s["participant"]) for s in shifts})
    with legible() as plt:
        fig, axes = plt.subplots(
            rows, cols, figsize=(3.2 * cols + 0.4, 2.8 * rows + 0.6), squeeze=False,
            sharey=True,
        )  # fmt: skip
        for ax in axes.ravel()[len(levels) :]:
            ax.set_visible(False)
        template = Line2D([], [], marker="o", linestyle="-", **_PERSON)  # participants' lines
        bundle = bundle_supported(template)
        for ax, lv in zip(axes.ravel(), levels, strict=False):
            mine = [s for s in shifts if s["mv_stimulus"] == lv]
            pair = str(mine[0]["pair"])
            # grouped once, in order (a scan of the panel per participant is quadratic)
            by_person: dict[Any, list[Mapping[str, Any]]] = {}
            for s in mine:
                by_person.setdefault(s["participant"], []).append(s)
            # The first participant's line is a Line2D (the legend's handle); the others, in
            # the same order and style, one LineBundle (the same pixels, a fraction of the time).
            bundled: list[tuple[np.ndarray, str]] = []
            for i, p in enumerate(people):
                pts = sorted(
                    (float(s["masker_level_db_sl"]), float(s["shift_db"]))
                    for s in by_person.get(p, ())
                )
                if pts and (i == 0 or not bundle):
                    xs, ys = zip(*pts, strict=True)
                    ax.plot(xs, ys, "o-", **_PERSON, color=f"C{i % 10}",
                            label="participants" if i == 0 else None)  # fmt: skip
                elif pts:
                    bundled.append((np.array(pts, dtype=float), f"C{i % 10}"))
                for x, y in pts:
                    if (p, pair, x) in flagged:
                        ax.scatter([x], [y], s=140, facecolors="none", edgecolors="red",
                                   linewidths=1.5, zorder=4, label="outlier")  # fmt: skip
            if bundled:
                LineBundle(ax, template, bundled)
            xs_all = sorted({float(s["masker_level_db_sl"]) for s in mine})
            at_level: dict[float, list[float]] = {}
            for s in mine:
                x = float(s["masker_level_db_sl"])
                if x == x:  # NaN matches no level
                    at_level.setdefault(x, []).append(float(s["shift_db"]))
            means = [float(np.mean(at_level.get(x, []) if x == x else [])) for x in xs_all]
            ax.plot(xs_all, means, "k-", lw=2.6, label="mean")
            ax.axhline(0.0, color="0.6", lw=0.8)
            ax.set_title(pair)
            ax.set_xlabel("masker level (dB SL)")
            ax.set_ylabel("AL shift (dB)")
        seen: dict[str, Any] = {}
        for ax in axes.ravel():
            for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
                seen.setdefault(lab, h)
        if seen:
            fig.legend(list(seen.values()), list(seen), loc="outside lower center",
                       ncols=len(seen), fontsize=8)  # fmt: skip
        fig.suptitle(title)
        return png_bytes(fig)
