"""Figures of a rendered scene, after the paper's Figure 4 (PNG, matplotlib Agg backend).

Three rows — (a) no masking (ideal), (b) masking without compensation, (c) with compensation —
and two columns: input intensities with the masked ALs they cause (left), perceived intensities
against the intended ones (right). Grey shading marks where a channel falls below its masked AL
and is not felt. In row (c), hatching marks the points whose compensated input is above the
rig's rated maximum (the rig cannot play them), and dotted lines show what would be perceived
there if the input were clipped at that maximum. With a gamut mapping, the dashed lines are the
mapped targets and row (c) adds the scene's own intended levels (dotted); with uncertainty,
shaded bands show the per-point intervals of what is felt. Drawn in the package's legible style
(fonts ≥ 8 pt at the saved size, constrained layout).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from masking_lab.formats.png_figure import legible, png_bytes
from masking_lab.rendering.render import Rendering, intended
from masking_lab.rendering.solver import forward

if TYPE_CHECKING:
    from matplotlib.axes import Axes

__all__ = ["clipped_perceived", "figure4_png"]

MV_COLOUR = "tab:red"
EV_COLOUR = "tab:blue"


def clipped_perceived(
    r: Rendering,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """What would be perceived with the compensated inputs clipped at the rig's maximum.

    Parameters
    ----------
    r : Rendering
        A rendered scene (with a masking pair and rated maxima, dB SL).

    Returns
    -------
    mv_perceived_db_sl, ev_perceived_db_sl : ndarray
        Perceived intensities (dB SL) under the clipped inputs.
    unplayable : ndarray of bool
        Points where some compensated input is above its channel's rated maximum.

    Examples
    --------
    >>> mv, ev, over = clipped_perceived(rendering)  # doctest: +SKIP
    """
    sol = r.solution
    over = np.asarray(sol.mv_exceeds_rating, bool) | np.asarray(sol.ev_exceeds_rating, bool)
    mv_in, ev_in = r.mv_input_db_sl, r.ev_input_db_sl
    if sol.max_mv_db_sl is not None:
        mv_in = np.minimum(mv_in, sol.max_mv_db_sl)
    if sol.max_ev_db_sl is not None:
        ev_in = np.minimum(ev_in, sol.max_ev_db_sl)
    if r.pair is None:
        return mv_in, ev_in, over
    mv_p, ev_p = forward(r.pair, mv_in, ev_in)
    return mv_p, ev_p, over


def figure4_png(r: Rendering, *, dpi: int = 100, bands: Any = None) -> bytes:
    """The Figure-4-like panel for ``r`` as PNG bytes.

    Parameters
    ----------
    r : Rendering
        A rendered scene.
    dpi : int
        Resolution, dots per inch (font sizes are in points, the same at any dpi).
    bands : RenderingUncertainty, optional
        Per-point intervals of the perceived intensities, drawn as shaded bands in rows (b)
        and (c) (:mod:`masking_lab.rendering.uncertainty`).

    Returns
    -------
    bytes
        A 14 × 10.5 inch PNG.

    Examples
    --------
    >>> png = figure4_png(render_scene(scene, pair))  # doctest: +SKIP
    """
    x = r.x_mm
    has = (
        bool(np.any(np.isfinite(r.mv_target_db_sl))),
        bool(np.any(np.isfinite(r.ev_target_db_sl))),
    )
    zeros = np.zeros_like(x)
    rows = [
        (
            "(a) no masking (ideal)",
            (r.mv_target_db_sl, r.ev_target_db_sl),
            (zeros, zeros),
            (r.mv_target_db_sl, r.ev_target_db_sl),
        ),
        (
            "(b) without compensation",
            (r.mv_target_db_sl, r.ev_target_db_sl),
            (r.mv_masked_al_uncomp_db_sl, r.ev_masked_al_uncomp_db_sl),
            (r.mv_perceived_uncomp_db_sl, r.ev_perceived_uncomp_db_sl),
        ),
        (
            "(c) with compensation",
            (r.mv_input_db_sl, r.ev_input_db_sl),
            (r.mv_masked_al_db_sl, r.ev_masked_al_db_sl),
            (r.mv_perceived_db_sl, r.ev_perceived_db_sl),
        ),
    ]
    mv_clip, ev_clip, over = clipped_perceived(r)
    with legible() as plt:
        fig, axes = plt.subplots(3, 2, figsize=(14, 10.5), sharex=True, squeeze=False)
        for row, (title, inputs, masked, perceived) in enumerate(rows):
            left, right = axes[row]
            for k, colour, name, by in ((0, MV_COLOUR, "MV", "EV"), (1, EV_COLOUR, "EV", "MV")):
                if not has[k]:
                    continue
                target = r.mv_target_db_sl if k == 0 else r.ev_target_db_sl
                left.plot(x, inputs[k], color=colour, label=f"{name} input")
                if row > 0:
                    # In the channel's own colour: it is that channel's threshold (issue 17:
                    # drawn in the masker's colour it read as the other channel's).
                    left.plot(
                        x, masked[k], "--", color=colour, label=f"masked AL of {name} (by {by})"
                    )
                right.plot(x, perceived[k], color=colour, label=f"{name} perceived")
                if bands is not None and row > 0:
                    ch = ("mv", "ev")[k] + ("" if row == 2 else "_uncomp")
                    lo, hi = getattr(bands, f"{ch}_lo"), getattr(bands, f"{ch}_hi")
                    shown = np.isfinite(lo) & np.isfinite(hi)  # no band where no level
                    lo, hi = np.where(shown, lo, np.nan), np.where(shown, hi, np.nan)
                    right.fill_between(
                        x,
                        lo,
                        hi,
                        color=colour,
                        alpha=0.2,
                        lw=0,
                        label=f"{name} {100 * bands.level:.0f} % interval (masking fits)",
                    )
                mapped = r.gamut_map != "none"
                right.plot(
                    x,
                    target,
                    "--",
                    color=colour,
                    alpha=0.6,
                    label=f"{name} target after {r.gamut_map} mapping"
                    if mapped
                    else f"{name} intended",
                )
                if mapped and row == 2:
                    right.plot(
                        x,
                        intended(r)[k],
                        ":",
                        color="0.3",
                        lw=1.0,
                        label=f"{name} intended by the scene",
                    )
                # Grey where this channel is below its masked AL: not felt.
                right.fill_between(
                    x,
                    0,
                    1,
                    where=perceived[k] < 0,
                    color="0.85",
                    lw=0,
                    transform=right.get_xaxis_transform(),
                    label=f"{name} not felt" if np.any(perceived[k] < 0) else None,
                )
            if row == 2:
                _mark_unplayable(r, left, right, over, (mv_clip, ev_clip), has)
            left.set_ylabel("input (dB SL)")
            right.set_ylabel("perceived (dB SL)")
            left.set_title(f"{title}: inputs" + (" and masked ALs" if row else ""))
            right.set_title(f"{title}: perceived vs intended")
            right.axhline(0.0, color="k", lw=0.5)
            # Legends beside the axes, never over the curves.
            for ax in (left, right):
                ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
        for ax in axes[-1]:
            ax.set_xlabel("position along the path (mm)")
        fig.suptitle(_suptitle(r))
        return png_bytes(fig, dpi=dpi)


def _mark_unplayable(
    r: Rendering,
    left: Axes,
    right: Axes,
    over: NDArray[np.bool_],
    clipped: tuple[NDArray[np.float64], NDArray[np.float64]],
    has: tuple[bool, bool],
) -> None:
    """Row (c): rated maxima, hatching where the rig cannot play, perceived if clipped."""
    x = r.x_mm
    mv_max, ev_max = r.solution.max_mv_db_sl, r.solution.max_ev_db_sl
    if mv_max is not None and mv_max == ev_max:
        # One line for both: two dotted lines at one level hid the first under the second.
        label = f"MV and EV rated maximum ({mv_max:g} dB SL)"
        left.axhline(mv_max, ls=":", lw=1.8, color="0.2", label=label)
    else:
        for limit, colour, name in ((mv_max, MV_COLOUR, "MV"), (ev_max, EV_COLOUR, "EV")):
            if limit is not None:
                label = f"{name} rated maximum ({limit:g} dB SL)"
                left.axhline(limit, ls=":", lw=1.8, color=colour, label=label)
    if not np.any(over):
        return
    n = int(np.sum(over))
    for ax, hatch_label in ((left, f"rig cannot play ({n} of {len(x)} points)"), (right, None)):
        ax.fill_between(
            x,
            0,
            1,
            where=over,
            facecolor="none",
            edgecolor="0.7",
            hatch="///",
            lw=0,
            transform=ax.get_xaxis_transform(),
            label=hatch_label,
        )
    for k, colour, name in ((0, MV_COLOUR, "MV"), (1, EV_COLOUR, "EV")):
        if has[k]:
            shown = np.where(over, clipped[k], np.nan)
            right.plot(x, shown, ":", color=colour, lw=2, label=f"{name} perceived if clipped")


def _suptitle(r: Rendering) -> str:
    mapping = "" if r.gamut_map == "none" else f"; gamut mapping: {r.gamut_map}"
    if r.pair is None:
        return f"scene {r.scene.name}: one channel, no mutual masking{mapping}"
    p = r.pair
    return (
        f"scene {r.scene.name}: {p.mv} masked by {p.ev} (f: a = {p.a_db:.3g} dB, b = {p.b:.3g}) "
        f"and {p.ev} masked by {p.mv} (g: c = {p.c_db:.3g} dB, d = {p.d:.3g}){mapping}"
    )
