"""The compiled staircase trial (procedures/staircase_loops.py) gives the numpy route's tracks bit
for bit: every level, answer, reversal, trial count and status, under every rule the settings
offer (bounds clamped or stopping, an initial one-down-one-up phase, unequal steps, a trial
cap), fed the same answers."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from masking_lab.procedures import staircase_batch, staircase_loops
from masking_lab.procedures.fused import compiled_loops
from masking_lab.procedures.staircase import StaircaseSettings
from masking_lab.procedures.staircase_batch import Observer, replay_many, simulate

SETTINGS = [
    StaircaseSettings(start_level_db=0.0),
    StaircaseSettings(start_level_db=-10.0, step_sizes_db=(4.0, 2.0, 1.0), down_up_ratio=0.7393),
    StaircaseSettings(start_level_db=3.0, min_level_db=-6.0, max_level_db=6.0, max_bound_hits=2),
    StaircaseSettings(start_level_db=0.0, min_level_db=-5.0, max_level_db=5.0, bound_policy="stop"),
    StaircaseSettings(start_level_db=0.0, initial_one_down_one_up=True, n_up=2, n_down=2),
    StaircaseSettings(start_level_db=1.5, n_reversals=5, n_reversals_averaged=4, max_trials=20),
]


def test_the_compiled_loop_runs_in_the_test_environment():
    assert compiled_loops("staircase_loops") is not None


def test_the_status_codes_are_the_batch_modules():
    codes = ("RUNNING", "COMPLETED", "CEILING", "FLOOR", "TRIAL_CAP")
    assert [getattr(staircase_loops, c) for c in codes] == [
        getattr(staircase_batch, c) for c in codes
    ]


def _both_routes(monkeypatch, run):
    used = []
    real = staircase_batch.compiled_loops
    monkeypatch.setattr(staircase_batch, "compiled_loops", lambda n: used.append(n) or real(n))
    compiled = run()
    assert used == ["staircase_loops"]
    monkeypatch.setattr(staircase_batch, "COMPILED_TRACKS", 10**9)
    numpy_route = run()
    monkeypatch.undo()
    for field in dataclasses.fields(compiled):
        a, b = getattr(compiled, field.name), getattr(numpy_route, field.name)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b, err_msg=field.name)
            assert a.dtype == b.dtype, field.name
        else:
            assert a == b, field.name
    return compiled


@pytest.mark.parametrize("settings", SETTINGS)
def test_replayed_answers_give_the_same_tracks(monkeypatch, settings):
    answers = np.random.default_rng(4).random((400, 90)) < 0.72
    tracks = _both_routes(monkeypatch, lambda: replay_many(settings, answers))
    assert len(set(tracks.status.tolist())) >= 2  # the rules were exercised, not one path


@pytest.mark.parametrize("settings", SETTINGS[:4])
def test_simulated_observers_give_the_same_tracks(monkeypatch, settings):
    thr = np.random.default_rng(1).normal(0.0, 4.0, 300)

    def run():
        return simulate(settings, thr, Observer(scale_db=1.5), np.random.default_rng(8))

    _both_routes(monkeypatch, run)


def test_few_tracks_load_no_numba(monkeypatch):
    monkeypatch.setattr(staircase_batch, "compiled_loops", lambda name: pytest.fail(name))
    tracks = replay_many(SETTINGS[0], np.ones((3, 40), dtype=bool))
    assert tracks.n_trials.tolist() == [40] * 3
