"""``masking-lab analyze DATA_DIR --out OUT_DIR``: analyse every session log in a folder: ALs,
shifts, statistics, ramp fits, export.

Read every session log (*.jsonl) under DATA_DIR, re-estimate each set's AL, compute AL shifts,
run the repeated-measures statistics per experiment, pool frequency levels, fit the masking
ramps and write thresholds.csv, anova.csv, sphericity.csv, posthoc.csv, one_sample.csv,
ramp_fits.csv, problems.csv, masking_params.json, report.txt, report.html and figures/ into
OUT_DIR, with trials.csv (one row per trial; trials.parquet with pyarrow), psychometric.csv (a
psychometric function per participant and set), participants.tsv/.json and study_status.csv.
Truncated or invalid logs are reported and skipped. Same inputs and settings give the same
bytes. OUT_DIR is written as a fresh folder swapped in only when the run completes: a
failed run leaves the previous results untouched.
"""

from __future__ import annotations

import argparse
import os
import sys
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

from masking_lab.commands.options import command_texts, output_folder

if TYPE_CHECKING:  # the analysis imports pandas; keep `masking-lab --help` fast
    from masking_lab.analysis.batch import RunSummary
    from masking_lab.analysis.settings import AnalysisSettings


def add_fit_options(p: argparse.ArgumentParser) -> None:
    """Options shared by ``analyze`` and ``fit``: pooling, uncertainty, export, figures."""
    g = p.add_argument_group("pooling and fits")
    g.add_argument(
        "--pooling",
        choices=("paired", "none", "all"),
        default="paired",
        help="rule for pooling frequency levels into one ramp: 'paired' pools levels whose "
        "Bonferroni paired comparison is not significant (paper; default), 'none', 'all'",
    )
    g.add_argument(
        "--pool-alpha",
        type=float,
        default=0.05,
        metavar="A",
        help="significance level of the 'paired' rule (default 0.05)",
    )
    g.add_argument(
        "--pool",
        action="append",
        default=[],
        metavar="[EXP:]L+L",
        help="pool these frequency levels explicitly, e.g. 'experiment1:MV120+MV180' or "
        "'120+180' (every experiment); repeatable; overrides --pooling where given",
    )
    g.add_argument(
        "--uncertainty",
        choices=("bootstrap", "asymptotic"),
        default="bootstrap",
        help="ramp uncertainty: bootstrap over participants (default) or asymptotic "
        "least-squares standard errors",
    )
    g.add_argument("--n-boot", type=int, default=2000, metavar="N", help="bootstrap replicates")
    g.add_argument("--ci-level", type=float, default=0.95, metavar="L", help="confidence level")
    g.add_argument("--seed", type=int, default=0, help="bootstrap seed (default 0)")
    g.add_argument(
        "--test-alpha",
        type=float,
        default=0.05,
        metavar="A",
        help="level at which a cell's one-sample t-test counts as masking (default 0.05)",
    )
    o = p.add_argument_group("output")
    o.add_argument(
        "--out", required=True, type=output_folder, metavar="OUT_DIR", help="folder for the outputs"
    )
    o.add_argument(
        "--created-utc",
        metavar="TIME",
        help="created_utc written into masking_params.json, e.g. 2024-05-01T12:00:00Z or 'now' "
        "(default: SOURCE_DATE_EPOCH if set, else derived from the data so runs are repeatable)",
    )
    o.add_argument(
        "--figures",
        choices=("all", "summary", "none"),
        default="summary",
        help="figures to draw: 'summary' the masking-function figures (default), 'all' adds a "
        "staircase-track figure per session (analyze only; drawn in parallel, slow for big "
        "studies), 'none' no figures",
    )
    o.add_argument("--quiet", action="store_true", help="no progress display")
    o.add_argument(
        "--progress",
        action="store_true",
        help="progress bars even when stderr is not a terminal (analyze only)",
    )


def fit_settings(args: argparse.Namespace, **analyze_only: Any) -> AnalysisSettings:
    """The :class:`AnalysisSettings` of :func:`add_fit_options`, plus ``analyze``'s own."""
    from masking_lab.analysis.settings import AnalysisSettings

    return AnalysisSettings(
        pooling=args.pooling,
        pool_alpha=args.pool_alpha,
        pool_groups=tuple(args.pool),
        uncertainty=args.uncertainty,
        n_boot=args.n_boot,
        ci_level=args.ci_level,
        seed=args.seed,
        test_alpha=args.test_alpha,
        created_utc=created_utc_from(args),
        **analyze_only,
    )


def created_utc_from(args: argparse.Namespace) -> str | None:
    """``--created-utc`` (``now`` → current time), else SOURCE_DATE_EPOCH, else None."""
    value = getattr(args, "created_utc", None)
    if value == "now":
        return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    if value:
        return value
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    if epoch and epoch.strip().isdigit():
        return datetime.fromtimestamp(int(epoch), UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    return None


def print_summary(command: str, summary: RunSummary) -> None:
    """Files written on stdout; warnings on stderr."""
    out_dir, files, warnings = summary.out_dir, summary.files, summary.warnings
    print(
        f"wrote {len(files)} files to {out_dir} (see {out_dir / 'report.html'} or "
        f"{out_dir / 'report.txt'})"
    )
    if warnings:
        print(f"masking-lab {command}: {len(warnings)} warning(s):", file=sys.stderr)
        for w in warnings[:20]:
            print(f"  {w}", file=sys.stderr)
        if len(warnings) > 20:
            print(f"  ... and {len(warnings) - 20} more in the report", file=sys.stderr)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("analyze", **command_texts(__doc__))
    p.add_argument(
        "data_dir", metavar="DATA_DIR", help="folder of session logs (searched recursively)"
    )
    e = p.add_argument_group("threshold estimation")
    e.add_argument(
        "--estimator",
        choices=("reversals", "ml"),
        default="reversals",
        help="AL estimator: mean of the last reversals (paper; default) or a maximum-likelihood "
        "psychometric fit (guess 1/3) to all trials",
    )
    e.add_argument(
        "--reversals",
        type=int,
        metavar="K",
        help="average the last K reversals (default: as logged, 8 in the paper)",
    )
    e.add_argument(
        "--lapse",
        default="0.02",
        metavar="RATE",
        help="lapse rate of the ML estimator, or 'fit' to estimate it (default 0.02)",
    )
    e.add_argument(
        "--unmasked-al",
        choices=("auto", "baseline", "calibration"),
        default="auto",
        help="unmasked ALs from the participant's baseline log (falling back to the session "
        "header's calibration: auto, default), from the baseline log only, or from the header",
    )
    t = p.add_argument_group("trial-level outputs")
    t.add_argument(
        "--pf-boot",
        type=int,
        default=200,
        metavar="N",
        help="parametric-bootstrap data sets per psychometric function in psychometric.csv "
        "(intervals and deviance p; 0: point estimates only; default 200)",
    )
    t.add_argument(
        "--no-trial-tables",
        action="store_true",
        help="skip trials.csv and psychometric.csv (a second read of every log and a fit per "
        "set: minutes for thousands of sessions)",
    )
    add_fit_options(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    import numpy  # noqa: F401 - loaded once, before the fork: the figure worker uses it too

    from masking_lab.analysis.figure_pool import FigurePool

    # Started before the analysis is imported: the worker loads matplotlib meanwhile.
    figure_pool = FigurePool(args.figures != "none")
    try:
        summary = _run(args, figure_pool)
    except BaseException:  # options or data refused: no waiting for figures
        figure_pool.close(cancel=True)
        raise
    figure_pool.close()
    print_summary("analyze", summary)
    return 0


def _run(args: argparse.Namespace, figure_pool: Any) -> RunSummary:
    from masking_lab.analysis.batch import run_analyze
    from masking_lab.analysis.settings import parse_lapse

    settings = fit_settings(
        args,
        estimator=args.estimator,
        n_reversals_averaged=args.reversals,
        lapse=parse_lapse(args.lapse),
        unmasked_al=args.unmasked_al,
        figures=args.figures,
        pf_boot=args.pf_boot,
        trial_tables=not args.no_trial_tables,
    )
    from masking_lab.commands.progress_bars import count_bar, progress_wanted

    show = not args.quiet and progress_wanted(True if args.progress else None)
    return run_analyze(
        args.data_dir,
        args.out,
        settings,
        progress=count_bar("logs read", show) if show else None,
        fit_progress=count_bar("psychometric fits", show) if show else None,
        figure_pool=figure_pool,
    )
