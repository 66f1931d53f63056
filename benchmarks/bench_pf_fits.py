"""Psychometric fits per second: the compiled climb against numpy's route, same process, same sets.

    python benchmarks/bench_pf_fits.py [--participants 10] [--boot 200] [--repeats 5]

Simulates a study (``masking_lab.simulation.synthetic_logs``: baseline, experiment I and II per
participant, the demo's 340 staircase sets at 10 participants), makes ``analyze``'s
psychometric jobs of its completed sets (the same seeds and bootstrap size) and times
:func:`masking_lab.analysis.psychometric.fit_pf_many` on numpy's route and compiled
(``analysis/pf_loops.py``), interleaved, process time with one BLAS thread. Prints the medians,
their ratio, what loading numba cost once, and whether the two routes' fits are identical
(``pickle.dumps`` of every field). ``analyze`` takes the compiled route from
``pf_table.PF_COMPILED_FROM`` bootstrap data sets on.
"""

from __future__ import annotations

import argparse
import pickle
import statistics
import sys
import tempfile
import time
from pathlib import Path

from threadpoolctl import threadpool_limits

from masking_lab.analysis.pf_likelihood import warm_compiled
from masking_lab.analysis.pf_table import pf_job, pf_seed, set_trials
from masking_lab.analysis.psychometric import PFJob, fit_pf_many
from masking_lab.formats.session_log import read_log
from masking_lab.simulation.synthetic_logs import simulate_study


def study_jobs(participants: int, n_boot: int, seed: int) -> list[PFJob]:
    """The psychometric jobs of a simulated study's sets, seeded as ``analyze`` seeds them."""
    with tempfile.TemporaryDirectory(prefix="bench_pf_") as tmp:
        simulate_study(Path(tmp), n_participants=participants, seed=seed)
        jobs = []
        for path in sorted(Path(tmp).rglob("*.jsonl")):
            log = read_log(path)
            rel = str(path.relative_to(tmp))
            who = log.header.get("participant")
            experiment = log.header.get("protocol", {}).get("experiment")
            for set_id, st in set_trials(log).items():
                jobs.append(pf_job(st, pf_seed(who, experiment, set_id, rel), n_boot))
    return jobs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--participants", type=int, default=10, help="simulated participants [10]")
    ap.add_argument("--boot", type=int, default=200, help="bootstrap data sets per set [200]")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs of each route [5]")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    jobs = study_jobs(args.participants, args.boot, args.seed)
    print(f"{len(jobs)} sets x {args.boot} bootstrap data sets, simulated and read in "
          f"{time.perf_counter() - t0:.1f} s", flush=True)  # fmt: skip
    t0 = time.process_time()
    if not warm_compiled():
        print("numba is unavailable here: only numpy's route runs", file=sys.stderr)
        return 1
    load_s = time.process_time() - t0
    with threadpool_limits(1):
        fits = {route: fit_pf_many(jobs, compiled=route) for route in (False, True)}  # warm
        times: dict[bool, list[float]] = {False: [], True: []}
        for _ in range(args.repeats):
            for route in (False, True):
                t0 = time.process_time()
                fit_pf_many(jobs, compiled=route)
                times[route].append(time.process_time() - t0)
    numpy_s, compiled_s = (statistics.median(times[r]) for r in (False, True))
    same = pickle.dumps(fits[False]) == pickle.dumps(fits[True])
    per = 1e3 / len(jobs)
    print(f"numpy route   {numpy_s:7.3f} s  ({numpy_s * per:.2f} ms a set)")
    print(f"compiled      {compiled_s:7.3f} s  ({compiled_s * per:.2f} ms a set)  "
          f"ratio {compiled_s / numpy_s:.2f}x")  # fmt: skip
    print(f"loading numba and the loops once: {load_s:.2f} s of CPU")
    print(f"fits identical on both routes: {'yes' if same else 'NO'}")
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
