"""How soon Ctrl-C ends `analyze` and `plan`, and whether the run prints only its own line.

A terminal's Ctrl-C signals every process of the foreground group: the run and its workers.
Each run here starts in a process group of its own and gets SIGINT, sent to the whole group,
after a chosen delay (spread over the run: start-up, forking, reading, fitting, writing). For
each command the benchmark prints the median and the longest time from the signal to the
run's exit, the exit codes ("hung": still running a minute after the signal, then killed),
and how many runs printed a traceback (``Traceback``, ``Exception ignored``,
``KeyboardInterrupt``) or hung besides ``masking-lab COMMAND: interrupted``,
this tree's and, with ``--baseline-src DIR``, another tree's interleaved in one run.
Nothing is asserted (tests/test_interrupted_workers.py asserts the behaviour).

Usage::

    python benchmarks/bench_interrupt.py
    python benchmarks/bench_interrupt.py --baseline-src DIR   # e.g. git archive of main
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_analysis import build_folder
from timing_setup import compile_tree, tree_console_code

from masking_lab.simulation.synthetic_logs import simulate_study

ROOT = Path(__file__).resolve().parents[1]
NOISE = ("Traceback", "Exception ignored", "KeyboardInterrupt")
#: A run still there this long after the signal has hung (reported as exit code "hung").
HANG_S = 60.0
HUNG = -1000


def interrupt_once(argv: list[str], src: Path | None, delay_s: float) -> tuple[float, int, bool]:
    """Seconds from SIGINT to exit, the exit code, and whether stderr held a traceback (inf,
    :data:`HUNG` and True for a run that hung)."""
    code = tree_console_code(src or ROOT, other_tree=src is not None)
    proc = subprocess.Popen(
        [sys.executable, "-c", code, *argv],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        start_new_session=True,  # a group of its own, as a terminal's foreground job
    )
    time.sleep(delay_s)
    sent = time.perf_counter()
    with contextlib.suppress(ProcessLookupError):  # already done: not an interrupted run
        os.killpg(proc.pid, signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=HANG_S)
    except subprocess.TimeoutExpired:  # hung: ended here, and counted as such
        os.killpg(proc.pid, signal.SIGKILL)
        _, err = proc.communicate()
        return float("inf"), HUNG, True
    waited = time.perf_counter() - sent
    return waited, proc.returncode, any(word in err.decode() for word in NOISE)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--baseline-src", metavar="DIR", help="also time the tree in DIR")
    ap.add_argument("--sessions", type=int, default=300, help="logs analyze reads (300)")
    ap.add_argument("--repeats", type=int, default=1, help="rounds over the delays (1)")
    args = ap.parse_args(argv)
    trees: list[tuple[str, Path | None]] = [("this", None)]
    if args.baseline_src:
        trees.append(("baseline", Path(args.baseline_src).resolve()))
    for _, src in trees:
        compile_tree(src or ROOT)
    work = Path(tempfile.mkdtemp(prefix="bench_interrupt_"))
    try:
        simulate_study(work / "pool", n_participants=10, seed=0)
        build_folder(work / "pool", work / "data", args.sessions)
        protocol = ROOT / "protocols" / "experiment1.yaml"
        analyze = ["analyze", str(work / "data"), "--out", str(work / "out")]
        plan = ["plan", str(protocol), "--out", str(work / "plan")]
        commands = {
            "analyze": (analyze, [0.3, 0.6, 0.9, 1.2, 1.5, 2.0, 2.5]),
            "plan": (plan, [1.0, 2.0, 3.0, 4.5, 6.0]),
        }
        rows = []
        for name, (cmd, delays) in commands.items():
            got: dict[str, list[tuple[float, int, bool]]] = {label: [] for label, _ in trees}
            for _ in range(args.repeats):
                for delay in delays:
                    for label, src in trees:  # interleaved: the same load for both
                        got[label].append(interrupt_once(cmd, src, delay))
                        shutil.rmtree(work / "out", ignore_errors=True)
                        shutil.rmtree(work / "plan", ignore_errors=True)
            for label, runs in got.items():
                waits = [w for w, rc, _ in runs if rc == 130]
                codes = sorted({"hung" if rc == HUNG else rc for _, rc, _ in runs}, key=str)
                noisy = sum(n for _, _, n in runs)
                rows.append((name, label, waits, codes, noisy, len(runs)))
        print(f"{os.cpu_count()} CPUs; SIGINT to the whole process group after each delay")
        print(f"{'command':<9}{'tree':<10}{'median s':>9}{'max s':>8}  exit codes  tracebacks")
        for name, label, waits, codes, noisy, n in rows:
            med = statistics.median(waits) if waits else float("nan")
            top = max(waits) if waits else float("nan")
            print(f"{name:<9}{label:<10}{med:>9.2f}{top:>8.2f}  {codes!s:<10}  {noisy} of {n}")
        if args.baseline_src:
            for name in commands:
                this = next(r for r in rows if r[0] == name and r[1] == "this")
                base = next(r for r in rows if r[0] == name and r[1] == "baseline")
                if this[2] and base[2]:
                    ratio = statistics.median(this[2]) / statistics.median(base[2])
                    print(f"{name}: median time to exit {ratio:.2f}x the baseline's")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
