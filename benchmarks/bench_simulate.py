"""Simulated sessions per second: the vectorized simulator against a per-session loop.

    python benchmarks/bench_simulate.py [--sessions 2000]

Both run the paper's staircase (experiment I settings: 1-up 3-down, steps 4,4,4,2 dB, 11
reversals, last 8 averaged, bounds −20…45 dB SL, 150-trial cap) against the same simulated
observers (logistic scale 1.5 dB, lapse 0.02, true thresholds 0–13 dB SL). The baseline is what
one would write without :mod:`masking_lab.procedures.staircase_batch`: a Python loop over sessions,
each driving
:class:`masking_lab.procedures.staircase.Staircase` trial by trial. Prints sessions per second for
each
and their ratio (one run, same machine, so the ratio is what to compare across machines).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from masking_lab.core.psychometric import Psychometric
from masking_lab.procedures.staircase import StaircaseSettings, start
from masking_lab.procedures.staircase_batch import Observer, simulate

SETTINGS = StaircaseSettings(
    start_level_db=20.0,
    step_sizes_db=(4.0, 4.0, 4.0, 2.0),
    n_reversals=11,
    n_reversals_averaged=8,
    min_level_db=-20.0,
    max_level_db=45.0,
    max_trials=150,
)


def per_session_loop(thresholds: np.ndarray, seed: int) -> list[float | None]:
    """One Staircase per session, one Python call per trial (the baseline)."""
    rng = np.random.default_rng(seed)
    psy = Psychometric(0.0, 1.5, lapse=0.02)
    als = []
    for thr in thresholds:
        track = start(SETTINGS)
        while not track.finished:
            p = float(psy.p_correct(track.level_db - thr))
            track = track.update(rng.random() < p)
        als.append(track.al_db)
    return als


def vectorized(thresholds: np.ndarray, seed: int) -> np.ndarray:
    """All sessions at once."""
    run = simulate(SETTINGS, thresholds, Observer(1.5, 0.02), np.random.default_rng(seed))
    return run.al_db


def best_of(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=3, help="best of N for the vectorized run")
    args = parser.parse_args()
    thresholds = np.random.default_rng(0).uniform(0.0, 13.0, args.sessions)

    loop_s = best_of(lambda: per_session_loop(thresholds, 1), 1)
    vec_s = best_of(lambda: vectorized(thresholds, 1), args.repeats)
    loop_rate = args.sessions / loop_s
    vec_rate = args.sessions / vec_s
    print(f"sessions: {args.sessions} (experiment I staircase, 11/8, steps 4,4,4,2 dB)")
    print(f"per-session loop over masking_lab.procedures.staircase: {loop_rate:10.0f} sessions/s")
    print(
        f"vectorized masking_lab.procedures.staircase_batch:            {vec_rate:10.0f} sessions/s"
    )
    print(f"ratio vectorized / loop:                    {vec_rate / loop_rate:10.1f}×")


if __name__ == "__main__":
    main()
