"""The scene plan's figure: the scene's predicted rendering error against the testing time of
each measurement budget (``plan_budgets.png``; matplotlib, no pyplot state)."""

from __future__ import annotations

from collections.abc import Sequence

from matplotlib.figure import Figure

from masking_lab.formats.png_figure import legible
from masking_lab.planning.scene_budget import BudgetRow

__all__ = ["budget_figure"]

_COLORS = ("#1b6ca8", "#d1495b", "#2a9d55", "#8e5ea2", "#e69f00", "#4d4d4d")


def budget_figure(
    rows: Sequence[BudgetRow], floor: dict[str, float] | None, *, title: str
) -> Figure:
    """RMS perceived error (dB) against the study's testing hours, one line per participant
    count, a marker per trial budget; the 90th percentile over studies as whiskers, the error
    with the ramps known exactly as a dashed line.

    Examples
    --------
    >>> row = BudgetRow(5, 30, 60, 0.8, 0.84, 1.16, 2.6, 0.65, 0.0)
    >>> fig = budget_figure([row], {"rms_db": 0.5, "max_db": 2.2}, title="bump_coarse")
    >>> fig.axes[0].get_ylabel()
    'RMS perceived error of the scene (dB)'
    """
    with legible():
        fig = Figure(figsize=(8.0, 4.8), layout="constrained")
        ax = fig.add_subplot(1, 1, 1)
        counts = sorted({r.participants for r in rows})
        for i, n in enumerate(counts):
            mine = sorted((r for r in rows if r.participants == n), key=lambda r: r.hours)
            color = _COLORS[i % len(_COLORS)]
            hours = [r.hours for r in mine]
            rms = [r.rms_db for r in mine]
            ax.errorbar(
                hours,
                rms,
                yerr=[[0.0] * len(mine), [r.rms_p90_db - r.rms_db for r in mine]],
                color=color,
                marker="o",
                capsize=3,
                label=f"{n} participants",
            )
            for r in mine:
                ax.annotate(
                    f"{r.trials}",
                    (r.hours, r.rms_db),
                    textcoords="offset points",
                    xytext=(4, -12),
                    color=color,
                )
        if floor is not None:
            ax.axhline(
                floor["rms_db"], color="#333333", linestyle="--", label="ramps known exactly"
            )
        ax.set_xlabel("testing time of the study (h; labels: trials per participant and function)")
        ax.set_ylabel("RMS perceived error of the scene (dB)")
        ax.set_title(title)
        ax.set_ylim(bottom=0)
        ax.legend(loc="upper right")
    return fig
