"""Figure 8a of the paper from the user-test report model: correct rate per measure and condition.

Bars are the mean correct rate over participants, error bars the between-participant SD (none
with one participant: a zero-height bar would claim no spread), dashed lines the chance level of
each measure, ``*``/``**`` the paired tests (p < 0.05 / p < 0.01). The title says how many
participants; a note under the axes says when compensated trials were clipped at the rig's
limits. Drawn in the package's legible style (fonts ≥ 8 pt at the saved size).
"""

from __future__ import annotations

from masking_lab.formats.png_figure import legible, png_bytes
from masking_lab.usertest.design import MEASURES
from masking_lab.usertest.report_model import (
    MEASURE_LABELS,
    UserTestReportModel,
    participants_text,
)

__all__ = ["figure8a_png"]

COLOURS = {"compensated": "tab:blue", "uncompensated": "tab:gray"}
LABELS = {"compensated": "with compensation", "uncompensated": "without compensation"}


def figure8a_png(model: UserTestReportModel, *, dpi: int = 110) -> bytes:
    """The bar chart as PNG bytes.

    Parameters
    ----------
    model : UserTestReportModel
        From :func:`masking_lab.usertest.report_model.build_usertest_model`.
    dpi : int
        Resolution, dots per inch (font sizes are in points, the same at any dpi).

    Returns
    -------
    bytes
        A 6.8 × 4.6 inch PNG without date or software metadata.

    Examples
    --------
    >>> png = figure8a_png(model)  # doctest: +SKIP
    """
    conditions = model.conditions
    with legible() as plt:
        fig, ax = plt.subplots(figsize=(6.8, 4.6))
        width = 0.8 / max(1, len(conditions))
        tops = [0.0] * len(MEASURES)
        for j, cond in enumerate(conditions):
            xs = [i + (j - (len(conditions) - 1) / 2) * width for i in range(len(MEASURES))]
            cells = [model.rate(cond, m) for m in MEASURES]
            means = [c.mean if c else 0.0 for c in cells]
            sds = [c.sd if c and c.sd is not None and c.sd > 0 else None for c in cells]
            ax.bar(
                xs,
                means,
                width * 0.95,
                color=COLOURS.get(cond, "tab:green"),
                label=LABELS.get(cond, cond),
                edgecolor="black",
                linewidth=0.6,
            )
            bar_x = [x for x, sd in zip(xs, sds, strict=True) if sd is not None]
            if bar_x:
                ax.errorbar(
                    bar_x,
                    [m for m, sd in zip(means, sds, strict=True) if sd is not None],
                    yerr=[sd for sd in sds if sd is not None],
                    fmt="none",
                    ecolor="black",
                    capsize=4,
                    label="± SD over participants" if j == 0 else None,
                )
            for i, (m, sd) in enumerate(zip(means, sds, strict=True)):
                tops[i] = max(tops[i], m + (sd or 0.0))
        for i, measure in enumerate(MEASURES):
            ax.hlines(
                model.chance[measure],
                i - 0.45,
                i + 0.45,
                colors="#b22222",
                linestyles="--",
                linewidth=1.0,
                label="chance (guessing)" if i == 0 else None,
            )
        starred = False
        for t in model.tests:
            if t.p is None or t.p >= 0.05 or t.measure not in MEASURES:
                continue
            k = MEASURES.index(t.measure)
            star = "**" if t.p < 0.01 else "*"
            ax.text(k, min(tops[k] + 0.03, 1.08), star, ha="center", fontsize=13)
            starred = True
        ax.set_xticks(range(len(MEASURES)))
        ax.set_xticklabels([f"{MEASURE_LABELS[m]} correct" for m in MEASURES])
        ax.set_ylabel("correct rate (fraction of trials)")
        ax.set_xlabel("what had to be identified")
        ax.set_ylim(0.0, 1.15)
        ax.set_yticks([0.0, 0.2, 0.4, 0.6, 0.8, 1.0])
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=2, frameon=False)
        spread = "mean ± SD" if model.n_participants > 1 else "mean; no SD from one participant"
        who = participants_text(model.n_participants)
        title = f"User test: correct answers of {who} ({spread})"
        if starred:
            title += "\n* p < 0.05, ** p < 0.01 (paired t-test, with vs without compensation)"
        ax.set_title(title)
        if model.clipped_trials:
            clip = "; ".join(
                f"{cond}: {k} of {n} trials clipped at the rig's limits"
                for cond, (k, n) in model.clipped_trials.items()
            )
            # A figure-level label: constrained layout keeps it clear of the legend.
            fig.supxlabel(clip, fontsize=8)
        return png_bytes(fig, dpi=dpi)
