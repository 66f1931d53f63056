"""The psi-marginal placement screened in float32 (procedures/psi_screen.py) places every trial
where the float64 expected entropy is least: along simulated tracks, at the extremes of the
posterior, by both the compiled and the numpy routes, and with numba's JIT disabled."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from masking_lab.core.psychometric import Psychometric
from masking_lab.procedures import psi_screen
from masking_lab.procedures.fused import compiled_loops
from masking_lab.procedures.quest_plus import QuestPlusSettings, expected_entropy, tables
from masking_lab.procedures.quest_plus_batch import simulate_quest_plus

SHIPPED = QuestPlusSettings(-20.0, 45.0, target_sd_db=0.4, max_trials=300)
GRIDS = {
    "shipped": SHIPPED,
    "normal prior": QuestPlusSettings(
        -20.0, 45.0, prior="normal", prior_mean_db=10.0, prior_sd_db=6.0, max_trials=300
    ),
    "coarse thresholds": QuestPlusSettings(
        -10.0, 30.0, threshold_min_db=-5.0, threshold_max_db=25.0, threshold_step_db=1.0
    ),
    # steep scales: p(wrong) of the lapse-free points underflows float32 far above threshold
    "steep": QuestPlusSettings(-20.0, 45.0, scales_db=(0.1, 0.5, 2.0), lapses=(0.0, 0.03)),
}


def _tracks(s: QuestPlusSettings, n_tracks: int, n_trials: int, seed: int):
    """Posteriors of simulated tracks after each trial (placed by the float64 argmin)."""
    t = tables(s)
    rng = np.random.default_rng(seed)
    truth = rng.uniform(-5.0, 25.0, n_tracks)
    psy = Psychometric(0.0, 1.5, 1 / 3, 0.03, s.p_at_threshold)
    post = np.repeat(t.prior[None], n_tracks, axis=0)
    idx = np.full(n_tracks, int(np.searchsorted(t.levels_db, t.first_level_db)))
    for _ in range(n_trials):
        c = rng.random(n_tracks) < psy.p_correct(t.levels_db[idx] - truth)
        post = post * np.where(c[:, None, None], t.p_correct[idx], t.p_wrong[idx])
        post /= post.reshape(n_tracks, -1).sum(axis=1)[:, None, None]
        yield post
        idx = np.argmin(expected_entropy(t, post), axis=1)


def test_the_compiled_loops_run_in_the_test_environment():
    # numba is a dependency: the suite must test the compiled route, not silently the fallback
    assert compiled_loops("psi_loops") is not None


@pytest.mark.parametrize("per_pass", [None, 7])  # 7: 24 tracks in passes of sorted tracks
@pytest.mark.parametrize("name", GRIDS)
def test_every_placement_of_simulated_tracks_is_the_float64_argmin(name, per_pass, monkeypatch):
    if per_pass is not None:
        monkeypatch.setattr(psi_screen, "_TRACKS_PER_PASS", per_pass)
    s = GRIDS[name]
    t = tables(s)
    for k, post in enumerate(_tracks(s, 24, 80, seed=len(name))):
        if k % 4:
            continue
        exact = np.argmin(expected_entropy(t, post), axis=1)
        np.testing.assert_array_equal(psi_screen.best_levels(t, post), exact)  # batch route
        np.testing.assert_array_equal(  # one track at a time, as a session places
            [psi_screen.best_levels(t, post[i : i + 1])[0] for i in range(0, 24, 5)], exact[::5]
        )


@pytest.mark.parametrize("use_compiled", [True, False])
def test_the_bounds_hold_the_float64_entropy_along_tracks(use_compiled):
    t = tables(GRIDS["steep"])
    for k, post in enumerate(_tracks(GRIDS["steep"], 12, 120, seed=3)):
        if k % 10 == 9:
            low, high = psi_screen.screen(t, post, use_compiled=use_compiled)
            exact = expected_entropy(t, post)
            assert np.isfinite(low).all() and np.isfinite(high).all()
            assert np.all((low <= exact) & (exact <= high))
            # tight enough to settle most placements without the float64 check
            assert np.median(high - low) < 1e-3


def _extreme_posteriors(shape):
    """Posteriors a long or unlucky track can reach: huge dynamic ranges (cells down to
    1e-300), exact zeros, a single cell, all mass at the edge of the grid."""
    n_t, n_n = shape

    @st.composite
    def one(draw):
        seed = draw(st.integers(0, 2**32 - 1))
        rng = np.random.default_rng(seed)
        kind = draw(st.sampled_from(["power", "zeros", "delta", "edge"]))
        p = rng.random(shape)
        if kind == "power":
            p = p ** draw(st.floats(1.0, 100.0))
        elif kind == "zeros":
            p[rng.random(shape) < draw(st.floats(0.5, 0.99))] = 0.0
            p[rng.integers(n_t), rng.integers(n_n)] = 1.0
        elif kind == "delta":
            p = np.zeros(shape)
            p[rng.integers(n_t), rng.integers(n_n)] = 1.0
        else:
            p[: n_t - 2] *= 1e-250
        return p / p.sum()

    return one()


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(post=_extreme_posteriors(tables(SHIPPED).prior.shape), use_compiled=st.booleans())
def test_the_bounds_hold_at_the_extremes_and_the_placement_is_the_argmin(post, use_compiled):
    t = tables(SHIPPED)
    batch = np.stack([post, post[::-1]])  # a second track, mirrored
    low, high = psi_screen.screen(t, batch, use_compiled=use_compiled)
    exact = expected_entropy(t, batch)
    assert np.isfinite(low).all() and np.isfinite(high).all()
    assert np.all((low <= exact) & (exact <= high))
    best = psi_screen.best_levels(t, np.repeat(batch, 3, axis=0))  # 6 tracks: compiled route
    # equal entropies (a flat region) may settle on either level: compare entropies, not indices
    picked = np.repeat(exact, 3, axis=0)[np.arange(6), best]
    np.testing.assert_allclose(picked, np.repeat(exact.min(axis=1), 3), rtol=0, atol=1e-12)


@pytest.mark.parametrize("use_compiled", [True, False])
def test_an_answer_that_no_joint_probability_reaches_adds_nothing(use_compiled):
    # All mass on a lapse-free, steep point at the lowest threshold: far above it p(wrong) is
    # below FLUSH in every cell the posterior holds, so that answer's m is 0 at every threshold
    # (0, never subnormal: no clamping before the logarithm) and its p·ln p is 0·ln 0 = 0.
    t = tables(GRIDS["steep"])
    both = psi_screen._float32_tables(t)
    n_s = t.levels_db.size
    n = int(np.argmax((both[0, :, n_s:] == 0).sum(axis=1)))  # the point with most zeros
    assert (both[0, n, n_s:] == 0).any()
    post = np.zeros(t.prior.shape)
    post[0, n] = 1.0
    low, high = psi_screen.screen(t, post[None], use_compiled=use_compiled)
    exact = expected_entropy(t, post[None])
    assert np.isfinite(low).all() and np.isfinite(high).all()
    assert np.all((low <= exact) & (exact <= high))
    nonzero = both[both > 0]
    assert nonzero.min() >= psi_screen.FLUSH * (1 - 2**-23)  # so every product is ≥ ~1e-36
    assert float(nonzero.min()) ** 2 > np.finfo(np.float32).tiny


def test_the_compiled_and_numpy_routes_place_alike():
    t = tables(SHIPPED)
    posts = list(_tracks(SHIPPED, 40, 60, seed=11))
    for post in posts[::12]:
        np.testing.assert_array_equal(
            psi_screen.best_levels(t, post),
            psi_screen._settle(
                t,
                post,
                np.ones(post.shape[:1] + t.levels_db.shape, dtype=bool),
                use_compiled=False,
            ),
        )
        rows = np.arange(post.shape[0])
        levels = rows % t.levels_db.size
        np.testing.assert_allclose(
            psi_screen.pair_entropies(t, post, rows, levels),
            psi_screen.pair_entropies(t, post, rows, levels, use_compiled=False),
            rtol=1e-13,
            atol=0,
        )


def test_joint_entropy_and_a_known_slope_take_the_float64_route(monkeypatch):
    def no_screen(*_args, **_kwargs):
        raise AssertionError("the screen runs only for the psi-marginal")

    monkeypatch.setattr(psi_screen, "screen", no_screen)
    for s, over in (
        (QuestPlusSettings(0.0, 20.0, scales_db=(0.75, 1.5), lapses=(0.02,)), "all"),
        (QuestPlusSettings(0.0, 20.0, scales_db=1.5, lapses=0.02), "threshold"),
    ):
        t = tables(s)
        post = next(_tracks(s, 5, 1, seed=2))
        np.testing.assert_array_equal(
            psi_screen.best_levels(t, post, over),
            np.argmin(expected_entropy(t, post, over), axis=1),
        )


def test_a_bound_that_is_not_a_number_falls_back_to_the_full_computation(monkeypatch):
    t = tables(SHIPPED)
    posts = list(_tracks(SHIPPED, 6, 20, seed=5))
    post = posts[-1]

    def nan_screen(tb, p, **_kwargs):
        nan = np.full((p.shape[0], tb.levels_db.size), np.nan)
        return nan, nan

    monkeypatch.setattr(psi_screen, "screen", nan_screen)
    np.testing.assert_array_equal(
        psi_screen.best_levels(t, post), np.argmin(expected_entropy(t, post), axis=1)
    )


def test_tracks_place_alike_with_numba_disabled():
    """A process without the JIT (the numpy routes) runs the same tracks."""
    code = (
        "import hashlib, numpy as np\n"
        "from masking_lab.procedures.quest_plus import QuestPlusSettings\n"
        "from masking_lab.procedures.quest_plus_batch import simulate_quest_plus\n"
        "from masking_lab.procedures.fused import compiled_loops\n"
        "s = QuestPlusSettings(-20.0, 45.0, max_trials=40)\n"
        "sim = simulate_quest_plus(s, np.linspace(0, 20, 10), rng=np.random.default_rng(4))\n"
        "print(compiled_loops('psi_loops') is not None,"
        " hashlib.sha256(sim.levels_db.tobytes()).hexdigest())\n"
    )
    out = {}
    for disabled in ("0", "1"):
        env = {**os.environ, "NUMBA_DISABLE_JIT": disabled}
        res = subprocess.run(
            [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
        )
        out[disabled] = res.stdout.split()
    assert out["0"][0] == "True" and out["1"][0] == "False"
    assert out["0"][1] == out["1"][1]
    here = simulate_quest_plus(
        QuestPlusSettings(-20.0, 45.0, max_trials=40),
        np.linspace(0, 20, 10),
        rng=np.random.default_rng(4),
    )
    import hashlib

    assert hashlib.sha256(here.levels_db.tobytes()).hexdigest() == out["0"][1]


def _tailed_posterior(t, tail_mass: float, spread_over: int) -> np.ndarray:
    """A narrow posterior near the middle of the threshold grid whose two tails hold
    ``tail_mass`` each, spread evenly over the outermost ``spread_over`` thresholds."""
    n_t, n_n = t.prior.shape
    post = np.zeros((n_t, n_n))
    mid = n_t // 2
    post[mid - 3 : mid + 4] = t.prior[mid - 3 : mid + 4]
    post *= (1.0 - 2 * tail_mass) / post.sum()
    for rows in (slice(0, spread_over), slice(n_t - spread_over, n_t)):
        post[rows] = tail_mass / (spread_over * n_n)
    return post


@pytest.mark.parametrize("use_compiled", [True, False])
@pytest.mark.parametrize("spread_over", [1, 40])
def test_tails_left_out_stay_within_the_bound(use_compiled, spread_over):
    t = tables(SHIPPED)
    loops = compiled_loops("psi_loops") if use_compiled else None
    # just under a side's budget: the tails are left out; over it, as many of their
    # thresholds as the budget holds
    n_t, mid = t.prior.shape[0], t.prior.shape[0] // 2
    for scale, left_out in ((0.99, True), (1.5, False)):
        post = _tailed_posterior(t, scale * psi_screen.TAIL / 4, spread_over)[None]
        p32, lo, hi = psi_screen._float32_posterior(post, loops)
        kept = int(spread_over / scale)
        assert (lo, hi) == ((mid - 3, mid + 4) if left_out else (kept, n_t - kept))
        assert bool(p32[:spread_over].any()) is not left_out
        low, high = psi_screen.screen(t, post, use_compiled=use_compiled)
        exact = expected_entropy(t, post)
        assert np.all((low <= exact) & (exact <= high))
        assert psi_screen.best_levels(t, post)[0] == np.argmin(exact[0])


def test_the_compiled_and_numpy_routes_leave_out_the_same_tails():
    t = tables(SHIPPED)
    loops = compiled_loops("psi_loops")
    spans = []
    for post in list(_tracks(SHIPPED, 24, 150, seed=8))[::25]:
        a, lo_a, hi_a = psi_screen._float32_posterior(post, loops)
        b, lo_b, hi_b = psi_screen._float32_posterior(post, None)
        assert (lo_a, hi_a) == (lo_b, hi_b)
        np.testing.assert_array_equal(a, b)
        spans.append(hi_a - lo_a)
    assert spans[-1] < spans[0] == t.prior.shape[0]  # late in a track tails are left out
