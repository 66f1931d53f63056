"""The bring-up self-test of a board (``masking-lab device check``).

Run on a rig with nobody touching it: it plays a silent trial (0 V) and, to measure the
watchdog, streams a small amplitude (:data:`WATCHDOG_PROBE_V`, at most the channel's limit) on
EV until the board's watchdog zeroes it. Each check gives ok, a warning (reported, not a
failure) or a failure:

- handshake: protocol 2, firmware >= fw-2.0.0, build hash, model and serial number;
- clock source (``hsi`` is the ±1 % fallback: a warning) and reset cause of this boot (a
  ``watchdog`` or ``brownout`` reset is a warning);
- limits (the board's and the rig config's; the stricter is in force) and the converter (bits,
  full scale, attenuator steps, checked against the rig config);
- interlock state (open fails: nothing can play);
- PING round trip (median and worst of 20, ms) and a silent PLAY (command to DONE, and the
  onsets' lateness in device time, µs);
- watchdog: trip time measured (a stream is set up, the host goes quiet, the WATCHDOG event's
  ``quiet_ms`` must lie within the period and 10 % (at least 50 ms) above it).
"""

from __future__ import annotations

import contextlib
import statistics
import time
from dataclasses import dataclass

from masking_lab.core.clock import RealClock, VirtualClock
from masking_lab.core.errors import DeviceError, DeviceFaultError, DeviceTimeModeError
from masking_lab.core.stimulus import parse_stimulus
from masking_lab.core.trial import TrialPlan
from masking_lab.device import protocol as proto
from masking_lab.device.config import DeviceConfig
from masking_lab.device.serial_device import SerialDevice

WATCHDOG_PROBE_V = 0.01
PINGS = 20


@dataclass(frozen=True)
class Check:
    """One line of the report: ``status`` is ``"ok"``, ``"warn"`` or ``"FAIL"``."""

    name: str
    status: str
    detail: str


def open_board(port: str, config: DeviceConfig) -> SerialDevice:
    """Open ``port`` with the clock its board runs on (a virtual-time emulator needs one)."""
    try:
        return SerialDevice(port, config, RealClock(), backend="serial")
    except DeviceTimeModeError as exc:
        if not exc.device_virtual:
            raise
        return SerialDevice(port, config, VirtualClock(), backend="serial")


def run_checks(port: str, config: DeviceConfig, *, watchdog: bool = True) -> list[Check]:
    """Run the self-test on ``port``; never raises for a device fault (it becomes a FAIL).

    Parameters
    ----------
    port : str
        Serial port of the board.
    config : DeviceConfig
        The rig config (limits, converter, serial settings).
    watchdog : bool
        Measure the watchdog trip time (streams :data:`WATCHDOG_PROBE_V` V on EV).
    """
    try:
        dev = open_board(port, config)
    except DeviceFaultError as exc:
        name = "interlock" if getattr(exc, "kind", "") == "interlock" else "handshake"
        return [Check(name, "FAIL", str(exc))]
    except DeviceError as exc:
        return [Check("handshake", "FAIL", str(exc))]
    checks: list[Check] = []
    try:
        checks += _identity_checks(dev)
        for step in (_ping_check, _play_check, *([_watchdog_check] if watchdog else [])):
            try:
                checks.append(step(dev))
            except DeviceError as exc:
                name = step.__name__.strip("_").replace("_check", "")
                checks.append(Check(name, "FAIL", str(exc)))
    finally:
        with contextlib.suppress(DeviceError):
            dev.close()
    return checks


def _identity_checks(dev: SerialDevice) -> list[Check]:
    hello = dev.hello
    assert hello is not None
    out = [
        Check(
            "handshake",
            "ok",
            f"protocol {hello.version}, firmware {hello.firmware}, build {hello.build}, "
            f"model {hello.model}, serial {hello.serial_number}"
            + (", virtual time (emulator)" if hello.virtual else ""),
        )
    ]
    clk = hello.clock_source
    out.append(
        Check(
            "clock source",
            "warn" if clk == "hsi" else "ok",
            clk
            + (": the 8 MHz HSE did not start; running on the ±1 % HSI" if clk == "hsi" else ""),
        )
    )
    rst = hello.reset_cause
    bad = rst in ("watchdog", "brownout")
    out.append(
        Check(
            "reset cause",
            "warn" if bad else "ok",
            rst + (": check the power supply and the firmware's main loop" if bad else ""),
        )
    )
    limits = ", ".join(
        f"{ch} {hello.max_v[ch]:g} V (config {dev.config.limits.max_drive_v[ch]:g} V, in force "
        f"{dev.identity.limits.max_drive_v[ch]:g} V)"
        for ch in ("EV", "MV")
    )
    out.append(Check("limits", "ok", limits))
    conv = ", ".join(
        f"{ch} {c.bits} bits, {c.full_scale_v:g} V full scale" for ch, c in dev.converters.items()
    )
    steps = "/".join(f"{s:g}" for s in hello.attenuation_db)
    source = "matches the rig config" if dev.config.converters else "rig config gives none"
    out.append(
        Check(
            "converter",
            "ok" if dev.config.converters else "warn",
            f"{conv}; attenuator steps {steps} dB ({source})",
        )
    )
    out.append(Check("interlock", "ok", "closed"))
    return out


def _ping_check(dev: SerialDevice) -> Check:
    rtts = []
    for _ in range(PINGS):
        t0 = time.perf_counter()
        dev.keepalive()
        rtts.append((time.perf_counter() - t0) * 1e3)
    return Check(
        "PING latency",
        "ok",
        f"round trip median {statistics.median(rtts):.2f} ms, worst {max(rtts):.2f} ms "
        f"({PINGS} PINGs)",
    )


def _play_check(dev: SerialDevice) -> Check:
    plan = TrialPlan(
        target=parse_stimulus("EV270"),
        target_amplitude_v=0.0,  # silent: the timing path without an output
        target_interval=1,
        masker=None,
        masker_amplitude_v=0.0,
        stimulus_s=0.02,
        gap_s=0.01,
        lead_in_s=0.05,
    )
    t0 = time.perf_counter()
    result = dev.play_trial(plan, dev.clock.now() + 0.05)
    took_ms = (time.perf_counter() - t0) * 1e3
    late_us = result.extra.get("device_late_us", [])
    worst = f"{max(late_us):.0f} µs" if late_us else "n/a"
    return Check(
        "PLAY latency",
        "ok",
        f"silent {plan.duration_s * 1e3:.0f} ms trial: PLAY to DONE {took_ms:.1f} ms; onsets "
        f"late by at most {worst} (device time)",
    )


def _watchdog_check(dev: SerialDevice) -> Check:
    period_ms = round(dev.watchdog_s * 1000)
    if period_ms == 0:
        return Check("watchdog", "warn", "the board reports no watchdog (wd_ms=0)")
    amp = min(WATCHDOG_PROBE_V, dev.identity.limits.max_drive_v["EV"])
    dev.set_amplitude("EV", parse_stimulus("EV270"), amp)
    sent = time.perf_counter()
    give_up = time.monotonic() + dev.watchdog_s * 4 + 2.0
    trip: proto.Frame | None = None
    with dev._lock:  # nothing else talks to the board: read its events directly
        while trip is None and time.monotonic() < give_up:
            frame = dev._read_frame(give_up, "WATCHDOG", quiet=True)
            if frame is not None and frame.kind == "event" and frame.name == "WATCHDOG":
                trip = frame
    if trip is None:
        dev.stop()
        return Check(
            "watchdog",
            "FAIL",
            f"no WATCHDOG within {dev.watchdog_s * 4 + 2:.1f} s of a quiet host (period "
            f"{period_ms} ms): the output stayed on; check the firmware",
        )
    host_ms = (time.perf_counter() - sent) * 1e3
    quiet_ms = trip.integer("quiet_ms", 0, 10**9) if "quiet_ms" in trip.fields else -1
    slack = max(50, period_ms // 10)
    ok = period_ms <= quiet_ms <= period_ms + slack
    dev._streams.clear()
    dev.stop()
    return Check(
        "watchdog",
        "ok" if ok else "FAIL",
        f"period {period_ms} ms; tripped after quiet_ms={quiet_ms} (allowed {period_ms}.."
        f"{period_ms + slack}); the host saw it {host_ms:.0f} ms after the last command",
    )


def format_report(port: str, checks: list[Check]) -> str:
    """The report ``masking-lab device check`` prints; the last line gives the verdict.

    Examples
    --------
    >>> print(format_report("/dev/ttyACM0", [Check("interlock", "ok", "closed")]))
    masking-lab device check /dev/ttyACM0
      ok    interlock      closed
    all 1 checks passed
    """
    lines = [f"masking-lab device check {port}"]
    lines += [f"  {c.status:<5} {c.name:<14} {c.detail}" for c in checks]
    failed = [c for c in checks if c.status == "FAIL"]
    warned = [c for c in checks if c.status == "warn"]
    if failed:
        lines.append(
            f"FAILED: {len(failed)} of {len(checks)} checks ({', '.join(c.name for c in failed)})"
        )
    else:
        note = f" ({len(warned)} warning(s))" if warned else ""
        lines.append(f"all {len(checks)} checks passed{note}")
    return "\n".join(lines)
