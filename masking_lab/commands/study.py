"""``masking-lab study --out OUT``: run the speed–accuracy study (docs/speed-accuracy.md).

Simulate the speed–accuracy study and write its tables, figures and the study document's
generated blocks (blocks/NAME.md) into OUT. Same arguments, same bytes, wherever --scheduler
runs the simulations' chunks.

Convergence of 1-up-3-down tracks by step size in 3IFC and 2AFC, the stop-rule / schedule /
estimator grid on experiment I, and the procedures (staircase settings, QUEST+) against the
Cramér-Rao bound (:mod:`masking_lab.planning.study`). The command writes only into OUT;
``python docs/generate.py study`` regenerates the repository's docs from it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from masking_lab.commands.options import add_scheduler_option, command_texts, output_folder
from masking_lab.commands.plan import _count, _positive_int
from masking_lab.commands.progress_bars import add_progress_options, progress_wanted, step_bar


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("study", **command_texts(__doc__))
    p.add_argument(
        "--out",
        type=output_folder,
        default="study_out",
        help="folder for the CSV, PNG and blocks/*.md files (default: study_out)",
    )
    p.add_argument(
        "--replicates",
        type=_positive_int,
        default=2000,
        help="simulated sessions per set in the stop-rule grid (default 2000)",
    )
    p.add_argument(
        "--ml-replicates",
        type=_count,
        default=500,
        help="sessions per set fitted by maximum likelihood; 0 skips the ML estimator "
        "(default 500)",
    )
    p.add_argument(
        "--convergence-replicates",
        type=_positive_int,
        default=2000,
        help="tracks per step size in the convergence study (default 2000)",
    )
    p.add_argument(
        "--max-reversals",
        type=_positive_int,
        default=41,
        help="longest stop rule of the reversal ladder (default 41)",
    )
    p.add_argument(
        "--quest-replicates",
        type=_count,
        default=400,
        help="QUEST+ tracks per set in the procedures study (default 400; 0 skips it)",
    )
    p.add_argument("--psi", action="store_true", help="add the psi-marginal (slow)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    add_scheduler_option(p)
    add_progress_options(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from masking_lab.planning.study import regenerate

    say = step_bar("study", progress_wanted(args.progress))
    regenerate(
        Path(args.out),
        replicates=args.replicates,
        ml_replicates=args.ml_replicates,
        convergence_replicates=args.convergence_replicates,
        max_reversals=args.max_reversals,
        quest_replicates=args.quest_replicates,
        psi=args.psi,
        seed=args.seed,
        progress=say,
        scheduler=args.scheduler,
    )
    return 0
