"""Text and figure of the procedures comparison (``masking-lab plan``; pure formatting).

The figure puts every setting at (mean trials per set, SD of the AL) with the Cramér-Rao bound
SD = 1/√(n·I*) of the protocol's observer drawn as the limit no unbiased procedure crosses; the
text lists each setting's trials, minutes, bias, SD, RMSE and efficiency (the bound's trials
for that SD over the trials used) and answers "fewest trials for ±X dB" across procedures.
Units: dB, trials per set, minutes per set.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from matplotlib.figure import Figure

from masking_lab.planning.procedure_plan import ProcedureComparison

__all__ = ["format_comparison", "format_fewest", "procedures_figure"]

_COLORS = ("#1b6ca8", "#d1495b", "#2a9d55", "#8e5ea2", "#e69f00", "#4d4d4d", "#00a6a6")


def _num(value: object, fmt: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        width = "".join(ch for ch in fmt.split(".")[0] if ch.isdigit())
        return "—".rjust(int(width or 0))
    return format(value, fmt)


def _shown(rows: Sequence[dict]) -> list[dict]:
    """The capped rows (as a session would run them) of every procedure."""
    return [r for r in rows if r.get("capped", True)]


def format_comparison(comparison: ProcedureComparison) -> str:
    """One line per procedure setting, with its efficiency against the Cramér-Rao bound.

    Examples
    --------
    >>> c = ProcedureComparison(
    ...     [{"procedure": "QUEST+", "setting": "SD ≤ 1.08 dB", "estimator": "posterior_mean",
    ...       "trials_median": 30.0, "trials_p90": 38.0, "trials_mean": 31.0,
    ...       "minutes_median": 4.0, "completed": 1.0, "ceiling": 0.0, "floor": 0.0,
    ...       "trial_cap": 0.0, "bias_db": 0.01, "sd_db": 1.02, "rmse_db": 1.03,
    ...       "worst_sd_db": 1.1, "cr_trials": 18.0, "efficiency": 0.58, "own": True}],
    ...     [], {"information": 0.0534, "p_correct": 0.708, "scale_db": 1.5, "lapse": 0.02,
    ...          "guess": 1 / 3}, [], 1.0, 1.96)
    >>> format_comparison(c).splitlines()[2].split()[-3:]
    ['1.03', '18.0', '58%']
    """
    b = comparison.bound
    lines = [
        f"Procedures against the Cramér-Rao bound (observer: scale {b['scale_db']:g} dB, lapse "
        f"{b['lapse']:g}, guess {b['guess']:.3g}; Fisher information peaks at "
        f"{b['information']:.4f} dB^-2 at p(correct) {b['p_correct']:.3f}):",
        f"{'procedure':<36}{'setting':<15}{'trials med':>8}{'p90':>6}{'mean':>6}"
        f"{'min':>6}{'AL %':>6}{'bias':>7}{'SD':>6}{'RMSE':>6}{'CR n':>6}{'eff':>6}",
    ]
    for r in _shown(comparison.rows):
        est = r["estimator"].replace("_", " ")
        name = f"{r['procedure']} ({est})"
        mark = "*" if r.get("own") else " "
        lines.append(
            f"{name:<36}{mark}{r['setting']:<14}{r['trials_median']:>6.0f}"
            f"{r['trials_p90']:>6.0f}{_num(r.get('trials_mean'), '6.1f')}"
            f"{r['minutes_median']:>6.1f}{100 * r['completed']:>6.1f}"
            f"{_num(r.get('bias_db'), '+7.2f')}{_num(r.get('sd_db'), '6.2f')}"
            f"{_num(r.get('rmse_db'), '6.2f')}{_num(r.get('cr_trials'), '6.1f')}"
            f"{_num(r.get('efficiency'), '6.0%')}"
        )
    lines.append(
        "* this protocol's setting. SD: root-mean-square within-set SD of AL − true threshold; "
        "CR n: trials the Cramér-Rao bound needs for that SD; eff = CR n / mean trials."
    )
    return "\n".join(lines)


def format_fewest(comparison: ProcedureComparison) -> str:
    """Fewest trials per set for ±X dB (z·SD in the worst set), one line per procedure.

    Examples
    --------
    >>> c = ProcedureComparison([], [], {}, [{"procedure": "QUEST+", "setting": "SD ≤ 0.45 dB",
    ...     "estimator": "posterior_mean", "met": True, "half_width_db": 0.97,
    ...     "trials_median": 110.0, "trials_p90": 125.0, "minutes_median": 14.1,
    ...     "efficiency": 0.7}], 1.0, 1.96)
    >>> format_fewest(c).splitlines()[1].split(": ")[1][:27]
    '±0.97 dB in 110 trials (90 '
    """
    x, z = comparison.precision_db, comparison.z
    lines = [f"Fewest trials for ±{x:g} dB ({z:g}·SD ≤ {x:g} dB in every set, no trial cap):"]
    for r in comparison.fewest:
        est = r["estimator"].replace("_", " ")
        head = f"  {r['procedure']} ({est}), {r['setting']}: "
        if r["met"]:
            lines.append(
                head + f"±{r['half_width_db']:.2f} dB in {r['trials_median']:.0f} trials "
                f"(90 % within {r['trials_p90']:.0f}, ~{r['minutes_median']:.1f} min) per set, "
                f"{_num(r.get('efficiency'), '.0%')} efficient"
            )
        else:
            lines.append(
                head + f"does not reach it; closest ±{r['half_width_db']:.2f} dB in "
                f"{r['trials_median']:.0f} trials"
            )
    return "\n".join(lines)


def procedures_figure(comparison: ProcedureComparison, title: str = "") -> Figure:
    """SD of the AL against mean trials per set, per procedure, with the Cramér-Rao limit.

    Staircase settings (reversal mean) are circles, one colour per schedule; QUEST+ settings a
    line along their posterior-SD targets; the protocol's own setting is ringed and the
    paper's 11/8 staircase labelled, each with its efficiency; the grey
    curve is the bound SD = 1/√(n·I*) and the dashed line the SD that gives ±X dB.
    """
    fig = Figure(figsize=(7.0, 4.6))
    ax = fig.add_subplot(1, 1, 1)
    rows = [
        r
        for r in _shown(comparison.rows)
        if r["estimator"] != "ml" and math.isfinite(r.get("sd_db", math.nan))
    ]
    names: list[str] = []
    for r in rows:
        if r["procedure"] not in names:
            names.append(r["procedure"])
    for i, name in enumerate(names):
        mine = sorted((r for r in rows if r["procedure"] == name), key=lambda r: r["trials_mean"])
        x = [r["trials_mean"] for r in mine]
        y = [r["sd_db"] for r in mine]
        bayes = not name.startswith("staircase")
        ax.plot(
            x,
            y,
            marker="s" if bayes else "o",
            linestyle="-" if bayes else "none",
            color=_COLORS[i % len(_COLORS)],
            label=name,
            markersize=5,
        )
        for r in mine:
            if not r.get("own") and (name, r["setting"]) == ("staircase 4,4,4,2", "11/8"):
                ax.annotate(
                    f"paper's 11/8 ({r['efficiency']:.0%})",
                    (r["trials_mean"], r["sd_db"]),
                    textcoords="offset points",
                    xytext=(6, -12),
                    fontsize=8,
                )
            if r.get("own"):
                ax.plot(
                    r["trials_mean"],
                    r["sd_db"],
                    marker="o",
                    markersize=13,
                    mfc="none",
                    color="black",
                )
                ax.annotate(
                    f"this protocol ({r['efficiency']:.0%})",
                    (r["trials_mean"], r["sd_db"]),
                    textcoords="offset points",
                    xytext=(8, 8),
                    fontsize=8,
                )
    info = comparison.bound.get("information", math.nan)
    top = max([r["trials_mean"] for r in rows], default=100.0) * 1.1
    n = np.linspace(max(2.0, top / 200), top, 200)
    ax.plot(n, 1.0 / np.sqrt(n * info), color="0.5", linewidth=2, label="Cramér-Rao bound")
    ax.axhline(
        comparison.precision_db / comparison.z,
        color="0.3",
        linestyle="--",
        linewidth=1,
        label=f"SD for ±{comparison.precision_db:g} dB",
    )
    ax.set_ylim(0, min(4.0, max([r["sd_db"] for r in rows], default=2.0) * 1.15))
    ax.set_xlabel("mean trials per set")
    ax.set_ylabel("SD of AL − true threshold (dB)")
    ax.set_title(title or "Procedures against the Cramér-Rao bound")
    ax.legend(fontsize=8, loc="upper right")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    return fig
