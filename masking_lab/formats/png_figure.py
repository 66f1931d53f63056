"""PNG figures that a reader can use at 100 %: one style, one byte-stable writer.

Every figure of the package (analysis, rendering, user test, plan) is drawn under
:func:`legible` — fonts of at least :data:`MIN_FONT_PT` points at the saved size, constrained
layout so titles, labels and legends do not overlap — and saved by :func:`png_bytes` with the
Agg backend and without the software/date metadata that would change the bytes from run to
run. :func:`small_texts` lists the text artists below the minimum (the tests use it).
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

__all__ = ["MIN_FONT_PT", "legible", "png_bytes", "pyplot", "small_texts"]

# Smallest font size at the saved size, points (issue 12: 5 pt legends were unreadable).
MIN_FONT_PT = 8.0

_STYLE = {
    "font.size": 9.0,
    "axes.titlesize": 9.5,
    "axes.labelsize": 9.0,
    "xtick.labelsize": 8.5,
    "ytick.labelsize": 8.5,
    "legend.fontsize": 8.0,
    "legend.title_fontsize": 8.5,
    "figure.titlesize": 10.5,
    "figure.constrained_layout.use": True,
}


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the non-interactive Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


@contextmanager
def legible(*, constrained: bool = True) -> Iterator[Any]:
    """Draw inside this block to get the package's legible style; yields ``pyplot``.

    Parameters
    ----------
    constrained : bool
        Use constrained layout (False for a figure with fixed margins that is drawn many
        times: a layout engine would move its axes between draws).

    Examples
    --------
    >>> with legible() as plt:
    ...     fig, ax = plt.subplots(figsize=(3, 2))
    ...     _ = ax.set_xlabel("masker level (dB SL)")
    >>> min(t.get_fontsize() for t in [ax.xaxis.label])
    9.0
    >>> plt.close(fig)
    """
    plt = pyplot()
    with plt.rc_context({**_STYLE, "figure.constrained_layout.use": constrained}):
        yield plt


def png_bytes(fig: Any, *, dpi: int = 100, close: bool = True) -> bytes:
    """The figure as PNG bytes, deterministic (no software or date metadata).

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure.
    dpi : int
        Dots per inch; font sizes are in points, so they are the same at any dpi.
    close : bool
        Close the figure afterwards (False to reuse it, e.g. one track figure per process).

    Returns
    -------
    bytes
        A PNG file.

    Examples
    --------
    >>> with legible() as plt:
    ...     fig, ax = plt.subplots(figsize=(2, 2))
    ...     data = png_bytes(fig)
    >>> data[:8] == b"\\x89PNG\\r\\n\\x1a\\n"
    True
    """
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, metadata={"Software": None})
    if close:
        pyplot().close(fig)
    return buf.getvalue()


def small_texts(fig: Any, minimum: float = MIN_FONT_PT) -> list[tuple[str, float]]:
    """Visible, non-empty text artists of ``fig`` smaller than ``minimum`` points.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        A drawn figure.
    minimum : float
        Smallest acceptable size, points.

    Returns
    -------
    list of (text, size_pt)
        Empty when every text is large enough.

    Examples
    --------
    >>> with legible() as plt:
    ...     fig, ax = plt.subplots()
    ...     _ = ax.text(0, 0, "tiny", fontsize=5)
    >>> small_texts(fig)
    [('tiny', 5.0)]
    >>> plt.close(fig)
    """
    from matplotlib.text import Text

    out = []
    for t in fig.findobj(Text):
        if t.get_visible() and t.get_text().strip() and t.get_fontsize() < minimum:
            ax = t.axes
            if ax is not None and not ax.get_visible():
                continue
            out.append((t.get_text(), float(t.get_fontsize())))
    return out
