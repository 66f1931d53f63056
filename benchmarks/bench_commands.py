"""``demo`` and ``plan`` timed as whole commands, as a user times them, beside a baseline.

    python benchmarks/bench_commands.py [--repeats 3] [--baseline-src DIR] [--baseline-json F]
                                        [--save-json F] [--only demo,plan]

Runs ``masking-lab demo`` and ``masking-lab plan`` with defaults on each shipped protocol that
``plan`` takes (baseline, experiment1, experiment1_questplus, experiment1_functional,
experiment2; usertest.yaml is a user test, not a measurement) in fresh child processes,
``--repeats`` times each, and prints the median wall-clock time and the
median CPU time (user + system of the command and its children, as ``/usr/bin/time`` reports
them), against a baseline in the same run:

* ``--baseline-src DIR``: a source tree of the previous version (e.g.
  ``git archive HEAD~3 masking_lab protocols data_schema | tar -x -C /tmp/prev``) run with the
  same interpreter (``PYTHONPATH=DIR``), interleaved with this version's runs so both see the
  same machine load; ``plan``'s tables (CSV and text) of both are then compared byte for byte;
* ``--baseline-json F``: figures stored by an earlier run's ``--save-json``.

The machine's load average is printed first: on a shared machine other processes inflate
wall-clock times, not CPU times.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from timing_setup import compile_tree, console_code

ROOT = Path(__file__).resolve().parents[1]
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


def run_once(args: list[str], src: Path | None, out: Path) -> tuple[float, float]:
    """Wall and CPU seconds (user + system, children included) of one command."""
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = str(src)
    # The tree's console script, as a user runs it (PYTHONPATH above picks the tree's package).
    argv = [sys.executable, "-c", console_code(src if src is not None else ROOT)]
    argv += [a.replace("{out}", str(out)) for a in args]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run(argv, env=env, capture_output=True, text=True, cwd=out.parent)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


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
    args = ap.parse_args()
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
    print(f"{'command':<28}{'wall s':>8}{'cpu s':>8}{'base wall':>11}{'base cpu':>10}{'ratio':>8}")
    figures: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory(prefix="bench_commands_") as tmp:
        for name, cmd in todo.items():
            slug = name.replace(" ", "_")
            mine, base = [], []
            for k in range(args.repeats):
                if args.baseline_src is not None:
                    base.append(run_once(cmd, args.baseline_src, Path(tmp) / f"base{k}_{slug}"))
                mine.append(run_once(cmd, None, Path(tmp) / f"this{k}_{slug}"))
            wall = statistics.median(w for w, _ in mine)
            cpu = statistics.median(c for _, c in mine)
            figures[name] = {"wall_s": wall, "cpu_s": cpu}
            if base:
                b_wall = statistics.median(w for w, _ in base)
                b_cpu = statistics.median(c for _, c in base)
            else:
                b_wall = stored.get(name, {}).get("wall_s", float("nan"))
                b_cpu = stored.get(name, {}).get("cpu_s", float("nan"))
            print(
                f"{name:<28}{wall:8.2f}{cpu:8.2f}{b_wall:11.2f}{b_cpu:10.2f}{wall / b_wall:7.2f}x"
            )
            if base and name.startswith("plan"):
                verdict = same_csvs(Path(tmp) / f"base0_{slug}", Path(tmp) / f"this0_{slug}")
                print(f"  its tables against the baseline's: {verdict}")
    if args.save_json is not None:
        args.save_json.write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()
