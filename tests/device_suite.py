"""The device suite: behavioural checks at the :class:`~masking_lab.device.base.Device` level,
and the targets they run on (no tests here; ``tests/test_device_suite.py`` runs them).

In the style of scikit-learn's ``parametrize_with_checks``: :data:`CHECKS` is a list of plain
functions ``check(target, device)``, and every target is a registered back-end behind a
:class:`Target` that opens a fresh device and lets a check see and provoke what the Device
interface cannot (what the outputs play now, a quiet host, a fault). Each check reads the
back-end's declared :class:`~masking_lab.device.registry.Capabilities` and asserts the claim
either way: a stated absence is checked like a presence, never skipped.

Targets: ``sim`` (in process), ``emulator`` (the Python twin of the firmware on a pty, virtual
time), ``host`` (the C firmware built for the host, on a pty, virtual time), ``qemu`` (the STM32
image under QEMU, real time) and ``nidaq-standin`` (the NI back-end against the recording
STAND-IN of ``nidaqmx`` in tests/nidaqmx_standin: not NI's driver, not hardware). The wire
targets' frames are checked by tests/test_device_conformance.py; this suite checks what a
session sees through the Device interface. Waits are on device events or bounded loops of
round trips; the only wall-clock bound is a guard against a hung peer (:data:`HANG_GUARD_S`).
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from typing import Any

import pytest
from firmware_support import rig_config, start

from masking_lab.core.clock import Clock, RealClock, VirtualClock
from masking_lab.core.errors import DeviceError, SafetyLimitError
from masking_lab.core.stimulus import Stimulus
from masking_lab.core.trial import TrialPlan
from masking_lab.device import registry
from masking_lab.device.base import Device
from masking_lab.device.config import default_device_config
from masking_lab.device.registry import Capabilities, open_device

HANG_GUARD_S = 30.0  # a peer that never answers fails the check after this long, s
MV120 = Stimulus("MV", 120.0)


def short_plan(target_v: float = 0.5, masker_v: float = 0.3) -> TrialPlan:
    """EV270 in interval 2 under MV120; 50 ms stimuli, 30 ms gaps, 20 ms lead-in (0.21 s)."""
    return TrialPlan(
        target=Stimulus("EV", 270.0),
        target_amplitude_v=target_v,
        target_interval=2,
        masker=MV120,
        masker_amplitude_v=masker_v,
        stimulus_s=0.05,
        gap_s=0.03,
        lead_in_s=0.02,
    )


class Target:
    """One back-end as the suite drives it. Subclasses override what they can do.

    ``backend`` names the registry row whose capabilities the target answers for;
    ``late_s`` is how late a reported onset may be (device clock, s).
    """

    name = ""
    backend = ""
    late_s = 0.02
    real_time = False  # trials take wall time, so a stop can land mid-trial

    @property
    def capabilities(self) -> Capabilities:
        return registry.BACKENDS[self.backend].capabilities

    def open(self) -> Device:
        raise NotImplementedError

    def outputs(self, device: Any) -> dict[str, float]:
        """Peak amplitude each channel plays now, V (as the device or its model reports it)."""
        raise NotImplementedError

    def go_quiet(self, device: Any) -> None:
        """Say nothing to the device until its watchdog has acted (or, with none, for long)."""
        raise NotImplementedError

    def fault(self, device: Any) -> None:
        """Provoke a fault the next call meets (only where the back-end declares faults)."""
        raise NotImplementedError

    def clear_fault(self, device: Any) -> None:
        """End what :meth:`fault` provoked."""

    @contextlib.contextmanager
    def mid_trial(self, device: Any, action: Callable[[], None]) -> Iterator[None]:
        """Run ``action`` while the next trial plays (real-time targets only)."""
        raise NotImplementedError
        yield

    def close(self) -> None:
        """Release what the target started (a firmware process)."""


class SimTarget(Target):
    name = backend = "sim"

    def open(self) -> Device:
        return open_device("sim", rig_config(), VirtualClock())

    def outputs(self, device: Any) -> dict[str, float]:
        return device.outputs()

    def go_quiet(self, device: Any) -> None:
        # far beyond any watchdog period, in virtual time
        device.clock.sleep_until(device.clock.now() + 60.0)


class WireTarget(Target):
    """A firmware implementation reached by SerialDevice over a pty (emulator, host, QEMU)."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.backend = "emulator" if name == "emulator" else "serial"
        self.virtual = name != "qemu"  # QEMU runs the image in real time (-icount)
        self.real_time = not self.virtual
        self.late_s = 0.25 if name == "qemu" else 0.02
        # the emulator is opened fresh through the registry; the builds run once per module
        # QEMU: the image built with the rig's limits and a 2 s watchdog ("qemu-att"): under
        # -icount a descheduled QEMU's clock jumps on resuming, which can trip 500 ms mid-trial
        build = "qemu-att" if name == "qemu" else name
        self.process = None if name == "emulator" else start(build, virtual_time=self.virtual)

    def open(self) -> Device:
        clock: Clock = VirtualClock() if self.virtual else RealClock()
        spec = "emulator" if self.process is None else f"serial:{self.process.port}"
        return open_device(spec, rig_config(), clock)

    def outputs(self, device: Any) -> dict[str, float]:
        diag = device._command("DIAG", events="record")
        return {"EV": diag.number("ev"), "MV": diag.number("mv")}

    def go_quiet(self, device: Any) -> None:
        # read without sending (a command would feed the watchdog) until the device says it
        # tripped; the event is then handled as the device handles any event
        deadline = time.monotonic() + HANG_GUARD_S
        while True:
            frame = device._read_frame(deadline, "WATCHDOG event")
            device._dispatch_unsolicited(frame, events="record")
            if frame.kind == "event" and frame.name == "WATCHDOG":
                return

    @contextlib.contextmanager
    def mid_trial(self, device: Any, action: Callable[[], None]) -> Iterator[None]:
        # the trial holds the link, so the action runs from another thread, as a signal
        # handler's stop() does; a 3 s trial leaves seconds of slack on a loaded host
        worker = threading.Timer(0.3, action)
        worker.start()
        try:
            yield
        finally:
            worker.join()

    def _interlock(self, device: Any, is_open: bool) -> None:
        if self.process is None:
            device.emulator.set_interlock(is_open)
        else:
            self.process.set_interlock(is_open)
        want = "open" if is_open else "closed"
        for _ in range(5000):  # round trips until the device reports it
            if device._command("DIAG", events="record").fields["il"] == want:
                return
        pytest.fail(f"{self.name} never reported its interlock {want}")

    def fault(self, device: Any) -> None:
        self._interlock(device, True)

    def clear_fault(self, device: Any) -> None:
        self._interlock(device, False)

    def close(self) -> None:
        if self.process is not None:
            self.process.close()


class NidaqStandinTarget(Target):
    """The NI back-end on the nidaqmx STAND-IN (a model of the driver, not hardware)."""

    name, backend = "nidaq-standin", "nidaq"
    real_time = True
    late_s = 0.25  # onsets from the host clock at start(): as late as the host's scheduler

    def __init__(self) -> None:
        import nidaqmx_standin

        self._patch = pytest.MonkeyPatch()
        self._standin = nidaqmx_standin
        self.state = nidaqmx_standin.install(self._patch)

    def open(self) -> Device:
        import nidaqmx._standin

        self.state = nidaqmx._standin.reset()  # a fresh model per device
        return open_device("nidaq", default_device_config(), RealClock())

    def outputs(self, device: Any) -> dict[str, float]:
        return {ch: self.state.levels.get(line, 0.0) for ch, line in device.lines.items()}

    def go_quiet(self, device: Any) -> None:
        self.state.watchdogs[-1].expire()  # the hardware's part: the timer ran out

    def fault(self, device: Any) -> None:
        from nidaqmx.errors import DaqError

        def fail(task: Any, n: int) -> None:  # the driver fails while the trial plays
            self.state.on_poll = None
            raise DaqError("Device not available.", -200324)

        self.state.on_poll = fail

    def clear_fault(self, device: Any) -> None:
        self.state.on_poll = None

    @contextlib.contextmanager
    def mid_trial(self, device: Any, action: Callable[[], None]) -> Iterator[None]:
        self.state.polls_until_done = 10**9  # a trial that plays until stopped

        def on_poll(task: Any, n: int) -> None:
            if n == 2:
                assert self.outputs(device)["MV"] > 0, "the trial was not playing"
                action()

        self.state.on_poll = on_poll
        try:
            yield
        finally:
            self.state.on_poll, self.state.polls_until_done = None, 3

    def close(self) -> None:
        self._patch.undo()
        self._standin.uninstall()  # after undo, which puts back what install() set aside


#: Each target and the registered back-end it answers for.
TARGET_BACKENDS = {
    "sim": "sim",
    "emulator": "emulator",
    "host": "serial",
    "qemu": "serial",
    "nidaq-standin": "nidaq",
}
TARGETS: dict[str, Callable[[], Target]] = {
    "sim": SimTarget,
    "emulator": lambda: WireTarget("emulator"),
    "host": lambda: WireTarget("host"),
    "qemu": lambda: WireTarget("qemu"),
    "nidaq-standin": NidaqStandinTarget,
}


# ------------------------------------------------------------------ the checks


def assert_zero(target: Target, device: Any) -> None:
    assert target.outputs(device) == {"EV": 0.0, "MV": 0.0}, target.name


def output_on(target: Target, device: Any) -> None:
    """Put 0.3 V on MV by streaming (back-ends without streaming get it in a trial instead)."""
    if target.capabilities.streaming:
        device.set_amplitude("MV", MV120, 0.3)
        assert target.outputs(device)["MV"] == pytest.approx(0.3, abs=0.01)


def check_limits_refused(target: Target, device: Any) -> None:
    """Over-limit drive on either channel is refused before anything plays."""
    limits = device.identity.limits.max_drive_v
    same_channel = replace(short_plan(), target=MV120, target_amplitude_v=limits["MV"] * 0.6)
    plans = [short_plan(target_v=limits["EV"] + 0.1), short_plan(masker_v=limits["MV"] * 2)]
    for plan in [*plans, replace(same_channel, masker_amplitude_v=limits["MV"] * 0.6)]:
        with pytest.raises(SafetyLimitError):
            device.play_trial(plan, device.clock.now())
        assert_zero(target, device)
    with pytest.raises(SafetyLimitError if target.capabilities.streaming else DeviceError):
        device.set_amplitude("MV", MV120, limits["MV"] + 0.1)
    assert_zero(target, device)


def check_onsets_reported(target: Target, device: Any) -> None:
    """A trial returns when it has ended, with three onsets near plan and what was played."""
    plan = short_plan()
    begin = device.clock.now() + (0.3 if target.real_time else 0.1)  # room for a loaded host
    result = device.play_trial(plan, begin)
    assert device.clock.now() >= begin + plan.duration_s - 1e-6
    assert result.planned_onsets_s == plan.planned_onsets_s(begin)
    assert len(result.actual_onsets_s) == 3
    for actual, planned in zip(result.actual_onsets_s, result.planned_onsets_s, strict=True):
        # early by at most one sample (sample grid, clock-offset estimate), late within bound
        assert -1e-3 <= actual - planned < target.late_s + 0.01, (actual, planned)
    steps = (result.extra.get("target_att_db"), result.extra.get("masker_att_db"))
    if steps[0] is None:  # no converter model (NI: the driver plays the request)
        assert (result.played_target_v, result.played_masker_v) == (0.5, 0.3)
    else:  # what the converter plays at the attenuator step the host chose, V
        conv = getattr(device, "converters", None) or device.config.converters
        assert result.played_target_v == pytest.approx(conv["EV"].played_v(0.5, steps[0]), abs=1e-6)
        assert result.played_masker_v == pytest.approx(conv["MV"].played_v(0.3, steps[1]), abs=1e-6)
        assert abs(result.played_target_v - 0.5) <= conv["EV"].lsb_v(steps[0]) / 2 + 1e-6
    assert_zero(target, device)  # a trial rests on 0 V


def check_streaming_as_declared(target: Target, device: Any) -> None:
    """Streaming plays where declared; where absent, set_amplitude refuses and nothing plays."""
    if target.capabilities.streaming:
        device.set_amplitude("MV", MV120, 0.2)
        device.set_amplitude("MV", MV120, 0.4)
        assert target.outputs(device)["MV"] == pytest.approx(0.4, abs=0.01)
        device.stop()
    else:
        with pytest.raises(DeviceError, match="streamed"):
            device.set_amplitude("MV", MV120, 0.2)
    assert_zero(target, device)


def check_stop_aborts_and_zeroes(target: Target, device: Any) -> None:
    """stop() zeroes a stream, and aborts a trial mid-play where trials take real time; then
    the next trial plays."""
    if target.capabilities.streaming:
        output_on(target, device)
        device.stop()
        assert_zero(target, device)
    if target.real_time:
        long = replace(short_plan(), stimulus_s=1.0)
        with target.mid_trial(device, device.stop), pytest.raises(DeviceError, match="STOP"):
            device.play_trial(long, device.clock.now() + 0.05)
        assert_zero(target, device)
    device.play_trial(short_plan(), device.clock.now() + 0.05)


def check_faults_zero_and_resume(target: Target, device: Any) -> None:
    """A fault zeroes both outputs, raises a DeviceError and is logged; after it, trials play.

    A back-end declaring no faults has no fault log: nothing it does can be a fault.
    """
    if not target.capabilities.faults:
        assert not hasattr(device, "fault_log"), "faults declared absent, but a fault log exists"
        return
    assert hasattr(device, "fault_log"), "faults declared, but the device keeps no fault log"
    output_on(target, device)
    logged = len(device.fault_log)
    target.fault(device)
    with pytest.raises(DeviceError):
        device.play_trial(short_plan(), device.clock.now() + 0.05)
    assert len(device.fault_log) > logged
    assert_zero(target, device)
    target.clear_fault(device)
    result = device.play_trial(short_plan(), device.clock.now() + 0.05)
    assert len(result.actual_onsets_s) == 3


def check_watchdog_as_declared(target: Target, device: Any) -> None:
    """With a watchdog, a quiet host finds both outputs at 0 V and the next trial plays; a
    back-end declaring none keeps playing however long the host is quiet."""
    output_on(target, device)
    target.go_quiet(device)
    if not target.capabilities.watchdog:
        assert target.outputs(device)["MV"] == pytest.approx(0.3, abs=0.01)
        device.stop()
        return
    assert_zero(target, device)
    result = device.play_trial(short_plan(), device.clock.now() + 0.05)
    assert len(result.actual_onsets_s) == 3
    if target.capabilities.faults:  # the trip is in the fault log by the next trial
        assert device.fault_log, "the watchdog acted but no fault was recorded"


CHECKS: list[Callable[[Target, Any], None]] = [
    check_limits_refused,
    check_onsets_reported,
    check_streaming_as_declared,
    check_stop_aborts_and_zeroes,
    check_faults_zero_and_resume,
    check_watchdog_as_declared,
]
