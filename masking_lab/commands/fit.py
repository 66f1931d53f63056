"""``masking-lab fit SHIFTS.csv --out OUT_DIR``: fit masking ramps (and run the statistics) from a
CSV of AL shifts.

Read a long CSV of AL shifts (columns: participant (optional), target, masker,
masker_frequency_hz (optional), masker_level_db_sl, shift_db; '#' lines are comments) and write
the same statistics, pooling, ramp fits, masking_params.json and reports (report.txt,
report.html) as `analyze`, into a fresh folder swapped in as OUT_DIR only when complete. Without
a participant column (a table of means) only the fits are made and the report says which tests
could not be run. Experiments are the directions 'EV270|MV' (EV masked by MV) and 'MV|EV270',
unless an 'experiment' column names them.
"""

from __future__ import annotations

import argparse

from masking_lab.commands.analyze import add_fit_options, fit_settings, print_summary
from masking_lab.commands.options import command_texts


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fit", **command_texts(__doc__))
    p.add_argument("shifts", metavar="SHIFTS.csv", help="long CSV of AL shifts")
    add_fit_options(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from masking_lab.analysis.batch import run_fit

    settings = fit_settings(args, figures="none" if args.figures == "none" else "summary")
    summary = run_fit(args.shifts, args.out, settings)
    print_summary("fit", summary)
    return 0
