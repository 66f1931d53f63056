"""``masking-lab plan PROTOCOL``: simulate a protocol to trade session time against threshold
precision.

Run the protocol's staircases against simulated observers for a grid of stop rules, step
schedules and estimators, and QUEST+ at posterior-SD stop rules beside them; print trials,
minutes, AL bias, SD and RMSE per setting with its efficiency against the Cramér-Rao bound,
answer 'fewest trials for ±X dB' across procedures, and write CSV tables, report.html and the
speed–accuracy figure to --out.

Simulated observers run the protocol's staircases thousands of times under a grid of stop
rules, step schedules and estimators, and QUEST+ on the same observers; the command prints what
each setting costs (trials, minutes) and buys (AL bias, SD, RMSE), its efficiency against the
Cramér-Rao bound, answers "how many reversals for ±X dB" and "fewest trials for ±X dB" across
procedures, and writes CSV tables and figures to ``--out`` (see docs/speed-accuracy.md and
docs/procedures.md).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable

from masking_lab.commands.options import command_texts


def _checked(
    convert: Callable[[str], float], what: str, ok: Callable[[float], bool], rule: str
) -> Callable[[str], float]:
    """An argparse ``type``: ``convert`` the text, then require ``ok`` (``rule`` says what)."""

    def parse(text: str) -> float:
        try:
            value = convert(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from None
        if not ok(value):
            shown = value if convert is int else text
            raise argparse.ArgumentTypeError(f"must be {rule}, got {shown}")
        return value

    return parse


_positive_int = _checked(int, "a whole number", lambda v: v >= 1, "≥ 1")
_count = _checked(int, "a whole number", lambda v: v >= 0, "≥ 0")
_positive_float = _checked(
    float, "a number", lambda v: math.isfinite(v) and v > 0, "a positive number"
)
_nonnegative_float = _checked(
    float, "a number", lambda v: math.isfinite(v) and v >= 0, "a number ≥ 0"
)
_finite_float = _checked(float, "a number", math.isfinite, "a finite number")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("plan", **command_texts(__doc__))
    p.add_argument("protocol", metavar="PROTOCOL", help="protocol YAML file")
    p.add_argument(
        "--replicates",
        type=_positive_int,
        default=2000,
        help="simulated sessions per set (default 2000)",
    )
    p.add_argument(
        "--ml-replicates",
        type=_count,
        default=500,
        help="sessions per set fitted by maximum likelihood; 0 skips the ML estimator "
        "(default 500: the fits cost far more than the simulation)",
    )
    p.add_argument(
        "--stop-rules",
        metavar="RULES",
        help="RUN/AVERAGED pairs, comma-separated (default 7/4,9/6,11/8,13/10,15/12 and the "
        "protocol's own)",
    )
    p.add_argument(
        "--schedules",
        metavar="STEPS",
        help="up-step schedules in dB, ';'-separated, e.g. '4,4,4,2;4,2;2' (default: the "
        "protocol's, its first and last step, its last step throughout)",
    )
    p.add_argument(
        "--ratios",
        metavar="RATIOS",
        help="down/up step ratios crossed with the schedules, e.g. 1,0.7393 (0.7393: "
        "García-Pérez's 2AFC value; see docs/speed-accuracy.md) (default: the "
        "protocol's)",
    )
    p.add_argument(
        "--ground-truth",
        metavar="FILE",
        help="simulated population (YAML/JSON as protocols/simulation/ground_truth.yaml; "
        "default: that file)",
    )
    p.add_argument(
        "--scale-db",
        type=_positive_float,
        help="observers' psychometric logistic scale in dB (slope; default: the ground truth's)",
    )
    p.add_argument(
        "--lapse", type=_nonnegative_float, help="observers' lapse rate (default: ground truth's)"
    )
    p.add_argument(
        "--true-threshold-db",
        type=_finite_float,
        metavar="DB",
        help="give every set this true threshold (protocol's level unit) instead of the ground "
        "truth's",
    )
    p.add_argument(
        "--no-spread",
        action="store_true",
        help="every observer has the population threshold (no between-participant spread)",
    )
    p.add_argument(
        "--response-s",
        type=_nonnegative_float,
        default=1.0,
        help="mean response time per trial in s, added to the protocol's timing (default 1.0)",
    )
    p.add_argument(
        "--precision-db",
        type=_positive_float,
        default=1.0,
        help="target ±X dB for 'reversals needed' (default 1.0)",
    )
    p.add_argument(
        "--z",
        type=_positive_float,
        default=1.96,
        help="±X dB means z·SD ≤ X in every set (default 1.96: 95 %% of sessions)",
    )
    p.add_argument(
        "--max-reversals",
        type=_positive_int,
        default=41,
        help="longest stop rule tried when answering 'reversals needed' (default 41)",
    )
    p.add_argument(
        "--ml-lapse",
        type=_nonnegative_float,
        default=0.02,
        help="lapse rate the ML fit assumes (default 0.02, as the analysis)",
    )
    p.add_argument(
        "--ml-fixed-scale",
        action="store_true",
        help="fix the ML fit's scale at the observers' true one (optimistic; the analysis fits it)",
    )
    p.add_argument(
        "--quest-replicates",
        type=_count,
        default=400,
        help="QUEST+ tracks per set for the procedures comparison (default 400; 0 skips it)",
    )
    p.add_argument(
        "--psi",
        action="store_true",
        help="add the psi-marginal (slope unknown) to the procedures comparison (slow)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--out", default="plan_out", help="output folder (default ./plan_out)")
    p.add_argument(
        "--per-set", action="store_true", help="print every setting per set, not just pooled"
    )
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    import numpy as np

    from masking_lab.core.errors import AnalysisError, ProtocolError
    from masking_lab.core.psychometric import LEVITT_1U3D
    from masking_lab.formats.fileio import write_bytes_atomic, write_text_atomic
    from masking_lab.formats.output_dir import staged_output
    from masking_lab.formats.protocol import load_protocol
    from masking_lab.planning import plan as P
    from masking_lab.planning.figures import png_bytes, speed_accuracy
    from masking_lab.planning.procedure_plan import compare_procedures
    from masking_lab.planning.procedure_report import (
        format_comparison,
        format_fewest,
        procedures_figure,
    )
    from masking_lab.planning.report import answer_text, format_per_set, format_table, rows_to_csv
    from masking_lab.planning.report_html import render_plan_html
    from masking_lab.procedures.staircase_batch import Observer
    from masking_lab.simulation.observer import load_ground_truth

    protocol = load_protocol(args.protocol)
    if args.ground_truth is not None and not Path(args.ground_truth).is_file():
        raise ProtocolError(
            args.ground_truth,
            "",
            "no such ground-truth file; check the path given to --ground-truth",
        )
    truth = load_ground_truth(args.ground_truth)
    truth_name = args.ground_truth or "protocols/simulation/ground_truth.yaml"
    scale = truth.scale_db if args.scale_db is None else args.scale_db
    lapse = truth.lapse if args.lapse is None else args.lapse
    # The threshold is the 0.794 point, so p(correct) must be able to exceed it.
    for flag, value in (("--lapse", lapse), ("--ml-lapse", args.ml_lapse)):
        if not value < 1 - LEVITT_1U3D:
            raise AnalysisError(
                f"{flag} {value:g}: p(correct) could never reach the 0.794 that defines the "
                f"threshold; use a lapse rate below {1 - LEVITT_1U3D:.3f} (typically 0–0.05)"
            )
    observer = Observer(scale, lapse, truth.guess)

    rules = (
        P.parse_stop_rules(args.stop_rules) if args.stop_rules else P.default_stop_rules(protocol)
    )
    ratios = P.parse_ratios(args.ratios) if args.ratios else None
    if args.schedules:
        schedules = P.parse_schedules(
            args.schedules, ratios or (P.protocol_schedule(protocol).down_up_ratio,)
        )
    else:
        schedules = P.default_schedules(protocol, ratios)
    settings = P.PlanSettings(
        stop_rules=rules,
        schedules=schedules,
        observer=observer,
        replicates=args.replicates,
        ml_replicates=args.ml_replicates,
        response_s=args.response_s,
        precision_db=args.precision_db,
        z=args.z,
        max_reversals=max(args.max_reversals, max(r.n_reversals for r in rules)),
        ml_lapse=args.ml_lapse,
        ml_fit_scale=not args.ml_fixed_scale,
        seed=args.seed,
    )
    thresholds = P.true_thresholds_db(
        protocol,
        truth,
        settings.replicates,
        np.random.default_rng(np.random.SeedSequence([args.seed, 0x7412])),
        spread=not args.no_spread,
        override_db=args.true_threshold_db,
        truth_source=truth_name,
    )

    def progress(msg: str) -> None:
        print(f"plan: {msg}", file=sys.stderr, flush=True)

    result = P.run_plan(protocol, settings, thresholds, progress=progress)
    comparison = None
    if args.quest_replicates:
        comparison = compare_procedures(
            protocol,
            result,
            settings,
            thresholds,
            quest_replicates=args.quest_replicates,
            psi=args.psi,
            progress=progress,
        )
    cap = P.protocol_staircase(protocol).max_trials
    unit = "dB SL" if protocol.level_unit == "db_sl" else "dB re 1 V"
    header = [
        f"masking-lab plan: {args.protocol} — {protocol.experiment} ({protocol.kind}, "
        f"{len(protocol.sets)} sets, levels in {unit})",
        f"{settings.replicates} simulated sessions per set ({settings.ml_replicates} for the ML "
        f"fit), seed {settings.seed}; observers: logistic scale {scale:g} dB, lapse {lapse:g}, "
        f"guess {truth.guess:.3g}; true thresholds: "
        + (
            f"{args.true_threshold_db:g} {unit} in every set"
            if args.true_threshold_db is not None
            else f"{truth_name}" + ("" if not args.no_spread else " (no spread)")
        ),
        f"one trial = {protocol.timing.trial_s:g} s + {settings.response_s:g} s response + "
        f"{protocol.timing.inter_trial_s:g} s pause = {result.trial_s:g} s; trial cap "
        f"{cap if cap is not None else 'none'}; bias = mean(AL − true threshold)",
    ]
    text = "\n".join(
        [
            *header,
            "",
            format_table(result),
            "",
            format_per_set(result, only_own=not args.per_set),
            "",
            f"Reversals needed for ±{settings.precision_db:g} dB (stop rules RUN/RUN−"
            f"{result.protocol_rule.n_reversals - result.protocol_rule.n_averaged}, no trial "
            "cap):",
            *(f"  {answer_text(a, settings, cap)}" for a in result.answers),
        ]
    )
    if comparison is not None:
        text += "\n\n" + format_comparison(comparison) + "\n\n" + format_fewest(comparison)
    print(text)

    out = Path(args.out)
    files = {
        "plan.txt": text + "\n",
        "plan_table.csv": rows_to_csv(result.table),
        "plan_sets.csv": rows_to_csv(result.per_set),
        "plan_ladder.csv": rows_to_csv(result.ladder),
    }
    figures = {
        "plan_speed_accuracy.png": speed_accuracy(
            result, title=f"{protocol.experiment}: speed against accuracy"
        )
    }
    if comparison is not None:
        files["plan_procedures.csv"] = rows_to_csv(comparison.rows)
        files["plan_procedures_sets.csv"] = rows_to_csv(comparison.per_set)
        figures["plan_procedures.png"] = procedures_figure(
            comparison, title=f"{protocol.experiment}: procedures against the Cramér-Rao bound"
        )
    pngs = {name: png_bytes(fig) for name, fig in figures.items()}
    files["report.html"] = render_plan_html(
        result,
        title=f"masking-lab plan: {protocol.experiment}",
        header=header,
        answers=[answer_text(a, settings, cap) for a in result.answers],
        figures=pngs,
    )
    # All files appear at once (the folder swapped in whole) unless --out holds other files.
    protect = [args.protocol, *([args.ground_truth] if args.ground_truth else [])]
    with staged_output(out, protect=protect, markers=("plan.txt",), shared="in_place") as stage:
        for name, content in files.items():
            write_text_atomic(stage / name, content)
        for name, png in pngs.items():
            write_bytes_atomic(stage / name, png)
    print(f"\nwrote {', '.join(str(out / n) for n in [*files, *figures])}", file=sys.stderr)
    return 0
