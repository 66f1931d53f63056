"""How `masking-lab analyze` compares with just reading its logs, and how it grows.

Simulates a ten-participant study once (baseline, experiment I, experiment II: 30 real session
logs written by ``masking_lab.simulation.synthetic_logs``), then builds folders of 100, 1,000
(and with ``--with-10000`` 10,000) sessions by copying those logs under new participant ids
(only the header line changes, so every file is a complete, realistic session of 4 or 15
staircases). For each folder, in one run:

- ``read bytes``: reading every file's bytes (the floor: no parsing at all);
- ``json.loads``: reading every file and ``json.loads`` of every line (stdlib, into dicts);
- ``analyze``: ``masking-lab analyze DATA --out OUT`` with its default options, run by the CLI's
  ``main`` in a child process after a warm-up analysis of the pool (imports and font caches are
  one-time costs, not per-session ones), with that process tree's peak memory (largest process
  from ``wait4``, and the sum over the tree sampled every 50 ms, workers included).

Prints times, the ratios analyze / read-bytes and analyze / json.loads (targets: 10,000
sessions in at most 15 s and 400 MB; at 1,000 sessions at most 0.6 x json.loads), and the
growth per session. Nothing is asserted; the file cache is warm for all three (files were
just written), so the comparison is like for like.

Usage::

    python benchmarks/bench_analysis.py                    # 100 and 1000 sessions
    python benchmarks/bench_analysis.py --with-10000       # and 10000 (~2 GB of logs)
    python benchmarks/bench_analysis.py --sizes 100 --analyze-args "--figures all"
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from masking_lab.simulation.synthetic_logs import simulate_study


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


def time_read_bytes(paths: list[Path]) -> float:
    """Seconds (s) to read every file's bytes."""
    t = time.perf_counter()
    for p in paths:
        p.read_bytes()
    return time.perf_counter() - t


def time_json_loads(paths: list[Path]) -> float:
    """Seconds (s) to read every file and ``json.loads`` every line (stdlib)."""
    t = time.perf_counter()
    for p in paths:
        for line in p.read_bytes().splitlines():
            if line:
                json.loads(line)
    return time.perf_counter() - t


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


def child(data: Path, out: Path, pool: Path, extra: list[str]) -> None:
    """In the child process: warm up on the pool, then time ``analyze`` of ``data``."""
    from masking_lab.commands.cli import main as cli_main

    # One-time costs (imports, matplotlib's font cache) are not per-session costs.
    cli_main(["analyze", str(pool), "--out", str(out.parent / "warmup"), "--quiet", *extra])
    t = time.perf_counter()
    code = cli_main(["analyze", str(data), "--out", str(out), "--quiet", *extra])
    print(json.dumps({"seconds": time.perf_counter() - t, "exit": code}), flush=True)


def run_analyze(data: Path, out: Path, pool: Path, extra: list[str]) -> tuple[float, float, float]:
    """Warm analyze time (s), largest process peak (MB), sampled process-tree peak (MB).

    The analysis runs in a child process (``--child``), so its memory is its own.
    """
    cmd = [sys.executable, __file__, "--child", str(data), str(out), str(pool), shlex.join(extra)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    peak = {"kb": 0}
    stop = threading.Event()

    def sample() -> None:
        while not stop.wait(0.05):
            peak["kb"] = max(peak["kb"], _tree_rss_kb(proc.pid))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    stdout = proc.stdout.read() if proc.stdout else b""
    _, status, usage = os.wait4(proc.pid, 0)
    stop.set()
    sampler.join()
    err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"analyze failed: {err[-2000:]}")
    result = json.loads(stdout.decode().strip().splitlines()[-1])
    if result["exit"] != 0:
        raise SystemExit(f"analyze exited {result['exit']}: {err[-2000:]}")
    return result["seconds"], usage.ru_maxrss / 1024, peak["kb"] / 1024


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sizes", default="100,1000", help="session counts, comma-separated")
    ap.add_argument("--with-10000", action="store_true", help="add 10000 sessions (~2 GB)")
    ap.add_argument("--analyze-args", default="", help="extra options for analyze, quoted")
    ap.add_argument("--workdir", help="folder for the generated logs (default: a temp folder)")
    ap.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        data, out, pool, extra_text = args.child
        child(Path(data), Path(out), Path(pool), shlex.split(extra_text))
        return 0
    sizes = sorted(
        {int(s) for s in args.sizes.split(",")} | ({10000} if args.with_10000 else set())
    )
    extra = shlex.split(args.analyze_args)

    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench_analysis_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        t0 = time.perf_counter()
        pool = work / "pool"
        simulate_study(pool, n_participants=10, seed=0)
        print(f"simulated the pool of 30 sessions in {time.perf_counter() - t0:.1f} s", flush=True)
        results = []
        for n in sizes:
            data = work / f"data_{n}"
            size = build_folder(pool, data, n)
            paths = sorted(data.rglob("*.jsonl"))
            t_bytes = time_read_bytes(paths)
            t_json = time_json_loads(paths)
            t_an, rss_main, rss_tree = run_analyze(data, work / f"out_{n}", pool, extra)
            results.append((n, size, t_bytes, t_json, t_an, rss_main, rss_tree))
            print(
                f"  {n:>6} sessions ({size / 1e6:7.1f} MB): read {t_bytes:6.2f} s, "
                f"json.loads {t_json:6.2f} s, analyze {t_an:6.2f} s",
                flush=True,
            )
            shutil.rmtree(data)
            shutil.rmtree(work / f"out_{n}", ignore_errors=True)
            shutil.rmtree(work / "warmup", ignore_errors=True)
        print()
        print(f"analyze options: {args.analyze_args or '(defaults)'}; {os.cpu_count()} CPUs")
        print(
            f"{'sessions':>9} {'MB':>7} {'read s':>7} {'json s':>7} {'analyze s':>10} "
            f"{'an/read':>8} {'an/json':>8} {'ms/sess':>8} {'peak MB':>8} {'tree MB':>8}"
        )
        for n, size, t_bytes, t_json, t_an, rss_main, rss_tree in results:
            print(
                f"{n:>9} {size / 1e6:>7.1f} {t_bytes:>7.2f} {t_json:>7.2f} {t_an:>10.2f} "
                f"{t_an / t_bytes:>8.1f} {t_an / t_json:>8.2f} {1000 * t_an / n:>8.2f} "
                f"{rss_main:>8.0f} {rss_tree:>8.0f}"
            )
        print(
            "an/read, an/json: analyze time over the time to read the bytes, and over stdlib "
            "json.loads of every line (same files, same run). peak MB: largest process "
            "(wait4, RSS); tree MB: PSS summed over the process tree, sampled every 50 ms."
        )
    finally:
        if not args.workdir:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
