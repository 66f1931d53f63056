"""Coverage of the Bayesian procedures' 95 % intervals when the observer is not the model
(the table in docs/procedures.md).

    OMP_NUM_THREADS=1 python benchmarks/interval_coverage.py [--tracks 200] [--seed 0] [--workers 2]
        [--columns quest,known,functional] [--cells 0.75/0.02,3/0.08,...]

Observers whose psychometric scale is the one the protocols assume (1.5 dB), half or twice it,
with a lapse of 0, 0.02, 0.04 or 0.08. For each procedure setting, the share of tracks whose
central 95 % credible interval (recomputed from the track's trials, as `analyze` does) holds
the truth, with its binomial standard error:

* ``quest``: single thresholds with the shipped ``experiment1_questplus.yaml`` (slope and lapse
  marginalised, the defaults of ``QuestPlusSettings``): over every track (capped ones too), and
  over the completed ones (those `analyze` turns into ALs) with their RMS error (dB);
* ``known``: the protocol as shipped before: slope and lapse known (scale 1.5 dB, lapse 0.02),
  posterior SD ≤ 1.08 dB, for contrast;
* ``functional``: the ramp's intercept and slope with the shipped
  ``experiment1_functional.yaml`` (one masker frequency).

Tracks run in vectorised batches (``quest_plus_batch``, ``functional_lockstep``) in chunks of
``--chunk`` tracks, spread over ``--workers`` processes. Every chunk draws from its own seed,
spawned from ``--seed`` by (column, cell, chunk), so the table does not depend on the number of
workers. Prints the wall time at the end.
"""

from __future__ import annotations

import argparse
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np

from masking_lab.analysis.functional import ramp_posterior
from masking_lab.formats.protocol import load_protocol
from masking_lab.formats.resources import shipped
from masking_lab.procedures.functional_batch import simulate_ramps
from masking_lab.procedures.quest_plus_batch import simulate_quest_plus
from masking_lab.procedures.quest_plus_kind import posterior_summary
from masking_lab.procedures.registry import settings_record

SCALES = (0.75, 1.5, 3.0)
LAPSES = (0.0, 0.02, 0.04, 0.08)
COLUMNS = ("quest", "known", "functional")
#: The paper's EV270/MV120 ramp (intercept dB, slope dB/dB) and the spread of simulated
#: participants around it; the unmasked AL's calibration error has SD 1 dB.
RAMP = (-7.442, 0.711)
RAMP_SD = (1.0, 0.05)


def _settings(column: str):
    if column == "functional":
        return load_protocol(shipped("protocols", "experiment1_functional.yaml")).sets[0].settings
    quest = load_protocol(shipped("protocols", "experiment1_questplus.yaml")).sets[0].settings
    if column == "known":
        # The protocol as shipped before issue 18: slope and lapse known, SD ≤ 1.08 dB.
        return replace(quest, scales_db=(1.5,), lapses=(0.02,), target_sd_db=1.08, max_trials=80)
    return quest


def run_chunk(job: tuple[str, float, float, int, np.random.SeedSequence]) -> dict[str, float]:
    """Hits (interval holds the truth) of one chunk of tracks: counts, not shares."""
    column, scale, lapse, n, seed = job
    rng = np.random.default_rng(seed)
    settings = _settings(column)
    if column == "functional":
        a = rng.normal(RAMP[0], RAMP_SD[0], n)
        b = rng.normal(RAMP[1], RAMP_SD[1], n)
        u = rng.normal(0.0, 1.0, n)
        sim = simulate_ramps(
            settings, a, b, scale_db=scale, lapse=lapse, unmasked_offset_db=u, rng=rng
        )
        record = settings_record(settings)
        hits_a = hits_b = 0
        for i in range(n):
            k = int(sim.n_trials[i])
            post = ramp_posterior(
                record, sim.maskers_db_sl[i, :k], sim.levels_db[i, :k], sim.correct[i, :k]
            )
            hits_a += post.intercept_ci_db[0] <= a[i] <= post.intercept_ci_db[1]
            hits_b += post.slope_ci[0] <= b[i] <= post.slope_ci[1]
        return {"n": n, "a": hits_a, "b": hits_b, "trials": float(sim.n_trials.sum())}
    truth = rng.uniform(0.0, 13.0, n)
    sim = simulate_quest_plus(settings, truth, scale_db=scale, lapse=lapse, rng=rng)
    out = {"n": n, "hits": 0, "trials": float(sim.n_trials.sum()), "completed": 0}
    out |= {"hits_completed": 0, "sq_err": 0.0}
    for i in range(n):
        k = int(sim.n_trials[i])
        mean, _, lo, hi = posterior_summary(settings, sim.levels_db[i, :k], sim.correct[i, :k])
        inside = int(lo <= truth[i] <= hi)
        out["hits"] += inside
        if sim.status[i] == "completed":  # the sets `analyze` turns into ALs
            out["completed"] += 1
            out["hits_completed"] += inside
            out["sq_err"] += (mean - truth[i]) ** 2
    return out


def _row(cell, columns, total) -> str:
    """One table row: every column's coverage ± binomial SE for this (scale, lapse) cell."""
    row = []
    for c in columns:
        r = total[(c, cell)]
        if c == "functional":
            row += [_share(r["a"], r["n"]), _share(r["b"], r["n"])]
        elif c == "quest":
            mean_n, done = r["trials"] / r["n"], r["completed"] / r["n"]
            rms = np.sqrt(r["sq_err"] / max(r["completed"], 1))
            among = _share(r["hits_completed"], max(r["completed"], 1))
            row.append(f"{_share(r['hits'], r['n'])} ({mean_n:.0f}, {done:.0%})")
            row.append(f"{among}; RMS {rms:.2f} dB")
        else:
            row.append(_share(r["hits"], r["n"]))
    return f"| {cell[0]:g} dB, {cell[1]:g} | " + " | ".join(row) + " |"


def _share(hits: float, n: float) -> str:
    p = hits / n
    return f"{p:.1%} ± {np.sqrt(p * (1 - p) / n):.1%}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tracks", type=int, default=200, help="tracks per cell and column")
    parser.add_argument("--chunk", type=int, default=25, help="tracks per job")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--columns", default=",".join(COLUMNS))
    parser.add_argument(
        "--cells", default="", help="scale/lapse pairs, e.g. 3/0.08,0.75/0.02 (default: all)"
    )
    args = parser.parse_args()
    columns = [c for c in args.columns.split(",") if c]
    unknown = sorted(set(columns) - set(COLUMNS))
    if unknown:
        parser.error(f"unknown column(s) {', '.join(unknown)}; choose from {', '.join(COLUMNS)}")
    all_cells = [(s, lam) for s in SCALES for lam in LAPSES]
    if args.cells:
        wanted = [tuple(float(v) for v in c.split("/")) for c in args.cells.split(",")]
        cells = [c for c in all_cells if c in wanted]
    else:
        cells = all_cells
    root = np.random.SeedSequence(args.seed)
    jobs, keys = [], []
    for cell in cells:  # cell by cell, so each row prints as soon as its tracks are done
        cj = all_cells.index(cell)
        for ci, column in enumerate(COLUMNS):
            if column not in columns:
                continue
            for k, start in enumerate(range(0, args.tracks, args.chunk)):
                n = min(args.chunk, args.tracks - start)
                # The seed of (column, cell, chunk) is fixed by its indices: any worker count,
                # any subset of columns or cells gives the same tracks.
                seed = np.random.SeedSequence(root.entropy, spawn_key=(ci, cj, k))
                jobs.append((column, *cell, n, seed))
                keys.append((column, cell))
    print(f"{args.tracks} tracks per cell, seed {args.seed}, {args.workers} workers\n")
    head = {
        "quest": "QUEST+ shipped (marginal): all tracks (mean trials, completed) | "
        "completed tracks; RMS error",
        "known": "QUEST+ slope & lapse known",
        "functional": "functional: intercept | functional: slope",
    }
    print("| observer scale, lapse | " + " | ".join(head[c] for c in columns) + " |")
    print("|---|" + "---:|" * sum(2 if c in ("functional", "quest") else 1 for c in columns))
    left = {cell: sum(1 for _, c in keys if c == cell) for cell in cells}
    total: dict[tuple[str, tuple[float, float]], dict[str, float]] = {}
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=max(1, args.workers)) as pool:
        for key, res in zip(keys, pool.map(run_chunk, jobs), strict=True):
            acc = total.setdefault(key, {})
            for name, v in res.items():
                acc[name] = acc.get(name, 0.0) + v
            left[key[1]] -= 1
            if not left[key[1]]:
                print(_row(key[1], columns, total), flush=True)
    wall = time.perf_counter() - t0
    print(f"\nwall time {wall:.0f} s ({len(jobs)} chunks)")


if __name__ == "__main__":
    main()
