"""The psi-marginal placement screened in float32 against the full float64 expected entropy.

    python benchmarks/bench_psi_screen.py [--tracks 120] [--repeats 7]

Simulates ``--tracks`` psi-marginal tracks on the shipped grid (experiment1_questplus.yaml:
131 levels × 131 thresholds × 7 scales × 4 lapses) to 300 trials, keeps their posteriors after
trials 10, 60, 150 and 299, and times one placement of the whole batch (what ``plan`` does per
trial) and of one track (what a session does) both ways:
:func:`masking_lab.procedures.psi_screen.best_levels` and ``argmin(expected_entropy(...))``,
the baseline. Prints µs per track (best of ``--repeats``), the ratio, how many levels per track
the float64 check had to settle, and whether both chose the same levels (they must).
"""

from __future__ import annotations

import argparse

import numpy as np
from bench_simulate import best_of  # shortest of n calls, s

from masking_lab.core.psychometric import Psychometric
from masking_lab.procedures.psi_screen import best_levels, screen
from masking_lab.procedures.quest_plus import QuestPlusSettings, expected_entropy, tables

SETTINGS = QuestPlusSettings(-20.0, 45.0, target_sd_db=0.4, max_trials=300)
SNAPSHOTS = (10, 60, 150, 299)


def posteriors(n_tracks: int, seed: int = 1) -> dict[int, np.ndarray]:
    """The tracks' posteriors after each trial of :data:`SNAPSHOTS` (observers as ``plan``'s)."""
    t = tables(SETTINGS)
    rng = np.random.default_rng(seed)
    truth = rng.uniform(0.0, 25.0, n_tracks)
    psy = Psychometric(0.0, 1.5, 1 / 3, 0.02, SETTINGS.p_at_threshold)
    post = np.repeat(t.prior[None], n_tracks, axis=0)
    idx = np.full(n_tracks, int(np.searchsorted(t.levels_db, t.first_level_db)))
    out = {}
    for trial in range(max(SNAPSHOTS) + 1):
        c = rng.random(n_tracks) < psy.p_correct(t.levels_db[idx] - truth)
        post = post * np.where(c[:, None, None], t.p_correct[idx], t.p_wrong[idx])
        post /= post.reshape(n_tracks, -1).sum(axis=1)[:, None, None]
        if trial in SNAPSHOTS:
            out[trial] = post.copy()
        idx = best_levels(t, post)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tracks", type=int, default=120, help="tracks per batch (plan: 120)")
    ap.add_argument("--repeats", type=int, default=7, help="timed calls per row")
    args = ap.parse_args()
    t = tables(SETTINGS)
    snaps = posteriors(args.tracks)
    print(f"psi-marginal placement, grid {t.p_correct.shape} (levels, thresholds, nuisance)")
    header = "trial  tracks  float64 µs/track  screened µs/track  ratio  settled/track  same levels"
    print(header)
    for trial, post in snaps.items():
        for batch in (post, post[:1]):
            n = batch.shape[0]
            full = np.argmin(expected_entropy(t, batch), axis=1)
            fast = best_levels(t, batch)
            low, high = screen(t, batch)
            settled = float(np.mean((low <= high.min(axis=1)[:, None]).sum(axis=1)))
            old = best_of(lambda b=batch: np.argmin(expected_entropy(t, b), axis=1), args.repeats)
            new = best_of(lambda b=batch: best_levels(t, b), args.repeats)
            print(
                f"{trial:5d}  {n:6d}  {old / n * 1e6:16.0f}  {new / n * 1e6:17.0f}  "
                f"{old / new:5.2f}  {settled:13.2f}  {bool(np.array_equal(full, fast))}"
            )


if __name__ == "__main__":
    main()
