"""The plan as one self-contained HTML page (``report.html`` of ``masking-lab plan``).

Renders the plan's result — the pooled table of every (schedule, stop rule, estimator), the
per-set rows of the protocol's own setting and the "reversals needed" answers — with the
``plan.html.j2`` template of :mod:`masking_lab.formats.html_report`; figures are embedded.
Durations in minutes, levels and errors in dB.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from masking_lab.formats.html_report import data_uri, render_page
from masking_lab.planning.plan import ESTIMATOR_LABELS, PlanResult
from masking_lab.planning.procedure_plan import ProcedureComparison
from masking_lab.planning.report import per_set_caption, plan_section_titles

__all__ = ["render_plan_html"]


def render_plan_html(
    result: PlanResult,
    *,
    title: str,
    header: Sequence[str],
    answers: Sequence[str],
    figures: Mapping[str, bytes],
    titles: Sequence[str] | None = None,
    comparison: ProcedureComparison | None = None,
) -> str:
    """The plan as an HTML document.

    Parameters
    ----------
    result : PlanResult
        From :func:`masking_lab.planning.plan.run_plan`.
    title : str
        Page title (names the protocol).
    header : sequence of str
        What was simulated (the lines that open ``plan.txt``).
    answers : sequence of str
        One sentence per schedule (:func:`masking_lab.planning.report.answer_text`).
    figures : mapping of str to bytes
        Caption → PNG, embedded in order.
    titles : sequence of str, optional
        The section titles of ``plan.txt``
        (:func:`masking_lab.planning.report.plan_section_titles`), used as the headings.
    comparison : ProcedureComparison, optional
        The procedures against the Cramér-Rao bound, and the fewest-trials answers.

    Returns
    -------
    str
        The page (no external resources).

    Examples
    --------
    >>> html = render_plan_html(  # doctest: +SKIP
    ...     result, title="plan", header=[], answers=[], figures={}
    ... )
    """
    own_rule, own_sched = result.protocol_rule, result.protocol_schedule
    steps = ",".join(f"{v:g}" for v in own_sched.step_sizes_db)
    per_set = [
        r
        for r in result.per_set
        if r["schedule"] == steps
        and r["down_up_ratio"] == own_sched.down_up_ratio
        and r["rule"] == own_rule.label
    ]
    return render_page(
        "plan.html.j2",
        {
            "title": title,
            "header": list(header),
            "answers": list(answers),
            "precision": result.settings.precision_db,
            "z": result.settings.z,
            "table": result.table,
            "per_set": per_set,
            "per_set_caption": per_set_caption(result),
            "estimators": ESTIMATOR_LABELS,
            "figures": [(name, data_uri(png)) for name, png in figures.items()],
            "titles": list(
                titles or plan_section_titles(result.settings.precision_db, comparison is not None)
            ),
            "comparison": comparison,
            "procedure_rows": [r for r in comparison.rows if r.get("capped", True)]
            if comparison is not None
            else [],
        },
    )
