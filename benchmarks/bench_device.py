"""Device-layer benchmark: host overhead and onset jitter against the emulator over a real pty.

Run:  python benchmarks/bench_device.py [--trials N] [--virtual-trials N]

Prints, in one run, a baseline (raw pty round trip of one PING through pyserial, no host logic)
and, as ratios to it:

- real time (``masking-lab emulate`` in its own process, hardware-timed PLAY): per-trial host
  overhead = time ``play_trial`` returns after the trial's scheduled end, and onset jitter =
  actual − planned onset (median, p99);
- virtual time: full ``play_trial`` round trip through the pty, with the emulator in its own
  process and in-process (what ``--device emulator`` uses), and the projected time of the
  demo's ~17,000 trials.

Takes about 30 s. Timings depend on the machine and its load; compare ratios within one run.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from contextlib import contextmanager

import numpy as np
import serial

from masking_lab.core.clock import RealClock, VirtualClock
from masking_lab.core.stimulus import parse_stimulus
from masking_lab.core.trial import TrialPlan
from masking_lab.device import protocol as proto
from masking_lab.device.config import default_device_config
from masking_lab.device.registry import open_device
from masking_lab.device.serial_device import SerialDevice

PLAN = TrialPlan(
    target=parse_stimulus("EV270"),
    target_amplitude_v=0.5,
    target_interval=2,
    masker=parse_stimulus("MV120"),
    masker_amplitude_v=0.3,
    stimulus_s=0.02,  # short intervals keep the benchmark short; timing logic is the same
    gap_s=0.01,
    lead_in_s=0.02,
)
PAPER_PLAN = TrialPlan(
    PLAN.target, 0.5, 2, PLAN.masker, 0.3, stimulus_s=1.8, gap_s=0.6, lead_in_s=1.2
)


@contextmanager
def emulator_process(*extra: str):
    proc = subprocess.Popen(
        [sys.executable, "-m", "masking_lab.commands.cli", "emulate", *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        line = proc.stdout.readline()
        if not line.startswith("emulator listening on "):
            raise SystemExit(f"emulator did not start: {line!r}")
        yield line.split()[-1]
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def ping_round_trips(port: str, n: int) -> list[float]:
    """Raw baseline: one framed PING and its OK through pyserial, no SerialDevice logic."""
    out = []
    with serial.Serial(port, timeout=1.0) as ser:
        ser.write(proto.encode_command(1, "HELLO"))
        ser.readline()
        for k in range(n):
            seq = 2 + k % 60000
            t0 = time.perf_counter()
            ser.write(proto.encode_command(seq, "PING"))
            reply = ser.readline()
            out.append(time.perf_counter() - t0)
            if proto.decode(reply).seq != seq:
                raise SystemExit("baseline: reply out of order")
    return out


def real_time_trials(port: str, n: int) -> tuple[list[float], list[float]]:
    clock = RealClock()
    overhead, jitter = [], []
    with SerialDevice(port, default_device_config(), clock) as dev:
        for _ in range(n):
            start = clock.now() + 0.005
            result = dev.play_trial(PLAN, start)
            overhead.append(clock.now() - (start + PLAN.duration_s))
            jitter += [
                a - p for a, p in zip(result.actual_onsets_s, result.planned_onsets_s, strict=True)
            ]
    return overhead, jitter


def virtual_trials(dev, clock: VirtualClock, n: int) -> list[float]:
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        dev.play_trial(PAPER_PLAN, clock.now() + 0.5)
        out.append(time.perf_counter() - t0)
    return out


def stats(xs: list[float]) -> tuple[float, float]:
    return float(np.median(xs)), float(np.percentile(xs, 99))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=150, help="real-time trials (0.1 s each)")
    ap.add_argument("--virtual-trials", type=int, default=3000, help="virtual-time trials")
    ap.add_argument("--pings", type=int, default=500)
    args = ap.parse_args()

    with emulator_process() as port:
        base_med, base_p99 = stats(ping_round_trips(port, args.pings))
        overhead, jitter = real_time_trials(port, args.trials)
    with emulator_process("--virtual-time") as port:
        clock = VirtualClock()
        with SerialDevice(port, default_device_config(), clock) as dev:
            v_proc = virtual_trials(dev, clock, args.virtual_trials)
    clock = VirtualClock()
    dev = open_device("emulator", None, clock)
    try:
        v_thread = virtual_trials(dev, clock, args.virtual_trials)
    finally:
        dev.close()

    def row(name: str, xs: list[float]) -> None:
        med, p99 = stats(xs)
        print(
            f"{name:<44} median {med * 1e3:8.3f} ms ({med / base_med:6.1f}x)   "
            f"p99 {p99 * 1e3:8.3f} ms ({p99 / base_p99:6.1f}x)"
        )

    print(f"device benchmark: emulator over a pseudo-terminal, {time.strftime('%Y-%m-%d %H:%M')}")
    print(
        f"{'baseline: raw PING round trip (pyserial)':<44} median {base_med * 1e3:8.3f} ms "
        f"         p99 {base_p99 * 1e3:8.3f} ms"
    )
    row(f"real time: host overhead after trial end (n={args.trials})", overhead)
    row(f"real time: onset jitter actual-planned (n={len(jitter)})", jitter)
    abs_j = [abs(x) for x in jitter]
    print(
        f"{'':<44} |jitter| max {max(abs_j) * 1e3:.3f} ms, "
        f"mean {statistics.fmean(jitter) * 1e3:+.3f} ms"
    )
    row("virtual time: play_trial, emulator process", v_proc)
    row("virtual time: play_trial, in-process emulator", v_thread)
    for name, xs in (("process", v_proc), ("in-process", v_thread)):
        per = statistics.fmean(xs)
        print(
            f"  virtual time, {name}: {1 / per:7.0f} trials/s -> 17,000 trials in "
            f"{17000 * per:5.1f} s of device time"
        )


if __name__ == "__main__":
    main()
