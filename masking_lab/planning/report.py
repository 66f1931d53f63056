"""Text and CSV of a plan: the pooled table, the per-set rows, the "reversals needed" answers.

Pure formatting of a :class:`~masking_lab.planning.plan.PlanResult` (levels and errors in dB,
durations in minutes); :mod:`masking_lab.commands.plan` prints and writes what these return.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from typing import Any

from masking_lab.planning.plan import Answer, PlanResult
from masking_lab.planning.settings import PlanSettings

__all__ = ["answer_text", "format_per_set", "format_table", "rows_to_csv"]


def answer_text(answer: Answer, settings: PlanSettings, cap: int | None) -> str:
    """One sentence answering "how many reversals do I need for ±X dB" for one schedule."""
    x = settings.precision_db
    crit = f"{settings.z:g}·SD ≤ {x:g} dB in every set, reversal mean"
    if answer.rule is None or answer.row is None:
        b = answer.best
        return (
            f"{answer.schedule.label}: no stop rule up to {settings.max_reversals} reversals "
            f"reaches ±{x:g} dB ({crit}); the closest, {b['rule']}, gives "
            f"±{b['half_width_db']:.2f} dB in {b['trials_median']:.0f} trials "
            f"(~{b['minutes_median']:.1f} min) per set"
        )
    r = answer.row
    text = (
        f"{answer.schedule.label}: {answer.rule.label} (run {answer.rule.n_reversals} reversals, "
        f"average the last {answer.rule.n_averaged}) gives ±{r['half_width_db']:.2f} dB "
        f"({crit}) in {r['trials_median']:.0f} trials, 90 % within {r['trials_p90']:.0f} "
        f"(~{r['minutes_median']:.1f}–{r['minutes_p90']:.1f} min) per set"
    )
    if cap is not None and answer.capped_by_protocol > 0:
        text += (
            f"; the protocol's max_trials={cap} would stop "
            f"{100 * answer.capped_by_protocol:.1f} % of them first"
        )
    return text


def rows_to_csv(rows: Sequence[dict]) -> str:
    """Rows as CSV text (columns in first-seen order; floats to 6 significant digits)."""
    columns: list[str] = []
    for r in rows:
        for k in r:
            if k not in columns:
                columns.append(k)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow(
            [(f"{r[c]:.6g}" if isinstance(r.get(c), float) else r.get(c, "")) for c in columns]
        )
    return buf.getvalue()


def _num(value: Any, fmt: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        width = "".join(ch for ch in fmt.split(".")[0] if ch.isdigit())
        return "—".rjust(int(width or 0))  # keep the columns aligned
    return format(value, fmt)


def format_table(result: PlanResult) -> str:
    """The pooled table: one line per (schedule, rule), both estimators side by side."""
    s = result.settings
    z = s.z
    lines = [
        f"{'':23}{'trials':^11}{'minutes':^13}{'ends (%)':^16}"
        f"{'reversal mean (dB)':^22}{'ML fit (dB)':^22}",
        f"{'schedule (dB)':<16}{'rule':<7}{'med':>5}{'p90':>6}{'med':>7}{'p90':>6}"
        f"{'AL':>6}{'ceil':>5}{'cap':>5}"
        f"{'bias':>8}{'SD':>6}{f'±{z:g}SD':>8}"
        f"{'bias':>8}{'SD':>6}{f'±{z:g}SD':>8}",
    ]
    by_key: dict[tuple, dict[str, dict]] = {}
    for row in result.table:
        key = (row["schedule"], row["down_up_ratio"], row["n_reversals"], row["n_averaged"])
        by_key.setdefault(key, {})[row["estimator"]] = row
    last_sched = None
    for ests in by_key.values():
        rm = ests["reversal_mean"]
        ml = ests.get("ml", {})
        sched = rm["schedule"] + (
            "" if rm["down_up_ratio"] == 1.0 else f" d/u {rm['down_up_ratio']:g}"
        )
        if last_sched is not None and sched != last_sched:
            lines.append("")
        last_sched = sched
        mark = "*" if rm.get("own") else " "
        ends = rm["ceiling"] + rm["floor"]
        lines.append(
            f"{sched:<16}{mark}{rm['rule']:<6}{rm['trials_median']:>5.0f}{rm['trials_p90']:>6.0f}"
            f"{rm['minutes_median']:>7.1f}{rm['minutes_p90']:>6.1f}"
            f"{100 * rm['completed']:>6.1f}{100 * ends:>5.1f}{100 * rm['trial_cap']:>5.1f}"
            f"{_num(rm.get('bias_db'), '+8.2f')}{_num(rm.get('sd_db'), '6.2f')}"
            f"{_num(z * rm.get('worst_sd_db', math.nan), '8.2f')}"
            f"{_num(ml.get('bias_db'), '+8.2f')}{_num(ml.get('sd_db'), '6.2f')}"
            f"{_num(z * ml.get('worst_sd_db', math.nan), '8.2f')}"
        )
    # A QUEST+ protocol has no row here (its row is in the procedures table): no star to explain.
    own = "* this protocol. " if any(r.get("own") for r in result.table) else ""
    lines.append(
        f"{own}Pooled over sets: bias is averaged, SD is the root-mean-square "
        f"within-set SD, ±{z:g}SD uses the worst set. AL = sessions ending with a threshold; "
        "ceil = ceiling or floor; cap = trial cap."
    )
    return "\n".join(lines)


def per_set_caption(result: PlanResult) -> str:
    """What the per-set rows are: the protocol's own staircase, or the paper's beside it."""
    steps = ",".join(f"{v:g}" for v in result.protocol_schedule.step_sizes_db)
    mine = any(r.get("own") for r in result.table)
    whose = "this protocol's setting" if mine else "the paper's staircase beside this protocol"
    return f"Per set, {whose} ({steps} dB, {result.protocol_rule.label})"


def format_per_set(result: PlanResult, *, only_own: bool) -> str:
    """Per-set rows for the protocol's own setting (or every setting)."""
    own_rule, own_sched = result.protocol_rule, result.protocol_schedule
    steps = ",".join(f"{v:g}" for v in own_sched.step_sizes_db)
    rows = [
        r
        for r in result.per_set
        if not only_own
        or (
            r["schedule"] == steps
            and r["down_up_ratio"] == own_sched.down_up_ratio
            and r["rule"] == own_rule.label
        )
    ]
    title = f"{per_set_caption(result)}:" if only_own else "Per set:"
    lines = [
        title,
        f"{'set':<12}{'schedule':<16}{'rule':<7}{'estimator':<15}{'trials':>7}{'p90':>5}"
        f"{'AL %':>7}{'bias':>8}{'SD':>6}",
    ]
    for r in rows:
        sched = r["schedule"] + (
            "" if r["down_up_ratio"] == 1.0 else f" d/u {r['down_up_ratio']:g}"
        )
        lines.append(
            f"{r['set']:<12}{sched:<16}{r['rule']:<7}{r['estimator']:<15}"
            f"{r['trials_median']:>7.0f}{r['trials_p90']:>5.0f}{100 * r['completed']:>7.1f}"
            f"{_num(r.get('bias_db'), '+8.2f')}{_num(r.get('sd_db'), '6.2f')}"
        )
    return "\n".join(lines)


def plan_section_titles(precision_db: float, comparison: bool) -> list[str]:
    """The section titles of ``plan.txt``, which ``report.html`` repeats as its headings.

    Examples
    --------
    >>> plan_section_titles(1.0, True)[-1]
    'Fewest trials for ±1 dB'
    """
    titles = [
        "Speed and accuracy of each setting",
        "Per set",
        f"Reversals needed for ±{precision_db:g} dB",
    ]
    if comparison:
        titles += [
            "Procedures against the Cramér-Rao bound",
            f"Fewest trials for ±{precision_db:g} dB",
        ]
    return titles
