"""``masking-lab study``: regenerate the speed–accuracy study (docs/speed-accuracy.md and
docs/study/).

Simulate the speed–accuracy study and rewrite its tables, figures and the generated blocks of
the study document. Same arguments, same bytes.

Convergence of 1-up-3-down tracks by step size in 3IFC and 2AFC, the stop-rule / schedule /
estimator grid on experiment I, and the procedures (staircase settings, QUEST+) against the
Cramér-Rao bound; tables and figures go to ``--out``, the generated blocks of ``--doc`` are
rewritten (:mod:`masking_lab.planning.study`).
"""

from __future__ import annotations

import argparse
import sys

from masking_lab.commands.options import command_texts
from masking_lab.commands.plan import _count, _positive_int


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("study", **command_texts(__doc__))
    p.add_argument("--out", default="docs/study", help="folder for CSV and PNG files")
    p.add_argument(
        "--doc", default="docs/speed-accuracy.md", help="document to update ('' to skip)"
    )
    p.add_argument("--replicates", type=_positive_int, default=2000)
    p.add_argument("--ml-replicates", type=_count, default=500)
    p.add_argument("--convergence-replicates", type=_positive_int, default=2000)
    p.add_argument("--max-reversals", type=_positive_int, default=41)
    p.add_argument(
        "--quest-replicates",
        type=_count,
        default=400,
        help="QUEST+ tracks per set in the procedures study (0 skips it)",
    )
    p.add_argument("--psi", action="store_true", help="add the psi-marginal (slow)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from masking_lab.planning.study import regenerate

    def say(msg: str) -> None:
        print(f"study: {msg}", file=sys.stderr, flush=True)

    regenerate(
        Path(args.out),
        Path(args.doc) if args.doc else None,
        replicates=args.replicates,
        ml_replicates=args.ml_replicates,
        convergence_replicates=args.convergence_replicates,
        max_reversals=args.max_reversals,
        quest_replicates=args.quest_replicates,
        psi=args.psi,
        seed=args.seed,
        progress=say,
    )
    return 0
