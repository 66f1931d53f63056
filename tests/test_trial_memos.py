"""What is remembered from trial to trial (attenuator steps, the emulator's plan of a PLAY)
gives what computing it afresh gives, and a refusal is never remembered."""

from __future__ import annotations

import dataclasses

import pytest

from masking_lab.core.errors import SafetyLimitError
from masking_lab.core.stimulus import parse_stimulus
from masking_lab.core.trial import TrialPlan
from masking_lab.device import serial_checks
from masking_lab.device.emulator_checks import CheckedPlay, Part
from masking_lab.device.emulator_state import plan_of
from masking_lab.device.levels_range import Converter

REF = Converter(12, 10.0, (0.0, 20.0, 40.0), linear_codes=1798)


def _fresh_steps(plan: TrialPlan, converters: dict[str, Converter]) -> serial_checks.Steps:
    """What the first trial at a level computes: the memo emptied first."""
    serial_checks._choose_steps.cache_clear()
    return serial_checks.choose_steps(plan, converters, "here")


def test_steps_asked_again_are_the_steps_computed_afresh() -> None:
    ev, mv = parse_stimulus("EV270"), parse_stimulus("MV120")
    converters = {"EV": REF, "MV": REF}
    for amp in (0.001, 0.03, 0.5, 2.0):
        plan = TrialPlan(ev, amp, 2, mv, amp / 3)
        first = serial_checks.choose_steps(plan, converters, "here")
        again = serial_checks.choose_steps(plan, converters, "here")
        assert first == again == _fresh_steps(plan, converters)
    # another converter with the same levels is another answer, not the remembered one
    coarse = Converter(16, 10.0, (0.0,))
    plan = TrialPlan(ev, 0.03, 2)
    assert serial_checks.choose_steps(plan, {"EV": coarse, "MV": REF}, "here").target_db == 0.0
    assert serial_checks.choose_steps(plan, converters, "here").target_db == 20.0


def test_a_refused_level_is_refused_every_time() -> None:
    plan = TrialPlan(parse_stimulus("MV270"), 9.0, 1)
    for where in ("trial 7", "trial 7", "trial 8"):
        with pytest.raises(SafetyLimitError, match=f"^{where}: MV amplitude 9 V exceeds"):
            serial_checks.choose_steps(plan, {"EV": REF, "MV": REF}, where)
    ok = TrialPlan(parse_stimulus("MV270"), 0.5, 1)
    assert serial_checks.choose_steps(ok, {"EV": REF, "MV": REF}, "x").target_v > 0


def test_plays_differing_only_in_their_start_share_one_plan() -> None:
    target = Part("EV", 270_000_000, 0, 50_000, played_uv=48_828)
    masker = Part("MV", 120_000_000, 0, 300_000, played_uv=300_781)
    play = CheckedPlay(target, masker, 2, 3, 1_800_000, 600_000, 600_000, 0)
    later = dataclasses.replace(play, at_us=5_000_000)
    assert plan_of(later) is plan_of(play)
    plan = plan_of(play)
    assert (plan.target.name, plan.target_amplitude_v, plan.target_interval) == (
        "EV270",
        0.048828,
        2,
    )
    assert (plan.masker and plan.masker.name, plan.masker_amplitude_v) == ("MV120", 0.300781)
    other = dataclasses.replace(play, ti=3, target=dataclasses.replace(target, played_uv=97_656))
    assert (plan_of(other).target_interval, plan_of(other).target_amplitude_v) == (3, 0.097656)
