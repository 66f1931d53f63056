"""``masking-lab gamut --params FILE --out DIR``: the perceived pairs the rig can render.

The perceptual gamut (paper §4.3, Figure 6): the image of the rig's input box (each channel from
0 dB SL to its rated maximum) under the fitted masking functions of one MV/EV pair, exactly, as
linear pieces with their vertices in dB SL. Prints the vertices and writes gamut.json and
gamut.png (Figure 6 with the device's box mapped into it). With b·d < 1 the gamut is one polygon;
with b·d ≥ 1 the pieces fold over each other (targets with two answers).
"""

from __future__ import annotations

import argparse

from masking_lab.commands.options import command_texts, output_folder, rating_options


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("gamut", **command_texts(__doc__))
    p.add_argument(
        "--params", required=True, metavar="FILE", help="masking_params.json from `masking-lab fit`"
    )
    p.add_argument("--mv", metavar="NAME", help="MV stimulus, e.g. MV180 (needed if several)")
    p.add_argument("--ev", metavar="NAME", default="EV270", help="EV stimulus (default EV270)")
    p.add_argument(
        "--out",
        required=True,
        type=output_folder,
        metavar="DIR",
        help="folder for gamut.json, gamut.png",
    )
    rating_options(
        p,
        "rig config whose channels.<EV|MV>.max_level_db_sl are the rated maxima unless "
        "--max-* say otherwise (default: the reference rig, protocols/devices/default.yaml)",
    )
    p.add_argument(
        "--fitted-range-only",
        action="store_true",
        help="cap each channel at the highest masker level its masking of the other was fitted "
        "on (no extrapolated ramp)",
    )
    p.add_argument("--no-figure", action="store_true", help="skip gamut.png")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from masking_lab.commands.solve import _only_mv
    from masking_lab.core.errors import SolverError
    from masking_lab.device.rig_limits import max_level_db_sl
    from masking_lab.formats.fileio import write_bytes_atomic, write_text_atomic
    from masking_lab.formats.masking_params import read_masking_params
    from masking_lab.rendering.gamut import perceptual_gamut
    from masking_lab.rendering.solver import pair_from_params

    params = read_masking_params(args.params)
    mv = args.mv or _only_mv(params, args.ev, args.params)
    pair = pair_from_params(params, mv=mv, ev=args.ev, source=args.params)
    limits = max_level_db_sl(args.device_config)
    max_mv = args.max_mv_db_sl if args.max_mv_db_sl is not None else limits.get("MV")
    max_ev = args.max_ev_db_sl if args.max_ev_db_sl is not None else limits.get("EV")
    if max_mv is None or max_ev is None:
        raise SolverError(
            "gamut: the rig config rates no maximum for "
            + " and ".join(n for n, v in (("MV", max_mv), ("EV", max_ev)) if v is None)
            + "; give --max-mv-db-sl/--max-ev-db-sl or channels.<MV|EV>.max_level_db_sl"
        )
    if args.fitted_range_only:
        from masking_lab.rendering.gamut import fitted_caps

        max_mv, max_ev = fitted_caps(pair, max_mv, max_ev)
    g = perceptual_gamut(pair, max_mv, max_ev)
    print(
        f"{pair.mv} with {pair.ev}: f = max(0, {pair.a_db:g} + {pair.b:g}·e_i), "
        f"g = max(0, {pair.c_db:g} + {pair.d:g}·m_i), b·d = {pair.bd_text}"
    )
    print(
        f"inputs MV {g.mv_box_db_sl[0]:g}..{g.mv_box_db_sl[1]:g} dB SL, EV "
        f"{g.ev_box_db_sl[0]:g}..{g.ev_box_db_sl[1]:g} dB SL"
        + (" (capped at the fitted masker ranges)" if args.fitted_range_only else "")
    )
    if g.outline is not None:
        print("gamut: one polygon, vertices (m_p, e_p) in dB SL, counter-clockwise:")
        for m, e in g.outline:
            print(f"  ({m:.6g}, {e:.6g})")
    else:
        print("gamut: b·d ≥ 1, the union of these pieces (they overlap where a target has two")
        print("answers), vertices (m_p, e_p) in dB SL, counter-clockwise:")
    for piece in g.pieces:
        verts = ", ".join(f"({m:.6g}, {e:.6g})" for m, e in piece.vertices)
        print(f"  case {piece.case}: {verts}")
    out = Path(args.out)
    written = [write_text_atomic(out / "gamut.json", json.dumps(g.as_dict(), indent=2) + "\n")]
    if not args.no_figure:
        from masking_lab.rendering.gamut_figure import gamut_png

        written.append(write_bytes_atomic(out / "gamut.png", gamut_png(g)))
    for path in written:
        print(f"  wrote {path}")
    return 0
