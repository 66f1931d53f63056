"""How the cost of `masking-lab analyze` grows with the number of logged sessions.

Simulates a ten-participant study once (baseline, experiment I, experiment II: 30 real session
logs written by ``masking_lab.simulation.synthetic_logs``), then builds folders of 100, 1,000 and
10,000
sessions by copying those logs under new participant ids (only the header line changes, so every
file is a complete, realistic session of 4 or 15 staircases). Each folder is analysed once,
in-process, with the default settings except figures (per-session track figures would dominate
and are measured separately with ``--figures all``).

Prints wall time, time per session, and each size's ratios to the smallest size in the same run:
the time ratio and the per-session ratio (1.0 = linear growth). No assertion on time anywhere.

Usage::

    python benchmarks/bench_analysis.py                       # 100, 1000, 10000 sessions
    python benchmarks/bench_analysis.py --sizes 100,1000 --estimator ml
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import tempfile
import time
from pathlib import Path

from masking_lab.analysis.batch import run_analyze
from masking_lab.analysis.settings import AnalysisSettings
from masking_lab.simulation.synthetic_logs import simulate_study


def build_folder(pool: Path, dest: Path, n_sessions: int) -> int:
    """Copy pool logs under new participant ids until ``n_sessions`` files exist; bytes written."""
    sources = sorted(pool.rglob("*.jsonl"))
    by_participant: dict[str, list[Path]] = {}
    for p in sources:
        by_participant.setdefault(p.parent.name, []).append(p)
    groups = [sorted(v) for _, v in sorted(by_participant.items())]
    written = 0
    k = 0
    while k < n_sessions:
        pid = f"B{k // 3:05d}"
        for src in groups[(k // 3) % len(groups)]:
            if k >= n_sessions:
                break
            head, rest = src.read_bytes().split(b"\n", 1)
            header = json.loads(head)
            header["participant"] = pid
            header["session_id"] = f"{pid}-{header['protocol']['experiment']}"
            data = json.dumps(header, separators=(",", ":")).encode() + b"\n" + rest
            out = dest / pid / f"{pid}_{header['protocol']['experiment']}.jsonl"
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_bytes(data)
            written += len(data)
            k += 1
    return written


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sizes", default="100,1000,10000", help="session counts, comma-separated")
    ap.add_argument("--estimator", choices=("reversals", "ml"), default="reversals")
    ap.add_argument("--figures", choices=("none", "summary", "all"), default="summary")
    ap.add_argument("--n-boot", type=int, default=2000)
    ap.add_argument("--workdir", help="folder for the generated logs (default: a temp folder)")
    args = ap.parse_args(argv)
    sizes = sorted(int(s) for s in args.sizes.split(","))

    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench_analysis_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        t0 = time.perf_counter()
        pool = work / "pool"
        simulate_study(pool, n_participants=10, seed=0)
        print(f"simulated the pool of 30 sessions in {time.perf_counter() - t0:.1f} s", flush=True)
        settings = AnalysisSettings(
            estimator=args.estimator, figures=args.figures, n_boot=args.n_boot
        )
        # Warm-up on the pool: one-time costs (imports, matplotlib's font cache) are not
        # per-session costs and would inflate the smallest size.
        run_analyze(pool, work / "out_warmup", settings)
        results = []
        for n in sizes:
            data = work / f"data_{n}"
            size = build_folder(pool, data, n)
            t = time.perf_counter()
            run_analyze(data, work / f"out_{n}", settings)
            elapsed = time.perf_counter() - t
            results.append((n, elapsed, size))
            print(f"  {n:>6} sessions ({size / 1e6:7.1f} MB): {elapsed:8.2f} s", flush=True)
            shutil.rmtree(data)
        base_n, base_t, _ = results[0]
        print()
        print(f"estimator={args.estimator} figures={args.figures} n_boot={args.n_boot}")
        print(
            f"{'sessions':>9} {'time s':>9} {'ms/session':>11} {'time ratio':>11} "
            f"{'per-session ratio':>18} {'growth exponent':>16}"
        )
        for n, t, _ in results:
            exponent = math.log(t / base_t) / math.log(n / base_n) if n != base_n else float("nan")
            print(
                f"{n:>9} {t:>9.2f} {1000 * t / n:>11.2f} {t / base_t:>11.2f} "
                f"{(t / n) / (base_t / base_n):>18.2f} {exponent:>16.2f}"
            )
        print("(ratios against the smallest size in this run; exponent 1.0 = linear)")
    finally:
        if not args.workdir:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
