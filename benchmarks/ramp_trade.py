"""The trade table of docs/speed-accuracy.md: trials per participant for one masking function at
the paper's precision, by the paper's route, QUEST+ per set and the functional procedure.

    OMP_NUM_THREADS=1 python benchmarks/ramp_trade.py [--replicates 60] [--seed 0] \
        [--scheduler local]

Simulated participants with the ground truth's EV270-by-MV120 ramp (a = -7.442 dB,
b = 0.711 dB/dB), logistic scale 1.5 dB, lapse 0.02; every route from the same calibration
errors (see masking_lab/planning/ramp_trade.py). Prints a Markdown table, each route's precision
over the paper route's with a paired bootstrap 95 % interval (the same participants resampled
for every route), and the Cramér-Rao trials for the paper's precision.
"""

from __future__ import annotations

import argparse
import math
import time

from masking_lab.planning.ramp_trade import (
    TradeSettings,
    cramer_rao_ramp,
    precision_ratios,
    summarize_trade,
    trade_estimates,
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--replicates", type=int, default=60)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--scheduler",
        default="local",
        help="'local' (a local Dask cluster), 'synchronous' or a scheduler address; the table "
        "is the same for any",
    )
    args = parser.parse_args()
    settings = TradeSettings(replicates=args.replicates)
    t0 = time.perf_counter()
    scheduler = None if args.scheduler == "local" else args.scheduler
    estimates = trade_estimates(settings, seed=args.seed, scheduler=scheduler)
    results = summarize_trade(settings, estimates)
    ratios = precision_ratios(settings, estimates, seed=args.seed)
    paper = results[0]
    print(
        f"{args.replicates} simulated participants, seed {args.seed}, "
        f"{time.perf_counter() - t0:.0f} s\n"
    )
    print(
        "| route | trials | minutes | SD intercept (dB) | SD slope (dB/dB) | RMS AL (dB) | "
        "at the paper's precision |"
    )
    print("|---|---:|---:|---:|---:|---:|---|")
    for r in results:
        ok = (
            r.sd_intercept_db <= paper.sd_intercept_db
            and r.sd_slope <= paper.sd_slope
            and r.rms_al_db <= paper.rms_al_db
        )
        print(
            f"| {r.route} | {r.trials_mean:.0f} | {r.minutes:.1f} | {r.sd_intercept_db:.2f} | "
            f"{r.sd_slope:.3f} | {r.rms_al_db:.2f} | {'yes' if ok else 'no'} |"
        )
    print(
        "\nPrecision over the paper route's (RMS error ratio; below 1 is better), paired "
        "bootstrap 95 % interval over participants:\n"
    )
    print("| route | intercept | slope | RMS AL |")
    print("|---|---:|---:|---:|")
    for name, r in ratios.items():
        cells = " | ".join(f"{v:.2f} ({lo:.2f}-{hi:.2f})" for v, lo, hi in r)
        print(f"| {name} | {cells} |")
    # Cramér-Rao: fewest trials for each of the paper's three precisions.
    need = []
    for k, target in enumerate((paper.sd_intercept_db, paper.sd_slope, paper.rms_al_db)):
        n = 1.0
        while cramer_rao_ramp(n, settings.levels_db_sl)[k] > target:
            n *= 1.01
        need.append(math.ceil(n))
    print(
        f"\nCramér-Rao (2-D design, slope and lapse known): {need[0]} trials for the intercept, "
        f"{need[1]} for the slope, {need[2]} for the RMS AL; {max(need)} for all three."
    )


if __name__ == "__main__":
    main()
