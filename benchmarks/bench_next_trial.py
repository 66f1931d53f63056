"""The Bayesian procedures' next-trial computation, idle and with the other cores saturated.

    python benchmarks/bench_next_trial.py [--samples 200] [--oracle-samples 20] [--grids ...]

Times every ``update`` (posterior update, stop rules and the placement of the next trial: what
the session does between an answer and the next stimulus) over tracks against simulated
observers, for the shipped QUEST+ grid (experiment1_questplus.yaml: 131 levels × 131
thresholds × 28 (7 scales × 4 lapses), psi-marginal placement), a 131 × 131 × 40 grid with
Watson's joint entropy (10 scales × 4 lapses) and the shipped functional (ramp) grid
(experiment1_functional.yaml), each

* idle, and with every other core saturated by busy processes this benchmark starts,
* as the session runs it (one BLAS thread, ``core.blas_threads``, and each update at the
  lowest real-time priority, ``session.priority``, when the system permits it), beside the
  same at normal priority and the library's default thread pools (the session before BLAS was
  pinned),
* for the joint grid also with L·ln L recomputed on every call (the placement before the
  entropy terms were cached),
* beside questplus (Watson's QUEST+ reference implementation; GPL-3, a test oracle, used only
  here and in tests) on the same QUEST+ grids and likelihoods (it has no ramp model and no
  psi-marginal placement, so the functional grid has no oracle row).

Prints wall-clock p50/p95/p99 and the CPU-time p99 of the update's thread in ms per row, the
budget (wall p99 ≤ 10 ms) and the ratio of each row's wall p99 to the session's. The machine's
load average is printed first: on a machine shared beyond its cores, time slices lost to other
users' processes set the wall-clock tail, and the CPU column shows the computation's own.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext

import numpy as np

from masking_lab.core.blas_threads import one_blas_thread
from masking_lab.core.masking import ramp
from masking_lab.core.psychometric import Psychometric
from masking_lab.formats.protocol import load_protocol
from masking_lab.formats.resources import shipped
from masking_lab.procedures.quest_plus import QuestPlusSettings, tables
from masking_lab.session.priority import placement_priority, placement_priority_note

BUDGET_MS = 10.0
JOINT = QuestPlusSettings(
    -20.0, 45.0, scales_db=tuple(float(v) for v in np.round(np.geomspace(0.5, 5.0, 10), 3)),
    lapses=(0.0, 0.01, 0.02, 0.04), entropy_over="all", max_trials=60,
)  # fmt: skip


@contextmanager
def saturated(busy: bool) -> Iterator[None]:
    """Every core but one spinning in a child process this benchmark owns (ended on exit)."""
    procs = []
    if busy:
        n = max(1, (os.cpu_count() or 2) - 1)
        code = "while True: pass"
        procs = [subprocess.Popen([sys.executable, "-c", code]) for _ in range(n)]
        time.sleep(0.5)  # let them reach the run queue
    try:
        yield
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait()


def time_updates(
    start: Callable[[], object], answer, samples: int, before=None, realtime: bool = False
) -> np.ndarray:
    """Wall and CPU seconds (this thread's) per ``update``, shape (samples, 2), over fresh
    tracks until ``samples`` updates are timed; ``realtime`` as the session's placement runs."""
    rng = np.random.default_rng(0)
    out: list[tuple[float, float]] = []
    while len(out) < samples:
        track, truth = start(), rng.uniform(0.0, 13.0)
        while not track.finished and len(out) < samples:  # type: ignore[attr-defined]
            correct = answer(track, truth, rng)
            if before is not None:
                before()
            c0, t0 = time.thread_time(), time.perf_counter()
            with placement_priority(realtime):
                track = track.update(correct)  # type: ignore[attr-defined]
            out.append((time.perf_counter() - t0, time.thread_time() - c0))
    return np.array(out)


def _threshold_answer(track, truth, rng) -> bool:
    return bool(rng.random() < Psychometric(truth, 1.5, 1 / 3, 0.02).p_correct(track.next_level()))


def _ramp_answer(track, truth, rng) -> bool:
    theta = float(ramp(track.next_masker_level_db_sl(), -7.442, 0.711)) + truth - 6.5
    return bool(rng.random() < Psychometric(theta, 1.5, 1 / 3, 0.02).p_correct(track.next_level()))


class _Oracle:
    """questplus on the same grids and likelihood table, stepped like a track."""

    def __init__(self, s: QuestPlusSettings) -> None:
        import questplus
        import xarray as xr

        t = tables(s)
        self.levels = t.levels_db
        self.n = 0
        self.max_trials = s.max_trials or 80
        self.q = questplus.QuestPlus(
            stim_domain={"intensity": t.levels_db},
            param_domain={
                "threshold": t.thresholds_db,
                "slope": np.asarray(s.scales_db),
                "lower_asymptote": np.array([s.guess]),
                "lapse_rate": np.asarray(s.lapses),
            },
            outcome_domain={"response": ["Correct", "Incorrect"]},
            func="weibull",  # replaced below by our table: questplus has no logistic
            stim_scale="dB",
            stim_selection_method="min_entropy",
            param_estimation_method="mean",
        )
        shape = (t.levels_db.size, t.thresholds_db.size, len(s.scales_db), 1, len(s.lapses))
        pc = t.p_correct.reshape(shape)
        coords = {
            "response": ["Correct", "Incorrect"],
            "intensity": t.levels_db,
            "threshold": t.thresholds_db,
            "slope": np.asarray(s.scales_db),
            "lower_asymptote": np.array([s.guess]),
            "lapse_rate": np.asarray(s.lapses),
        }
        like = xr.DataArray(np.stack([pc, 1.0 - pc]), dims=list(coords), coords=coords)
        self.q.likelihoods = like.transpose(*self.q.likelihoods.dims)
        self.level = float(self.q.next_stim["intensity"])

    @property
    def finished(self) -> bool:
        return self.n >= self.max_trials

    def next_level(self) -> float:
        return self.level

    def update(self, correct: bool) -> _Oracle:
        outcome = {"response": "Correct" if correct else "Incorrect"}
        self.q.update(stim={"intensity": self.level}, outcome=outcome)
        self.level = float(self.q.next_stim["intensity"])  # the placement
        self.n += 1
        return self


def _row(name: str, sec: np.ndarray, ref_p99: float | None) -> tuple[str, float]:
    p50, p95, p99 = np.percentile(sec[:, 0] * 1e3, [50, 95, 99])
    cpu99 = float(np.percentile(sec[:, 1] * 1e3, 99))
    ratio = f"{p99 / ref_p99:9.1f}x" if ref_p99 else " " * 10
    flag = "" if ref_p99 else ("  ok" if p99 <= BUDGET_MS else "  OVER BUDGET")
    return f"  {name:<32}{p50:8.2f}{p95:8.2f}{p99:8.2f}{cpu99:8.2f} {ratio}{flag}", p99


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=200, help="timed updates per row")
    ap.add_argument("--oracle-samples", type=int, default=20, help="timed questplus updates")
    ap.add_argument(
        "--grids", default="shipped,joint,functional", help="comma-separated subset of these"
    )
    args = ap.parse_args()
    wanted = set(args.grids.split(","))
    quest = load_protocol(shipped("protocols", "experiment1_questplus.yaml")).sets[0].settings
    functional = load_protocol(shipped("protocols", "experiment1_functional.yaml")).sets[0].settings
    grids = [
        ("shipped", "QUEST+ shipped 131×131×28 psi-marginal", quest, _threshold_answer),
        ("joint", "QUEST+ joint 131×131×40", JOINT, _threshold_answer),
        ("functional", "functional shipped 230×899×27", functional, _ramp_answer),
    ]
    load = ", ".join(f"{v:.1f}" for v in os.getloadavg())
    print(f"{os.cpu_count()} cores, load average {load} (before the benchmark's own load)")
    print(f"session {placement_priority_note()}")
    print("  wall-clock p50/p95/p99 and CPU p99 (this thread) per update, ms; ratio of wall p99")
    print(f"  {'row':<32}{'p50':>8}{'p95':>8}{'p99':>8}{'cpu p99':>8} {'ratio':>10}")
    for key, title, settings, answer in grids:
        if key not in wanted:
            continue
        settings.start()  # tables are cached per settings: built outside the timing
        for busy in (False, True):
            print(f"{title}, {'other cores saturated' if busy else 'idle'}")
            with saturated(busy):
                with one_blas_thread():
                    ours = time_updates(settings.start, answer, args.samples, realtime=True)
                line, ref = _row("session (1 BLAS thread, RR)", ours, None)
                print(line)
                with one_blas_thread():
                    sec = time_updates(settings.start, answer, args.samples)
                print(_row("1 BLAS thread, normal priority", sec, ref)[0])
                rows = [("library default threads", nullcontext(), None)]
                if key == "joint":
                    t = tables(settings)
                    drop = lambda t=t: t.__dict__.pop("xlogx_tables", None)  # noqa: E731
                    rows.append(("1 thread, L·ln L every call", one_blas_thread(), drop))
                for name, ctx, before in rows:
                    with ctx:
                        sec = time_updates(settings.start, answer, args.samples, before)
                    print(_row(name, sec, ref)[0])
                if key != "functional":
                    with one_blas_thread():
                        sec = time_updates(
                            lambda s=settings: _Oracle(s), answer, args.oracle_samples
                        )
                    print(_row("questplus (1 BLAS thread)", sec, ref)[0])


if __name__ == "__main__":
    main()
