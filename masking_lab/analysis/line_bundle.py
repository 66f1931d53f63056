"""Many marker lines drawn as one artist, pixel for pixel as one ``Line2D`` each (*shell*).

The AL-shift figure draws a thin line with markers per participant and panel: at 10,000
sessions about 11,000 of them per figure. As ``Line2D`` artists each costs about 0.6 ms of
Python (creating it through ``Axes.plot``, then drawing it twice: the constrained-layout pass
and the real draw), most of the figure's time. :class:`LineBundle` holds the lines as paths
(drawn in the real draw only: the layout pass draws nothing and a bundle has no extent)
and makes, in the same order, the same renderer calls that ``Line2D.draw`` makes for each
(``draw_path`` of the line, then ``draw_markers`` of its markers, with the same graphics-
context settings, read off a template ``Line2D`` built with the same style), so the PNG bytes
do not change; it updates the axes' data limits as adding the lines would.

Only the styles the template can stand for are bundled (solid line, no dashes, sketch, path
effects, marker subsampling or draw style); :func:`bundle_supported` says so, and the caller
draws one ``Line2D`` per line otherwise.
"""

from __future__ import annotations

from collections.abc import Sequence
from numbers import Real
from typing import Any

import matplotlib as mpl
import numpy as np
from matplotlib import colors as mcolors
from matplotlib.artist import Artist, allow_rasterization
from matplotlib.backend_bases import RendererBase
from matplotlib.lines import Line2D
from matplotlib.path import Path

__all__ = ["LineBundle", "bundle_supported"]


def bundle_supported(template: Line2D) -> bool:
    """Whether :class:`LineBundle` draws lines of ``template``'s style exactly as Line2D does:
    a solid line with filled markers whose face and edge take the line's colour.

    Examples
    --------
    >>> bundle_supported(Line2D([], [], marker="o", lw=0.9, ms=3.5, alpha=0.7))
    True
    >>> bundle_supported(Line2D([], [], ls="--", marker="o"))
    False
    """
    t: Any = template  # Line2D's own attributes (no public getter for "auto" colours)
    marker = t._marker
    rc: Any = mpl.rcParams
    return bool(
        template.get_linestyle() == "-"
        and not template.is_dashed()
        and template.get_sketch_params() is None
        and not template.get_path_effects()
        and template.get_drawstyle() == "default"
        and template.get_markevery() is None
        and template.get_visible()
        and template.get_linewidth() > 0
        and template.get_markersize() > 0
        and marker.get_marker() not in (",", "None", "none", None, "")
        and marker.is_filled()
        and marker.get_fillstyle() == "full"
        and not marker.get_alt_path()
        and _is_auto(t._markerfacecolor)
        and _is_auto(t._markeredgecolor)
        and not rc["_internal.classic_mode"]
    )


def _is_auto(color: Any) -> bool:
    return isinstance(color, str) and color.lower() == "auto"


class LineBundle(Artist):
    """Lines with markers, each drawn as a ``Line2D`` of ``template``'s style would be.

    Parameters
    ----------
    ax : matplotlib.axes.Axes
        The axes; the bundle is added to it (zorder of the template) and its data limits
        are updated with every point, as :meth:`~matplotlib.axes.Axes.add_line` would.
    template : Line2D
        The style of every line (not added anywhere); :func:`bundle_supported` must hold.
    lines : sequence of (xy, color)
        Per line, in drawing order: its points, an (n, 2) array of data coordinates
        (masker level, dB SL; shift, dB), and its colour (any matplotlib colour), which its
        markers' face and edge take too.
    """

    def __init__(self, ax: Any, template: Line2D, lines: Sequence[tuple[np.ndarray, Any]]) -> None:
        super().__init__()
        if not bundle_supported(template):
            raise ValueError("LineBundle: a style that Line2D draws differently")
        self._template = template
        alpha = template.get_alpha()
        named: dict[str, tuple[float, float, float, float]] = {}  # "C0".."C9": many lines each
        short = Path(np.zeros((1, 2)))
        self._lines: list[tuple[Path, tuple[float, float, float, float]]] = []
        for xy, color in lines:
            if not len(xy):
                continue
            if isinstance(color, str):
                rgba = named.get(color) or named.setdefault(color, mcolors.to_rgba(color, alpha))
            else:
                rgba = mcolors.to_rgba(color, alpha)
            self._lines.append((_path(xy, short), rgba))
        self.set_zorder(template.get_zorder())
        ax.add_artist(self)  # axes, figure, transData and the clip to the axes patch
        if self._lines:
            # One update with every point: the same extents as one per line (min and max).
            every = Path(np.concatenate([p.vertices for p, _ in self._lines]))
            ax.dataLim.update_from_path(every, ax.ignore_existing_data_limits)
            ax.ignore_existing_data_limits = False
            ax._request_autoscale_view()  # as Axes.plot does after adding its lines

    @allow_rasterization
    def draw(self, renderer: Any) -> None:
        """Each line's path, then its markers, line by line (``Line2D.draw``'s calls)."""
        if not self.get_visible() or not self._lines or _drawing_disabled(renderer):
            return
        # Line2D's own attributes, as its draw reads them (the bytes tests pin this version's).
        t: Any = self._template
        me: Any = self
        transform = self.get_transform()
        affine = transform.get_affine().frozen()
        line_gc = renderer.new_gc()
        me._set_gc_clip(line_gc)
        line_gc.set_url(self.get_url())
        line_gc.set_antialiased(t._antialiased)
        line_gc.set_linewidth(t._linewidth)
        line_gc.set_joinstyle(t._solidjoinstyle)
        line_gc.set_capstyle(t._solidcapstyle)
        line_gc.set_snap(t.get_snap())
        line_gc.set_dashes(*t._dash_pattern)
        marker = t._marker
        marker_gc = renderer.new_gc()
        me._set_gc_clip(marker_gc)
        marker_gc.set_url(self.get_url())
        marker_gc.set_linewidth(t._markeredgewidth)
        marker_gc.set_antialiased(t._antialiased)
        snap = marker.get_snap_threshold()
        if isinstance(snap, Real):
            snap = renderer.points_to_pixels(t._markersize) >= snap
        marker_gc.set_snap(snap)
        marker_gc.set_joinstyle(marker.get_joinstyle())
        marker_gc.set_capstyle(marker.get_capstyle())
        marker_path = marker.get_path()
        marker_trans = marker.get_transform().scale(renderer.points_to_pixels(t._markersize))
        # Linear axes: the non-affine part is the identity, so each line's path is both what
        # Line2D strokes and the points it puts markers on (the same vertices, the same flags).
        linear = transform.is_affine
        renderer.open_group("line_bundle", self.get_gid())
        for path, rgba in self._lines:
            # the line, then its markers (face and edge: the line's colour and alpha)
            line_gc.set_foreground(rgba, isRGBA=True)
            line = path if linear else transform.transform_path_non_affine(path)
            renderer.draw_path(line_gc, line, affine)
            marker_gc.set_foreground(rgba, isRGBA=True)
            points = path if linear else Path(transform.transform_non_affine(path.vertices))
            renderer.draw_markers(marker_gc, marker_path, marker_trans, points, affine, rgba)
        renderer.close_group("line_bundle")
        line_gc.restore()
        marker_gc.restore()
        self.stale = False


# Paths this short are never simplified (Path() decides at 128 vertices).
_SHORT_MAX = 127


def _path(xy: Any, short: Path) -> Path:
    """``Path(xy)`` for a line's (n, 2) points; a short one without the constructor's checks
    (a tenth of its time: ~11,000 lines per figure at 10,000 sessions), taking its settings
    from ``short``, a short path made by Path() under the same rcParams."""
    verts = np.asarray(xy, dtype=float)
    if verts.ndim == 2 and verts.shape[1] == 2 and len(verts) <= _SHORT_MAX:
        made: Any = Path  # its constructor without the checks (not in matplotlib's stubs)
        return made._fast_from_codes_and_verts(verts, None, internals_from=short)
    return Path(verts)


def _drawing_disabled(renderer: Any) -> bool:
    """Whether this is matplotlib's layout pass before a save, whose renderer's draw methods
    are no-ops (``RendererBase._draw_disabled``): the bundle's ~11,000 lines would be walked
    for nothing."""
    own = getattr(renderer, "__dict__", {})
    return all(
        getattr(own.get(name), "__wrapped__", None) is getattr(RendererBase, name)
        for name in ("draw_path", "draw_markers")
    )
