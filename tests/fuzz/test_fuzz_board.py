"""Hostile boards through `run` (issue 21.9): every change of :mod:`fuzz_board` ends in a clean
device fault (exit 3) with nothing of the hostile trial logged; an honest board is what the
oracle calls wrong (it can fail)."""

from __future__ import annotations

import random
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fuzz_board import BOARD_CHANGES, board_trial


@pytest.mark.parametrize("change", BOARD_CHANGES)
def test_a_hostile_board_ends_in_a_clean_device_fault(tmp_path, change):
    for seed in range(3):
        (outcome,), ran_to_end = board_trial(random.Random(seed), tmp_path / "w", 20.0, change)
        assert outcome.kind == "clean", (outcome.argv, outcome.detail)
        assert outcome.code == 3 and not ran_to_end


def test_the_oracle_calls_an_honest_board_wrong(tmp_path):
    (outcome,), ran_to_end = board_trial(random.Random(1), tmp_path / "w", 20.0, "none")
    assert ran_to_end and outcome.kind == "wrong"
    assert "run exit 0, not a device fault" in outcome.detail
