"""What the serial host checks around a board: its HELLO against the rig config, and each trial
against what the converter can play (attenuator steps, quantisation). Pure: no I/O.

The host refuses a board that speaks another protocol or runs firmware older than
:data:`~masking_lab.device.protocol.MIN_FIRMWARE`, and a board whose converter (bits, full
scale, attenuator steps) is not the one the rig config describes: the level checks made before
the session were made for the config's converter.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

from masking_lab.core.errors import DeviceProtocolError, DeviceTimeModeError, SafetyLimitError
from masking_lab.core.stimulus import Stimulus
from masking_lab.core.trial import TrialPlan
from masking_lab.device import protocol as proto
from masking_lab.device import serial_faults
from masking_lab.device.config import DeviceConfig
from masking_lab.device.levels_range import MAX_ERROR_DB, Converter
from masking_lab.device.reply_checks import Expected


def accept_hello(
    port: str, hello: proto.Hello, config: DeviceConfig, *, clock_virtual: bool
) -> dict[str, Converter]:
    """Check a board's HELLO before a session; return the converters in force.

    Raises
    ------
    DeviceProtocolError
        Another protocol, older firmware, a converter unlike the config's, a limit ≤ 0 V.
    DeviceTimeModeError
        The board runs in the other time mode than the session clock.
    DeviceFaultError
        The interlock is open.
    """
    check_version(port, hello)
    converters = converters_from(port, hello, config.converters, config.path)
    if not all(v > 0 for v in hello.max_v.values()):
        raise DeviceProtocolError(
            f"device on {port} reports limits {dict(hello.max_v)} V: a limit must be > 0 V"
        )
    virtual = hello.virtual
    if virtual != clock_virtual:
        mode = "virtual" if virtual else "real"
        want = "a virtual clock (simulation)" if virtual else "a real clock"
        raise DeviceTimeModeError(
            f"device on {port} runs in {mode} time and needs {want}; start the emulator "
            f"{'without' if virtual else 'with'} --virtual-time, or switch the session clock",
            device_virtual=virtual,
        )
    if hello.interlock_open:
        raise serial_faults.interlock_error(port, "at HELLO (session not started)")
    return converters


def check_version(port: str, hello: proto.Hello) -> None:
    """Refuse a board with another protocol or older firmware (DeviceProtocolError).

    Examples
    --------
    >>> from masking_lab.device.protocol import Hello
    >>> old = Hello(1, {"EV": 5.0, "MV": 5.0}, 0, False, False, "M", "S", "emu-1.0.0")
    >>> check_version("/dev/ttyACM0", old)
    Traceback (most recent call last):
    ...
    masking_lab.core.errors.DeviceProtocolError: device on /dev/ttyACM0 runs firmware emu-1.0.0 \
speaking protocol 1 (protocol version 1 is not 2): this host needs protocol 2 and firmware \
>= fw-2.0.0; flash firmware >= fw-2.0.0 (make -C firmware flash) or use the masking-lab \
version that matches the board
    """
    why = proto.firmware_too_old(hello.version, hello.firmware)
    if why is not None:
        raise DeviceProtocolError(
            f"device on {port} runs firmware {hello.firmware} speaking protocol {hello.version} "
            f"({why}): this host needs protocol {proto.PROTOCOL_VERSION} and firmware "
            f">= {proto.MIN_FIRMWARE}; flash firmware >= {proto.MIN_FIRMWARE} "
            "(make -C firmware flash) or use the masking-lab version that matches the board"
        )


def converters_from(
    port: str, hello: proto.Hello, configured: Mapping[str, Converter], config_path: str
) -> dict[str, Converter]:
    """The converters in force: the config's, after checking they match the board's HELLO.

    A channel the config gives no converter for takes the board's (with the default
    ``min_lsb``). A mismatch in bits, full scale (beyond 1 ppm) or attenuator steps is a
    DeviceProtocolError naming the field, both values and what to fix. The board's linear
    range (HELLO ``lin``) is taken when the config gives none; a config whose
    ``linear_codes`` exceeds the board's is a mismatch (its levels could clip).
    """
    out: dict[str, Converter] = {}
    for ch in ("EV", "MV"):
        lin = hello.linear_codes.get(ch)
        board = Converter(
            hello.bits[ch], hello.full_scale_v[ch], hello.attenuation_db, linear_codes=lin
        )
        want = configured.get(ch)
        if want is None:
            out[ch] = board
            continue
        diffs = []
        if want.bits != board.bits:
            diffs.append(f"bits {board.bits} (config {want.bits})")
        if not math.isclose(want.full_scale_v, board.full_scale_v, rel_tol=1e-6):
            diffs.append(f"full scale {board.full_scale_v:g} V (config {want.full_scale_v:g} V)")
        if tuple(want.steps_db) != tuple(board.steps_db):
            diffs.append(
                f"attenuator steps {_steps(board.steps_db)} dB (config {_steps(want.steps_db)} dB)"
            )
        if lin is not None and want.linear_codes is not None and want.linear_codes > lin:
            diffs.append(f"linear range {lin} codes (config {want.linear_codes})")
        if diffs:
            raise DeviceProtocolError(
                f"device on {port} reports for {ch}: {'; '.join(diffs)}, unlike the rig config "
                f"{config_path} (channels.{ch}.converter): the levels were checked for the "
                "config's converter. Fix the config to describe this board, or connect the "
                "board the config describes"
            )
        if lin is not None and (want.linear_codes is None or want.linear_codes > lin):
            want = replace(want, linear_codes=lin)
        out[ch] = want
    return out


def hello_details(hello: proto.Hello) -> dict[str, Any]:
    """The protocol-2 HELLO fields the session log keeps (build, clock, reset cause, converter)."""
    return {
        "protocol": hello.version,
        "build": hello.build,
        "clock_source": hello.clock_source,
        "reset_cause": hello.reset_cause,
        "bits": dict(hello.bits),
        "full_scale_v": dict(hello.full_scale_v),
        "attenuation_db": list(hello.attenuation_db),
        "linear_codes": dict(hello.linear_codes),
    }


@dataclass(frozen=True)
class Steps:
    """Attenuator steps chosen for one trial, dB, and what the converter plays, V."""

    target_db: float
    masker_db: float
    target_v: float
    masker_v: float


def choose_steps(plan: TrialPlan, converters: Mapping[str, Converter], where: str) -> Steps:
    """Pick each channel's attenuator step for ``plan``; refuse a level played > 1 dB off.

    Raises
    ------
    SafetyLimitError
        An amplitude that no step renders within 1 dB, or a channel's amplitudes beyond the
        output's linear range at every step (nothing is sent).
    """
    masker_v = plan.masker_amplitude_v if plan.masker is not None else 0.0
    # Every trial is checked; a refusal is an exception, which the cache never keeps.
    return _choose_steps(
        plan.target,
        plan.target_amplitude_v,
        plan.masker,
        masker_v,
        converters["EV"],
        converters["MV"],
        where,
    )


# Pure in its arguments (frozen stimuli and converters, amplitudes); a staircase revisits the
# same levels, so most trials of a session ask again what an earlier one asked.
@functools.lru_cache(maxsize=4096)
def _choose_steps(
    target: Stimulus,
    target_v: float,
    masker: Stimulus | None,
    masker_v: float,
    ev: Converter,
    mv: Converter,
    where: str,
) -> Steps:
    converters = {"EV": ev, "MV": mv}
    amps: dict[str, list[float]] = {"EV": [], "MV": []}
    amps[target.channel].append(target_v)
    if masker is not None:
        amps[masker.channel].append(masker_v)
    step = {ch: converters[ch].pick_step(a) for ch, a in amps.items()}
    for ch, a in amps.items():
        conv = converters[ch]
        if not conv.fits(a, step[ch]):  # no step plays it without clipping: the board refuses
            raise SafetyLimitError(
                f"{where}: {ch} amplitude {sum(a):.6g} V exceeds the output's linear range at "
                f"every attenuator step (at {step[ch]:g} dB: {conv.max_code} codes, "
                f"{conv.linear_max_v(step[ch]):.6g} V; HELLO lin); nothing was sent. Lower "
                "the level or the masker"
            )
    played: dict[str, float] = {}
    for what, stim, amp in (
        ("target", target, target_v),
        ("masker", masker, masker_v),
    ):
        if stim is None:
            played[what] = 0.0
            continue
        conv, att = converters[stim.channel], step[stim.channel]
        played[what] = conv.played_v(amp, att)
        if amp > 0 and conv.error_db(amp, att) > MAX_ERROR_DB:
            raise SafetyLimitError(
                f"{where}: {what} {stim.name} at {amp:.6g} V cannot be played within "
                f"{MAX_ERROR_DB:g} dB by the {stim.channel} converter ({conv.bits} bits, "
                f"{conv.full_scale_v:g} V full scale, attenuator steps {_steps(conv.steps_db)} "
                f"dB: plays {played[what]:.6g} V); nothing was sent. Raise the level floor or add "
                "an attenuator step"
            )
    t_att = step[target.channel]
    m_att = step[masker.channel] if masker is not None else 0.0
    return Steps(t_att, m_att, played["target"], played["masker"])


def play_fields(plan: TrialPlan, at_device_s: float, steps: Steps) -> dict[str, Any]:
    """The fields of the PLAY command for ``plan`` at device time ``at_device_s`` (s)."""
    masker = plan.masker
    return {
        "tch": plan.target.channel,
        "tcar": plan.target.carrier_hz,
        "tenv": plan.target.envelope_hz or 0.0,
        "tamp": plan.target_amplitude_v,
        "ti": plan.target_interval,
        "mch": masker.channel if masker else "-",
        "mcar": masker.carrier_hz if masker else 0.0,
        "menv": (masker.envelope_hz or 0.0) if masker else 0.0,
        "mamp": plan.masker_amplitude_v if masker else 0.0,
        "stim": plan.stimulus_s,
        "gap": plan.gap_s,
        "lead": plan.lead_in_s,
        "n": plan.n_intervals,
        "at": at_device_s,
        "tatt": steps.target_db,
        "matt": steps.masker_db,
    }


def expected_done(
    plan: TrialPlan,
    at_device_s: float,
    steps: Steps,
    converters: Mapping[str, Converter],
    late_s: float,
) -> Expected:
    """What the DONE of ``plan`` sent with ``at=at_device_s`` must report (device time)."""
    t_lsb = converters[plan.target.channel].lsb_v(steps.target_db)
    m_lsb = converters[plan.masker.channel].lsb_v(steps.masker_db) if plan.masker else 0.0
    return Expected(
        onsets_s=tuple(plan.planned_onsets_s(at_device_s)),
        stimulus_s=plan.stimulus_s,
        late_s=late_s,
        target_v=steps.target_v,
        masker_v=steps.masker_v,
        target_lsb_v=t_lsb,
        masker_lsb_v=m_lsb,
    )


def _steps(steps: tuple[float, ...]) -> str:
    return "/".join(f"{s:g}" for s in steps)
