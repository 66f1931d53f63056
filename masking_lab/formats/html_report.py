"""HTML reports from Jinja2 templates: autoescaped, self-contained, no network needed.

:func:`render_page` renders one of the package's templates (``masking_lab/formats/templates``,
shipped as package data) with autoescaping on, so text from logs or file names can never
inject markup; figures are embedded as ``data:`` URIs (:func:`data_uri`) and the style sheet is
inline, so a report is one file that opens offline. The number filters (:func:`fmt_num`,
:func:`fmt_p`) print ``—`` for a missing or non-finite number, never ``nan`` or ``None``.

The analysis, user-test and plan reports build their own models; this module only renders.
"""

from __future__ import annotations

import base64
import math
from collections.abc import Mapping
from functools import cache
from typing import Any

__all__ = ["data_uri", "fmt_num", "fmt_p", "render_page"]

_MIME = {"png": "image/png", "svg": "image/svg+xml"}


def fmt_num(value: Any, digits: int = 3, signed: bool = False) -> str:
    """A number with ``digits`` decimals; ``—`` for None or a non-finite number.

    Examples
    --------
    >>> fmt_num(1.23456), fmt_num(None), fmt_num(float("nan")), fmt_num(2, 1, signed=True)
    ('1.235', '—', '—', '+2.0')
    """
    if value is None or isinstance(value, bool):
        return "—" if value is None else str(value)
    try:
        v = float(value)
    except (TypeError, ValueError):
        return str(value)
    if not math.isfinite(v):
        return "—"
    return f"{v:+.{digits}f}" if signed else f"{v:.{digits}f}"


def fmt_p(p: Any) -> str:
    """A p value: ``< 0.001`` below 0.001, else three decimals; ``—`` if missing.

    Examples
    --------
    >>> fmt_p(0.00001), fmt_p(0.0456), fmt_p(None)
    ('< 0.001', '0.046', '—')
    """
    if p is None:
        return "—"
    v = float(p)
    if not math.isfinite(v):
        return "—"
    return "< 0.001" if v < 0.001 else f"{v:.3f}"


def data_uri(data: bytes, kind: str = "png") -> str:
    """An image embedded in a page: ``data:image/png;base64,...``.

    Parameters
    ----------
    data : bytes
        The image file's bytes.
    kind : {"png", "svg"}
        Its format.

    Examples
    --------
    >>> data_uri(b"<svg/>", "svg")
    'data:image/svg+xml;base64,PHN2Zy8+'
    """
    return f"data:{_MIME[kind]};base64,{base64.b64encode(data).decode('ascii')}"


@cache
def _environment() -> Any:
    import jinja2

    from masking_lab.formats.template_cache import compiled_template_cache

    env = jinja2.Environment(
        loader=jinja2.PackageLoader("masking_lab.formats", "templates"),
        autoescape=True,
        undefined=jinja2.StrictUndefined,  # a typo in a template fails loudly, not silently
        trim_blocks=True,
        lstrip_blocks=True,
        keep_trailing_newline=True,
        bytecode_cache=compiled_template_cache(),  # compiled once per template and version
    )
    env.filters["num"] = fmt_num
    env.filters["p"] = fmt_p
    return env


def load_template(template: str) -> None:
    """Load ``template`` now (kept for :func:`render_page`), e.g. while figures are drawn
    elsewhere: compiling the analysis page, where no earlier run left it compiled
    (:mod:`~masking_lab.formats.template_cache`), takes ~45 ms."""
    _environment().get_template(template)


def render_page(template: str, context: Mapping[str, Any]) -> str:
    """Render ``template`` (a file in ``masking_lab/formats/templates``) with ``context``.

    Parameters
    ----------
    template : str
        Template file name, e.g. ``"analysis.html.j2"``.
    context : mapping
        Template variables; every page needs ``title``.

    Returns
    -------
    str
        The HTML document.

    Examples
    --------
    >>> html = render_page("base.html.j2", {"title": "a < b"})
    >>> "<title>a &lt; b</title>" in html
    True
    """
    return _environment().get_template(template).render(**context)
