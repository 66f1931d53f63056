"""The fuzz campaign: mutated inputs of every file kind through every command that reads them,
the generators of issue 21's classes (hostile logs and CSVs, schema-driven ground truths, scenes,
calibrations and protocols: :mod:`fuzz_hostile`), hostile boards through a whole ``run``
(:mod:`fuzz_board`), plus hostile serial frames; prints tried /
clean errors / accepted / tracebacks / hangs / non-finite / silently wrong / validate gaps.

Usage (from the repository root)::

    nice .venv/bin/python tests/fuzz/campaign.py --n 5000 --seed 21

``--n`` counts inputs (files, log folders and serial exchanges); each goes through every
command of its kind, each run counted under ``runs``. Findings are printed with the command and
the end of the traceback. The exit status is 1 if there is any finding, or if every input of a
kind was refused (a generator that never gets past the readers tests nothing behind them).
"""

from __future__ import annotations

import argparse
import logging
import random
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fuzz_board import board_trial
from fuzz_corpus import KINDS, RandomPicker, mutate, seed, trial
from fuzz_hostile import HOSTILE_KINDS, hostile_trial
from fuzz_serial import serial_trial

ALL_KINDS = (*KINDS, *HOSTILE_KINDS, "board_hostile")
# Kinds whose inputs are never right to accept (a hostile device ends every run in a fault).
NEVER_ACCEPTED = ("serial", "board_hostile")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=2000, help="mutated inputs (default 2000)")
    parser.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    parser.add_argument("--timeout", type=float, default=20.0, help="hang limit per run, s")
    parser.add_argument(
        "--serial-share", type=float, default=0.1, help="fraction of serial exchanges (0.1)"
    )
    parser.add_argument(
        "--kinds",
        nargs="+",
        default=list(ALL_KINDS),
        choices=ALL_KINDS,
        help="file kinds to mutate (serial frames: --serial-share)",
    )
    parser.add_argument("--save", type=Path, help="folder to keep the inputs of findings in")
    args = parser.parse_args(argv)
    logging.getLogger("masking_lab").setLevel(logging.CRITICAL)  # device faults are expected
    rng = random.Random(args.seed)
    picker = RandomPicker(rng)
    counts: Counter[str] = Counter()
    per_kind: Counter[str] = Counter()
    accepted_per_kind: Counter[str] = Counter()
    findings: list[str] = []
    started = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="masking-fuzz-") as tmp:
        work = Path(tmp) / "work"
        for i in range(args.n):
            if rng.random() < args.serial_share:
                kind = "serial"
                status, detail = serial_trial(picker, timeout_s=args.timeout)
                outcomes = [(status, ("serial",), 1, detail)]
            elif (kind := args.kinds[i % len(args.kinds)]) == "board_hostile":
                data = b""
                done, _ = board_trial(rng, work, args.timeout)
                outcomes = [(o.kind, o.argv, o.code, o.detail) for o in done]
            elif kind in HOSTILE_KINDS:
                data = b""
                done, accepted = hostile_trial(kind, rng, work, args.timeout)
                accepted_per_kind[kind] += accepted
                outcomes = [(o.kind, o.argv, o.code, o.detail) for o in done]
            else:
                data = mutate(seed(kind), picker, rng.randint(1, 3))
                outcomes = [
                    (o.kind, o.argv, o.code, o.detail)
                    for o in trial(kind, data, work, args.timeout)
                ]
                # Accepted: validate (every kind's first command) passed it.
                accepted_per_kind[kind] += outcomes[0][0] == "clean" and outcomes[0][2] == 0
            per_kind[kind] += 1
            counts["tried"] += 1
            # Per input: a finding if any command had one; else a clean error if any command
            # refused it (serial: a DeviceError counts as one); else accepted.
            worst = "accepted"
            for status, cmd, code, detail in outcomes:
                counts["runs"] += 1
                if status != "clean":
                    counts[f"finding_{status}"] += 1
                    worst = status
                    findings.append(f"[{status}] {kind}: {' '.join(cmd)[:120]}\n{detail[-800:]}")
                    if args.save is not None and kind != "serial":
                        args.save.mkdir(parents=True, exist_ok=True)
                        (args.save / f"{i:05d}-{kind}").write_bytes(data)
                elif code and worst == "accepted":
                    worst = "clean_error"
            counts[worst] += 1
            if (i + 1) % 100 == 0:
                so_far = ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))
                print(
                    f"  {i + 1}/{args.n} inputs, {time.monotonic() - started:.0f} s: {so_far}",
                    flush=True,
                )
    for finding in findings[:30]:
        print(finding)
    print(f"kinds: {dict(sorted(per_kind.items()))}")
    accepted = dict(sorted(accepted_per_kind.items()))
    print(f"accepted by validate (serial, board_hostile: not counted): {accepted}")
    print(
        f"tried {counts['tried']} inputs ({counts['runs']} command runs, seed {args.seed}, "
        f"{time.monotonic() - started:.0f} s): clean errors {counts['clean_error']} / accepted "
        f"{counts['accepted']} / tracebacks {counts['traceback']} / hangs {counts['hang']} / "
        f"non-finite outputs {counts['non_finite']} / silently wrong {counts['wrong']} / "
        f"validate gaps {counts['validate_gap']}"
    )
    print(
        "command runs with findings: "
        + ", ".join(f"{k[8:]} {v}" for k, v in sorted(counts.items()) if k.startswith("finding_"))
    )
    refused = [k for k in per_kind if k not in NEVER_ACCEPTED and not accepted_per_kind[k]]
    if refused:
        print(
            f"every input was refused for: {', '.join(sorted(refused))} (the generator tests "
            "nothing behind the readers)"
        )
    return 1 if findings or refused else 0


if __name__ == "__main__":
    sys.exit(main())
