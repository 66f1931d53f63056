"""Figure benchmark: what the per-session staircase-track figures cost, and what reuse buys.

Run:  python benchmarks/bench_figures.py [--participants N] [--workers W]

Simulates a study (baseline, experiments I and II per participant) and draws every session's
track figure three ways, printing seconds per figure and ratios against the first:

- baseline: a new figure per session (what ``analyze --figures all`` did before; building 15
  axes is most of a figure's cost);
- reused: one figure per grid shape, only the data artists replaced (one process);
- reused, in W worker processes (:func:`masking_lab.analysis.track_figures.draw_tracks`).

Timings depend on the machine and its load; compare the ratios within one run.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from masking_lab.analysis import track_figures
from masking_lab.analysis.track_figures import draw_tracks, track_job
from masking_lab.formats.session_log import read_log
from masking_lab.simulation.synthetic_logs import simulate_study


def _fresh(jobs: list) -> float:
    """Seconds per figure when every figure is built anew (the canvas cache emptied)."""
    t0 = time.perf_counter()
    for job in jobs:
        for fig, _ in track_figures._CANVAS.values():
            fig.clf()
        track_figures._CANVAS.clear()
        track_figures._track_png(job)
    return (time.perf_counter() - t0) / len(jobs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--participants", type=int, default=4)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        logs = simulate_study(root / "data", n_participants=args.participants, seed=1)
        parsed = [read_log(p) for p in logs]
        jobs = [track_job(root / "out" / f"{k}.png", log, {}) for k, log in enumerate(parsed)]
        track_figures._track_png(jobs[0])  # import and font caches warm
        fresh = _fresh(jobs)
        t0 = time.perf_counter()
        draw_tracks(jobs, workers=1)
        reused = (time.perf_counter() - t0) / len(jobs)
        t0 = time.perf_counter()
        draw_tracks(jobs, workers=args.workers)
        parallel = (time.perf_counter() - t0) / len(jobs)
    print(f"{len(jobs)} track figures ({args.participants} participants x 3 sessions)")
    print(f"  new figure per session (baseline): {fresh:6.3f} s/figure  1.00x")
    print(f"  one reused figure, 1 process:      {reused:6.3f} s/figure  {fresh / reused:.2f}x")
    print(
        f"  reused, {args.workers} worker processes:      {parallel:6.3f} s/figure  "
        f"{fresh / parallel:.2f}x"
    )


if __name__ == "__main__":
    main()
