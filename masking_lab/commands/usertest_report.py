"""``masking-lab usertest-report DATA_DIR --out OUT``: analyse user-test logs: correct rates,
paired tests, confusion, Figure 8a.

Read every user-test session log under DATA_DIR (threshold logs are skipped and listed) and
write, into OUT: correct rates per participant and condition (rates.csv: both, geometry only,
texture only), their mean and SD per condition (summary.csv), a paired t-test per measure
between compensated and uncompensated (tests.csv), geometry and texture confusion matrices per
condition (confusion_*.csv), the sessions used (sessions.csv), the report as text (report.txt)
and as one self-contained page (report.html), and a bar chart like the paper's Figure 8a
(figure8a.png). The same logs give the same bytes. OUT is written as a fresh folder swapped in
only when complete: a failed run leaves the previous report untouched. Exit 0, or 2 when there
is nothing to analyse.
"""

from __future__ import annotations

import argparse

from masking_lab.commands.options import command_texts, output_folder


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("usertest-report", **command_texts(__doc__))
    p.add_argument("data", metavar="DATA_DIR", help="folder holding the session logs")
    p.add_argument(
        "--out", required=True, type=output_folder, metavar="OUT", help="output folder (created)"
    )
    p.add_argument("--no-figure", action="store_true", help="skip figure8a.png")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from masking_lab.usertest.design import MEASURES
    from masking_lab.usertest.report import write_usertest_report

    report = write_usertest_report(args.data, args.out, figure=not args.no_figure)
    data, analysis = report.data, report.analysis
    print(
        f"user test: {len(data.sessions)} session(s), {len(data.records)} trials, "
        f"{len(data.skipped)} other file(s) skipped"
    )
    for row in analysis.summary.to_dict(orient="records"):
        if row["measure"] in MEASURES:
            sd = row["sd"]
            spread = f" ± {sd:.3f}" if sd == sd else ""  # NaN with one participant
            print(f"  {row['condition']:<13} {row['measure']:<8} {row['mean']:.3f}{spread}")
    for t in analysis.tests:
        if t.p is None:
            print(f"  {t.measure}: no paired test ({t.note})")
        else:
            p = "p < 0.001" if t.p < 0.001 else f"p = {t.p:.3f}"
            print(f"  {t.measure}: t({t.n - 1}) = {t.t:.2f}, {p}")
    for note in data.notes:
        print(f"  note: {note}")
    for path in report.written:
        print(f"  wrote {path}")
    return 0
