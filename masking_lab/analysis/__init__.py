"""The analysis wing: session logs or a table of AL shifts → thresholds, statistics, pooled
masking ramps, ``masking_params.json``, a report and figures (paper §2.4).

Modules, from the science outwards:

- ``thresholds``: per-set ALs from session logs and the long table of AL shifts.
- ``stats``: repeated-measures ANOVA, Mauchly's test, paired and one-sample t-tests.
- ``pooling``: which frequency levels share one ramp.
- ``ramp_fit``: the ramp ``shift = max(0, a + b·x)`` and its participant bootstrap.
- ``settings``: :class:`AnalysisSettings` and option parsing.
- ``experiment``: :func:`analyze_shifts`, the pure per-experiment computation.
- ``tables``: rows and columns of the CSV outputs.
- ``report``: the report model (:func:`build_report`); ``report_text``: ``report.txt``;
  ``report_html``: ``report.html`` (Jinja2 templates, figures embedded).
- ``export``: ``masking_params.json`` and writing every output.
- ``figures``: masking-function figures; ``track_figures``: per-session staircase tracks,
  drawn in worker processes reusing one figure (matplotlib, loaded on use).
- ``batch``: the shell behind ``masking-lab analyze`` and ``fit`` (:func:`run_analyze`,
  :func:`run_fit`).

The names below are loaded on first use, so importing the package stays cheap (``masking-lab
--help`` does not load pandas or SciPy).
"""

from masking_lab.core.exports import lazy_exports

_HOME = {
    "AnalysisSettings": "settings",
    "ExperimentResult": "experiment",
    "ReportModel": "report",
    "RunSummary": "batch",
    "analyze_shifts": "experiment",
    "build_report": "report",
    "render_html": "report_html",
    "render_text": "report_text",
    "run_analyze": "batch",
    "run_fit": "batch",
}
__all__ = sorted(_HOME)
__getattr__, __dir__ = lazy_exports(__name__, _HOME)
