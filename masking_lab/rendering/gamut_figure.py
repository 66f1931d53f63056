"""The perceptual gamut drawn after the paper's Figure 6 (PNG, matplotlib Agg backend).

The (m_p, e_p) plane, dB SL, with the boundary lines of the four solver regions of Table 4
(they meet where U = a + b·e_p and V = c + d·m_p are both 0), the rated input box mapped into
it (one filled polygon per linear piece, so a fold at b·d ≥ 1 shows as overlapping pieces), the felt
quadrant, and optionally a scene's targets: inside the gamut and outside it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from masking_lab.formats.png_figure import legible, png_bytes
from masking_lab.rendering.gamut import Gamut

__all__ = ["gamut_png"]

CASE_COLOURS = {1: "0.6", 2: "tab:blue", 3: "tab:red", 4: "tab:purple"}
CASE_LABELS = {
    1: "case 1: no masking",
    2: "case 2: EV masked (g rising)",
    3: "case 3: MV masked (f rising)",
    4: "case 4: both masked",
}


def gamut_png(
    g: Gamut,
    *,
    mv_target_db_sl: ArrayLike | None = None,
    ev_target_db_sl: ArrayLike | None = None,
    mapped: tuple[ArrayLike, ArrayLike] | None = None,
    title: str = "",
    dpi: int = 100,
) -> bytes:
    """The gamut as PNG bytes, with optional scene targets and their mapped versions (dB SL).

    Parameters
    ----------
    g : Gamut
        From :func:`masking_lab.rendering.gamut.perceptual_gamut`.
    mv_target_db_sl, ev_target_db_sl : array_like, optional
        A scene's intended perceived pairs, dB SL.
    mapped : (array_like, array_like), optional
        The same points after gamut mapping, dB SL.
    title : str
        Figure title.
    dpi : int
        Resolution, dots per inch.

    Returns
    -------
    bytes
        A 9 × 7 inch PNG.

    Examples
    --------
    >>> from masking_lab.rendering.gamut import perceptual_gamut
    >>> from masking_lab.rendering.pair import MutualMasking
    >>> png = gamut_png(perceptual_gamut(MutualMasking(-2.0, 0.5, -1.0, 0.4), 30.0, 30.0))
    >>> png[:4] == b"\\x89PNG"
    True
    """
    pair = g.pair
    with legible() as plt:
        fig, ax = plt.subplots(figsize=(9, 7))
        seen: set[int] = set()
        for piece in g.pieces:
            v = np.vstack([piece.vertices, piece.vertices[:1]])
            colour = CASE_COLOURS[piece.case]
            ax.fill(
                v[:, 0],
                v[:, 1],
                color=colour,
                alpha=0.25,
                lw=0,
                label=None if piece.case in seen else CASE_LABELS[piece.case] + " (renderable)",
            )
            ax.plot(v[:, 0], v[:, 1], color=colour, lw=0.8)
            seen.add(piece.case)
        if g.outline is not None:
            o = np.vstack([g.outline, g.outline[:1]])
            ax.plot(o[:, 0], o[:, 1], color="k", lw=1.6, label="gamut outline")
        # Region boundaries of Table 4 in the target plane: U = 0 (e_p = −a/b), V = 0
        # (m_p = −c/d), and the edges U + b·V = 0, V + d·U = 0 of cases 2 and 3.
        lo = min(float(np.min([p.vertices[:, 0].min() for p in g.pieces])), 0.0) - 5
        hi = max(float(np.max([p.vertices[:, 0].max() for p in g.pieces])), 0.0) + 5
        m = np.linspace(lo, hi, 200)
        if pair.b:
            ax.axhline(-pair.a_db / pair.b, color="0.4", ls=":", lw=0.8, label="U = 0, V = 0")
        if pair.d:
            ax.axvline(-pair.c_db / pair.d, color="0.4", ls=":", lw=0.8)
        if pair.b and pair.d:
            v_line = pair.c_db + pair.d * m
            # U + b·V = 0 ⇔ e_p = −(a + b·V)/b, for V ≥ 0;  V + d·U = 0 ⇔ e_p = (−V/d − a)/b.
            with np.errstate(invalid="ignore"):
                ax.plot(
                    m,
                    np.where(v_line >= 0, -(pair.a_db + pair.b * v_line) / pair.b, np.nan),
                    color="tab:blue",
                    ls="--",
                    lw=0.8,
                    label="U + b·V = 0 (case 2 edge)",
                )
                ax.plot(
                    m,
                    np.where(v_line <= 0, (-v_line / pair.d - pair.a_db) / pair.b, np.nan),
                    color="tab:red",
                    ls="--",
                    lw=0.8,
                    label="V + d·U = 0 (case 3 edge)",
                )
        ax.axhline(0.0, color="k", lw=0.5)
        ax.axvline(0.0, color="k", lw=0.5)
        if mv_target_db_sl is not None and ev_target_db_sl is not None:
            mt = np.asarray(mv_target_db_sl, float)
            et = np.asarray(ev_target_db_sl, float)
            inside = g.contains(mt, et)
            ax.plot(
                mt[inside], et[inside], ".", ms=3, color="tab:green", label="target: renderable"
            )
            ax.plot(
                mt[~inside], et[~inside], ".", ms=3, color="k", label="target: outside the gamut"
            )
            if mapped is not None:
                ax.plot(
                    np.asarray(mapped[0], float),
                    np.asarray(mapped[1], float),
                    ".",
                    ms=3,
                    color="tab:orange",
                    label="target after gamut mapping",
                )
        ax.set_xlabel("perceived MV m_p (dB SL)")
        ax.set_ylabel("perceived EV e_p (dB SL)")
        (m0, m1), (e0, e1) = g.mv_box_db_sl, g.ev_box_db_sl
        ax.set_title(
            title
            or (
                f"{pair.mv} / {pair.ev}: inputs MV {m0:g}–{m1:g}, EV {e0:g}–{e1:g} dB SL "
                f"mapped to what is felt (b·d = {pair.bd_text})"
            )
        )
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
        return png_bytes(fig, dpi=dpi)
