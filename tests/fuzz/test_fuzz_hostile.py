"""The campaign's generators for issue 21 (tests/fuzz/fuzz_hostile.py), a few seeded inputs of
each: no traceback, hang, non-finite output, silently wrong result or validate gap, and each
generator gets some inputs past the readers (else it would test nothing behind them)."""

from __future__ import annotations

import random
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fuzz_hostile import HOSTILE_KINDS, hostile_trial


@pytest.mark.parametrize("kind", HOSTILE_KINDS)
def test_seeded_inputs_of_each_class_end_cleanly(kind, tmp_path):
    rng = random.Random(21)
    accepted = 0
    for _ in range(4):
        outcomes, ok = hostile_trial(kind, rng, tmp_path / "work", 60.0)
        accepted += ok
        for o in outcomes:
            assert o.kind == "clean", (o.argv, o.detail)
    assert accepted > 0
