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
    """The scene's predicted error against the study's testing hours, one line per participant
    count, labelled with the trials per participant and function: (a) the RMS perceived error
    (dB) with the 90th percentile over studies as whiskers and the error with the ramps known
    exactly dashed; (b) the part due to the measurement alone (RMS, dB).

    Examples
    --------
    >>> row = BudgetRow(5, 30, 60, 0.8, 0.84, 1.16, 2.6, 0.65, 0.0)
    >>> fig = budget_figure([row], {"rms_db": 0.5, "max_db": 2.2}, title="bump_coarse")
    >>> [ax.get_ylabel() for ax in fig.axes]
    ['RMS perceived error (dB)', 'RMS error from the measurement (dB)']
    """
    with legible():
        fig = Figure(figsize=(11.0, 4.6), layout="constrained")
        total, meas = fig.subplots(1, 2)
        counts = sorted({r.participants for r in rows})
        for i, n in enumerate(counts):
            mine = sorted((r for r in rows if r.participants == n), key=lambda r: r.hours)
            color = _COLORS[i % len(_COLORS)]
            hours = [r.hours for r in mine]
            total.errorbar(
                hours,
                [r.rms_db for r in mine],
                yerr=[[0.0] * len(mine), [r.rms_p90_db - r.rms_db for r in mine]],
                color=color,
                marker="o",
                capsize=3,
                label=f"{n} participants",
            )
            meas.plot(hours, [r.measurement_rms_db for r in mine], color=color, marker="o")
            for r in mine:
                meas.annotate(
                    f"{r.trials}",
                    (r.hours, r.measurement_rms_db),
                    textcoords="offset points",
                    xytext=(4, 4),
                    color=color,
                )
        if floor is not None:
            total.axhline(
                floor["rms_db"], color="#333333", linestyle="--", label="ramps known exactly"
            )
        total.set_ylabel("RMS perceived error (dB)")
        total.set_title("(a) the scene's error, 90th percentile whiskers")
        meas.set_ylabel("RMS error from the measurement (dB)")
        meas.set_title("(b) the measurement's part (labels: trials per function)")
        meas.set_ylim(bottom=0)
        for ax in (total, meas):
            ax.set_xlabel("testing time of the study (h)")
        total.legend(loc="best")
        fig.suptitle(title)
    return fig
