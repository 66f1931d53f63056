"""The three device implementations answer alike at the output's linear range (HELLO ``lin``).

The reference board's DAC output buffer is linear to 1798 of its 2048 codes each side of
mid-scale. Behind a deep attenuator step the voltage limit allows more codes than that, so the
firmware core caps every code limit by the linear range: a level needing more codes is refused
at the command (``ERR LIMIT``), never clipped nor left to the output stage. The emulator, the
host build and the STM32 image under QEMU (built with the same limits and 0/20/40 dB steps) get
the same frames at, one code below and one code above the range at the deepest steps, and at
the rounding edge (half an LSB), alone and as target plus masker on one channel.
"""

from __future__ import annotations

import contextlib
import time

import pytest
from firmware_support import Link, start

from masking_lab.device import protocol as proto
from masking_lab.device.emulator_checks import Converter

IMPLEMENTATIONS = ("emulator", "host", "qemu-att")
LIN = 1798  # codes: 0.2 V .. VDDA - 0.2 V of the STM32 DAC, buffer on
DAC = Converter(12, 10_000_000)  # every implementation's converter here: 12 bits, ±10 V
BASE = {"tcar": 270.0, "tenv": 0.0, "ti": 1, "n": 1, "stim": 0.02, "gap": 0.0, "lead": 0.0}


def volts(codes: float, att_db: int) -> float:
    """The request (V, whole µV) that is ``codes`` LSBs behind ``att_db`` dB."""
    return round(codes * 20.0 / 4096 / 10 ** (att_db / 20), 6)


def frames() -> list[tuple[str, dict[str, object]]]:
    """(label, PLAY fields): at, below and above the linear range at 40 and 20 dB."""
    out = []
    for ch in ("EV", "MV"):
        for att in (40, 20):
            for label, codes in (
                ("one below", LIN - 1),
                ("at", LIN),
                ("one above", LIN + 1),
                ("just under half an LSB above", LIN + 0.49),
                ("just over half an LSB above", LIN + 0.51),
            ):
                fields = dict(BASE, tch=ch, tamp=volts(codes, att), tatt=att, mch="-")
                out.append((f"{ch} {att} dB {label}", fields))
        # target and masker on one channel share its step: their codes add up
        for label, (t, m) in (("sum at", (900, LIN - 900)), ("sum one above", (900, LIN - 899))):
            fields = dict(BASE, tch=ch, tamp=volts(t, 40), tatt=40, mch=ch, mcar=120.0)
            fields.update(menv=0.0, mamp=volts(m, 40), matt=40)
            out.append((f"{ch} 40 dB {label}", fields))
    return out


def expected_codes(fields: dict[str, object]) -> int:
    """The codes the channel needs, by the documented rounding (half up, per part)."""
    att = int(fields["tatt"])  # type: ignore[call-overload]
    codes = DAC.code(round(float(fields["tamp"]) * 1e6), att)  # type: ignore[arg-type]
    if fields["mch"] != "-":
        codes += DAC.code(round(float(fields["mamp"]) * 1e6), att)  # type: ignore[arg-type]
    return codes


def outcome(link: Link, within_s: float = 10.0) -> proto.Frame:
    """The DONE or FAULT event that ends an accepted PLAY, asking the device's TIME meanwhile
    (which also feeds its watchdog). The bound is in device time, so a loaded host that
    deschedules the device cannot trip it."""
    deadline = link.call("TIME").number("t") + within_s
    while True:
        for i, f in enumerate(link.events):
            if f.name in ("DONE", "FAULT"):
                return link.events.pop(i)
        now = link.call("TIME").number("t")
        assert now < deadline, f"neither DONE nor FAULT within {within_s} s of device time"
        time.sleep(0.03)


def answers(target: str) -> tuple[str, list[tuple[str, str, str]]]:
    """HELLO lin and, per frame, (answer, DONE tamp/mamp or ERR text) from one implementation."""
    dev = start(target)
    link = Link(dev.port)
    try:
        lin = link.call("HELLO").fields["lin"]
        got = []
        for _label, fields in frames():
            at = round(link.call("TIME").number("t") + 0.15, 6)
            reply = link.call("PLAY", at=at, **fields)
            if reply.ok:
                end = outcome(link)  # DONE, or FAULT if the output stage met a bad sample
                if end.name == "DONE":
                    got.append(("OK", f"{end.fields['tamp']}/{end.fields['mamp']}", ""))
                else:
                    got.append((f"OK then FAULT {end.fields.get('code')}", "", ""))
            else:
                got.append((f"ERR {reply.code}", "", reply.text))
        return lin, got
    finally:
        link.close()
        with contextlib.suppress(Exception):
            dev.close()


@pytest.fixture(scope="module")
def all_answers() -> dict[str, tuple[str, list[tuple[str, str, str]]]]:
    return {target: answers(target) for target in IMPLEMENTATIONS}


def test_every_implementation_reports_the_same_linear_range(all_answers):
    assert {target: lin for target, (lin, _) in all_answers.items()} == dict.fromkeys(
        IMPLEMENTATIONS, f"{LIN},{LIN}"
    )


def test_frames_at_the_linear_limit_get_the_same_answer_everywhere(all_answers):
    labels = [label for label, _ in frames()]
    ref = all_answers["emulator"][1]
    for target in IMPLEMENTATIONS[1:]:
        for label, a, b in zip(labels, ref, all_answers[target][1], strict=True):
            assert a == b, f"{label}: emulator {a} / {target} {b}"


def test_a_level_beyond_the_linear_range_is_refused_and_one_within_it_plays(all_answers):
    for (label, fields), (answer, played, text) in zip(
        frames(), all_answers["emulator"][1], strict=True
    ):
        codes = expected_codes(fields)
        if codes <= LIN:
            assert answer == "OK", f"{label}: {codes} codes must play ({text})"
            att = int(fields["tatt"])  # type: ignore[call-overload]
            tamp = DAC.played_uv(DAC.code(round(float(fields["tamp"]) * 1e6), att), att)
            assert float(played.split("/")[0]) == pytest.approx(tamp / 1e6, abs=1e-9), label
        else:
            assert answer == "ERR LIMIT", f"{label}: {codes} codes must be refused"
            assert f"linear range of {LIN} codes" in text and f"{fields['tch']} amplitude" in text
    # the cases straddle the range: each side is exercised on both channels
    needs = [expected_codes(f) for _, f in frames()]
    assert needs.count(LIN) >= 8 and needs.count(LIN + 1) >= 8 and min(needs) == LIN - 1
