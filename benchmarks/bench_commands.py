"""``demo`` and ``plan`` timed as whole commands, as a user times them, beside a baseline.

    python benchmarks/bench_commands.py [--repeats 3] [--baseline-src DIR] [--baseline-json F]
                                        [--save-json F] [--only demo,plan] [--floors] [--cold]

Runs ``masking-lab demo`` and ``masking-lab plan`` with defaults on each shipped protocol that
``plan`` takes (baseline, experiment1, experiment1_questplus, experiment1_functional,
experiment2; usertest.yaml is a user test, not a measurement) in fresh child processes,
``--repeats`` times each, and prints the median wall-clock time and the
median CPU time (user + system of the command and of every process it started: its workers,
and the workers those fork, which ``/usr/bin/time`` misses once their parent has ended;
``timing_setup.adopt_orphans``), against a baseline in the same run:

* ``--baseline-src DIR``: a source tree of the previous version (e.g.
  ``git archive HEAD~3 masking_lab protocols data_schema firmware | tar -x -C /tmp/prev``: with
  ``firmware/``, a version whose demo runs on the C firmware does so there too) run with the
  same interpreter (``PYTHONPATH=DIR``), interleaved with this version's runs so both see the
  same machine load; ``plan``'s tables (CSV and text) of both are then compared byte for byte;
* ``--baseline-json F``: figures stored by an earlier run's ``--save-json``.

With ``--cold``, every run (this tree's and the baseline's) starts with an empty numba cache
(``NUMBA_CACHE_DIR``, a fresh folder per run): the first ``plan`` after an install, which
compiles the simulation's loops before it can use them (~10 s of CPU for the QUEST+ protocol).
masking_lab's own cache starts empty too (``MASKING_LAB_CACHE``), where the demo compiles the C
firmware's host build it runs its sessions on (~1.3 s of CPU).
``--floors`` beside it still times the simulation with numba's cache as it is: the loops, not
their compilation.

With ``--floors``, each ``plan`` row is followed by the time of its simulation alone: the
chunks ``plan`` runs for that protocol with its defaults (the staircase plan's and the QUEST+
comparison's, ``masking_lab.commands.plan_simulation.simulation``), run one after another in
one fresh process with one BLAS thread (numba loaded once, by the first chunk that needs it),
as process CPU seconds, and that CPU spread over the machine's cores: what ``plan`` cannot go
below while its tables stay the same. It runs right after each of the command's runs (the
machine's speed drifts within minutes) and the median is printed, with the command's wall time
and CPU over it. (A functional protocol's plan simulates other routes: n/a.)

The machine's load average is printed first: on a shared machine other processes inflate
wall-clock times, not CPU times. The last column says whether each median is within issue 22's
target (10 s for the demo and for every ``plan`` with defaults); without a baseline its columns
print ``-``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from timing_setup import adopt_orphans, compile_tree, console_code, reap_orphans

ROOT = Path(__file__).resolve().parents[1]
#: Issue 22's target for the demo and for every ``plan`` with defaults: the median within 10 s.
TARGET_WALL_S = 10.0
PLAN_PROTOCOLS = (
    "baseline",
    "experiment1",
    "experiment1_questplus",
    "experiment1_functional",
    "experiment2",
)


def commands() -> dict[str, list[str]]:
    """Name → masking-lab arguments (``{out}`` is replaced by a fresh folder per run)."""
    out: dict[str, list[str]] = {"demo": ["demo", "--out", "{out}"]}
    for name in PLAN_PROTOCOLS:
        protocol = str(ROOT / "protocols" / f"{name}.yaml")
        out[f"plan {name}"] = ["plan", protocol, "--out", "{out}", "--no-progress"]
    return out


def run_once(
    args: list[str], src: Path | None, out: Path, *, cold: bool = False
) -> tuple[float, float]:
    """Wall and CPU seconds (user + system, children included) of one command.

    ``cold``: numba's cache and masking_lab's start empty (``NUMBA_CACHE_DIR``,
    ``MASKING_LAB_CACHE``: fresh folders beside ``out``), as on the first run after an install,
    so the command compiles every loop it uses (and the demo its firmware).
    """
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = str(src)
    if cold:
        cache = out.parent / f"{out.name}_numba_cache"
        cache.mkdir()
        env["NUMBA_CACHE_DIR"] = str(cache)
        own = out.parent / f"{out.name}_masking_lab_cache"
        own.mkdir()
        env["MASKING_LAB_CACHE"] = str(own)
    # The tree's console script, as a user runs it (PYTHONPATH above picks the tree's package).
    argv = [sys.executable, "-c", console_code(src if src is not None else ROOT)]
    argv += [a.replace("{out}", str(out)) for a in args]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run(argv, env=env, capture_output=True, text=True, cwd=out.parent)
    wall = time.perf_counter() - t0
    reap_orphans()  # workers forked by workers and left unwaited (timing_setup.adopt_orphans)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def simulation_cpu(protocol: Path) -> dict[str, float]:
    """In a fresh process (this file with ``--simulation-cpu``): CPU seconds of ``plan``'s
    simulation chunks for ``protocol``, run in that process one by one; ``{}`` when ``plan``
    does not simulate chunks for it (a functional protocol)."""
    done = subprocess.run(
        [sys.executable, __file__, "--simulation-cpu", str(protocol)],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    if done.returncode != 0:
        raise SystemExit(f"--simulation-cpu {protocol} failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout)


def _simulation_cpu_here(protocol: str) -> dict[str, float]:
    """The child of :func:`simulation_cpu`: build the chunks as ``plan`` does, then time them."""
    from threadpoolctl import threadpool_limits

    from masking_lab.commands.cli import build_parser
    from masking_lab.commands.plan_simulation import simulation
    from masking_lab.formats.protocol import load_protocol
    from masking_lab.procedures.registry import kind_of

    loaded = load_protocol(protocol)
    if any(kind_of(s.settings).places_masker for s in loaded.sets):
        return {}
    sim = simulation(build_parser().parse_args(["plan", protocol]), loaded)
    chunks = [*sim.staircase, *sim.quest]
    with threadpool_limits(1, user_api="blas"):  # as plan's workers run every chunk
        t0 = time.process_time()
        for fn, fn_args in chunks:
            fn(*fn_args)
        cpu = time.process_time() - t0
    return {"cpu_s": cpu, "chunks": len(chunks)}


def same_csvs(a: Path, b: Path) -> str:
    """'identical' or the tables (CSV, text) whose bytes differ between two plan folders."""
    names = sorted(p.name for p in [*a.glob("*.csv"), *a.glob("*.txt")])
    differ = [n for n in names if (a / n).read_bytes() != (b / n).read_bytes()]
    return "identical" if not differ else "DIFFER: " + ", ".join(differ)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--baseline-src", type=Path, default=None)
    ap.add_argument("--baseline-json", type=Path, default=None)
    ap.add_argument("--save-json", type=Path, default=None)
    ap.add_argument("--only", default="demo,plan", help="demo, plan or both (comma-separated)")
    ap.add_argument(
        "--protocols",
        default=",".join(PLAN_PROTOCOLS),
        help="the plan protocols to time (comma-separated names in protocols/)",
    )
    ap.add_argument(
        "--floors",
        action="store_true",
        help="after each plan row, its simulation alone in one process (see above)",
    )
    ap.add_argument(
        "--cold",
        action="store_true",
        help="every run starts with empty numba and masking_lab caches, as the first run after "
        "an install (plan then compiles its simulation's loops, the demo its C firmware)",
    )
    ap.add_argument("--simulation-cpu", metavar="PROTOCOL", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.repeats < 1:
        ap.error(f"--repeats must be at least 1 (a median needs a run), got {args.repeats}")
    if args.simulation_cpu:
        print(json.dumps(_simulation_cpu_here(args.simulation_cpu)))
        return
    adopt_orphans()  # so that every run's CPU includes the workers its workers fork
    wanted = set(args.only.split(","))
    protocols = set(args.protocols.split(","))
    todo = {
        k: v
        for k, v in commands().items()
        if k.split()[0] in wanted and (k == "demo" or k.split()[1] in protocols)
    }
    stored = json.loads(args.baseline_json.read_text()) if args.baseline_json else {}
    for tree in [ROOT, *([args.baseline_src] if args.baseline_src else [])]:
        compile_tree(tree)  # as installed: bytecode present (benchmarks/timing_setup.py)
    load = ", ".join(f"{v:.1f}" for v in os.getloadavg())
    print(f"{os.cpu_count()} cores, load average {load}; median of {args.repeats} runs")
    print(
        f"{'command':<28}{'wall s':>8}{'cpu s':>8}{'base wall':>11}{'base cpu':>10}{'ratio':>8}"
        f"  target (issue 22)"
    )
    figures: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory(prefix="bench_commands_") as tmp:
        for name, cmd in todo.items():
            slug = name.replace(" ", "_")
            mine, base = [], []
            alone: list[dict[str, float]] = []
            for k in range(args.repeats):
                if args.baseline_src is not None:
                    out = Path(tmp) / f"base{k}_{slug}"
                    base.append(run_once(cmd, args.baseline_src, out, cold=args.cold))
                mine.append(run_once(cmd, None, Path(tmp) / f"this{k}_{slug}", cold=args.cold))
                if args.floors and name.startswith("plan"):  # interleaved: the same load
                    alone.append(simulation_cpu(ROOT / "protocols" / f"{name.split()[1]}.yaml"))
            wall = statistics.median(w for w, _ in mine)
            cpu = statistics.median(c for _, c in mine)
            figures[name] = {"wall_s": wall, "cpu_s": cpu}
            if base:
                b_wall = statistics.median(w for w, _ in base)
                b_cpu = statistics.median(c for _, c in base)
            else:
                b_wall = stored.get(name, {}).get("wall_s", float("nan"))
                b_cpu = stored.get(name, {}).get("cpu_s", float("nan"))
            if math.isfinite(b_wall):
                base_text = f"{b_wall:11.2f}{b_cpu:10.2f}{wall / b_wall:7.2f}x"
            else:  # no baseline given: its columns stay empty
                base_text = f"{'-':>11}{'-':>10}{'-':>8}"
            within = "met" if wall <= TARGET_WALL_S else "over"
            print(f"{name:<28}{wall:8.2f}{cpu:8.2f}{base_text}  ≤ {TARGET_WALL_S:g} s: {within}")
            if base and name.startswith("plan"):
                verdict = same_csvs(Path(tmp) / f"base0_{slug}", Path(tmp) / f"this0_{slug}")
                print(f"  its tables against the baseline's: {verdict}")
            if alone and not alone[0]:
                print("  its simulation alone: n/a (a functional protocol's routes)")
            elif alone:
                sim_cpu = statistics.median(a["cpu_s"] for a in alone)
                figures[name] |= {"simulation_cpu_s": sim_cpu, "chunks": alone[0]["chunks"]}
                cores = os.cpu_count() or 1
                spread = sim_cpu / cores
                print(
                    f"  its simulation alone ({alone[0]['chunks']:.0f} chunks, one process): "
                    f"{sim_cpu:.2f} s CPU = {spread:.2f} s on {cores} cores; the command "
                    f"{wall:.2f} s = {wall / spread:.2f}x that, its CPU {cpu / sim_cpu:.2f}x"
                )
    if args.save_json is not None:
        args.save_json.write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()
