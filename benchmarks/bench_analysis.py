"""How `masking-lab analyze` compares with just reading its logs, and how it grows.

Simulates a ten-participant study once (baseline, experiment I, experiment II: 30 real session
logs written by ``masking_lab.simulation.synthetic_logs``), then builds folders of 100, 1,000
(and with ``--with-10000`` 10,000) sessions by copying those logs under new participant ids
(only the header line changes, so every file is a complete, realistic session of 4 or 15
staircases). For each folder, in one run, every row timed as a whole command (a fresh Python
process, start-up and imports included, as a user times it):

- ``read``: reading every file's bytes (no parsing at all);
- ``read+sha``: reading and SHA-256 of every file (the provenance analyze records);
- ``typed``: reading, SHA-256 and the typed msgspec decode of every line (the analysis view
  of ``masking_lab.formats.log_records``) in as many processes as analyze uses: the floor of
  analyze's own read;
- ``json``: reading and stdlib ``json.loads`` of every line in one process;
- ``analyze``: ``masking-lab analyze DATA --out OUT --quiet`` with the given options, with
  its process tree's peak memory (largest process from ``wait4``, and the sum over the tree
  sampled every 50 ms, workers included).

Prints the times and the ratios analyze / typed (target: at most 2 at 10,000 sessions) and
analyze / json (target: at most 1 at 1,000 sessions), and memory (target: 300 MB at 10,000).

Nothing is asserted; the file cache is warm for all (the files were just written, and every
row reads them), so the comparison is like for like.

With ``--floors``, two more figures per size show what analyze's own work costs, whoever does
it (process CPU seconds, each in a fresh process):

- ``imports``: every module analyze's processes import (the top-level entries of one run's
  ``python -X importtime`` over all its processes), each imported once in one process, Python's
  start-up included: with ``c`` cores, about this CPU / ``c`` of a run's wall time goes to its
  imports (spread over processes, some of them forked, a run's imports cost somewhat less: the
  sum of ``-X importtime`` over a 3-session run's processes was 1.2–1.4 s against 1.6–2.3 s);
- ``pf fits`` (when the run wrote ``psychometric.csv``): the psychometric fits of exactly the
  sets in that file, with the bootstrap size analyze was given (``--pf-boot``), its seeds and
  route (compiled climb, numba's load included), and each set's report plot, in one process:
  with ``c`` cores a run cannot write those outputs in less than this CPU / ``c``.

Usage::

    python benchmarks/bench_analysis.py                    # 100 and 1000 sessions
    python benchmarks/bench_analysis.py --with-10000       # and 10000 (~2 GB of logs)
    python benchmarks/bench_analysis.py --sizes 100 --analyze-args=--no-trial-tables
    python benchmarks/bench_analysis.py --baseline-src DIR   # and analyze from DIR/masking_lab
    python benchmarks/bench_analysis.py --sizes 3 --repeat 5 --baseline-src DIR  # fixed cost
    python benchmarks/bench_analysis.py --sizes 3,1000 --floors  # what analyze's work costs
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from timing_setup import adopt_orphans, compile_tree, reap_orphans, tree_console_code

from masking_lab.analysis.pf_table import PF_BOOTSTRAP
from masking_lab.simulation.synthetic_logs import simulate_study

ROOT = Path(__file__).resolve().parents[1]


def build_folder(pool: Path, dest: Path, n_sessions: int) -> int:
    """Copy pool logs under new participant ids until ``n_sessions`` files exist; bytes written."""
    sources = sorted(pool.rglob("*.jsonl"))
    by_participant: dict[str, list[Path]] = {}
    for p in sources:
        by_participant.setdefault(p.parent.name, []).append(p)
    groups = [sorted(v) for _, v in sorted(by_participant.items())]
    written = 0
    k = 0
    while k < n_sessions:
        pid = f"B{k // 3:05d}"
        for src in groups[(k // 3) % len(groups)]:
            if k >= n_sessions:
                break
            head, rest = src.read_bytes().split(b"\n", 1)
            header = json.loads(head)
            header["participant"] = pid
            header["session_id"] = f"{pid}-{header['protocol']['experiment']}"
            data = json.dumps(header, separators=(",", ":")).encode() + b"\n" + rest
            out = dest / pid / f"{pid}_{header['protocol']['experiment']}.jsonl"
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_bytes(data)
            written += len(data)
            k += 1
    return written


FLOORS = ("read", "read+sha", "typed", "json")


def floor(kind: str, data: Path) -> None:
    """In a child process: one floor over every log under ``data`` (see the module docstring)."""
    paths = sorted(data.rglob("*.jsonl"))
    if kind == "typed":
        from concurrent.futures import ProcessPoolExecutor

        chunks = [paths[i : i + 32] for i in range(0, len(paths), 32)]
        with ProcessPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
            sum(pool.map(_typed_chunk, chunks))
        return
    for p in paths:
        raw = p.read_bytes()
        if kind == "read+sha":
            hashlib.sha256(raw).hexdigest()
        elif kind == "json":
            for line in raw.splitlines():
                if line:
                    json.loads(line)


def _typed_chunk(paths: list[Path]) -> int:
    from masking_lab.formats.log_records import ANALYSIS_DECODER

    n = 0
    for p in paths:
        raw = p.read_bytes()
        hashlib.sha256(raw).hexdigest()
        n += len(ANALYSIS_DECODER.decode_lines(raw))
    return n


def run_floor(kind: str, data: Path) -> float:
    """Wall time (s) of one floor as a whole command."""
    t = time.perf_counter()
    subprocess.run([sys.executable, __file__, "--floor", kind, str(data)], check=True)
    return time.perf_counter() - t


def imports_cpu(data: Path, out: Path, extra: list[str]) -> float:
    """CPU seconds of importing, once and in one fresh process, every module that one run of
    ``masking-lab analyze`` imports in any of its processes (``-X importtime``)."""
    code = tree_console_code(ROOT, other_tree=False)
    cmd = [sys.executable, "-X", "importtime", "-c", code, "analyze", str(data), "--out"]
    cmd += [str(out), "--quiet", *extra]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"analyze -X importtime failed: {done.stderr[-2000:]}")
    names: dict[str, None] = {}  # top-level entries (one space after the last bar), in order
    for line in done.stderr.splitlines():
        if line.startswith("import time:") and "|" in line:
            field = line.rsplit("|", 1)[1]
            if field.startswith(" ") and not field.startswith("  ") and field.strip():
                names.setdefault(field.strip(), None)
    names.pop("imported package", None)  # the header line
    load = "import importlib, sys\nfor n in sys.argv[1:]: importlib.import_module(n)"
    env = dict(os.environ, MPLBACKEND="Agg")
    before = os.times()
    subprocess.run([sys.executable, "-c", load, *names], check=True, env=env)
    after = os.times()
    return (after.children_user - before.children_user) + (
        after.children_system - before.children_system
    )


def pf_cpu(data: Path, out: Path, extra: list[str]) -> dict[str, float]:
    """In a fresh process (this file with ``--pf-floor``): CPU seconds of the psychometric fits
    and plots of the sets in ``out``/psychometric.csv, each with the bootstrap size analyze was
    given (``--pf-boot`` in ``extra``; the file's ``n_bootstrap`` counts the refits that stayed
    in bounds, often fewer); ``{}`` without that file."""
    if not (out / "psychometric.csv").is_file():
        return {}
    option = argparse.ArgumentParser(add_help=False)
    option.add_argument("--pf-boot", type=int, default=PF_BOOTSTRAP)
    n_boot = option.parse_known_args(extra)[0].pf_boot
    done = subprocess.run(
        [sys.executable, __file__, "--pf-floor", str(data), str(out), str(n_boot)],
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        raise SystemExit(f"--pf-floor failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout)


def _pf_plot(job: Any, fit: Any) -> Any:
    from masking_lab.analysis.report_lab import pf_plot

    return pf_plot(job.levels_db, job.correct, fit)


def _pf_cpu_here(data: Path, out: Path, n_boot: int) -> dict[str, float]:
    """The child of :func:`pf_cpu`: the jobs as analyze makes them, then the fits timed."""
    import csv

    from threadpoolctl import threadpool_limits

    from masking_lab.analysis.pf_table import fit_all_with, pf_job, pf_seed, set_trials
    from masking_lab.formats.session_log import read_log

    with open(out / "psychometric.csv", encoding="utf-8", newline="") as fh:
        rows = list(csv.DictReader(fh))
    by_log: dict[str, Any] = {}
    jobs = []
    for r in rows:
        if r["log"] not in by_log:
            by_log[r["log"]] = set_trials(read_log(data / r["log"]))
        seed = pf_seed(r["participant"], r["experiment"], r["set_id"], r["log"])
        jobs.append(pf_job(by_log[r["log"]][r["set_id"]], seed, n_boot))
    with threadpool_limits(1, user_api="blas"):  # as analyze fits
        t0 = time.process_time()
        fit_all_with(jobs, _pf_plot, workers=1)
        cpu = time.process_time() - t0
    return {"cpu_s": cpu, "sets": len(jobs), "n_boot": n_boot}


def _pss_kb(pid: int) -> int:
    """Proportional set size (kB) of ``pid``: shared pages split between their sharers."""
    try:
        with open(f"/proc/{pid}/smaps_rollup", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Pss:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return 0


def _tree_rss_kb(root: int) -> int:
    """Memory (kB, PSS) of ``root`` and its descendants, from /proc (0 where unreadable).

    PSS, not RSS: forked workers share the parent's pages, and summing RSS would count them
    once per process.
    """
    children: dict[int, list[int]] = {}
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            with open(f"/proc/{entry.name}/stat", encoding="ascii") as fh:
                ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        children.setdefault(ppid, []).append(int(entry.name))
    total, todo = 0, [root]
    while todo:
        pid = todo.pop()
        total += _pss_kb(pid)
        todo += children.get(pid, [])
    return total


def run_analyze(
    data: Path, out: Path, extra: list[str], src: str | None = None
) -> tuple[float, float, float, float]:
    """Wall time (s) of ``masking-lab analyze`` as a whole command, the largest process's peak
    (MB, RSS from ``wait4``), the sampled process-tree peak (MB, PSS) and the CPU time (s,
    user + system of the process and of every worker, those forked by its workers included,
    which ``timing_setup.reap_orphans`` waits for: on a shared machine the steadier figure).

    ``src``: a folder holding another ``masking_lab`` package (e.g. ``git archive main
    masking_lab | tar -x -C DIR``), imported instead of the installed one (an editable
    install's import hook would win over ``PYTHONPATH``, so it is dropped first).
    """
    # the console script, as a user runs it
    code = tree_console_code(Path(src) if src else ROOT, other_tree=bool(src))
    cmd = [sys.executable, "-c", code, "analyze", str(data), "--out", str(out), "--quiet", *extra]
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    peak = {"kb": 0}
    stop = threading.Event()

    def sample() -> None:
        while not stop.wait(0.05):
            peak["kb"] = max(peak["kb"], _tree_rss_kb(proc.pid))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    err = proc.stderr.read() if proc.stderr else b""
    _, status, usage = os.wait4(proc.pid, 0)
    seconds = time.perf_counter() - t
    stop.set()
    sampler.join()
    orphans = reap_orphans()  # a baseline's unwaited second figure worker (timing_setup)
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"analyze failed: {err.decode(errors='replace')[-2000:]}")
    cpu = usage.ru_utime + usage.ru_stime + orphans
    return seconds, usage.ru_maxrss / 1024, peak["kb"] / 1024, cpu


def _medians(runs: list[tuple[float, ...]]) -> tuple[float, ...]:
    """Each column's median over repeated runs (wall, peak, tree peak, CPU)."""
    return tuple(statistics.median(col) for col in zip(*runs, strict=True))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sizes", default="100,1000", help="session counts, comma-separated")
    ap.add_argument("--with-10000", action="store_true", help="add 10000 sessions (~2 GB)")
    ap.add_argument("--analyze-args", default="", help="extra options for analyze, quoted")
    ap.add_argument(
        "--workdir",
        help="folder for the generated logs and analyze's outputs, kept afterwards (default: a "
        "temp folder, removed)",
    )
    ap.add_argument(
        "--baseline-src",
        metavar="DIR",
        help="also time analyze from the masking_lab package in DIR (before/after in one run)",
    )
    ap.add_argument(
        "--repeat",
        type=int,
        default=1,
        metavar="N",
        help="time analyze (and the baseline, interleaved) N times; print medians",
    )
    ap.add_argument(
        "--floors",
        action="store_true",
        help="also time analyze's imports once and its psychometric fits alone (see above)",
    )
    ap.add_argument("--floor", nargs=2, help=argparse.SUPPRESS)
    ap.add_argument("--pf-floor", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.floor:
        floor(args.floor[0], Path(args.floor[1]))
        return 0
    if args.pf_floor:
        data, out, n_boot = args.pf_floor
        print(json.dumps(_pf_cpu_here(Path(data), Path(out), int(n_boot))))
        return 0
    sizes = sorted(
        {int(s) for s in args.sizes.split(",")} | ({10000} if args.with_10000 else set())
    )
    extra = shlex.split(args.analyze_args)
    adopt_orphans()  # analyze's CPU then includes its second figure worker's
    trees = [Path(__file__).resolve().parents[1]]
    for tree in trees + ([Path(args.baseline_src)] if args.baseline_src else []):
        compile_tree(tree)  # as installed: bytecode present (benchmarks/timing_setup.py)

    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench_analysis_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        t0 = time.perf_counter()
        pool = work / "pool"
        simulate_study(pool, n_participants=10, seed=0)
        print(f"simulated the pool of 30 sessions in {time.perf_counter() - t0:.1f} s", flush=True)
        results = []
        baselines: list[tuple[int, float, float, float, float]] = []
        own: dict[int, dict[str, float]] = {}
        for n in sizes:
            data = work / f"data_{n}"
            size = build_folder(pool, data, n)
            floors = {kind: run_floor(kind, data) for kind in FLOORS}
            runs, base_runs = [], []
            for _ in range(args.repeat):  # interleaved with the baseline: the same load for both
                runs.append(run_analyze(data, work / f"out_{n}", extra))
                if args.baseline_src:
                    base = run_analyze(data, work / f"base_{n}", extra, args.baseline_src)
                    base_runs.append(base)
                    shutil.rmtree(work / f"base_{n}", ignore_errors=True)
            t_an, rss_main, rss_tree, cpu = _medians(runs)
            results.append((n, size, floors, t_an, rss_main, rss_tree, cpu))
            if args.floors:
                own[n] = {"imports": imports_cpu(data, work / f"imports_{n}", extra)}
                shutil.rmtree(work / f"imports_{n}", ignore_errors=True)
                own[n] |= {f"pf_{k}": v for k, v in pf_cpu(data, work / f"out_{n}", extra).items()}
            if args.baseline_src:
                baselines.append((n, *_medians(base_runs)))
            print(
                f"  {n:>6} sessions ({size / 1e6:7.1f} MB): "
                + ", ".join(f"{k} {v:.2f} s" for k, v in floors.items())
                + f", analyze {t_an:.2f} s"
                + (f" (baseline {baselines[-1][1]:.2f} s)" if args.baseline_src else ""),
                flush=True,
            )
            if not args.workdir:  # a --workdir keeps the logs and the last outputs to look at
                shutil.rmtree(data)
                shutil.rmtree(work / f"out_{n}", ignore_errors=True)
        print()
        print(f"analyze options: {args.analyze_args or '(defaults)'}; {os.cpu_count()} CPUs")
        print(
            f"{'sessions':>9} {'MB':>7} {'read s':>7} {'+sha s':>7} {'typed s':>8} {'json s':>7} "
            f"{'analyze s':>10} {'an/typed':>9} {'an/json':>8} {'ms/sess':>8} {'peak MB':>8} "
            f"{'tree MB':>8} {'CPU s':>7}"
        )
        for n, size, f, t_an, rss_main, rss_tree, cpu in results:
            print(
                f"{n:>9} {size / 1e6:>7.1f} {f['read']:>7.2f} {f['read+sha']:>7.2f} "
                f"{f['typed']:>8.2f} {f['json']:>7.2f} {t_an:>10.2f} {t_an / f['typed']:>9.2f} "
                f"{t_an / f['json']:>8.2f} {1000 * t_an / n:>8.2f} {rss_main:>8.0f} "
                f"{rss_tree:>8.0f} {cpu:>7.1f}"
            )
        print(
            "Every time is a whole command (a fresh process). an/typed: analyze over the typed "
            "msgspec decode + SHA-256 in as many processes as analyze uses (target <= 2 at "
            "10,000); an/json: over stdlib json.loads of every line in one process (target <= 1 "
            "at 1,000). peak MB: largest process (wait4, RSS; target <= 300 at 10,000); tree "
            "MB: PSS summed over the process tree, sampled every 50 ms; CPU s: user + system "
            "of analyze and its workers."
        )
        cores = os.cpu_count() or 1
        for n, f in own.items():
            t_an, t_json = next((r[3], r[2]["json"]) for r in results if r[0] == n)
            line = f"analyze's own work at {n} sessions: imports once {f['imports']:.2f} s CPU"
            if "pf_cpu_s" in f:
                spread = f["pf_cpu_s"] / cores
                line += (
                    f"; psychometric fits and plots ({f['pf_sets']:.0f} sets x "
                    f"{f['pf_n_boot']:.0f} bootstrap data sets, one process) {f['pf_cpu_s']:.2f} s "
                    f"CPU = {spread:.2f} s on {cores} cores, {spread / t_json:.2f}x json, "
                    f"{spread / t_an:.2f} of analyze's wall"
                )
            print(line)
        for n, t_base, rss_main, rss_tree, cpu_base in baselines:
            t_an, cpu = next((r[3], r[6]) for r in results if r[0] == n)
            print(
                f"baseline ({args.baseline_src}) at {n} sessions: {t_base:.2f} s, peak "
                f"{rss_main:.0f} MB, tree {rss_tree:.0f} MB, CPU {cpu_base:.1f} s; analyze / "
                f"baseline: wall {t_an / t_base:.2f}, CPU {cpu / cpu_base:.2f}"
            )
    finally:
        if not args.workdir:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
