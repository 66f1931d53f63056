"""How long after the last command each device implementation zeroes its outputs.

Starts the Python emulator, the host-built C firmware and the STM32 image under QEMU (each
built with ``make -C firmware`` first), switches a stream on (SETUP 0.4 V), goes quiet, and
prints, per implementation: the watchdog period it reports (HELLO ``wd_ms``), the quiet time
the device measured when it zeroed (``WATCHDOG quiet_ms``, device clock) and when the host saw
the event (host clock). Run: ``.venv/bin/python benchmarks/watchdog_latency.py [N]``.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import pytest  # firmware_support skips through pytest when a tool is missing
from firmware_support import TARGETS, Link, start


def measure(target: str, repeats: int) -> str:
    try:
        device = start(target)
    except pytest.skip.Exception as exc:
        return f"{target:9s} skipped: {exc}"
    try:
        link = Link(device.port)
        wd_ms = link.call("HELLO").number("wd_ms")
        quiet, seen = [], []
        for _ in range(repeats):
            sent = time.monotonic()
            assert link.call("SETUP", ch="EV", car=270.0, env=0.0, amp=0.4).ok
            trip = link.event("WATCHDOG", timeout=wd_ms / 1000 * 4 + 2)
            seen.append((time.monotonic() - sent) * 1000)
            quiet.append(trip.number("quiet_ms"))
            diag = link.call("DIAG")
            assert diag.number("ev") == 0 and diag.number("dac_ev") == 0, diag
        link.close()
    finally:
        device.close()
    return (
        f"{target:9s} wd_ms={wd_ms:5.0f}  device quiet_ms at zeroing: median "
        f"{statistics.median(quiet):6.1f} max {max(quiet):6.1f}  "
        f"(host saw WATCHDOG after median {statistics.median(seen):6.1f} ms, n={repeats})"
    )


def main() -> None:
    repeats = int(sys.argv[1]) if len(sys.argv) > 1 else 5
    for target in TARGETS:
        print(measure(target, repeats), flush=True)


if __name__ == "__main__":
    main()
