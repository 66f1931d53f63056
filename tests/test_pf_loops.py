"""The compiled psychometric climb (analysis/pf_loops.py) gives the numpy route's numbers bit
for bit (issue 22): its loops fuse the arithmetic between numpy's own exp, tanh, log and
log1p, and sum the score and information in np.einsum's order, so psychometric.csv keeps its
bytes whichever route a run takes."""

from __future__ import annotations

import numpy as np
import pytest

from masking_lab.analysis import pf_likelihood, pf_table
from masking_lab.analysis.pf_likelihood import nll, refit, set_nll, warm_compiled
from masking_lab.analysis.pf_table import SetTrials, fit_all, pf_job
from masking_lab.analysis.psychometric import PFJob, fit_pf_many, pf_curve
from masking_lab.procedures.fused import compiled_loops

LOOPS = compiled_loops("pf_loops", "masking_lab.analysis")


def _bits(a: np.ndarray) -> np.ndarray:
    """The IEEE bits (so that -0.0 and 0.0, or two NaNs' payloads, tell apart)."""
    return np.ascontiguousarray(a, dtype=np.float64).view(np.int64)


def _batch(rng: np.random.Generator, rows: int, levels: int, guess: float):
    """Bootstrap-like data sets of one psychometric function, and their bounds and start."""
    x = np.sort(rng.uniform(-8.0, 8.0, levels))
    n = rng.integers(1, 12, levels).astype(float)
    truth = (rng.uniform(-3, 3), rng.uniform(0.3, 3.0), rng.uniform(0.0, 0.08))
    k = rng.binomial(n.astype(int), pf_curve(x, *truth, guess), (rows, levels)).astype(float)
    span = max(x[-1] - x[0], 1.0)
    bounds = np.array([[x[0] - span, x[-1] + span], [np.log(0.1), np.log(20.0)], [0.0, 0.1]])
    start = np.array([truth[0], -np.log(truth[1]), 0.02])
    return x, n, k, start, bounds


def test_the_compiled_loops_load_in_the_test_environment():
    assert LOOPS is not None
    assert warm_compiled() is True


@pytest.mark.parametrize("seed", range(6))
def test_a_compiled_climb_is_the_numpy_climb_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    for levels in (1, 2, 3, 7, 8, 9, 16, 31):
        for guess, fit_lapse in ((1 / 3, True), (1 / 3, False), (0.5, True)):
            x, n, k, start, bounds = _batch(rng, int(rng.integers(1, 400)), levels, guess)
            want = refit(x, n, k, start, bounds, guess, fit_lapse)
            got = refit(x, n, k, start, bounds, guess, fit_lapse, compiled=True)
            np.testing.assert_array_equal(_bits(got[0]), _bits(want[0]))
            np.testing.assert_array_equal(got[1], want[1])


def test_a_compiled_climb_from_the_bounds_holds_them_alike():
    """Rows starting on a bound (a lapse held at 0 or 0.1, a flat scale), all answers
    correct or all wrong: the active set and the step halving take the same turns."""
    rng = np.random.default_rng(5)
    x, n, k, _, bounds = _batch(rng, 300, 6, 1 / 3)
    k[:40] = n  # all correct
    k[40:80] = 0.0  # all wrong
    starts = np.tile([0.0, 0.0, 0.02], (300, 1))
    starts[80:120, 2] = 0.0
    starts[120:160, 2] = 0.1
    starts[160:200, 1] = bounds[1, 1]
    starts[200:240, 0] = bounds[0, 0]
    for fit_lapse in (True, False):
        want = refit(x, n, k, starts, bounds, 1 / 3, fit_lapse)
        got = refit(x, n, k, starts, bounds, 1 / 3, fit_lapse, compiled=True)
        np.testing.assert_array_equal(_bits(got[0]), _bits(want[0]))
        np.testing.assert_array_equal(got[1], want[1])
        assert not want[1].all()  # some rows end outside: the case is exercised


def test_the_compiled_likelihood_is_nlls_bit_for_bit():
    rng = np.random.default_rng(9)
    for levels in (1, 5, 8, 13, 127, 128, 129, 300):  # numpy's pairwise blocks end at 128
        x, n, k, _, _ = _batch(rng, 50, levels, 1 / 3)
        xr, nr = np.tile(x, (50, 1)), np.tile(n, (50, 1))
        th = np.column_stack(
            [rng.uniform(-9, 9, 50), rng.uniform(-2.3, 3.0, 50), rng.uniform(0, 0.1, 50)]
        )
        rows = rng.permutation(50)[:30]
        want = nll(xr[rows], nr[rows], k[rows], th[:30], 1 / 3)
        got = pf_likelihood._nll_rows(LOOPS, (xr, nr, k), rows, th[:30], 1 / 3)
        np.testing.assert_array_equal(_bits(got), _bits(want))


def test_a_profile_grids_compiled_likelihood_is_nlls_bit_for_bit():
    rng = np.random.default_rng(4)
    for levels in (1, 6, 9, 40):
        x, n, k, _, bounds = _batch(rng, 1, levels, 1 / 3)
        aa, ll = np.meshgrid(np.linspace(*bounds[0], 81), np.linspace(*bounds[1], 24))
        grid = np.column_stack([aa.ravel(), ll.ravel(), np.full(aa.size, 0.02)])
        want = nll(x, n, k, grid, 1 / 3)
        got = set_nll(x, n, k[0], grid, 1 / 3, compiled=True)
        np.testing.assert_array_equal(_bits(got), _bits(want))
        np.testing.assert_array_equal(_bits(set_nll(x, n, k[0], grid, 1 / 3)), _bits(want))


def test_the_compiled_score_and_information_are_einsums_bit_for_bit():
    rng = np.random.default_rng(3)
    for levels, n_par in ((1, 2), (4, 3), (12, 3), (40, 2)):
        x, n, k, _, _ = _batch(rng, 200, levels, 1 / 3)
        xr, nr = np.tile(x, (200, 1)), np.tile(n, (200, 1))
        th = np.column_stack(
            [rng.uniform(-9, 9, 200), rng.uniform(-2.3, 3.0, 200), rng.uniform(0, 0.1, 200)]
        )
        rows = np.arange(0, 200, 3)
        want = pf_likelihood._scoring(xr[rows], nr[rows], k[rows], th[rows], 1 / 3, n_par)
        got = pf_likelihood._scoring_rows(LOOPS, (xr, nr, k), rows, th[rows], 1 / 3, n_par)
        for w, g in zip(want, got, strict=True):
            np.testing.assert_array_equal(_bits(g), _bits(w))


def test_the_step_bookkeeping_is_numpys_bit_for_bit():
    """The candidates (clip), their acceptance and the active set, on ties made on purpose:
    values on the bounds, zero scores of both signs, likelihoods exactly 1e-12 above."""
    rng = np.random.default_rng(12)
    m = 4000
    lo = np.tile([-5.0, -2.3, 0.0], (m, 1))
    hi = np.tile([5.0, 3.0, 0.1], (m, 1))
    th = np.where(rng.random((m, 3)) < 0.3, lo, np.where(rng.random((m, 3)) < 0.3, hi, 0.0))
    th += np.where(th == 0.0, rng.uniform(-1, 1, (m, 3)) * [5, 2, 0.05], 0.0)
    th[rng.random(m) < 0.1, 2] = -0.0  # a lapse of -0.0 stepping by -0.0 sits on 0.0 as +0.0
    step = rng.choice([-1.0, -0.0, 0.0, 1.0, 1e-3, -0.05], (m, 3))
    scale = rng.choice([1.0, 0.5, 0.25], m)
    pending = np.sort(rng.choice(m, m // 2, replace=False))
    want = np.clip(th[pending] + scale[pending, None] * step[pending], lo[pending], hi[pending])
    got = np.empty_like(want)
    LOOPS.candidates(th, scale, step, lo, hi, pending, got)
    np.testing.assert_array_equal(_bits(got), _bits(want))

    was = rng.uniform(0, 10, m)
    cv = np.where(rng.random(pending.size) < 0.5, was[pending] + 1e-12, was[pending] + 2e-12)
    new, val, sc = th.copy(), was.copy(), scale.copy()
    left = LOOPS.accept(got, cv, was, pending, new, val, sc)
    ok = cv <= was[pending] + 1e-12
    new_np, val_np, sc_np = th.copy(), was.copy(), scale.copy()
    new_np[pending[ok]], val_np[pending[ok]] = got[ok], cv[ok]
    sc_np[pending[~ok]] /= 2
    assert left.tolist() == pending[~ok].tolist() and 0 < ok.sum() < ok.size
    for a, b in ((new, new_np), (val, val_np), (sc, sc_np)):
        np.testing.assert_array_equal(_bits(a), _bits(b))

    for n_par in (2, 3):
        score = rng.choice([-1.0, -0.0, 0.0, 1.0], (m, n_par))
        info = rng.normal(0, 1, (m, n_par, n_par))
        info[rng.random((m, n_par, n_par)) < 0.2] = -0.0
        on, l2, h2 = th[:, :n_par], lo[:, :n_par], hi[:, :n_par]
        held = ((on <= l2) & (score < 0)) | ((on >= h2) & (score > 0))
        free = (~held).astype(float)
        info_np = info * free[:, :, None] * free[:, None, :] + held[:, :, None] * np.eye(n_par)
        s2, i2 = score.copy(), info.copy()
        assert LOOPS.hold(th, lo, hi, s2, i2, n_par) == bool(held.any())
        np.testing.assert_array_equal(_bits(i2), _bits(info_np))
        np.testing.assert_array_equal(_bits(s2), _bits(score * free))


def _jobs() -> list[PFJob]:
    rng = np.random.default_rng(21)
    jobs = []
    for i in range(30):
        x = np.repeat(np.linspace(-6.0, 6.0, 3 + i % 6), 5 + i % 9)
        truth = (rng.uniform(-2, 2), rng.uniform(0.4, 1.5), rng.uniform(0.0, 0.06))
        r = rng.random(x.size) < pf_curve(x, *truth, 1 / 3)
        jobs.append(PFJob(x.tolist(), r.tolist(), n_boot=80, seed=i))
        if i % 7 == 0:
            jobs.append(PFJob(x.tolist(), r.tolist(), lapse=0.02, n_boot=50, seed=i))
    return jobs


def test_fits_made_compiled_are_the_fits_made_with_numpy():
    jobs = _jobs()
    want = fit_pf_many(jobs)
    got = fit_pf_many(jobs, compiled=True)
    assert sum(f.ok for f in want) > 25
    assert repr(got) == repr(want)  # every field, NaNs and intervals included


def test_a_study_large_enough_climbs_compiled_with_the_same_fits(monkeypatch):
    trials = SetTrials({"level_unit": "db_sl"}, [0.0, 2.0, 4.0, 6.0] * 12, [False, True] * 24)
    jobs = [pf_job(trials, seed, 60) for seed in range(8)]
    want = fit_all(jobs, workers=1)
    routes = []
    real = pf_table.fit_pf_many

    def spy(js, compiled):
        routes.append(compiled)
        return real(js, compiled=compiled)

    monkeypatch.setattr(pf_table, "fit_pf_many", spy)
    monkeypatch.setattr(pf_table, "PF_COMPILED_FROM", 8 * 60)
    assert repr(fit_all(jobs, workers=1)) == repr(want)
    monkeypatch.setattr(pf_table, "PF_COMPILED_FROM", 8 * 60 + 1)
    assert repr(fit_all(jobs, workers=1)) == repr(want)
    assert routes == [True, False]


def test_without_numba_the_numpy_route_runs(monkeypatch):
    monkeypatch.setattr(pf_likelihood, "_loops", lambda: None)
    assert warm_compiled() is False
    rng = np.random.default_rng(1)
    x, n, k, start, bounds = _batch(rng, 50, 5, 1 / 3)
    want = refit(x, n, k, start, bounds, 1 / 3, True)
    got = refit(x, n, k, start, bounds, 1 / 3, True, compiled=True)
    np.testing.assert_array_equal(_bits(got[0]), _bits(want[0]))


def test_loops_that_fail_to_compile_leave_the_numpy_route(monkeypatch):
    """A numba that imports but cannot compile here (a version mismatch) must not fail a run:
    the study's fits are then made on numpy's route, with the same numbers."""

    class Broken:
        def __getattr__(self, name):
            def fail(*args):
                raise RuntimeError(f"numba cannot compile {name}")

            return fail

    monkeypatch.setattr(pf_likelihood, "_loops", lambda: Broken())
    assert warm_compiled() is False
    trials = SetTrials({"level_unit": "db_sl"}, [0.0, 2.0, 4.0, 6.0] * 12, [False, True] * 24)
    jobs = [pf_job(trials, seed, 60) for seed in range(4)]
    want = fit_all(jobs, workers=1)
    monkeypatch.setattr(pf_table, "PF_COMPILED_FROM", 1)
    assert repr(fit_all(jobs, workers=1)) == repr(want)
