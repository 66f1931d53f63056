"""The user-test report as one self-contained HTML page (``report.html``), from its model.

Reads only :class:`masking_lab.usertest.report_model.UserTestReportModel` and the Figure 8a
PNG, and renders ``usertest.html.j2`` through :mod:`masking_lab.formats.html_report`.
"""

from __future__ import annotations

from masking_lab.formats.html_report import data_uri, render_page
from masking_lab.usertest.design import MEASURES
from masking_lab.usertest.report_model import (
    MEASURE_LABELS,
    UserTestReportModel,
    participants_text,
)

__all__ = ["render_usertest_html"]


def render_usertest_html(model: UserTestReportModel, figure: bytes | None = None) -> str:
    """The user-test report as an HTML document.

    Parameters
    ----------
    model : UserTestReportModel
        From :func:`masking_lab.usertest.report_model.build_usertest_model`.
    figure : bytes or None
        Figure 8a as PNG (embedded), or None.

    Returns
    -------
    str
        The page (no external resources).

    Examples
    --------
    >>> html = render_usertest_html(model, figure8a_png(model))  # doctest: +SKIP
    """
    return render_page(
        "usertest.html.j2",
        {
            "title": "masking-lab user-test report",
            "m": model,
            "participants": participants_text(model.n_participants),
            "measures": MEASURES,
            "labels": MEASURE_LABELS,
            "figure": None if figure is None else data_uri(figure),
        },
    )
