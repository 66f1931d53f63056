"""Figures for ``masking-lab plan`` and the speed–accuracy study (matplotlib, no pyplot state).

Every function returns a :class:`matplotlib.figure.Figure`; :func:`png_bytes` renders it with
the Agg canvas and no software/date metadata, so the same numbers give the same bytes (the
study's committed PNGs do not change unless its results do).
"""

from __future__ import annotations

import io
from collections.abc import Sequence

from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from masking_lab.formats.png_figure import legible
from masking_lab.planning.plan import ESTIMATOR_LABELS, PlanResult

_COLORS = ("#1b6ca8", "#d1495b", "#2a9d55", "#8e5ea2", "#e69f00", "#4d4d4d", "#00a6a6")
_MARKERS = {"reversal_mean": "o", "ml": "^"}


def png_bytes(fig: Figure, dpi: int = 100) -> bytes:
    """The figure as PNG bytes, without metadata that would change from run to run."""
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, metadata={"Software": None})
    return buf.getvalue()


def _schedule_key(row: dict) -> tuple[str, float]:
    return (row["schedule"], float(row["down_up_ratio"]))


def _schedule_label(key: tuple[str, float]) -> str:
    steps, ratio = key
    return f"steps {steps} dB" if ratio == 1.0 else f"steps {steps} dB, down/up {ratio:g}"


def speed_accuracy(result: PlanResult, title: str = "") -> Figure:
    """Median session minutes against the AL's SD, one point per (schedule, rule, estimator).

    Reversal-mean points are circles, ML points triangles; each schedule has a colour and a
    thin line along its reversal ladder; the protocol's own setting is ringed and labelled;
    the dashed line is the SD that gives ±``precision_db`` at ``z``.
    """
    with legible():
        fig = Figure(figsize=(10.0, 5.6), layout="constrained")
        ax = fig.add_subplot(1, 1, 1)
        _speed_accuracy_axes(result, ax, title)
    return fig


def _speed_accuracy_axes(result: PlanResult, ax: Axes, title: str) -> None:
    s = result.settings
    keys: list[tuple[str, float]] = []
    for row in result.table:
        if _schedule_key(row) not in keys:
            keys.append(_schedule_key(row))
    longest = max(r.n_reversals for r in s.stop_rules)
    for i, key in enumerate(keys):
        color = _COLORS[i % len(_COLORS)]
        rungs = [
            r
            for r in result.ladder
            if _schedule_key(r) == key and r["n_reversals"] <= max(longest, _needed(result, key))
        ]
        ax.plot(
            [r["minutes_median"] for r in rungs],
            [r["sd_db"] for r in rungs],
            color=color,
            linewidth=0.8,
            alpha=0.5,
        )
        for est in ("reversal_mean", "ml"):
            rows = [r for r in result.table if _schedule_key(r) == key and r["estimator"] == est]
            if not rows:
                continue
            ax.plot(
                [r["minutes_median"] for r in rows],
                [r["sd_db"] for r in rows],
                linestyle="none",
                marker=_MARKERS[est],
                color=color,
                markersize=6,
                label=f"{_schedule_label(key)}, {ESTIMATOR_LABELS[est]}",
            )
            # Rule names only along the protocol's own schedule, alternating above and below
            # the points: one label per point of every schedule collided.
            own_schedule = any(r.get("own") for r in rows)
            for k, r in enumerate(rows if est == "reversal_mean" and own_schedule else ()):
                ax.annotate(
                    r["rule"],
                    (r["minutes_median"], r["sd_db"]),
                    textcoords="offset points",
                    xytext=(6, 5 if k % 2 == 0 else -12),
                    fontsize=8,
                    color=color,
                    bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.8},
                    zorder=5,
                )
    own = [r for r in result.table if r.get("own") and r["estimator"] == "reversal_mean"]
    for r in own:
        ax.plot(
            r["minutes_median"],
            r["sd_db"],
            marker="o",
            markersize=15,
            markerfacecolor="none",
            markeredgecolor="black",
            markeredgewidth=1.4,
            linestyle="none",
            label=f"this protocol ({r['rule']}, {r['schedule']} dB)",
        )
    target = s.precision_db / s.z
    ax.axhline(target, color="black", linestyle="--", linewidth=0.8, label="precision target")
    ax.annotate(
        f"SD giving ±{s.precision_db:g} dB ({s.z:g}·SD)",
        (0.99, target),
        xycoords=("axes fraction", "data"),
        ha="right",
        va="bottom",
        fontsize=8,
    )
    ax.set_xlabel("session length per set, median (min)")
    ax.set_ylabel("SD of the AL estimate (dB)")
    ax.set_ylim(bottom=0)
    ax.grid(True, linewidth=0.4, alpha=0.5)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    ax.set_title(title or "Speed against accuracy of the staircase settings", fontsize=10)


def _needed(result: PlanResult, key: tuple[str, float]) -> int:
    for a in result.answers:
        sched = a.schedule
        if (",".join(f"{v:g}" for v in sched.step_sizes_db), sched.down_up_ratio) == key:
            return a.rule.n_reversals if a.rule is not None else result.settings.max_reversals
    return 0


def convergence(
    rows: Sequence[dict], levitt_p: float, garcia_perez_p: float, title: str = ""
) -> Figure:
    """p(correct) where 1-up-3-down tracks settle, against step size / psychometric scale.

    ``rows`` have ``step_over_scale``, ``down_up_ratio``, ``p_converged`` (at the reversal-mean
    AL) with ``p_low``/``p_high`` (95 % interval) and ``p_trials`` (mean p(correct) over the
    trials). Solid lines: reversal mean; dashed: trials. Dotted horizontals mark Levitt's 0.794
    and the 0.8315 that a 0.7393 down/up ratio (García-Pérez's 2AFC value) targets.
    """
    with legible():
        fig = Figure(figsize=(9.0, 4.8), layout="constrained")
        ax = fig.add_subplot(1, 1, 1)
        _convergence_axes(rows, levitt_p, garcia_perez_p, title, ax)
    return fig


def _convergence_axes(
    rows: Sequence[dict], levitt_p: float, garcia_perez_p: float, title: str, ax: Axes
) -> None:
    ratios = sorted({float(r["down_up_ratio"]) for r in rows}, reverse=True)
    for i, ratio in enumerate(ratios):
        mine = sorted(
            (r for r in rows if float(r["down_up_ratio"]) == ratio),
            key=lambda r: r["step_over_scale"],
        )
        x = [r["step_over_scale"] for r in mine]
        y = [r["p_converged"] for r in mine]
        lo = [r["p_converged"] - r["p_low"] for r in mine]
        hi = [r["p_high"] - r["p_converged"] for r in mine]
        name = "equal steps" if ratio == 1.0 else f"down/up {ratio:g}"
        ax.errorbar(
            x,
            y,
            yerr=[lo, hi],
            marker="o",
            color=_COLORS[i],
            capsize=3,
            label=f"{name}: at the reversal-mean AL",
        )
        ax.plot(
            x,
            [r["p_trials"] for r in mine],
            marker="s",
            markersize=4,
            linestyle="--",
            color=_COLORS[i],
            label=f"{name}: mean over trials",
        )
    for p, label, color in (
        (levitt_p, f"Levitt {levitt_p:.3f}", _COLORS[0]),
        (garcia_perez_p, f"García-Pérez target {garcia_perez_p:.4f}", _COLORS[1]),
    ):
        ax.axhline(p, color=color, linestyle=":", linewidth=1)
        ax.annotate(
            label,
            (0.99, p),
            xycoords=("axes fraction", "data"),
            ha="right",
            va="bottom",
            fontsize=8,
        )
    ax.set_xscale("log", base=2)
    ax.set_xlabel("up step / psychometric scale")
    ax.set_ylabel("p(correct) where the track settles")
    ax.grid(True, linewidth=0.4, alpha=0.5)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    ax.set_title(title or "Where 1-up-3-down tracks converge", fontsize=10)
