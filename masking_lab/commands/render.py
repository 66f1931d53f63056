"""``masking-lab render SCENE --params P --out DIR``: render a scene: per-point targets,
compensated inputs, perceived intensities.

Render a scene file (protocols/scenes/*.yaml): for every interaction point write the perceived
targets, the masking-compensated inputs (paper Table 4), and the masked ALs and perceived
intensities with and without compensation (points.csv), a summary (summary.json) and a figure
like the paper's Figure 4 (figure4.png). Only the masking functions of the scene's own stimulus
pair are loaded; a single-channel scene needs none. If they are not fitted, the protocol that
measures just that pair is written to DIR and the command exits 2. Points needing more than the
rated level are reported, never clipped. Exit 1 if some points have no unique compensated input.
"""

from __future__ import annotations

import argparse
import sys

from masking_lab.commands.options import command_texts, output_folder, rating_options
from masking_lab.commands.progress_bars import add_progress_options, progress_wanted, step_bar


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("render", **command_texts(__doc__))
    p.add_argument("scene", metavar="SCENE", help="scene YAML file")
    p.add_argument("--params", metavar="FILE", help="masking_params.json from `masking-lab fit`")
    p.add_argument(
        "--out", required=True, type=output_folder, metavar="DIR", help="output folder (created)"
    )
    rating_options(
        p,
        "rig config whose channels.<EV|MV>.max_level_db_sl are the rated maxima unless "
        "--max-* say otherwise (default: the reference rig, protocols/devices/default.yaml)",
    )
    p.add_argument(
        "--gamut-map",
        choices=("clip", "scale", "compress", "none"),
        default="clip",
        help="bring targets the rig cannot render into its gamut: clip (nearest renderable "
        "pair, the default), scale (one gain on the whole scene), compress (soft knee that "
        "keeps the profile), none (flag the points above a rating, play nothing different)",
    )
    p.add_argument(
        "--fitted-range-only",
        action="store_true",
        help="restrict the gamut to the masker levels the ramps were fitted on: each channel's "
        "maximum is capped at the top of the fitted range of the ramp it drives",
    )
    p.add_argument(
        "--uncertainty-draws",
        type=int,
        default=200,
        metavar="N",
        help="parameter draws carrying the masking fits' uncertainty to per-point intervals of "
        "what is felt (default 200; 0: none)",
    )
    p.add_argument("--no-figure", action="store_true", help="skip figure4.png and gamut.png")
    add_progress_options(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from masking_lab.core.errors import SolverError
    from masking_lab.device.rig_limits import max_level_db_sl
    from masking_lab.formats.masking_params import determination_warnings, read_masking_params
    from masking_lab.formats.output_dir import staged_output
    from masking_lab.rendering.outputs import (
        measurement_protocols,
        write_measurement_protocol,
        write_rendering,
    )
    from masking_lab.rendering.render import needed_pairs, render_scene, summarize
    from masking_lab.rendering.scene import load_scene
    from masking_lab.rendering.solver import MissingMaskingError, PairProblem, pair_from_params

    # A bar of the five steps on a terminal (or with --progress); the figures take longest.
    step = step_bar("render", progress_wanted(args.progress), total=5, lines_when_off=False)
    scene = load_scene(args.scene)
    limits = max_level_db_sl(args.device_config)
    max_mv = args.max_mv_db_sl if args.max_mv_db_sl is not None else limits.get("MV")
    max_ev = args.max_ev_db_sl if args.max_ev_db_sl is not None else limits.get("EV")
    pair = None
    for mv, ev in needed_pairs(scene):
        try:
            if not args.params:
                raise MissingMaskingError(
                    f"scene {scene.name!r} plays {mv} with {ev} and needs their masking "
                    "functions: pass --params masking_params.json",
                    [PairProblem(ev, mv, "missing"), PairProblem(mv, ev, "missing")],
                )
            params = read_masking_params(args.params)
            pair = pair_from_params(params, mv=mv, ev=ev, source=args.params)
            for warning in determination_warnings(params, args.params, (mv, ev)):
                print(f"masking-lab render: warning: {warning}", file=sys.stderr)
        except MissingMaskingError as exc:
            protocols = " and ".join(
                str(write_measurement_protocol(doc, args.out, writer="render"))
                for doc in measurement_protocols(exc.problems, writer="render")
            )
            raise SolverError(
                f"{exc}\n  wrote {protocols}: the protocol(s) that measure just this pair, one per "
                f"masking direction. Check them with `masking-lab validate`, run them after the "
                "participants' baseline, analyse them together with the rest of the study, and "
                "render again"
            ) from exc
    if args.fitted_range_only and pair is not None and max_mv is not None and max_ev is not None:
        from masking_lab.rendering.gamut import fitted_caps

        max_mv, max_ev = fitted_caps(pair, max_mv, max_ev)
    gamut_map = args.gamut_map
    if gamut_map != "none" and (max_mv is None or max_ev is None):
        # Nothing is rated on some channel: there is no gamut to map into.
        gamut_map = "none"
    step("solving the compensated inputs")
    rendering = render_scene(
        scene, pair, max_mv_db_sl=max_mv, max_ev_db_sl=max_ev, gamut_map=gamut_map
    )
    step(f"uncertainty ({args.uncertainty_draws} draws)")
    uncertainty = None
    if pair is not None and args.uncertainty_draws:
        from masking_lab.rendering.uncertainty import pair_spread, perceived_intervals

        spread = pair_spread(params, mv=pair.mv, ev=pair.ev)
        uncertainty = perceived_intervals(rendering, spread, n_draws=args.uncertainty_draws)
    step("comparing gamut mappings")
    trade = None
    if max_mv is not None and max_ev is not None:
        from masking_lab.rendering.render import compare_strategies

        trade = compare_strategies(scene, pair, max_mv, max_ev)
    # All files appear at once (the folder swapped in whole) unless --out holds other files.
    out = Path(args.out)
    protect = [args.scene, *([args.params] if args.params else [])]
    step("writing points, summary and figures")
    with staged_output(out, protect=protect, markers=("summary.json",), shared="in_place") as st:
        staged = write_rendering(
            rendering, st, figure=not args.no_figure, uncertainty=uncertainty, strategies=trade
        )
        written = [out / p.name for p in staged]
    step("done")
    summary = summarize(rendering)
    if pair is None:
        print(f"{scene.name}: single-channel scene, targets passed straight through")
    else:
        print(
            f"{scene.name}: {pair.mv} with {pair.ev} (a={pair.a_db:g}, b={pair.b:g}, "
            f"c={pair.c_db:g}, d={pair.d:g}, b·d={pair.bd_text}); "
            + ", ".join(f"{k} {v}" for k, v in summary["status_counts"].items() if v)
        )
    for name, ch in summary["channels"].items():
        lo, hi = ch["input_range_db_sl"] or ("-", "-")
        line = f"  {name} ({ch['stimulus']}): inputs {_f(lo)}..{_f(hi)} dB SL"
        if ch["points_above_rating"]:
            spans = ", ".join(f"{a:.1f}-{b:.1f}" for a, b in ch["above_rating_mm"])
            line += (
                f"; {ch['points_above_rating']} of {summary['n_points']} points need more than "
                f"the rated {ch['max_rated_db_sl']:g} dB SL (at {spans} mm)"
            )
        if ch["points_beyond_fitted_range"]:
            lo_fit, hi_fit = ch["masks_other_fitted_range_db_sl"]
            line += (
                f"; at {ch['points_beyond_fitted_range']} points it masks beyond the "
                f"{lo_fit:g}-{hi_fit:g} dB SL the other ramp was fitted on (extrapolated)"
            )
        unc = ch["uncompensated"]
        line += (
            f"; uncompensated: worst error {_f(unc['max_abs_error_db'])} dB, "
            f"{unc['points_not_felt']} points not felt"
        )
        print(line)
    gm = summary["gamut_mapping"]
    played = gm["as_played"]
    print(
        f"  gamut mapping {gm['strategy']}: {gm['points_moved']} of {summary['n_points']} targets "
        f"moved into the gamut"
        + (f" (gain {gm['gain']:.3g})" if gm["strategy"] == "scale" else "")
        + (
            f", {gm['points_from_gamut_edge']} with inputs found on the gamut's edge"
            if gm["points_from_gamut_edge"]
            else ""
        )
        + f"; as played: RMS error {_f(played['rms_error_db'])} dB, max "
        f"{_f(played['max_error_db'])} dB, {100 * (played['share_within_ratings'] or 0):.0f}% "
        "of points within the ratings"
    )
    if trade is not None:
        others = ", ".join(
            f"{name} {_f(t['rms_error_db'])}/{_f(t['max_error_db'])} dB, "
            f"{100 * (t['share_within_ratings'] or 0):.0f}% within"
            for name, t in trade.items()
            if name != gm["strategy"]
        )
        print(f"  other mappings (RMS/max error as played): {others}")
    if uncertainty is not None:
        u = uncertainty.summary()
        how = ", ".join(f"{fn} {m}" for fn, m in u["method_by_function"].items())
        print(
            f"  uncertainty ({u['n_draws']} draws of the fits: {how}; "
            f"{100 * u['level']:.0f} % intervals): compensation not better than none at "
            f"{u['points_compensation_not_better']} points; {u['points_beyond_fitted_range']} "
            "points rely on a ramp beyond its fitted masker range"
        )
    for note in summary["notes"]:
        print(f"  note: {note}")
    for path in written:
        print(f"  wrote {path}")
    unsolved = summary["status_counts"]["none"] + summary["status_counts"]["multiple"]
    if unsolved:
        # Name each real cause: a NaN target or an ill-conditioned pair is not a b·d ≥ 1 fold.
        why = [f"{n} {text}" for text, n in summary["no_answer_reasons"].items()]
        if summary["status_counts"]["multiple"]:
            why.append(
                f"{summary['status_counts']['multiple']} with several answers (b·d ≥ 1: the "
                "masking folds)"
            )
        print(
            f"  {unsolved} points have no unique compensated input (see the status column of "
            "points.csv): " + "; ".join(why)
        )
        return 1
    return 0


def _f(x: object) -> str:
    return f"{x:.1f}" if isinstance(x, float) else str(x)
