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


def test_lockstep_tracks_run_alike_compiled_and_with_numpy(monkeypatch):
    s = QuestPlusSettings(-20.0, 45.0, target_sd_db=0.8, max_trials=80)
    thr = np.random.default_rng(3).uniform(0.0, 25.0, 12)

    def run():
        return simulate_quest_plus(s, thr, rng=np.random.default_rng(11))

    real = quest_plus_batch.compiled_loops
    asked = []
    monkeypatch.setattr(
        quest_plus_batch, "compiled_loops", lambda name: asked.append(name) or real(name)
    )
    compiled = run()
    assert asked == ["update_loops"]
    monkeypatch.setattr(
        quest_plus_batch,
        "compiled_loops",
        lambda name: None if name == "update_loops" else real(name),
    )
    numpy_route = run()
    for name in ("levels_db", "mean_db", "sd_db", "n_trials"):
        np.testing.assert_array_equal(getattr(compiled, name), getattr(numpy_route, name))


@pytest.mark.parametrize(
    "s",
    [
        QuestPlusSettings(0.0, 20.0, max_trials=5, entropy_over="all"),  # joint entropy
        QuestPlusSettings(0.0, 20.0, scales_db=1.5, lapses=0.02, max_trials=5),  # slope known
    ],
)
def test_tracks_placed_without_the_screen_update_with_numpy(monkeypatch, s):
    # their placement loads no numba, so neither does their update
    monkeypatch.setattr(quest_plus_batch, "compiled_loops", lambda name: pytest.fail(name))
    sim = simulate_quest_plus(s, np.full(8, 10.0), rng=np.random.default_rng(0))
    assert sim.n_trials.tolist() == [5] * 8


def test_a_sum_of_negative_zeros_is_positive_as_numpys():
    """numpy adds the pairwise sum to the reduction's identity 0.0: -0.0 + 0.0 = +0.0."""
    for n in range(1, 300):
        a = np.full(n, -0.0)
        assert not np.signbit(a.sum())
        assert not np.signbit(LOOPS.pairwise_sum(a))
