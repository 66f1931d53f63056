"""Device-layer benchmark: host overhead and onset jitter against the emulator over a real pty.

Run:  python benchmarks/bench_device.py [--trials N] [--virtual-trials N]

Prints, in one run, a baseline (raw pty round trip of one PING through pyserial, no host logic)
and, as ratios to it:

- real time (``masking-lab emulate`` in its own process, hardware-timed PLAY): per-trial host
  overhead = time ``play_trial`` returns after the trial's scheduled end, and onset jitter =
  actual − planned onset (median, p99);
- virtual time: full ``play_trial`` round trip through the pty, with the emulator in its own
  process, in-process (what ``--device emulator`` uses) and the C firmware's host build (what
  the demo uses where a C compiler is found: ``masking_lab.device.host_build``), each with its
  CPU per trial (this process, whose threads include an in-process emulator, plus the device's
  own process), and the projected time and CPU of the demo's ~17,000 trials.

Takes about 40 s. Timings depend on the machine and its load; compare ratios within one run.
"""

from __future__ import annotations

import argparse
import os
import resource
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
from masking_lab.device.host_build import host_firmware
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


def cpu_s(pid: int | None = None) -> float:
    """CPU seconds (user + system) of this process (all its threads), or of process ``pid``."""
    if pid is None:
        r = resource.getrusage(resource.RUSAGE_SELF)
        return r.ru_utime + r.ru_stime
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@contextmanager
def firmware_process(*extra: str):
    """The C firmware's host build (compiled into the cache first if need be): (port, pid)."""
    built = host_firmware()
    if built.program is None:
        raise SystemExit(f"no host build of the C firmware: {built.reason}")
    proc = subprocess.Popen(
        [str(built.program), *extra], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    )
    try:
        yield proc.stdout.readline().strip(), proc.pid
    finally:
        proc.terminate()
        proc.wait(timeout=10)


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
        yield line.split()[-1], proc.pid
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


def virtual_trials(
    dev, clock: VirtualClock, n: int, device_pid: int | None = None
) -> tuple[list[float], float]:
    """Wall time of each of ``n`` trials, and their CPU per trial: this process's and the device
    process's (after 100 trials not timed: the first frames, the caches)."""
    for _ in range(100):
        dev.play_trial(PAPER_PLAN, clock.now() + 0.5)
    out = []
    cpu0 = cpu_s() + (cpu_s(device_pid) if device_pid else 0.0)
    for _ in range(n):
        t0 = time.perf_counter()
        dev.play_trial(PAPER_PLAN, clock.now() + 0.5)
        out.append(time.perf_counter() - t0)
    cpu1 = cpu_s() + (cpu_s(device_pid) if device_pid else 0.0)
    return out, (cpu1 - cpu0) / n


def stats(xs: list[float]) -> tuple[float, float]:
    return float(np.median(xs)), float(np.percentile(xs, 99))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=150, help="real-time trials (0.1 s each)")
    ap.add_argument("--virtual-trials", type=int, default=3000, help="virtual-time trials")
    ap.add_argument("--pings", type=int, default=500)
    args = ap.parse_args()

    with emulator_process() as (port, _):
        base_med, base_p99 = stats(ping_round_trips(port, args.pings))
        overhead, jitter = real_time_trials(port, args.trials)
    with emulator_process("--virtual-time") as (port, pid):
        clock = VirtualClock()
        with SerialDevice(port, default_device_config(), clock) as dev:
            v_proc, cpu_proc = virtual_trials(dev, clock, args.virtual_trials, pid)
    clock = VirtualClock()
    dev = open_device("emulator", None, clock)
    try:
        v_thread, cpu_thread = virtual_trials(dev, clock, args.virtual_trials)
    finally:
        dev.close()
    with firmware_process("--virtual-time") as (port, pid):
        clock = VirtualClock()
        with SerialDevice(port, default_device_config(), clock) as dev:
            v_fw, cpu_fw = virtual_trials(dev, clock, args.virtual_trials, pid)

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
    row("virtual time: play_trial, C firmware host build", v_fw)
    runs = (
        ("emulator process", v_proc, cpu_proc),
        ("in-process emulator", v_thread, cpu_thread),
        ("C firmware host build", v_fw, cpu_fw),
    )
    for name, xs, cpu in runs:
        per = statistics.fmean(xs)
        print(
            f"  virtual time, {name:<21}: {1 / per:6.0f} trials/s, CPU {cpu * 1e3:.3f} ms/trial "
            f"({cpu / cpu_thread:.2f}x the in-process emulator's) -> 17,000 trials in "
            f"{17000 * per:5.1f} s, {17000 * cpu:5.1f} s of CPU"
        )


if __name__ == "__main__":
    main()
