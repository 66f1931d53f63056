"""QUEST+ tracks per second: the vectorised simulator against a loop over scalar tracks.

    python benchmarks/bench_quest_plus.py [--tracks 200]

Both run the shipped experiment-I QUEST+ settings (flat prior −20…45 dB SL, 0.5 dB grids, slope
known, stop at posterior SD ≤ 1.08 dB after ≥ 10 trials, cap 80) against the same simulated
observers (logistic scale 1.5 dB, lapse 0.02, thresholds 0–13 dB SL). The baseline drives
:class:`masking_lab.procedures.quest_plus.QuestPlus` one trial at a time, as the session runner
does; the vectorised run is :func:`masking_lab.procedures.quest_plus_batch.simulate_quest_plus`,
which ``plan`` uses. Prints tracks per second for each and their ratio (one run, one machine).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from masking_lab.core.psychometric import Psychometric
from masking_lab.procedures.quest_plus import QuestPlusSettings
from masking_lab.procedures.quest_plus_batch import simulate_quest_plus

SETTINGS = QuestPlusSettings(-20.0, 45.0, target_sd_db=1.08, min_trials=10, max_trials=80)


def scalar_loop(thresholds: np.ndarray, seed: int) -> list[int]:
    """One QuestPlus per track, one Python update per trial (the runner's path)."""
    rng = np.random.default_rng(seed)
    psy = Psychometric(0.0, 1.5, lapse=0.02)
    out = []
    for thr in thresholds:
        track = SETTINGS.start()
        while not track.finished:
            p = psy.p_correct(track.next_level() - thr)
            track = track.update(bool(rng.random() < p))
        out.append(track.n_trials)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tracks", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    thr = np.random.default_rng(args.seed).uniform(0.0, 13.0, args.tracks)
    SETTINGS.start()  # the likelihood table is cached per settings; build it outside the timing
    t0 = time.perf_counter()
    scalar_loop(thr, args.seed)
    t_loop = time.perf_counter() - t0
    t0 = time.perf_counter()
    simulate_quest_plus(SETTINGS, thr, rng=np.random.default_rng(args.seed))
    t_batch = time.perf_counter() - t0
    print(f"scalar loop: {args.tracks / t_loop:10.1f} tracks/s")
    print(f"vectorised:  {args.tracks / t_batch:10.1f} tracks/s")
    print(f"ratio:       {t_loop / t_batch:10.1f}x")


if __name__ == "__main__":
    main()
