"""The compiled QUEST+ update (procedures/update_loops.py) gives numpy's numbers bit for bit:
its pairwise sum is numpy's on rows of any length and magnitude, and lockstep tracks run with
it have the same levels, posterior means and SDs as with the numpy route."""

from __future__ import annotations

import numpy as np
import pytest

from masking_lab.procedures import quest_plus_batch
from masking_lab.procedures.fused import compiled_loops
from masking_lab.procedures.quest_plus import QuestPlusSettings
from masking_lab.procedures.quest_plus_batch import simulate_quest_plus

LOOPS = compiled_loops("update_loops")


def test_the_compiled_update_runs_in_the_test_environment():
    assert LOOPS is not None


@pytest.mark.parametrize("seed", range(4))
def test_the_pairwise_sum_is_numpys_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    for n in [*range(1, 300), *rng.integers(300, 20_000, 60)]:
        # posterior-like rows: many tiny cells beside a few large ones
        a = rng.random(int(n)) ** 12 * 10.0 ** float(rng.integers(-300, 2))
        assert LOOPS.pairwise_sum(a) == a.sum()
        assert LOOPS.pairwise_sum(a) == a[None].sum(axis=1)[0]


def test_the_update_is_numpys_bit_for_bit():
    rng = np.random.default_rng(7)
    post = rng.random((9, 131, 28))
    post /= post.reshape(9, -1).sum(axis=1)[:, None, None]
    tables = rng.random((2, 40, 131, 28))
    answer, level = rng.integers(0, 2, 9), rng.integers(0, 40, 9)
    expected = post * tables[answer, level]
    expected /= expected.reshape(9, -1).sum(axis=1)[:, None, None]
    LOOPS.update_posteriors(post, tables, answer, level)
    np.testing.assert_array_equal(post, expected)


@pytest.mark.parametrize("entropy_over", ["threshold", "all"])
def test_lockstep_tracks_run_alike_compiled_and_with_numpy(monkeypatch, entropy_over):
    s = QuestPlusSettings(-20.0, 45.0, target_sd_db=0.8, max_trials=80, entropy_over=entropy_over)
    thr = np.random.default_rng(3).uniform(0.0, 25.0, 12)

    def run():
        return simulate_quest_plus(s, thr, rng=np.random.default_rng(11))

    compiled = run()
    real = quest_plus_batch.compiled_loops
    monkeypatch.setattr(
        quest_plus_batch,
        "compiled_loops",
        lambda name: None if name == "update_loops" else real(name),
    )
    numpy_route = run()
    for name in ("levels_db", "mean_db", "sd_db", "n_trials"):
        np.testing.assert_array_equal(getattr(compiled, name), getattr(numpy_route, name))
