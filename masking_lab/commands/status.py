"""``masking-lab status DATA_DIR``: the study at a glance: who has done what, unmasked ALs,
outlier flags.

Read every session log under DATA_DIR (nothing is written) and print the participant ×
protocol matrix (complete; partial with the sets and trials done so far; refused when the
device refused a set; missing), each participant's unmasked ALs (completed baseline sets, dB
re 1 V) and the values flagged as outliers, with the rule. Works on a study still running.
`masking-lab analyze` puts the same tables, with individual shift plots, into its reports.
"""

from __future__ import annotations

import argparse

from masking_lab.commands.options import command_texts


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("status", **command_texts(__doc__))
    p.add_argument("data", metavar="DATA_DIR", help="folder of session logs (searched recursively)")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from masking_lab.analysis.lab_outputs import study_at_a_glance
    from masking_lab.analysis.report_lab import lab_text_sections

    section, problems = study_at_a_glance(args.data)
    for title, lines in lab_text_sections(section):
        if title in ("Psychometric functions", "Figures"):
            continue  # analyze's: they need the fits
        print(f"{title}\n{'-' * len(title)}")
        print("\n".join(lines) + "\n")
    if problems:
        print("Logs not read\n-------------")
        print("\n".join(f"  {p}" for p in problems))
    return 0
