"""Figures of a rendered scene, after the paper's Figure 4 (PNG, matplotlib Agg backend).

Three rows — (a) no masking (ideal), (b) masking without compensation, (c) with compensation —
and two columns: input intensities with the masked ALs they cause (left), perceived intensities
against the intended ones (right). Grey shading marks where a channel falls below its masked AL
and is not felt.
"""

from __future__ import annotations

import io

import numpy as np

from masking_lab.rendering.render import Rendering

MV_COLOUR = "tab:red"
EV_COLOUR = "tab:blue"


def figure4_png(r: Rendering, *, dpi: int = 110) -> bytes:
    """The Figure-4-like panel for ``r`` as PNG bytes.

    Parameters
    ----------
    r : Rendering
        A rendered scene.
    dpi : int
        Resolution, dots per inch.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = r.x_mm
    has_mv = bool(np.any(np.isfinite(r.mv_target_db_sl)))
    has_ev = bool(np.any(np.isfinite(r.ev_target_db_sl)))
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
    fig, axes = plt.subplots(3, 2, figsize=(10, 9), sharex=True, squeeze=False)
    try:
        for row, (title, inputs, masked, perceived) in enumerate(rows):
            left, right = axes[row]
            for k, present, colour, other, name, by in (
                (0, has_mv, MV_COLOUR, EV_COLOUR, "MV", "EV"),
                (1, has_ev, EV_COLOUR, MV_COLOUR, "EV", "MV"),
            ):
                if not present:
                    continue
                target = r.mv_target_db_sl if k == 0 else r.ev_target_db_sl
                left.plot(x, inputs[k], color=colour, label=f"{name} input")
                left.plot(x, masked[k], "--", color=other, label=f"masked AL of {name} (by {by})")
                right.plot(x, perceived[k], color=colour, label=f"{name} perceived")
                right.plot(x, target, "--", color=colour, alpha=0.6, label=f"{name} intended")
                # Grey where this channel is below its masked AL: not felt.
                right.fill_between(
                    x,
                    0,
                    1,
                    where=perceived[k] < 0,
                    color="0.85",
                    lw=0,
                    transform=right.get_xaxis_transform(),
                )
            if row == 2:
                for limit, colour, name in (
                    (r.solution.max_mv_db_sl, MV_COLOUR, "MV"),
                    (r.solution.max_ev_db_sl, EV_COLOUR, "EV"),
                ):
                    if limit is not None:
                        left.axhline(limit, ls=":", color=colour, label=f"{name} rated maximum")
                left.legend(fontsize=7, loc="upper right")
            left.set_ylabel("input (dB SL)")
            right.set_ylabel("perceived (dB SL)")
            left.set_title(f"{title}: input", fontsize=10)
            right.set_title(f"{title}: perceived", fontsize=10)
            right.axhline(0.0, color="k", lw=0.5)
        for ax in axes[-1]:
            ax.set_xlabel("haptic interaction point (mm)")
        axes[0][0].legend(fontsize=7, loc="upper right")
        axes[0][1].legend(fontsize=7, loc="upper right")
        pair = ""
        if r.pair is not None:
            p = r.pair
            pair = f" ({p.mv}, {p.ev}: a={p.a_db:.3g}, b={p.b:.3g}, c={p.c_db:.3g}, d={p.d:.3g})"
        fig.suptitle(f"scene {r.scene.name}{pair}", fontsize=11)
        # Fixed margins: tight_layout costs a full extra draw per figure.
        fig.subplots_adjust(left=0.07, right=0.98, top=0.92, bottom=0.06, hspace=0.35, wspace=0.2)
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=dpi)
        return buf.getvalue()
    finally:
        plt.close(fig)
