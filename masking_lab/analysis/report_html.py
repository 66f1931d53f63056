"""The analysis report as one self-contained HTML page (``report.html``), from the report model.

Reads only :class:`masking_lab.analysis.report.ReportModel` (the same model as ``report.txt``)
plus the masking-function figures as PNG bytes, and renders the ``analysis.html.j2`` template
through :mod:`masking_lab.formats.html_report`: ANOVA with sphericity, paired comparisons, the
one-sample tests of every cell, pooling decisions, fitted masking functions with their
intervals, problems and warnings, and the provenance of every input (sha256).
"""

from __future__ import annotations

from collections.abc import Mapping

from masking_lab.analysis.report import LogsInput, ReportModel, experiment_heading
from masking_lab.formats.html_report import data_uri, load_template, render_page

__all__ = ["prepare_html", "render_html"]


def prepare_html() -> None:
    """Compile the page's template now (a run does it while its figures are being drawn)."""
    load_template("analysis.html.j2")


def render_html(model: ReportModel, figures: Mapping[str, bytes] | None = None) -> str:
    """The report as an HTML document.

    Parameters
    ----------
    model : ReportModel
        From :func:`masking_lab.analysis.report.build_report`.
    figures : mapping of str to bytes, optional
        Experiment id → PNG of its masking functions (embedded; none drawn if empty).

    Returns
    -------
    str
        The page (UTF-8 text, no external resources).

    Examples
    --------
    >>> from masking_lab.analysis.report import ShiftsTableInput, build_report
    >>> from masking_lab.analysis.settings import AnalysisSettings
    >>> model = build_report(
    ...     [], AnalysisSettings(), source="fit", inputs=ShiftsTableInput("s.csv", 4, None)
    ... )
    >>> "<td class=\\"text\\">n_boot</td><td class=\\"text\\">2000</td>" in render_html(model)
    True
    """
    problems = (
        model.inputs.line_problems
        + tuple((path, reason, "file skipped") for path, reason in model.inputs.skipped)
        if isinstance(model.inputs, LogsInput)
        else ()
    )
    return render_page(
        "analysis.html.j2",
        {
            "title": f"masking-lab {model.source} report",
            "m": model,
            "problems": problems,
            "figures": {k: data_uri(v) for k, v in (figures or {}).items()},
            "heading": experiment_heading,
        },
    )
