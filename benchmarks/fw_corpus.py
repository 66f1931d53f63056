"""The adversarial frame corpus at scale: 100,000 frames per run, and the figures.

Sends the seeded corpus of ``tests/adversarial_corpus.py`` to

- ``vt``: the Python emulator and the host build under ASan+UBSan, in virtual time, every
  accepted trial rendered sample by sample through the output stage (1 kHz);
- ``rt``: the STM32 image under QEMU, the sanitizer host build and the emulator, in real
  time, configured from QEMU's HELLO;

and prints, per run: frames, answers by kind, mismatches (the first one in full), the largest
sample each implementation output against its limit, trials rendered, the frames at the
output's linear range (HELLO ``lin``) at the deepest attenuator steps, the longest wait for a
byte from each implementation, sanitizer reports and frames per second. The ``rt`` run uses
the QEMU image built with 0/20/40 dB steps (``tests/firmware_support.py``, ``qemu-att``).
Builds the firmware first (make). Run:

    .venv/bin/python benchmarks/fw_corpus.py [--frames 100000] [--seed 23] [--runs vt,rt]
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from adversarial_corpus import CorpusRun, real_time_run, virtual_time_run


def report(label: str, run: CorpusRun) -> bool:
    first = next(iter(run.results.values()))
    kinds = Counter(first.answers)
    sanitizer = run.stderr.count("runtime error") + run.stderr.count("Sanitizer")
    print(f"== {label}: {run.frames} frames to {', '.join(run.results)}")
    print("   answers: " + ", ".join(f"{k} {v}" for k, v in sorted(kinds.items())))
    print(f"   mismatches: {'0' if run.mismatch is None else 'FIRST ' + run.mismatch}")
    for r in run.results.values():
        print(
            f"   {r.name:9s} peak EV {r.peak_v['EV']:.6f} V / limit {run.limits[0]:g} V, "
            f"MV {r.peak_v['MV']:.6f} V / {run.limits[1]:g} V; events "
            + ", ".join(f"{k} {v}" for k, v in sorted(r.side_events.items()))
        )
    print(f"   frames at the linear range's edge (deep attenuator steps): {run.linear_frames}")
    print(
        "   longest silence within a batch: "
        + ", ".join(f"{r.name} {r.longest_silence_s:.2f} s" for r in run.results.values())
    )
    print(f"   sanitizer reports: {sanitizer}")
    print(f"   {run.seconds:.1f} s, {run.frames / run.seconds:.0f} frames/s per implementation")
    over = any(
        r.peak_v["EV"] > run.limits[0] or r.peak_v["MV"] > run.limits[1]
        for r in run.results.values()
    )
    return run.mismatch is None and sanitizer == 0 and not over


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=23)
    ap.add_argument("--runs", default="vt,rt", help="comma-separated: vt, rt")
    args = ap.parse_args()
    ok = True
    for name in args.runs.split(","):
        if name == "vt":
            ok &= report("virtual time", virtual_time_run(args.frames, args.seed))
        elif name == "rt":
            ok &= report("real time", real_time_run(args.frames, args.seed))
        else:
            ap.error(f"unknown run {name!r}: choose vt, rt")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
