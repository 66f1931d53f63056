"""Compiled loop (numba) for one trial of many lockstep staircases.

Imported only through :func:`masking_lab.procedures.fused.compiled_loops`; the numpy route in
:func:`masking_lab.procedures.staircase_batch.run_staircases` is the reference. One trial's
bookkeeping (the run counter, reversals, the step and the bounds) is about forty numpy calls on
the running tracks' arrays; here it is one pass over those tracks with the same comparisons and
the same two rounded operations (``−up·ratio`` and ``level + step``), so every level, reversal and
status is the numpy route's bit for bit (tests/test_staircase_loops.py). The answers still come
from the caller's ``respond``, so the random draws are the same too.
"""

from __future__ import annotations

import numba
import numpy as np

# staircase_batch's status codes, repeated so that this module stays a leaf that numba compiles
# alone (tests/test_staircase_loops.py checks that they agree)
RUNNING, COMPLETED, CEILING, FLOOR, TRIAL_CAP = range(5)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def staircase_trial(t, active, lv, correct, level, run, direction, n_rev, hits, status,
                    last_correct, rev_levels, rev_trials, steps, rules, hi, lo,
                    capped):  # fmt: skip
    """Apply trial ``t``'s answers ``correct`` (at levels ``lv``) to the tracks ``active``.

    Updates the per-track state arrays in place, as the numpy route does, and returns the tracks
    still running. ``rules``: (n_up, n_down, down_up_ratio, initial one-down-one-up as 0/1,
    n_reversals, clamp as 0/1, max_bound_hits); ``capped``: the trial cap ends the tracks still
    running after this trial.
    """
    n_up, n_down, ratio = int(rules[0]), int(rules[1]), rules[2]
    initial_rule, n_reversals = rules[3] != 0.0, int(rules[4])
    clamp, max_bound_hits = rules[5] != 0.0, int(rules[6])
    last_step = steps.size - 1
    still = np.empty(active.size, dtype=active.dtype)
    n_still = 0
    for i in range(active.size):
        row = active[i]
        x, c = lv[i], correct[i]
        same = t > 0 and last_correct[row] == c
        r = run[row]
        r = (r + 1 if same else 1) if c else (r - 1 if same else -1)  # the run counter
        k = n_rev[row]
        initial = initial_rule and k == 0
        wants_down = r >= n_down
        wants_up = r <= -n_up
        # the initial phase: one down after a correct answer, one up after a wrong one
        want = (-1 if c else 1) if initial else (-1 if wants_down else (1 if wants_up else 0))
        d = direction[row]
        if want != 0 and d != 0 and d != want:  # a reversal
            rev_levels[row, k] = x
            rev_trials[row, k] = t
            k += 1
        if want != 0:
            direction[row] = want
        n_rev[row] = k
        done = k >= n_reversals
        up = steps[min(k, last_step)]
        down = -up * ratio
        if done:
            step = 0.0
        elif initial:
            step = down if c else up
        else:
            step = down if wants_down else (up if wants_up else 0.0)
        moving = step != 0.0
        target = x + step
        rising = step > 0
        beyond = moving and (target > hi if rising else target < lo)
        free = moving and not beyond
        new_level = target if free else x
        h = hits[row]
        new_hits = 0 if free else h
        new_status = COMPLETED if done else RUNNING
        if beyond:
            ended = CEILING if rising else FLOOR
            if clamp:
                bound = hi if rising else lo
                new_hits = h + 1 if x == bound else 0
                new_level = bound
                if new_hits >= max_bound_hits:
                    new_status = ended
            else:
                new_status = ended  # the level stays at the trial's level
        if capped and new_status == RUNNING:
            new_status = TRIAL_CAP
        run[row] = 0 if moving else r
        level[row] = new_level
        hits[row] = new_hits
        status[row] = new_status
        last_correct[row] = c
        if new_status == RUNNING:
            still[n_still] = row
            n_still += 1
    return still[:n_still]
