"""Coverage of the Bayesian procedures' 95 % intervals when the observer is not the model
(the table in docs/procedures.md).

    OMP_NUM_THREADS=1 python benchmarks/coverage.py [--tracks 60] [--seed 0]

Observers with the psychometric scale the protocols assume (1.5 dB), half and twice it, and a
lapse of 0.02 or 0.08. For each procedure setting, the share of tracks whose central 95 %
credible interval (recomputed from the track's trials, as `analyze` does) holds the truth:
single thresholds for QUEST+ (slope known, the shipped protocol; and psi-marginal with slope
and lapse marginalised), intercept and slope for the functional procedure (shipped grids).
"""

from __future__ import annotations

import argparse

import numpy as np

from masking_lab.analysis.functional import ramp_posterior
from masking_lab.core.masking import ramp
from masking_lab.core.psychometric import Psychometric
from masking_lab.procedures.functional import FunctionalRampSettings
from masking_lab.procedures.quest_plus import QuestPlusSettings
from masking_lab.procedures.quest_plus_batch import simulate_quest_plus
from masking_lab.procedures.quest_plus_kind import posterior_summary
from masking_lab.procedures.registry import settings_record

OBSERVERS = [(1.5, 0.02), (0.75, 0.02), (3.0, 0.02), (1.5, 0.08), (0.75, 0.08), (3.0, 0.08)]
QUEST_KNOWN = QuestPlusSettings(-20.0, 45.0, target_sd_db=1.08, min_trials=10, max_trials=80)
QUEST_MARGINAL = QuestPlusSettings(
    -20.0, 45.0, scales_db=(0.5, 0.75, 1.1, 1.5, 2.2, 3.0, 4.5), lapses=(0.0, 0.04, 0.08),
    target_sd_db=1.6, min_trials=10, max_trials=120,
)  # fmt: skip
FUNCTIONAL = FunctionalRampSettings(max_trials=87)


def quest_coverage(settings, scale, lapse, n, rng):
    truth = rng.uniform(0.0, 13.0, n)
    sim = simulate_quest_plus(settings, truth, scale_db=scale, lapse=lapse, rng=rng)
    hits = 0
    for i in range(n):
        k = int(sim.n_trials[i])
        _, _, lo, hi = posterior_summary(settings, sim.levels_db[i, :k], sim.correct[i, :k])
        hits += lo <= truth[i] <= hi
    return hits / n, float(np.mean(sim.n_trials))


def functional_coverage(scale, lapse, n, rng):
    record = settings_record(FUNCTIONAL)
    psy = Psychometric(0.0, scale, 1 / 3, lapse)
    hits_a = hits_b = 0
    for _ in range(n):
        a, b = rng.normal(-7.442, 1.0), rng.normal(0.711, 0.05)
        u = rng.normal(0.0, 1.0)  # calibration error of the unmasked AL, dB
        state = FUNCTIONAL.start()
        while not state.finished:
            theta = u + float(ramp(state.next_masker_level_db_sl(), a, b))
            state = state.update(bool(rng.random() < psy.p_correct(state.next_level() - theta)))
        post = ramp_posterior(record, state.maskers_db_sl, state.levels_db, state.responses)
        hits_a += post.intercept_ci_db[0] <= a <= post.intercept_ci_db[1]
        hits_b += post.slope_ci[0] <= b <= post.slope_ci[1]
    return hits_a / n, hits_b / n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tracks", type=int, default=60)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    print(f"{args.tracks} tracks per cell, seed {args.seed}\n")
    print(
        "| observer scale, lapse | QUEST+ slope known | psi-marginal | functional a | "
        "functional b |"
    )
    print("|---|---:|---:|---:|---:|")
    for scale, lapse in OBSERVERS:
        known, _ = quest_coverage(QUEST_KNOWN, scale, lapse, args.tracks, rng)
        marg, trials = quest_coverage(QUEST_MARGINAL, scale, lapse, args.tracks, rng)
        fa, fb = functional_coverage(scale, lapse, args.tracks, rng)
        print(
            f"| {scale:g} dB, {lapse:g} | {known:.0%} | {marg:.0%} ({trials:.0f} trials) | "
            f"{fa:.0%} | {fb:.0%} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
