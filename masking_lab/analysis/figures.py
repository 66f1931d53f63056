"""Figures of the analysis: masking functions (like paper Figure 3) and staircase tracks.

Matplotlib with the Agg backend, PNG, byte-stable: no software/date metadata, fixed size and
DPI, and the same input always draws the same pixels. Files are written through a temp file,
fsynced and renamed, like every other output.
"""

from __future__ import annotations

import io
import math
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from masking_lab.analysis.experiment import ExperimentResult
from masking_lab.analysis.pooling import level_sort_key
from masking_lab.formats.fileio import write_bytes_atomic
from masking_lab.formats.session_log import SessionLog

__all__ = ["experiment_figure", "masking_function_figure", "safe_stem", "track_figure"]

_COLORS = ("#1b6ca8", "#d1495b", "#2e933c", "#8f5ba6", "#e08e0b", "#555555")


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def masking_function_figure(
    path: str | Path,
    *,
    experiment: str,
    cells: Sequence[Mapping[str, Any]],
    fits: Sequence[Mapping[str, Any]],
) -> Path:
    """Mean AL shift against masker level with the fitted ramps (one experiment).

    Parameters
    ----------
    path : path
        PNG to write.
    experiment : str
        Experiment id (title).
    cells : sequence of mapping
        One per cell: ``mv_stimulus``, ``pair`` ("target|masker"), ``masker_level_db_sl``,
        ``mean_shift_db``, ``se_db`` (None without participants).
    fits : sequence of mapping
        One per pooled group: ``label``, ``levels`` (MV stimuli), ``intercept_db``, ``slope``
        (None if not fitted), ``fitted_range_db_sl``, ``status``.
    """
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.0, 3.8), dpi=100)
    levels = sorted({c["mv_stimulus"] for c in cells}, key=level_sort_key)
    color = {lv: _COLORS[i % len(_COLORS)] for i, lv in enumerate(levels)}
    markers = "osD^vP"
    for i, lv in enumerate(levels):
        pts = sorted(
            (c for c in cells if c["mv_stimulus"] == lv), key=lambda c: c["masker_level_db_sl"]
        )
        x = [c["masker_level_db_sl"] for c in pts]
        y = [c["mean_shift_db"] for c in pts]
        err = [c["se_db"] if c.get("se_db") is not None else 0.0 for c in pts]
        ax.errorbar(
            x,
            y,
            yerr=err,
            fmt=markers[i % len(markers)],
            color=color[lv],
            capsize=2,
            label=f"{pts[0]['pair']}" if pts else lv,
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
            label=f"ramp {fit['label']}: {fit['intercept_db']:.2f} + {fit['slope']:.3f}·x",
        )
    ax.axhline(0.0, color="#999999", linewidth=0.6)
    ax.set_xlabel("masker level (dB SL)")
    ax.set_ylabel("AL shift (dB)")
    ax.set_title(f"{experiment}: mean AL shift ± SE, fitted ramps", fontsize=9)
    ax.legend(fontsize=6, loc="upper left", frameon=False)
    fig.tight_layout()
    return _save(fig, path)


def experiment_figure(path: str | Path, result: ExperimentResult) -> Path:
    """The masking-function figure of one experiment's results.

    Parameters
    ----------
    path : path
        PNG to write.
    result : ExperimentResult
        Cells (mean shift ± SE, dB, against masker level, dB SL) and ramp fits to draw.

    Returns
    -------
    Path
        The file written.

    Examples
    --------
    >>> for r in results:  # doctest: +SKIP
    ...     experiment_figure(out / f"masking_{safe_stem(r.experiment)}.png", r)
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
    return masking_function_figure(path, experiment=result.experiment, cells=cells, fits=fits)


def track_figure(path: str | Path, log: SessionLog, als_db: Mapping[str, float | None]) -> Path:
    """Staircase tracks of one session: level per trial, reversals marked, AL line.

    Parameters
    ----------
    path : path
        PNG to write.
    log : SessionLog
        The parsed session.
    als_db : mapping
        Set id → AL in the set's level unit (None if the set has no threshold).
    """
    plt = _pyplot()
    from matplotlib import ticker

    sets = log.sets()
    n = max(1, len(sets))
    ncols = min(5, n)
    nrows = math.ceil(n / ncols)
    fig, axes = plt.subplots(
        nrows, ncols, figsize=(2.4 * ncols, 1.9 * nrows), dpi=80, squeeze=False
    )
    for ax in axes.ravel()[n:]:
        ax.set_visible(False)
    for ax, (set_id, rec) in zip(axes.ravel(), sorted(sets.items()), strict=False):
        unit = rec.start.get("level_unit", "db_sl")
        key = "level_db_sl" if unit == "db_sl" else "level_db_v"
        pts = [
            (i, float(t[key]), bool(t.get("correct")), bool(t.get("reversal")))
            for i, t in enumerate(rec.trials)
            if isinstance(t.get(key), int | float)
        ]
        if pts:
            idx, lv, ok, rev = (np.array(v) for v in zip(*pts, strict=True))
            ax.step(idx, lv, where="post", color="#777777", linewidth=0.7)
            ax.plot(idx[ok], lv[ok], "o", ms=2.2, color="#1b6ca8")
            ax.plot(idx[~ok], lv[~ok], "o", ms=2.2, mfc="none", color="#d1495b")
            ax.plot(idx[rev], lv[rev], "x", ms=4, color="#000000")
        al = als_db.get(set_id)
        if al is not None:
            ax.axhline(al, color="#2e933c", linewidth=1.0)
        status = rec.end.get("status") if rec.end else "incomplete"
        ax.set_title(f"{set_id} ({status})", fontsize=7)
        ax.tick_params(labelsize=6)
        # Few ticks: tick layout is most of the drawing time of a 15-panel figure.
        ax.xaxis.set_major_locator(ticker.MaxNLocator(3, integer=True))
        ax.yaxis.set_major_locator(ticker.MaxNLocator(4))
        ax.set_ylabel("dB SL" if unit == "db_sl" else "dB re 1 V", fontsize=6)
    h = log.header
    fig.suptitle(
        f"{h.get('participant', '?')} {h.get('protocol', {}).get('experiment', '?')} "
        f"{h.get('session_id', '')}: ● correct ○ wrong × reversal — AL",
        fontsize=8,
    )
    # Fixed margins: tight_layout costs more than drawing the tracks.
    fig.subplots_adjust(left=0.06, right=0.99, bottom=0.08, top=0.88, wspace=0.35, hspace=0.6)
    return _save(fig, path)


def _save(fig: Any, path: str | Path) -> Path:
    plt = _pyplot()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None})
    plt.close(fig)
    return write_bytes_atomic(Path(path), buf.getvalue())


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
