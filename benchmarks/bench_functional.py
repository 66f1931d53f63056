"""Next-trial selection of the functional (ramp) procedure, on one core, for the shipped grid.

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python benchmarks/bench_functional.py [--tracks 3]

Runs ``protocols/experiment1_functional.yaml``'s settings (5 masker × 46 target levels; 31
intercepts × 29 slopes; 3 unmasked-AL offsets × 3 scales × 3 lapses: 5.6 M table cells) against
simulated observers with the paper's EV270/MV120 ramp and times every ``update`` (one
multiply-normalise plus the placement over all 230 stimuli). Prints the median, 95th percentile
and maximum selection time in ms, the budget (50 ms), and, as a baseline in the same run, the
time of one known-slope QUEST+ update (131 × 131 grid; ratio functional / QUEST+).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from masking_lab.core.masking import ramp
from masking_lab.core.psychometric import Psychometric
from masking_lab.formats.protocol import load_protocol
from masking_lab.formats.resources import shipped
from masking_lab.procedures.functional import ramp_tables
from masking_lab.procedures.quest_plus import QuestPlusSettings

BUDGET_MS = 50.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tracks", type=int, default=3)
    args = parser.parse_args()
    if os.environ.get("OMP_NUM_THREADS") != "1":
        print("note: set OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 to measure one core")
    protocol = load_protocol(shipped("protocols", "experiment1_functional.yaml"))
    settings = protocol.sets[0].settings
    t0 = time.perf_counter()
    tables = ramp_tables(settings)
    build_s = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    psy = Psychometric(0.0, 1.5, lapse=0.02)
    times = []
    for _ in range(args.tracks):
        track = settings.start()
        while not track.finished:
            theta = float(ramp(track.next_masker_level_db_sl(), -7.442, 0.711))
            answer = bool(rng.random() < psy.p_correct(track.next_level() - theta))
            t0 = time.perf_counter()
            track = track.update(answer)
            times.append(time.perf_counter() - t0)
    ms = np.array(times) * 1e3
    # The baseline stays the known-slope QUEST+ grid (131 × 131 × 1), so ratios compare over
    # time; the defaults now marginalise slope and lapse (bench_next_trial.py times those).
    quest = QuestPlusSettings(
        -20.0, 45.0, scales_db=1.5, lapses=0.02, target_sd_db=0.01, max_trials=60
    ).start()
    q_times = []
    while not quest.finished:
        t0 = time.perf_counter()
        quest = quest.update(bool(rng.random() < 0.7))
        q_times.append(time.perf_counter() - t0)
    q_ms = float(np.median(q_times) * 1e3)
    cells = tables.p_correct.size
    print(
        f"table: {cells / 1e6:.2f} M cells, {tables.p_correct.nbytes / 2**20:.1f} MiB, "
        f"built in {build_s:.2f} s"
    )
    print(
        f"selection over {ms.size} trials: median {np.median(ms):.1f} ms, "
        f"p95 {np.percentile(ms, 95):.1f} ms, max {ms.max():.1f} ms (budget {BUDGET_MS:.0f} ms)"
    )
    print(f"QUEST+ update (baseline): median {q_ms:.2f} ms; ratio {np.median(ms) / q_ms:.1f}x")


if __name__ == "__main__":
    main()
