"""Solver throughput and latency, as ratios against baselines measured in the same run.

    python benchmarks/bench_solver.py            # 10^3 … 10^7 points
    python benchmarks/bench_solver.py --max-exp 6 --root-points 500

For each size n it times the vectorised :func:`masking_lab.rendering.solver.solve` on n random
targets
and compares it with (a) a per-point Python loop over :meth:`MutualMasking.solve_point` and
(b) a generic root finder (``scipy.optimize.root``, hybr) on the same targets. The baselines are
slow, so they are timed on the first ``--loop-points`` / ``--root-points`` targets and their
per-point cost is scaled to n (stated in the table). It then times one scalar call against a
1 kHz haptic loop's budget of 1000 µs. Nothing here asserts a speed; it prints numbers.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from scipy.optimize import root

from masking_lab.rendering.solver import MutualMasking, forward, solve

# Paper §3.4's pooled values: MV by EV (1.39, 1.09), EV by MV (−6.22, 0.66).
PAIR = MutualMasking(1.39, 1.09, -6.22, 0.66, mv="MV180", ev="EV270")
HAPTIC_BUDGET_US = 1000.0  # one tick of a 1 kHz loop


def best_time(fn, repeats: int) -> float:
    """Fastest of ``repeats`` wall-clock runs of ``fn()``, s."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def loop_solve(m_p: np.ndarray, e_p: np.ndarray) -> list:
    """Baseline (a): the scalar path called once per point from Python."""
    solve_point = PAIR.solve_point
    return [solve_point(m, e) for m, e in zip(m_p.tolist(), e_p.tolist(), strict=True)]


def root_solve(m_p: np.ndarray, e_p: np.ndarray) -> tuple[int, int, float]:
    """Baseline (b): scipy.optimize.root per point, started at the targets.

    Returns (points not solved to 1e-6 dB, points where scipy reported no convergence, worst
    |forward − target| in dB). The kinks of the ramps upset its Jacobian estimate, so it often
    reports failure even where it has landed on the answer.
    """
    failures, flagged, worst = 0, 0, 0.0
    for m, e in zip(m_p.tolist(), e_p.tolist(), strict=True):

        def residual(x, m=m, e=e):
            mp, ep = PAIR.forward_point(x[0], x[1])
            return [mp - m, ep - e]

        res = root(residual, [m, e], method="hybr")
        err = max(abs(v) for v in residual(res.x))
        failures += err > 1e-6
        flagged += not res.success
        worst = max(worst, err)
    return failures, flagged, worst


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--min-exp", type=int, default=3, help="smallest size 10^k (default 3)")
    ap.add_argument("--max-exp", type=int, default=7, help="largest size 10^k (default 7)")
    ap.add_argument("--loop-points", type=int, default=100_000, help="points timed in the loop")
    ap.add_argument("--root-points", type=int, default=2_000, help="points timed with scipy")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()

    rng = np.random.default_rng(args.seed)
    n_max = 10**args.max_exp
    # Targets over the paper's range and beyond, all four Table 4 cases.
    m_all = rng.uniform(-20.0, 30.0, n_max)
    e_all = rng.uniform(-20.0, 30.0, n_max)

    k_loop = min(args.loop_points, n_max)
    loop_s = best_time(lambda: loop_solve(m_all[:k_loop], e_all[:k_loop]), 3) / k_loop
    k_root = min(args.root_points, n_max)
    t0 = time.perf_counter()
    failures, flagged, worst = root_solve(m_all[:k_root], e_all[:k_root])
    root_s = (time.perf_counter() - t0) / k_root

    print(
        f"solver throughput, b·d = {PAIR.bd:.3f}; baselines per point: Python loop "
        f"{loop_s * 1e6:.2f} µs (timed on {k_loop:,} points), scipy.optimize.root "
        f"{root_s * 1e6:.0f} µs (timed on {k_root:,} points; {failures} off by > 1e-6 dB, "
        f"{flagged} flagged as not converged, worst |error| {worst:.1e} dB)"
    )
    print()
    print(
        f"{'points':>10} {'vector s':>10} {'Mpoints/s':>10} {'loop s*':>10} {'root s*':>10} "
        f"{'loop/vector':>12} {'root/vector':>12}"
    )
    for k in range(args.min_exp, args.max_exp + 1):
        n = 10**k
        m_p, e_p = m_all[:n], e_all[:n]
        repeats = max(1, min(20, 10**6 // n))
        vec_s = best_time(lambda m_p=m_p, e_p=e_p: solve(PAIR, m_p, e_p), repeats)
        loop_n, root_n = loop_s * n, root_s * n
        print(
            f"{n:>10,} {vec_s:>10.4f} {n / vec_s / 1e6:>10.1f} {loop_n:>10.2f} "
            f"{root_n:>10.1f} {loop_n / vec_s:>12.0f} {root_n / vec_s:>12.0f}"
        )
    print("  * loop and root times scaled from their per-point cost above")

    # Check once that the vector answers are right (forward model gives the targets back).
    sol = solve(PAIR, m_all[:100_000], e_all[:100_000])
    back_m, back_e = forward(PAIR, sol.mv_input_db_sl, sol.ev_input_db_sl)
    err = max(np.abs(back_m - m_all[:100_000]).max(), np.abs(back_e - e_all[:100_000]).max())
    print(f"  forward(solve(target)) − target: max {err:.1e} dB over 100,000 points")

    # Scalar latency for a haptic loop: many single calls, per-call quantiles.
    solve_point = PAIR.solve_point
    targets = list(zip(m_all[:1000].tolist(), e_all[:1000].tolist(), strict=True))
    per_call = []
    for _ in range(200):
        t0 = time.perf_counter()
        for m, e in targets:
            solve_point(m, e)
        per_call.append((time.perf_counter() - t0) / len(targets) * 1e6)
    median = statistics.median(per_call)
    p99 = sorted(per_call)[int(0.99 * len(per_call)) - 1]
    print()
    print(
        f"scalar solve_point: median {median:.2f} µs/call (99th percentile of 1000-call "
        f"batches {p99:.2f} µs) = {median / HAPTIC_BUDGET_US:.2%} of a 1 kHz loop's "
        f"{HAPTIC_BUDGET_US:.0f} µs budget; one call alone: "
        f"{_single_call_us(solve_point, targets):.2f} µs median"
    )


def _single_call_us(fn, targets) -> float:
    """Median latency of isolated calls (timer overhead included), µs."""
    samples = []
    for m, e in targets[:500]:
        t0 = time.perf_counter_ns()
        fn(m, e)
        samples.append((time.perf_counter_ns() - t0) / 1000.0)
    return statistics.median(samples)


if __name__ == "__main__":
    main()
