"""Instruction counts of the worst frames on the STM32 image under QEMU ``-icount shift=0``.

With ``-icount shift=0`` QEMU's virtual clock advances exactly 1 ns per guest instruction, so
the device clock (µs) that the firmware core reads around its own work measures instructions:
1 µs = 1000 instructions. DIAG reports, since the previous DIAG, the longest command handler
(``hmax_us``), the longest ``fw_poll`` (``pmax_us``) and the longest refill of the output
stage in one main-loop iteration (``omax_us``: synthesis of every sample due). One iteration
is at most handler + fw_poll + refill. Deterministic: the same image gives the same
counts, however loaded the host (±1000 instructions: the clock's 1 µs resolution).

The budget: no handler or main-loop iteration over 5 ms at 168 MHz = 840,000 instructions.
Run: ``.venv/bin/python benchmarks/fw_icount.py`` (builds the QEMU image first).
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from icount_support import BUDGET, FRAMES, PADDED, Qemu, measure


def main() -> int:
    qemu = Qemu()
    worst = 0.0
    try:
        print(f"QEMU netduinoplus2, -icount shift=0 (1 instruction = 1 ns); budget {BUDGET:,}")
        head = f"{'frame':38s} {'reply':>5s} {'handler':>10s} {'fw_poll':>10s}"
        print(f"{head} {'refill':>10s} {'samples':>8s}")
        for label, (name, fields) in FRAMES.items():
            m = measure(qemu, name, fields, pad=label == PADDED)
            worst = max(worst, m["handler"] + m["poll"] + m["refill"])
            print(
                f"{label:38s} {'OK' if m['ok'] else 'ERR':>5s} {m['handler']:>10,.0f} "
                f"{m['poll']:>10,.0f} {m['refill']:>10,.0f} {m['samples']:>8,.0f}"
            )
    finally:
        qemu.close()
    share = worst / BUDGET
    print(f"worst handler + fw_poll + refill: {worst:,.0f} instructions = {share:.1%} of budget")
    return 0 if worst <= BUDGET else 1


if __name__ == "__main__":
    sys.exit(main())
