"""``masking-lab fit SHIFTS.csv --out OUT_DIR``: statistics, pooling, ramp fits and export from a
long table of AL shifts, for labs that bring their own tables."""

from __future__ import annotations

import argparse

from masking_lab.commands.analyze import add_fit_options, created_utc_from, print_summary


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "fit",
        help="fit masking ramps (and run the statistics) from a CSV of AL shifts",
        description="Read a long CSV of AL shifts (columns: participant (optional), target, "
        "masker, masker_frequency_hz (optional), masker_level_db_sl, shift_db; '#' lines are "
        "comments) and write the same statistics, pooling, ramp fits, masking_params.json and "
        "report as `analyze`. Without a participant column (a table of means) only the fits are "
        "made and the report says which tests could not be run. Experiments are the directions "
        "'EV270|MV' (EV masked by MV) and 'MV|EV270', unless an 'experiment' column names them.",
    )
    p.add_argument("shifts", metavar="SHIFTS.csv", help="long CSV of AL shifts")
    add_fit_options(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from masking_lab.analysis.batch import run_fit
    from masking_lab.analysis.settings import AnalysisSettings

    settings = AnalysisSettings(
        pooling=args.pooling,
        pool_alpha=args.pool_alpha,
        pool_groups=tuple(args.pool),
        uncertainty=args.uncertainty,
        n_boot=args.n_boot,
        ci_level=args.ci_level,
        seed=args.seed,
        test_alpha=args.test_alpha,
        created_utc=created_utc_from(args),
        figures="none" if args.figures == "none" else "summary",
    )
    summary = run_fit(args.shifts, args.out, settings)
    print_summary("fit", summary)
    return 0
