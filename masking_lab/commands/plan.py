"""``masking-lab plan PROTOCOL | --scene SCENE``: simulate a protocol to trade session time
against threshold precision, or plan the measurements a scene needs.

Run the protocol's staircases against simulated observers for a grid of stop rules, step
schedules and estimators, and QUEST+ at posterior-SD stop rules beside them; print trials,
minutes, AL bias, SD and RMSE per setting with its efficiency against the Cramér-Rao bound,
answer 'fewest trials for ±X dB' across procedures, and write CSV tables, report.html and the
speed–accuracy figure to --out. With --scene SCENE instead of a protocol: list the masking
functions a scene needs and the masker ranges it plays (present within the fitted range,
extrapolated, or missing), write the protocols that measure what is missing, and predict the
scene's rendering error for a few budgets of participants × trials (docs/scenes.md).

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
from pathlib import Path
from typing import TYPE_CHECKING, Any

from masking_lab.commands.options import add_scheduler_option, command_texts, output_folder
from masking_lab.commands.plan_scene import add_scene_options, run_scene
from masking_lab.commands.progress_bars import add_progress_options

if TYPE_CHECKING:  # `--help` must not import the protocol layer
    from masking_lab.formats.protocol import ThresholdProtocol


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


def _rig_resolution(protocol: Any, truth: Any, device_config: str | None) -> list[str]:
    """Header lines: does the rig's converter play every set's levels within 1 dB?"""
    from masking_lab.device.config import load_device_config
    from masking_lab.device.level_check import level_problems

    config = load_device_config(device_config)
    if not config.converters:
        return [f"rig {config.name}: no converter described; resolution not checked"]
    problems = level_problems(
        protocol,
        config.converters,
        truth.unmasked_al_db_v,
        config.limits.max_drive_v,
        al_source="the ground truth",
    )
    if not problems:
        return [f"rig {config.name}: every level of every set plays within 1 dB"]
    return [
        f"rig {config.name}: FLAGGED, {len(problems)} setting(s) below the rig's resolution:",
        *(f"  {p}" for p in problems),
    ]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("plan", **command_texts(__doc__))
    p.add_argument(
        "protocol", metavar="PROTOCOL", nargs="?", help="protocol YAML file (or give --scene)"
    )
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
        default=None,
        help="QUEST+ tracks per set for the procedures comparison (default 400, or 40 when the "
        "protocol's QUEST+ marginalises slope or lapse: each of its trials costs ~30 times "
        "more; 0 skips it)",
    )
    p.add_argument(
        "--psi",
        action="store_true",
        help="add the psi-marginal (slope unknown) to the procedures comparison (slow)",
    )
    p.add_argument(
        "--device-config",
        metavar="FILE",
        help="rig config whose converters are checked against every set's level range: a "
        "floor below the rig's resolution is flagged; with --scene, its channels' "
        "max_level_db_sl are the ratings (default: protocols/devices/default.yaml)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--quest-max-trials",
        type=_positive_int,
        metavar="N",
        help="trial cap of the capped QUEST+ rows (default: the protocol's QUEST+ max_trials, "
        "or for a staircase protocol its staircase's trial cap)",
    )
    p.add_argument(
        "--out",
        type=output_folder,
        default=None,
        help="output folder (default ./plan_out, or plan_out-2, -3, ... when that holds a plan "
        "already)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace the plan already in --out (otherwise refused, so no plan is lost)",
    )
    p.add_argument(
        "--per-set", action="store_true", help="print every setting per set, not just pooled"
    )
    add_scheduler_option(p)
    add_progress_options(p)
    add_scene_options(p)
    p.set_defaults(handler=run)


def _places_masker(protocol: ThresholdProtocol) -> bool:
    from masking_lab.procedures.registry import kind_of

    return any(kind_of(s.settings).places_masker for s in protocol.sets)


#: Simulated participants per route for a functional protocol (its functional track is ~0.35 s
#: of CPU, its five staircases and five QUEST+ tracks ~0.05 s).
_FUNCTIONAL_REPLICATES = 60


def _masking_function_plan(args: argparse.Namespace, protocol: object, out: Path) -> int:
    """A protocol whose procedure measures masking functions: plan compares, for its first
    pair, the paper's route, QUEST+ per set and the functional procedure
    (planning/ramp_trade.py; docs/speed-accuracy.md section 4)."""

    from masking_lab.formats.fileio import write_text_atomic
    from masking_lab.planning.ramp_trade import format_trade, trade_for_protocol
    from masking_lab.simulation.observer import load_ground_truth

    truth = load_ground_truth(args.ground_truth)
    replicates = min(args.replicates, _FUNCTIONAL_REPLICATES)
    trade, results, ratios = trade_for_protocol(
        protocol,
        truth,
        replicates=replicates,
        seed=args.seed,
        scheduler=None if args.scheduler == "local" else args.scheduler,
    )
    text = format_trade(trade, results, ratios)
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "masking_function_trade.txt", text)
    print(text, end="")
    return 0


def run(args: argparse.Namespace) -> int:
    from masking_lab.core.blas_threads import one_blas_thread

    # The batch products ((tracks × 131) · (131 × 131)) gain little from a second BLAS thread
    # and lose 3× CPU to its spin-waits whenever another program holds a core.
    with one_blas_thread():
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    from masking_lab.commands.plan_simulation import simulation
    from masking_lab.commands.progress_bars import progress_wanted, step_bar
    from masking_lab.core.errors import AnalysisError
    from masking_lab.formats.fileio import write_bytes_atomic, write_text_atomic
    from masking_lab.formats.output_dir import staged_output
    from masking_lab.formats.protocol import load_protocol
    from masking_lab.planning import plan as P
    from masking_lab.planning.parallel import started_tasks
    from masking_lab.planning.procedure_plan import compare_procedures
    from masking_lab.planning.report import (
        answer_text,
        format_per_set,
        format_table,
        plan_section_titles,
        rows_to_csv,
    )
    from masking_lab.planning.report_html import render_plan_html
    from masking_lab.planning.settings import protocol_procedure_text, runs_staircase

    if (args.protocol is None) == (args.scene is None):
        raise AnalysisError(
            "plan: give either a PROTOCOL to simulate or --scene SCENE to plan a scene's "
            "measurements (not both)"
        )
    if args.scene is not None:
        return run_scene(args, plan_folder(args.out, force=args.force))
    protocol = load_protocol(args.protocol)
    out = plan_folder(args.out, force=args.force)
    if _places_masker(protocol):
        return _masking_function_plan(args, protocol, out)
    sim = simulation(args, protocol)
    settings, thresholds, truth, truth_name = (
        sim.settings,
        sim.thresholds_db,
        sim.truth,
        sim.truth_name,
    )
    staircase, quest, quest_kw = sim.staircase, sim.quest, sim.quest_kw
    scale, lapse = settings.observer.scale_db, settings.observer.lapse

    progress = step_bar("plan", progress_wanted(args.progress))

    # The staircase plan's chunks (the ML fits first, the longest) and then the QUEST+ tracks'
    # run together on the workers; this process assembles the staircase plan and draws its
    # figure while the QUEST+ chunks still run, so no core idles at the end. Every chunk has
    # its own seed, so the tables do not depend on where or in which order it ran.
    n_stair, n_quest = len(staircase), len(quest)
    progress(f"simulating {n_stair + n_quest} chunks ({args.scheduler})")
    pngs: dict[str, bytes] = {}
    with started_tasks([*staircase, *quest], scheduler=args.scheduler) as pending:
        # matplotlib (~0.6 s to import) is loaded here, while the workers compute, not before
        # they start (nor in them: they are forked without it).
        from masking_lab.planning.figures import png_bytes, speed_accuracy
        from masking_lab.planning.procedure_report import (
            format_comparison,
            format_fewest,
            procedures_figure,
        )

        result = P.assemble_plan(
            protocol, settings, thresholds, pending.wait(0, n_stair), progress=progress
        )
        pngs["plan_speed_accuracy.png"] = png_bytes(
            speed_accuracy(result, title=f"{protocol.experiment}: speed against accuracy")
        )
        comparison = None
        if quest:
            comparison = compare_procedures(
                protocol,
                result,
                settings,
                thresholds,
                progress=progress,
                outcomes=pending.wait(n_stair, n_stair + n_quest),
                **quest_kw,
            )
    cap = P.protocol_staircase(protocol).max_trials
    own_text = protocol_procedure_text(protocol)
    if not runs_staircase(protocol):
        own_text += (
            f"; the staircase rows are the paper's staircase beside it (trial cap {cap}), not "
            "this protocol"
        )
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
        f"{protocol.timing.inter_trial_s:g} s pause = {result.trial_s:g} s; bias = mean(AL − "
        "true threshold)",
        *_rig_resolution(protocol, truth, args.device_config),
        f"this protocol: {own_text}",
    ]
    titles = plan_section_titles(settings.precision_db, comparison is not None)
    bodies = [
        format_table(result),
        format_per_set(result, only_own=not args.per_set),
        "\n".join(
            [
                f"stop rules RUN/RUN−"
                f"{result.protocol_rule.n_reversals - result.protocol_rule.n_averaged}, no trial "
                "cap:",
                *(f"  {answer_text(a, settings, cap)}" for a in result.answers),
            ]
        ),
    ]
    if comparison is not None:
        bodies += [format_comparison(comparison), format_fewest(comparison)]
    text = "\n".join(header)
    for title, body in zip(titles, bodies, strict=True):
        text += f"\n\n{title}\n{'-' * len(title)}\n{body}"
    print(text)

    files = {
        "plan.txt": text + "\n",
        "plan_table.csv": rows_to_csv(result.table),
        "plan_sets.csv": rows_to_csv(result.per_set),
        "plan_ladder.csv": rows_to_csv(result.ladder),
    }
    if comparison is not None:
        files["plan_procedures.csv"] = rows_to_csv(comparison.rows)
        files["plan_procedures_sets.csv"] = rows_to_csv(comparison.per_set)
        pngs["plan_procedures.png"] = png_bytes(
            procedures_figure(
                comparison,
                title=f"{protocol.experiment}: procedures against the Cramér-Rao bound",
            )
        )
    files["report.html"] = render_plan_html(
        result,
        title=f"masking-lab plan: {protocol.experiment}",
        header=header,
        answers=[answer_text(a, settings, cap) for a in result.answers],
        figures=pngs,
        titles=titles,
        comparison=comparison,
    )
    # All files appear at once (the folder swapped in whole) unless --out holds other files.
    protect = [args.protocol, *([args.ground_truth] if args.ground_truth else [])]
    with staged_output(out, protect=protect, markers=("plan.txt",), shared="in_place") as stage:
        for name, content in files.items():
            write_text_atomic(stage / name, content)
        for name, png in pngs.items():
            write_bytes_atomic(stage / name, png)
    print(f"\nwrote {', '.join(str(out / n) for n in [*files, *pngs])}", file=sys.stderr)
    return 0


def plan_folder(out: str | None, *, force: bool) -> Path:
    """Where a plan goes: ``--out`` (a plan already there is refused unless ``force``), or
    ``plan_out``, ``plan_out-2``, ... the first that holds no plan (the demo's rule).

    Raises
    ------
    AnalysisError
        If ``--out`` names a file, or a folder holding a plan without ``force``.

    Examples
    --------
    >>> plan_folder("/nonexistent/p", force=False)
    PosixPath('/nonexistent/p')
    """
    from masking_lab.core.errors import AnalysisError

    if out is None:
        base = Path("plan_out")
        folder, k = base, 1
        while (folder / "plan.txt").exists():
            k += 1
            folder = base.with_name(f"{base.name}-{k}")
        return folder
    folder = Path(out)
    if folder.exists() and not folder.is_dir():
        raise AnalysisError(f"--out {folder}: a file, not a folder; name a folder for the plan")
    if (folder / "plan.txt").exists() and not force:
        raise AnalysisError(
            f"--out {folder} holds a plan already; pass --force to replace it, or leave out "
            "--out to write plan_out-2, -3, ..."
        )
    return folder
