"""The scene plan as text, CSV rows and one HTML page with the same headings (pure).

Levels in dB SL, errors in dB, testing time in hours.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from masking_lab.formats.html_report import data_uri, render_page
from masking_lab.planning.scene_budget import BudgetRow
from masking_lab.planning.scene_needs import FunctionNeed

__all__ = [
    "FUNCTION_FIELDS",
    "SECTION_TITLES",
    "ScenePlan",
    "format_scene_plan",
    "function_rows",
    "rows_csv",
    "scene_plan_html",
    "status_text",
]

SECTION_TITLES = (
    "Stimulus pairs and masker ranges",
    "Measurement protocols",
    "Rendering error by measurement budget",
)


FUNCTION_FIELDS = (
    "direction",
    "target",
    "masker",
    "used_min_db_sl",
    "used_max_db_sl",
    "fitted_min_db_sl",
    "fitted_max_db_sl",
    "status",
    "below_fitted_db",
    "above_fitted_db",
    "entry_status",
)


@dataclass(frozen=True)
class ScenePlan:
    """Everything the report shows.

    Attributes
    ----------
    header : list of str
        What was planned from (files, rig, mapping, prior).
    pair_line : str
        The stimulus pair and what each channel renders (empty for a single-channel scene).
    needs : list of FunctionNeed
    protocols : list of (file name, need, lo, hi, procedure text)
    rows : list of BudgetRow
    floor : dict or None
        Error with the ramps known exactly (``rms_db``, ``max_db``).
    as_fitted : dict or None
        Error with the parameters as they are, when nothing is measured (``rms_db``,
        ``max_db``).
    notes : list of str
    """

    header: list[str]
    pair_line: str
    needs: list[FunctionNeed]
    protocols: list[tuple[str, FunctionNeed, float, float, str]]
    rows: list[BudgetRow]
    floor: dict[str, float] | None
    as_fitted: dict[str, float] | None
    notes: list[str]


def _range(r: tuple[float, float] | None) -> str:
    return "—" if r is None else f"{r[0]:.1f}–{r[1]:.1f}"


def status_text(n: FunctionNeed) -> str:
    """``within``, ``extrapolated: 5.0 dB above`` or ``missing (no entry)``.

    Examples
    --------
    >>> status_text(FunctionNeed("EV270", "MV180", (23, 30), "extrapolated", (5, 25), 0, 5.0,
    ...                          "fitted", -5.9, 0.66))
    'extrapolated: 5.0 dB above the fitted range'
    """
    if n.status == "missing":
        why = "no entry" if n.entry_status == "missing" else f"status {n.entry_status}"
        return f"missing ({why})"
    if n.status == "within":
        return "present, within the fitted range"
    parts = [f"{v:.1f} dB {side}" for v, side in ((n.below_db, "below"), (n.above_db, "above"))]
    return (
        "extrapolated: "
        + " and ".join(p for p, v in zip(parts, (n.below_db, n.above_db), strict=True) if v > 0)
        + " the fitted range"
    )


def function_rows(needs: Sequence[FunctionNeed]) -> list[dict[str, Any]]:
    """One CSV row per masking function (ranges in dB SL of the masker)."""
    out = []
    for n in needs:
        used = n.used_range_db_sl or (None, None)
        fit = n.fitted_range_db_sl or (None, None)
        out.append(
            {
                "direction": n.direction,
                "target": n.target,
                "masker": n.masker,
                "used_min_db_sl": used[0],
                "used_max_db_sl": used[1],
                "fitted_min_db_sl": fit[0],
                "fitted_max_db_sl": fit[1],
                "status": n.status,
                "below_fitted_db": n.below_db,
                "above_fitted_db": n.above_db,
                "entry_status": n.entry_status,
            }
        )
    return out


def rows_csv(rows: Sequence[Mapping[str, Any]], fields: Sequence[str] = ()) -> str:
    """CSV text; empty fields for None, floats to 6 significant digits; with no rows, the
    header of ``fields`` alone.

    Examples
    --------
    >>> print(rows_csv([{"a": 1.23456789, "b": None}]), end="")
    a,b
    1.23457,
    >>> rows_csv([], ["a", "b"])
    'a,b\\n'
    """
    buf = io.StringIO()
    names = list(rows[0]) if rows else list(fields)
    w = csv.DictWriter(buf, fieldnames=names, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow(
            {
                k: "" if v is None else (_csv_float(v) if isinstance(v, float) else v)
                for k, v in r.items()
            }
        )
    return buf.getvalue()


def _csv_float(v: float) -> str:
    """6 significant digits; empty for a non-finite number (none may reach a file)."""
    return f"{v:.6g}" if math.isfinite(v) else ""


def _f(v: float, digits: int = 2) -> str:
    return f"{v:.{digits}f}" if math.isfinite(v) else "—"


def _function_lines(plan: ScenePlan) -> list[str]:
    if not plan.needs:
        return ["single-channel scene: nothing masks it, so it needs no masking function"]
    lines = [plan.pair_line, ""]
    lines.append(
        f"{'direction':<16} {'masking function':<24} {'masker used':>12} {'fitted':>10}  status"
    )
    for n in plan.needs:
        lines.append(
            f"{n.direction:<16} {n.label:<24} {_range(n.used_range_db_sl):>12} "
            f"{_range(n.fitted_range_db_sl):>10}  {status_text(n)}"
        )
    lines.append("(masker levels in dB SL of the masker: the inputs the scene plays)")
    return lines


def _protocol_lines(plan: ScenePlan) -> list[str]:
    if not plan.protocols:
        return [
            "nothing to measure: every masking function the scene needs is fitted over the "
            "masker levels it plays"
        ]
    return [
        f"{name}: {need.label}, masker {lo:g}–{hi:g} dB SL; {how}"
        for name, need, lo, hi, how in plan.protocols
    ]


def _budget_table_lines(plan: ScenePlan) -> list[str]:
    if not plan.rows:
        return []
    lines = [
        f"{'participants':>12} {'trials/fn':>9} {'trials/part.':>12} {'hours':>6} "
        f"{'RMS (dB)':>9} {'RMS p90':>8} {'max (dB)':>9} {'from meas.':>10}"
    ]
    for r in plan.rows:
        lines.append(
            f"{r.participants:>12d} {r.trials:>9d} {r.trials_per_participant:>12d} "
            f"{r.hours:>6.1f} {_f(r.rms_db):>9} {_f(r.rms_p90_db):>8} {_f(r.max_db):>9} "
            f"{_f(r.measurement_rms_db):>10}"
        )
    return lines


def _budget_summary(plan: ScenePlan) -> list[str]:
    lines = []
    if plan.as_fitted is not None:
        lines.append(
            "with the parameters as fitted (no new measurement): RMS "
            f"{_f(plan.as_fitted['rms_db'])} dB, max {_f(plan.as_fitted['max_db'])} dB"
        )
    if plan.floor is not None:
        lines.append(
            "with the ramps known exactly (no budget does better): RMS "
            f"{_f(plan.floor['rms_db'])} dB, max {_f(plan.floor['max_db'])} dB"
        )
    if not lines and not plan.rows:
        lines.append("single-channel scene: its targets pass straight through, error 0 dB")
    return lines + plan.notes


def section_bodies(plan: ScenePlan) -> list[list[str]]:
    """The three sections' lines, in :data:`SECTION_TITLES` order."""
    return [
        _function_lines(plan),
        _protocol_lines(plan),
        _budget_table_lines(plan) + _budget_summary(plan),
    ]


def format_scene_plan(plan: ScenePlan) -> str:
    """The plan as text (``plan.txt``): the header, then the three titled sections."""
    text = "\n".join(plan.header)
    for title, body in zip(SECTION_TITLES, section_bodies(plan), strict=True):
        text += f"\n\n{title}\n{'-' * len(title)}\n" + "\n".join(body)
    return text + "\n"


def scene_plan_html(
    plan: ScenePlan, *, title: str, figures: Mapping[str, bytes] | None = None
) -> str:
    """The plan as one self-contained HTML page with :data:`SECTION_TITLES` as headings;
    ``figures`` (name → PNG) are embedded under the budgets' table."""
    return render_page(
        "scene_plan.html.j2",
        {
            "title": title,
            "header": plan.header,
            "titles": SECTION_TITLES,
            "pair_line": plan.pair_line,
            "needs": [
                (n, status_text(n), _range(n.used_range_db_sl), _range(n.fitted_range_db_sl))
                for n in plan.needs
            ],
            "protocol_lines": _protocol_lines(plan),
            "rows": plan.rows,
            "budget_notes": _budget_summary(plan),
            "figures": [(name, data_uri(png)) for name, png in (figures or {}).items()],
        },
    )
