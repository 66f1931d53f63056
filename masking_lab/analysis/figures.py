"""Figures of the analysis: the masking functions of each experiment (like paper Figure 3).

Drawn in the package's legible style (:func:`masking_lab.formats.png_figure.legible`: fonts of
at least 8 pt at the saved size, constrained layout) and saved byte-stable: no software/date
metadata, fixed size and DPI, so the same input always draws the same pixels. Files are written
through a temp file, fsynced and renamed, like every other output. The per-session staircase
tracks are in :mod:`masking_lab.analysis.track_figures`.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from masking_lab.analysis.pooling import level_sort_key
from masking_lab.formats.png_figure import legible, png_bytes

if TYPE_CHECKING:  # the figure worker draws without loading pandas
    from masking_lab.analysis.experiment import ExperimentResult

__all__ = [
    "experiment_figure_data",
    "experiment_figure_png",
    "experiment_title",
    "masking_function_png",
    "pair_words",
    "safe_stem",
]

_COLORS = ("#1b6ca8", "#d1495b", "#2e933c", "#8f5ba6", "#e08e0b", "#555555")


def pair_words(pair: str) -> str:
    """``"EV270|MV120"`` as words: ``"EV270 masked by MV120"``.

    Examples
    --------
    >>> pair_words("EV270|MV120")
    'EV270 masked by MV120'
    """
    target, _, masker = pair.partition("|")
    return f"{target} masked by {masker}" if masker else target


def masking_function_png(
    *,
    title: str,
    cells: Sequence[Mapping[str, Any]],
    fits: Sequence[Mapping[str, Any]],
) -> bytes:
    """Mean AL shift against masker level with the fitted ramps (one experiment), as PNG.

    Parameters
    ----------
    title : str
        Figure title (names the experiment, target and maskers).
    cells : sequence of mapping
        One per cell: ``mv_stimulus``, ``pair`` ("target|masker"), ``masker_level_db_sl``,
        ``mean_shift_db``, ``se_db`` (dB; None without participants).
    fits : sequence of mapping
        One per pooled group: ``label``, ``levels`` (MV stimuli), ``intercept_db`` (dB),
        ``slope`` (dB per dB SL; None if not fitted), ``fitted_range_db_sl``, ``status``.

    Returns
    -------
    bytes
        A 6.4 × 4.4 inch PNG at 100 dpi.

    Examples
    --------
    >>> cells = [dict(mv_stimulus="MV120", pair="EV270|MV120", masker_level_db_sl=x,
    ...               mean_shift_db=x - 5.0, se_db=0.5) for x in (5.0, 15.0, 25.0)]
    >>> png = masking_function_png(title="t", cells=cells, fits=[])
    >>> png[1:4]
    b'PNG'
    """
    levels = sorted({c["mv_stimulus"] for c in cells}, key=level_sort_key)
    color = {lv: _COLORS[i % len(_COLORS)] for i, lv in enumerate(levels)}
    markers = "osD^vP"
    with legible() as plt:
        fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=100)
        for i, lv in enumerate(levels):
            pts = sorted(
                (c for c in cells if c["mv_stimulus"] == lv), key=lambda c: c["masker_level_db_sl"]
            )
            x = [c["masker_level_db_sl"] for c in pts]
            y = [c["mean_shift_db"] for c in pts]
            se = [c.get("se_db") for c in pts]
            has_bars = any(v is not None and math.isfinite(v) and v > 0 for v in se)
            err = [v if v is not None and math.isfinite(v) else 0.0 for v in se]
            ax.errorbar(
                x,
                y,
                yerr=err if has_bars else None,
                fmt=markers[i % len(markers)],
                color=color[lv],
                capsize=2,
                label=pair_words(pts[0]["pair"]) + (" (mean ± SE)" if has_bars else " (mean)"),
                linestyle="none",
            )
        for fit in fits:
            if fit.get("intercept_db") is None or fit.get("slope") is None:
                continue
            lo, hi = fit["fitted_range_db_sl"]
            xs = np.linspace(lo, hi, 200)
            ys = np.maximum(0.0, fit["intercept_db"] + fit["slope"] * xs)
            first = fit["levels"][0]
            ax.plot(
                xs,
                ys,
                color=color.get(first, "#000000"),
                linewidth=1.4,
                label=f"ramp {fit['label']}: max(0, {fit['intercept_db']:.2f} + "
                f"{fit['slope']:.3f}·x)",
            )
        ax.axhline(0.0, color="#999999", linewidth=0.6, label="no shift")
        ax.set_xlabel("masker level x (dB SL)")
        ax.set_ylabel("AL shift (dB)")
        ax.set_title(title)
        ax.legend(loc="upper left", frameon=False)
        return png_bytes(fig)


def experiment_title(result: ExperimentResult) -> str:
    """``"experiment1: EV270 masked by MV120, MV180, MV270"`` (targets and maskers named).

    Examples
    --------
    >>> experiment_title(results[0])  # doctest: +SKIP
    'experiment1: EV270 masked by MV120, MV180, MV270'
    """
    pairs = [result.pair_of_level[lv] for lv in result.levels]
    targets = list(dict.fromkeys(t for t, _ in pairs))
    maskers = list(dict.fromkeys(m for _, m in pairs))
    if len(targets) == 1:
        what = f"{targets[0]} masked by {', '.join(maskers)}"
    elif len(maskers) == 1:
        what = f"{', '.join(targets)} masked by {maskers[0]}"
    else:
        what = ", ".join(pair_words(f"{t}|{m}") for t, m in pairs)
    return f"{result.experiment}: {what}"


def experiment_figure_png(result: ExperimentResult) -> bytes:
    """The masking-function figure of one experiment's results, as PNG bytes.

    Parameters
    ----------
    result : ExperimentResult
        Cells (mean shift ± SE, dB, against masker level, dB SL) and ramp fits to draw.

    Returns
    -------
    bytes
        The PNG.

    Examples
    --------
    >>> png = experiment_figure_png(results[0])  # doctest: +SKIP
    """
    return masking_function_png(**experiment_figure_data(result))


def experiment_figure_data(result: ExperimentResult) -> dict[str, Any]:
    """The arguments of :func:`masking_function_png` for one experiment's results: plain
    data (str, float, lists, dicts), so a worker process draws it without loading pandas.

    Examples
    --------
    >>> sorted(experiment_figure_data(results[0]))  # doctest: +SKIP
    ['cells', 'fits', 'title']
    """
    cells = [
        {
            "mv_stimulus": c.mv_stimulus,
            "pair": c.pair,
            "masker_level_db_sl": c.masker_level_db_sl,
            "mean_shift_db": c.mean_shift_db,
            "se_db": None if c.test is None else c.test.se,
        }
        for c in result.cells
    ]
    fits = [
        {
            "label": g.label,
            "levels": g.levels,
            "intercept_db": g.fit.intercept_db if g.fit.status == "fitted" else None,
            "slope": g.fit.slope,
            "fitted_range_db_sl": g.fit.fitted_range_db_sl,
            "status": g.fit.status,
        }
        for g in result.fits
    ]
    return {"title": experiment_title(result), "cells": cells, "fits": fits}


def safe_stem(name: str) -> str:
    """``name`` made safe as a file name stem: runs of other characters become ``_``.

    Parameters
    ----------
    name : str
        E.g. an experiment id or ``participant_experiment_session``.

    Returns
    -------
    str
        Letters, digits, ``.``, ``_`` and ``-`` only; ``"unnamed"`` if nothing is left.

    Examples
    --------
    >>> safe_stem("EV270|MV"), safe_stem("//")
    ('EV270_MV', 'unnamed')
    """
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("_") or "unnamed"
