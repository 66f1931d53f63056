"""Staircase-track figures, one per session (``analyze --figures all``).

A track figure has a panel per set: the level of every trial, correct and wrong answers,
reversals and the set's AL. They are off by default: at ~0.4 s per session, almost all of it
matplotlib building axes, they cost more than the whole analysis of a big study. When asked
for, :func:`track_jobs` extracts the few numbers each figure needs (a small picklable
:class:`TrackJob`), and :func:`draw_tracks` draws them in worker processes, each reusing one
figure per grid shape: only the data artists are replaced between sessions.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from masking_lab.core.worker_processes import rest_here, worker_pool
from masking_lab.formats.fileio import write_bytes_atomic
from masking_lab.formats.png_figure import legible, png_bytes

if TYPE_CHECKING:
    from masking_lab.formats.session_log import SessionLog

__all__ = ["TrackJob", "TrackPanel", "draw_tracks", "track_job"]

# Panels per row; a session of the paper has at most 15 sets (3 rows).
_NCOLS = 5
# Sessions per task sent to a worker: big enough that process overhead is small.
_CHUNK = 8


@dataclass(frozen=True)
class TrackPanel:
    """One set's track.

    Attributes
    ----------
    set_id, status : str
        The set and how it ended (``completed``, ``incomplete``, ...).
    unit : str
        Level axis label with unit (``level (dB SL)`` or ``level (dB re 1 V)``).
    levels : tuple of float
        Level of each trial, in ``unit``.
    correct, reversal : tuple of bool
        Per trial: answered correctly; a reversal of the staircase.
    al : float or None
        The set's AL in ``unit`` (None: no threshold).
    """

    set_id: str
    status: str
    unit: str
    levels: tuple[float, ...]
    correct: tuple[bool, ...]
    reversal: tuple[bool, ...]
    al: float | None


@dataclass(frozen=True)
class TrackJob:
    """One track figure to draw.

    Attributes
    ----------
    path : str
        PNG to write.
    title : str
        Participant, experiment and session.
    panels : tuple of TrackPanel
        One per set, in set order.
    """

    path: str
    title: str
    panels: tuple[TrackPanel, ...]


_DPI = 100  # saved size: 9-11 pt text reads at 100 % (it was 8 pt at 80 dpi, ~6.5 pt on screen)


def track_job(path: str | Path, log: SessionLog, als: Mapping[str, float | None]) -> TrackJob:
    """The numbers of one session's track figure.

    Parameters
    ----------
    path : path
        PNG to write.
    log : SessionLog
        The parsed session.
    als : mapping
        Set id → AL in the set's level unit (dB SL for masked sets, dB re 1 V otherwise;
        None if the set has no threshold).

    Returns
    -------
    TrackJob

    Examples
    --------
    >>> job = track_job("t.png", log, {"s1": 12.0})  # doctest: +SKIP
    """
    panels = []
    for set_id, rec in sorted(log.sets().items()):
        db_sl = rec.start.get("level_unit", "db_sl") == "db_sl"
        key = "level_db_sl" if db_sl else "level_db_v"
        trials = [t for t in rec.trials if isinstance(t.get(key), int | float)]
        panels.append(
            TrackPanel(
                set_id=str(set_id),
                status=str(rec.end.get("status") if rec.end else "incomplete"),
                unit="level (dB SL)" if db_sl else "level (dB re 1 V)",
                levels=tuple(float(t[key]) for t in trials),
                correct=tuple(bool(t.get("correct")) for t in trials),
                reversal=tuple(bool(t.get("reversal")) for t in trials),
                al=als.get(set_id),
            )
        )
    h = log.header
    title = (
        f"staircase tracks: participant {h.get('participant', '(none)')}, "
        f"{(h.get('protocol') or {}).get('experiment', '(no experiment)')}, "
        f"session {h.get('session_id', '(none)')}"
    )
    return TrackJob(str(path), title, tuple(panels))


def draw_tracks(jobs: Sequence[TrackJob], *, workers: int = 1) -> list[Path]:
    """Draw every job's figure; in ``workers`` processes when there are several jobs.

    Parameters
    ----------
    jobs : sequence of TrackJob
        The figures.
    workers : int
        Processes (1: draw here).

    Returns
    -------
    list of Path
        The files written, in job order.

    Examples
    --------
    >>> draw_tracks([], workers=2)
    []
    """
    if workers <= 1 or len(jobs) <= _CHUNK:
        # A worker process costs about a second to start (matplotlib import, first figure).
        return _draw_chunk(list(jobs))
    # Even shares for small batches, at most _CHUNK per task for big ones.
    size = max(1, min(_CHUNK, math.ceil(len(jobs) / workers)))
    chunks = [list(jobs[i : i + size]) for i in range(0, len(jobs), size)]
    with worker_pool(workers) as pool:
        # the chunks of a worker that died (killed for memory, say) are drawn here
        drawn = rest_here(pool.map(_draw_chunk, chunks), _draw_chunk, chunks)
        return [p for done in drawn for p in done]


# One figure per grid shape, per process: building 15 axes is most of a figure's cost.
_CANVAS: dict[int, tuple[Any, Any]] = {}


def _canvas(nrows: int) -> tuple[Any, Any]:
    if nrows not in _CANVAS:
        with legible(constrained=False) as plt:
            fig, axes = plt.subplots(
                nrows,
                _NCOLS,
                figsize=(3.2 * _NCOLS, 2.6 * nrows + 0.8),
                dpi=_DPI,
                squeeze=False,
                layout="none",  # fixed margins: a layout engine redraws every time
            )
            height = 2.6 * nrows + 0.8
            fig.subplots_adjust(
                left=0.06,
                right=0.99,
                bottom=0.5 / height,
                top=1.0 - 0.75 / height,
                wspace=0.32,
                hspace=0.75,
            )
        _CANVAS[nrows] = (fig, axes)
    return _CANVAS[nrows]


def _draw_chunk(jobs: list[TrackJob]) -> list[Path]:
    return [write_bytes_atomic(Path(job.path), _track_png(job)) for job in jobs]


def _track_png(job: TrackJob) -> bytes:
    from matplotlib import ticker

    nrows = max(1, math.ceil(len(job.panels) / _NCOLS))
    fig, axes = _canvas(nrows)
    with legible(constrained=False):
        for k, ax in enumerate(axes.ravel()):
            for artist in [*ax.lines, *ax.collections]:
                artist.remove()
            if k >= len(job.panels):
                ax.set_visible(False)
                continue
            ax.set_visible(True)
            p = job.panels[k]
            idx = np.arange(len(p.levels))
            lv = np.asarray(p.levels, dtype=float)
            ok = np.asarray(p.correct, dtype=bool)
            rev = np.asarray(p.reversal, dtype=bool)
            ax.step(idx, lv, where="post", color="#777777", linewidth=0.8, label="track")
            ax.plot(idx[ok], lv[ok], "o", ms=4.5, color="#1b6ca8", label="correct")
            # Wrong answers: large, white-filled, thick red ring drawn on top of the track, so
            # they stand out at 100 % (issue 17: thin 3 pt rings vanished into the line).
            ax.plot(idx[~ok], lv[~ok], "o", ms=6, mfc="white", mec="#c0392b", mew=1.8,
                    zorder=3, label="wrong")  # fmt: skip
            ax.plot(idx[rev], lv[rev], "x", ms=6, mew=1.3, color="#000000", zorder=4,
                    label="reversal")  # fmt: skip
            if p.al is not None and math.isfinite(p.al):
                ax.axhline(p.al, color="#2e933c", linewidth=1.0, label="AL")
            ax.relim()
            ax.autoscale_view()
            # An explicit y skips matplotlib's title placement pass (a bounding-box walk).
            ax.set_title(f"{p.set_id} ({p.status})", fontsize=10, y=1.0)
            ax.set_xlabel("trial", fontsize=9.5)
            ax.set_ylabel(p.unit, fontsize=9.5)
            ax.tick_params(labelsize=9)
            # Few ticks: tick layout is most of the drawing time of a 15-panel figure.
            ax.xaxis.set_major_locator(ticker.MaxNLocator(4, integer=True))
            ax.yaxis.set_major_locator(ticker.MaxNLocator(4))
        for legend in fig.legends:
            legend.remove()
        first = axes.ravel()[0]
        handles, labels = first.get_legend_handles_labels()
        fig.legend(
            handles, labels, loc="upper right", ncol=len(labels), fontsize=9.5, frameon=False
        )
        # suptitle() replaces the text of the figure's one title when it exists already.
        fig.suptitle(job.title, x=0.01, ha="left", fontsize=11)
        return png_bytes(fig, dpi=_DPI, close=False)
