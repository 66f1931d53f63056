"""QUEST+'s cached entropy terms: the joint path with L·ln L kept per grid gives the numbers the
per-call computation gave, bit for bit (the questplus oracle tests pin that computation)."""

from __future__ import annotations

import numpy as np
import pytest

from masking_lab.core.psychometric import Psychometric
from masking_lab.procedures.quest_plus import QuestPlusSettings, expected_entropy, tables


def _per_call_entropy(t, posterior: np.ndarray) -> np.ndarray:
    """The joint expected entropy with L·ln L computed on every call (the uncached route)."""
    r = posterior.shape[0]
    flat = posterior.reshape(r, -1)
    plogp = flat * np.log(np.where(flat > 0, flat, 1.0))
    out = np.zeros((r, t.levels_db.size))
    for like in (t.p_correct, t.p_wrong):
        lf = like.reshape(like.shape[0], -1)
        pk = flat @ lf.T
        out += pk * np.log(pk) - (plogp @ lf.T + flat @ (lf * np.log(lf)).T)
    return out


GRIDS = [
    # the shipped experiment-I grid: slope known (one nuisance point, joint = marginal)
    QuestPlusSettings(-20.0, 45.0, target_sd_db=1.08, min_trials=10, max_trials=80),
    # slope and lapse unknown, Watson's joint entropy, lapse 0 (p_wrong down to ~1e-60)
    QuestPlusSettings(
        -10.0, 30.0, level_step_db=1.0, scales_db=(0.5, 1.0, 2.0, 4.0), lapses=(0.0, 0.02, 0.05),
        entropy_over="all", max_trials=40,
    ),
]  # fmt: skip


@pytest.mark.parametrize("case", range(len(GRIDS)))
def test_cached_joint_entropy_equals_the_per_call_computation(case):
    s = GRIDS[case]
    t = tables(s)
    rng = np.random.default_rng(case)
    track = s.start()
    psy = Psychometric(float(rng.uniform(0.0, 15.0)), 1.5, 1 / 3, 0.02)
    posteriors = [track.posterior]
    while not track.finished:
        track = track.update(bool(rng.random() < psy.p_correct(track.next_level())))
        posteriors.append(track.posterior)
    batch = np.stack(posteriors)  # every step of the track at once: the batch (GEMM) route
    for post in posteriors:
        ours = expected_entropy(t, post[None], "all")
        np.testing.assert_array_equal(ours, _per_call_entropy(t, post[None]))
    np.testing.assert_array_equal(expected_entropy(t, batch, "all"), _per_call_entropy(t, batch))
    assert track.n_trials >= 10


def test_the_entropy_terms_are_computed_once_per_grid_and_read_only():
    t = tables(GRIDS[1])
    c, w = t.xlogx_tables
    assert t.xlogx_tables[0] is c and t.xlogx_tables[1] is w
    for table, like in ((c, t.p_correct), (w, t.p_wrong)):
        assert table.shape == (like.shape[0], like.shape[1] * like.shape[2])
        assert not table.flags.writeable
        assert np.all(np.isfinite(table)) and np.all(table <= 0.0)
        lf = like.reshape(like.shape[0], -1)
        np.testing.assert_array_equal(table, lf * np.log(lf))
