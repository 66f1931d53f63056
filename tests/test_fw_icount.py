"""No command handler or main-loop step over 5 ms at 168 MHz (issue 23, item 2).

Instruction counts on the STM32 image under QEMU ``-icount shift=0`` (deterministic: one
instruction is one ns of the guest clock, see ``tests/icount_support.py``), for the frames
that used to stall the board: a paper-length masked AM trial (v1: 21-30 M instructions in the
PLAY handler), the longest trial and a 256-byte frame. The output stage synthesises samples
as it refills; a handler, fw_poll and the longest refill together must fit the budget.
"""

from __future__ import annotations

import pytest
from icount_support import BUDGET, FRAMES, PADDED, Qemu, measure


@pytest.fixture(scope="module")
def qemu():
    q = Qemu()
    yield q
    q.close()


@pytest.mark.parametrize(
    "label", ["PLAY paper masked AM (3 x 1.8 s)", "PLAY longest trial (9 x 6.6 s, AM)", PADDED]
)
def test_play_handler_and_synthesis_fit_the_5_ms_budget(qemu, label):
    name, fields = FRAMES[label]
    m = measure(qemu, name, fields, pad=label == PADDED)
    assert m["ok"] == 1.0
    assert 0 < m["handler"] <= BUDGET / 10, m  # constant work: no scan of the tone
    assert m["samples"] > 1000 and m["refill"] > 0, m  # the output stage rendered the trial
    # one main-loop iteration: this handler, then fw_poll and the longest refill seen
    assert m["handler"] + m["poll"] + m["refill"] <= BUDGET, m
