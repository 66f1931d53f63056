"""The firmware emulator's command handlers (the counterpart of ``firmware/core/commands.c``).

A mixin of :class:`masking_lab.device.emulator.FirmwareEmulator`: each ``_cmd_<name>`` handles
one decoded command with the emulator's lock held, checks its fields and levels with
:mod:`masking_lab.device.emulator_checks` (so every implementation answers alike) and replies
through the emulator's ``_ok``/``_err``/``_send_event``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from masking_lab.core.stimulus import CHANNELS
from masking_lab.device import protocol as proto
from masking_lab.device.base import TrialPlan
from masking_lab.device.emulator_checks import ONE, Checker
from masking_lab.device.emulator_state import (
    INTERLOCK_TEXT,
    OnsetLateness,
    PlayState,
    interlock_text,
    plan_of,
    render_trial,
    to_us,
    virtual_play,
)

if TYPE_CHECKING:
    from masking_lab.device.config import DeviceConfig

FIRMWARE_VERSION = "fw-2.0.0"  # the firmware release whose behaviour this emulates
PROTOCOL_VERSION = 2


class EmulatorCommands:
    """Command handlers; the state they use lives in ``FirmwareEmulator.__init__``."""

    # attributes and helpers provided by FirmwareEmulator (declared so mypy checks their use)
    _amp: dict[str, float]
    _play: PlayState | None
    config: DeviceConfig
    virtual_time: bool
    watchdog_s: float
    render_buffers: bool
    limits: dict[str, float]
    checker: Checker
    overdrive: float
    build: str
    _lateness: OnsetLateness
    _interlock_open: bool
    _vt_us: int
    _stream: dict[str, tuple[float, float | None]]
    _last_sample: dict[str, float]
    _peak: dict[str, float]
    _wd_trips: int

    if TYPE_CHECKING:  # defined by FirmwareEmulator; signatures here only for the checker

        def _device_now(self) -> float: ...
        def _zero(self, why: str, aborted_why: str | None = None) -> None: ...
        def _fault(self, code: str, why: str) -> None: ...
        def _unplug_locked(self, why: str) -> None: ...
        def _take_fault(self, kind: str) -> bool: ...
        def _ok(self, seq: int, fields: dict[str, Any] | None = None) -> None: ...
        def _err(self, seq: int, code: str, text: str) -> None: ...
        def _send_event(self, name: str, fields: dict[str, Any]) -> None: ...
        def _note(self, text: str) -> None: ...

    def _cmd_hello(self, frame: proto.Frame) -> None:
        self._zero("HELLO (new host session)")
        self._note(f"HELLO from host #{frame.seq}")
        self._ok(frame.seq, self._hello_fields())

    def _hello_fields(self) -> dict[str, Any]:
        emu = self.config.emulator
        fields: dict[str, Any] = {"proto": PROTOCOL_VERSION, "fw": FIRMWARE_VERSION}
        fields.update(model=emu.model.replace(" ", "_"), sn=emu.serial_number.replace(" ", "_"))
        fields.update(max_ev=self.limits["EV"], max_mv=self.limits["MV"])
        fields.update(wd_ms=round(self.watchdog_s * 1000), fs=self.config.waveform.sample_rate_hz)
        fields.update(vt=int(self.virtual_time), il=interlock_text(self._interlock_open))
        fields.update(build=self.build, clk="host", rst="power", **self.checker.hello_fields())
        return fields

    def _cmd_time(self, frame: proto.Frame) -> None:
        self._ok(frame.seq, {"t": self._device_now()})

    def _cmd_ping(self, frame: proto.Frame) -> None:
        self._ok(frame.seq, {"t": self._device_now()})

    def _cmd_diag(self, frame: proto.Frame) -> None:
        fields: dict[str, Any] = {"ev": self._amp["EV"], "mv": self._amp["MV"]}
        fields.update(playing=int(bool(self._play)))
        fields.update(il=interlock_text(self._interlock_open), dac_ev=self._last_sample["EV"])
        fields.update(dac_mv=self._last_sample["MV"], wd=self._wd_trips, t=self._device_now())
        fields.update(pk_ev=round(self._peak["EV"], 6), pk_mv=round(self._peak["MV"], 6))
        self._ok(frame.seq, fields)

    def _interlocked(self, frame: proto.Frame) -> bool:
        if not self._interlock_open:
            return False
        self._err(frame.seq, "INTERLOCK", INTERLOCK_TEXT)
        return True

    def _cmd_stop(self, frame: proto.Frame) -> None:
        self._zero("STOP", aborted_why="STOP")
        self._note(f"STOP #{frame.seq}: outputs zeroed")
        self._ok(frame.seq)

    def _cmd_setup(self, frame: proto.Frame) -> None:
        if self._interlocked(frame):
            return
        ch, car, env, amp_uv = self.checker.stream(frame.fields, setup=True)
        if self._play is not None:
            self._err(frame.seq, "BUSY", "SETUP while a trial is playing")
            return
        _, played_uv = self.checker.level(ch, amp_uv, 0)
        self._stream[ch] = (car / ONE, env / ONE or None)
        self._amp[ch] = played_uv / ONE
        self._ok(frame.seq)

    def _cmd_amp(self, frame: proto.Frame) -> None:
        if self._interlocked(frame):
            return
        ch, _, _, amp_uv = self.checker.stream(frame.fields, setup=False)
        if self._play is not None:
            self._err(frame.seq, "BUSY", "AMP while a trial is playing")
            return
        if ch not in self._stream:
            self._err(frame.seq, "STATE", f"AMP on {ch} before SETUP of {ch}")
            return
        _, played_uv = self.checker.level(ch, amp_uv, 0)
        self._amp[ch] = played_uv / ONE
        self._ok(frame.seq)

    def _cmd_play(self, frame: proto.Frame) -> None:
        if self._interlocked(frame):
            return
        if self._play is not None:
            self._err(frame.seq, "BUSY", "PLAY while a trial is playing")
            return
        checked = self.checker.play(frame.fields, to_us(self._device_now()), self.virtual_time)
        checked = self.checker.play_levels(checked)
        plan = plan_of(checked)  # amplitudes as played (quantised)
        # PLAY owns the outputs: any streamed output stops first.
        self._stream.clear()
        self._amp = dict.fromkeys(CHANNELS, 0.0)
        at = checked.at_us / ONE
        if self.virtual_time:  # integer µs, so the onsets match the C firmware to the digit
            start_us = max(checked.at_us, self._vt_us)
            self._ok(frame.seq, {"start": start_us / 1e6})
            play = PlayState(frame.seq, start_us / 1e6, plan, [], actual=[])
            if self.render_buffers:  # like the host build's --vt-render: OK, then render
                self._play = play
                if not self._render_within_limits(plan):
                    return  # ABORTED why=LIMIT + FAULT code=LIMIT sent, outputs zeroed
                self._play = None
            onsets_us, end_us = virtual_play(plan, start_us, self._lateness)
            self._vt_us = max(self._vt_us, end_us)
            if self._take_fault("unplug_on_play"):
                self._unplug_locked("unplug injected during PLAY")
                return
            play.actual = [t / 1e6 for t in onsets_us]
            self._send_done(play, end_us / 1e6)
            return
        now = self._device_now()
        start = max(at, now)
        planned = plan.planned_onsets_s(start)
        play = PlayState(frame.seq, start, plan, planned)
        self._ok(frame.seq, {"start": start})
        for k, onset in enumerate(planned):
            play.steps.append((onset, "on", k))
            play.steps.append((onset + plan.stimulus_s, "off", k))
        self._play = play
        if self.render_buffers:
            self._render_within_limits(plan)  # over a limit: ABORTED + FAULT, zeroed

    def _render_within_limits(self, plan: TrialPlan) -> bool:
        """Render the trial like the output stage; False (ABORTED + FAULT LIMIT) if over."""
        wf = self.config.waveform
        rendered = render_trial(plan, wf.sample_rate_hz, wf.ramp_s, self.overdrive)
        for ch, (peak, last) in rendered.items():
            if peak > self.limits[ch] + 1e-9:
                self._fault(
                    "LIMIT", f"a rendered {ch} sample is over the {self.limits[ch]:g} V limit"
                )
                return False
            self._last_sample[ch], self._peak[ch] = last, max(self._peak[ch], peak)
        return True

    def _send_done(self, play: PlayState, end: float) -> None:
        plan = play.plan
        fields: dict[str, Any] = {"seq": play.seq, "on": play.actual, "end": end}
        fields.update(tamp=plan.target_amplitude_v, mamp=plan.masker_amplitude_v)
        self._send_event("DONE", fields)
