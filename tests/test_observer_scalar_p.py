"""The simulated participant's one-level p(correct) is the array version's value, bit for bit."""

from __future__ import annotations

import math

import numpy as np
import pytest

from masking_lab.core.psychometric import Psychometric
from masking_lab.simulation.observer import scalar_p_correct


@pytest.mark.parametrize(
    ("scale", "guess", "lapse"), [(1.5, 1 / 3, 0.02), (0.7, 0.5, 0.0), (4.0, 0.0, 0.1)]
)
def test_scalar_p_correct_equals_array_version(scale: float, guess: float, lapse: float) -> None:
    psy = Psychometric(-3.0, scale, guess, lapse)
    rng = np.random.default_rng(5)
    levels = np.concatenate(
        [
            rng.uniform(-60.0, 60.0, 5_000),
            rng.normal(psy.location_db, 0.01, 1_000),
            [psy.location_db, 0.0, -0.0, 1e6, -1e6, 745.0 * scale, -745.0 * scale],
        ]
    )
    for x in [*levels.tolist(), -math.inf, math.inf]:
        want = float(psy.p_correct(x))
        assert scalar_p_correct(psy, psy.location_db, x) == want, x
