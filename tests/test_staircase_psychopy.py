"""Conformance: our staircase's level track equals psychopy.data.StairHandler's.

Equivalent settings: stepType 'lin' over dB values, the same step list, nUp/nDown, nReversals,
applyInitialRule ↔ initial_one_down_one_up, minVal/maxVal ↔ clamped bounds, nTrials=0 (PsychoPy's
nTrials is a minimum, not a cap). Deliberate differences, not exercised here: PsychoPy raises
nReversals to len(stepSizes) if it is smaller (we keep the setting as written); we end a track
pinned at a bound as ceiling/floor after ``max_bound_hits`` hits (PsychoPy keeps going); and we
support a down/up step ratio ≠ 1, which PsychoPy cannot express.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from masking_lab.procedures.staircase import StaircaseSettings, start

psychopy_data = pytest.importorskip("psychopy.data", reason="PsychoPy is in the [test] extra")
from psychopy import logging as psychopy_logging  # noqa: E402

psychopy_logging.console.setLevel(psychopy_logging.ERROR)


def _both(steps, n_up, n_down, n_reversals, initial, lo, hi, responses) -> tuple[object, object]:
    ours = start(
        StaircaseSettings(
            start_level_db=10.0,
            step_sizes_db=tuple(steps),
            n_up=n_up,
            n_down=n_down,
            n_reversals=n_reversals,
            n_reversals_averaged=1,
            initial_one_down_one_up=initial,
            min_level_db=lo,
            max_level_db=hi,
            max_bound_hits=10**9,
            max_trials=None,
        )
    )
    theirs = psychopy_data.StairHandler(
        startVal=10.0,
        stepSizes=list(steps),
        nUp=n_up,
        nDown=n_down,
        nReversals=n_reversals,
        nTrials=0,
        stepType="lin",
        applyInitialRule=initial,
        minVal=lo,
        maxVal=hi,
        originPath=-1,  # no copy of the calling script (a walk up the whole stack)
    )
    it = iter(responses)
    for level in theirs:
        assert level == pytest.approx(ours.level_db, abs=1e-9)
        r = next(it, None)
        if r is None:
            break
        theirs.addResponse(int(r))
        ours = ours.update(r)
        if ours.finished:
            break
    return ours, theirs


@settings(max_examples=400, deadline=None)
@given(
    steps=st.lists(st.sampled_from([0.5, 1.0, 2.0, 3.0, 4.0]), min_size=1, max_size=4),
    n_up=st.integers(1, 3),
    n_down=st.integers(1, 4),
    extra_reversals=st.integers(0, 10),
    initial=st.booleans(),
    lo=st.sampled_from([None, -10.0]),
    hi=st.sampled_from([None, 20.0]),
    responses=st.lists(st.booleans(), min_size=1, max_size=200),
)
def test_level_track_matches_stairhandler(
    steps, n_up, n_down, extra_reversals, initial, lo, hi, responses
):
    n_reversals = len(steps) + extra_reversals
    ours, theirs = _both(steps, n_up, n_down, n_reversals, initial, lo, hi, responses)
    n = ours.n_trials
    assert list(ours.levels_db) == pytest.approx(list(theirs.intensities)[:n], abs=1e-9)
    assert list(ours.reversal_levels_db) == pytest.approx(theirs.reversalIntensities, abs=1e-9)
    assert (ours.status == "completed") == bool(theirs.finished)


def test_paper_settings_over_simulated_observers():
    """The paper's 1-up-3-down, 11 reversals, with responses from a 3IFC observer."""
    rng = np.random.default_rng(2020)
    for _ in range(200):
        threshold = rng.uniform(-5, 15)
        ours = start(StaircaseSettings(start_level_db=20.0, max_bound_hits=10**9))
        theirs = psychopy_data.StairHandler(
            startVal=20.0,
            stepSizes=[4, 4, 4, 2],
            nUp=1,
            nDown=3,
            nReversals=11,
            nTrials=0,
            stepType="lin",
            applyInitialRule=False,
            originPath=-1,
        )
        for level in theirs:
            assert level == pytest.approx(ours.level_db)
            p = 1 / 3 + (2 / 3) / (1 + np.exp(-(level - threshold) / 1.5))
            r = bool(rng.random() < p)
            theirs.addResponse(int(r))
            ours = ours.update(r)
        assert ours.status == "completed"
        assert list(ours.reversal_levels_db) == pytest.approx(theirs.reversalIntensities)
        assert ours.al_db == pytest.approx(float(np.mean(theirs.reversalIntensities[-8:])))
