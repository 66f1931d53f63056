"""The transformed up-down staircase on a dB scale (pure: no I/O, no clock, no RNG).

A :class:`Staircase` is an immutable snapshot; :meth:`Staircase.update` returns the next one.
Its whole state is rebuilt by :func:`replay` from the settings and the responses, which is how a
crashed session resumes.

Rules (paper §2.3 defaults: 1-up 3-down, stop after 11 reversals, AL = mean of the last 8):

* ``n_down`` consecutive correct answers lower the level by the down step; ``n_up`` consecutive
  wrong answers raise it by the up step. The run counter restarts after every step.
* A reversal is a change of direction; its level is the level of the trial that caused it.
* The up step after ``k`` reversals is ``step_sizes_db[min(k, len - 1)]``; the down step is that
  times ``down_up_ratio`` (García-Pérez 1998 recommends 0.7393 for 1-up 3-down in **2AFC**,
  whose zero-drift point is 83.15 % correct; docs/speed-accuracy.md shows it is not
  step-size invariant in 3IFC; :func:`masking_lab.procedures.downup_ratio.downup_ratio_for`
  computes a ratio for a target).
* ``initial_one_down_one_up``: until the first reversal, every answer moves the level (one
  correct → down, one wrong → up), and the step at the first reversal follows the same rule.
* Bounds: with ``bound_policy="clamp"`` a step past a bound stops at the bound, and each step asked
  for beyond a bound the level already sits on is a *hit*; ``max_bound_hits`` hits in a row end the
  track as ``ceiling`` (upper) or ``floor`` (lower). With ``"stop"`` the first step past a bound
  ends it. A ceiling or floor is never a threshold: :attr:`Staircase.al_db` is None.

With ``down_up_ratio = 1``, ``bound_policy = "clamp"`` and no hit limit reached, the level track
and reversal levels equal ``psychopy.data.StairHandler(stepType='lin')`` given the same responses
(see tests/test_staircase_psychopy.py and docs/staircase.md).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from typing import Literal

from masking_lab.core.errors import StaircaseError
from masking_lab.core.roots import brentq
from masking_lab.procedures.base import ThresholdEstimate, TrackState
from masking_lab.procedures.base import replay as _replay

Direction = Literal["start", "up", "down"]
Status = Literal["running", "completed", "ceiling", "floor", "trial_cap"]
BoundPolicy = Literal["clamp", "stop"]


@dataclass(frozen=True)
class StaircaseSettings:
    """Settings of a transformed up-down staircase. All levels and steps in dB.

    Attributes
    ----------
    start_level_db : float
        Level of the first trial, dB (dB SL or dB re 1 V: the caller's unit).
    step_sizes_db : tuple[float, ...]
        Up step in dB after 0, 1, 2, … reversals; the last entry repeats.
    down_up_ratio : float
        Down step / up step (1.0 = equal steps, as PsychoPy).
    n_up, n_down : int
        Consecutive wrong / correct answers that raise / lower the level.
    n_reversals : int
        Reversals after which the track stops (11 in the paper).
    n_reversals_averaged : int
        Last reversals averaged into the AL (8 in the paper).
    initial_one_down_one_up : bool
        Use a 1-down 1-up rule until the first reversal (PsychoPy's ``applyInitialRule``).
    min_level_db, max_level_db : float or None
        Bounds in dB; the runner passes the device limit as ``max_level_db``.
    bound_policy : {"clamp", "stop"}
        What a step past a bound does (see module docstring).
    max_bound_hits : int
        With ``"clamp"``: consecutive hits on a bound that end the track as ceiling/floor.
    max_trials : int or None
        Trial cap; reaching it before ``n_reversals`` ends the track as ``trial_cap``.
    """

    start_level_db: float
    step_sizes_db: tuple[float, ...] = (4.0, 4.0, 4.0, 2.0)
    down_up_ratio: float = 1.0
    n_up: int = 1
    n_down: int = 3
    n_reversals: int = 11
    n_reversals_averaged: int = 8
    initial_one_down_one_up: bool = False
    min_level_db: float | None = None
    max_level_db: float | None = None
    bound_policy: BoundPolicy = "clamp"
    max_bound_hits: int = 3
    max_trials: int | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "step_sizes_db", tuple(float(s) for s in self.step_sizes_db))
        for name, problem in self._problems():
            raise StaircaseError(f"staircase setting {name}: {problem}")

    def _problems(self) -> Iterable[tuple[str, str]]:
        if not math.isfinite(self.start_level_db):
            yield "start_level_db", f"must be a finite number of dB, got {self.start_level_db}"
        if not self.step_sizes_db:
            yield "step_sizes_db", "needs at least one step size"
        for i, s in enumerate(self.step_sizes_db):
            if not (math.isfinite(s) and s > 0):
                yield f"step_sizes_db[{i}]", f"must be a positive number of dB, got {s}"
        if not (math.isfinite(self.down_up_ratio) and self.down_up_ratio > 0):
            yield "down_up_ratio", f"must be > 0, got {self.down_up_ratio}"
        if not (isinstance(self.n_up, int) and self.n_up >= 1):
            yield "n_up", f"must be an integer ≥ 1, got {self.n_up!r}"
        if not (isinstance(self.n_down, int) and self.n_down >= 1):
            yield "n_down", f"must be an integer ≥ 1, got {self.n_down!r}"
        if not (isinstance(self.n_reversals, int) and self.n_reversals >= 1):
            yield "n_reversals", f"must be an integer ≥ 1, got {self.n_reversals!r}"
        if not (
            isinstance(self.n_reversals_averaged, int)
            and 1 <= self.n_reversals_averaged <= self.n_reversals
        ):
            yield (
                "n_reversals_averaged",
                f"must be between 1 and n_reversals={self.n_reversals}, "
                f"got {self.n_reversals_averaged!r} (cannot average more reversals than are run)",
            )
        lo, hi = self.min_level_db, self.max_level_db
        if lo is not None and hi is not None and not lo < hi:
            yield "min_level_db", f"must be below max_level_db ({lo} ≥ {hi})"
        if lo is not None and self.start_level_db < lo:
            yield "start_level_db", f"{self.start_level_db} dB is below min_level_db={lo} dB"
        if hi is not None and self.start_level_db > hi:
            yield "start_level_db", f"{self.start_level_db} dB is above max_level_db={hi} dB"
        if self.bound_policy not in ("clamp", "stop"):
            yield "bound_policy", f"must be 'clamp' or 'stop', got {self.bound_policy!r}"
        if not (isinstance(self.max_bound_hits, int) and self.max_bound_hits >= 1):
            yield "max_bound_hits", f"must be an integer ≥ 1, got {self.max_bound_hits!r}"
        if self.max_trials is not None and not (
            isinstance(self.max_trials, int) and self.max_trials >= 1
        ):
            yield "max_trials", f"must be an integer ≥ 1 or null, got {self.max_trials!r}"

    def up_step_db(self, n_reversals_so_far: int) -> float:
        """Up step in dB after ``n_reversals_so_far`` reversals."""
        return self.step_sizes_db[min(n_reversals_so_far, len(self.step_sizes_db) - 1)]

    @property
    def kind(self) -> str:
        """The protocol's name for this procedure: ``"staircase"``."""
        return "staircase"

    def start(self) -> Staircase:
        """A fresh track at :attr:`start_level_db` (see :func:`start`)."""
        return start(self)


@dataclass(frozen=True)
class Staircase(TrackState):
    """Immutable state of one staircase track.

    Attributes
    ----------
    settings : StaircaseSettings
        The rules.
    level_db : float
        Level of the next trial, dB.
    levels_db : tuple[float, ...]
        Level of every trial run so far, dB.
    responses : tuple[bool, ...]
        Whether each trial was answered correctly.
    reversal_levels_db : tuple[float, ...]
        Level of each reversal, dB.
    reversal_trials : tuple[int, ...]
        0-based index of the trial at which each reversal happened.
    run : int
        Run counter: +k after k correct in a row, −k after k wrong in a row, 0 after a step.
    direction : {"start", "up", "down"}
        Direction of the last step.
    bound_hits : int
        Consecutive steps asked for beyond the bound the level sits on.
    status : {"running", "completed", "ceiling", "floor", "trial_cap"}
        ``running`` until the track stops.
    """

    settings: StaircaseSettings
    level_db: float
    levels_db: tuple[float, ...] = ()
    responses: tuple[bool, ...] = ()
    reversal_levels_db: tuple[float, ...] = ()
    reversal_trials: tuple[int, ...] = ()
    run: int = 0
    direction: Direction = "start"
    bound_hits: int = 0
    status: Status = "running"
    _initial_step_pending: bool = field(default=False, repr=False)

    @property
    def step_db(self) -> float:
        """Current up step in dB (the down step is this × ``down_up_ratio``)."""
        return self.settings.up_step_db(len(self.reversal_levels_db))

    @property
    def al_db(self) -> float | None:
        """The AL estimate in dB: mean of the last ``n_reversals_averaged`` reversal levels.

        None unless the track completed its reversals: a ceiling, floor or trial cap is not a
        threshold.
        """
        if self.status != "completed":
            return None
        k = self.settings.n_reversals_averaged
        last = self.reversal_levels_db[-k:]
        return math.fsum(last) / len(last)

    def next_level(self) -> float:
        """The level of the next trial, dB (the :class:`~masking_lab.procedures.base.Procedure`
        name for :attr:`level_db`)."""
        return self.level_db

    def estimate(self) -> ThresholdEstimate:
        """The AL as a :class:`~masking_lab.procedures.base.ThresholdEstimate` (see :attr:`al_db`).

        Examples
        --------
        >>> start(StaircaseSettings(start_level_db=0.0)).estimate().level_db is None
        True
        """
        return ThresholdEstimate(
            level_db=self.al_db, sd_db=None, method="reversal_mean", status=self.status
        )

    def update(self, correct: bool) -> Staircase:
        """Return the staircase after one trial at :attr:`level_db` answered ``correct``.

        Raises
        ------
        StaircaseError
            If the track has already finished.
        """
        if self.finished:
            raise StaircaseError(
                f"the staircase has finished ({self.status}); it takes no more responses"
            )
        s = self.settings
        correct = bool(correct)
        trial_level = self.level_db
        trial_index = len(self.levels_db)
        responses = (*self.responses, correct)
        levels = (*self.levels_db, trial_level)

        # Run counter, exactly as PsychoPy: continue a run of equal answers, else restart it.
        same_as_last = bool(self.responses) and self.responses[-1] == correct
        if correct:
            run = self.run + 1 if same_as_last else 1
        else:
            run = self.run - 1 if same_as_last else -1

        initial_phase = s.initial_one_down_one_up and not self.reversal_levels_db
        if initial_phase:
            wanted: Direction | None = "down" if correct else "up"
        elif run >= s.n_down:
            wanted = "down"
        elif run <= -s.n_up:
            wanted = "up"
        else:
            wanted = None

        reversal = wanted is not None and self.direction not in ("start", wanted)
        direction = wanted if wanted is not None else self.direction
        reversal_levels = self.reversal_levels_db
        reversal_trials = self.reversal_trials
        initial_step_pending = self._initial_step_pending
        if reversal:
            if initial_phase:
                initial_step_pending = True  # the step at the first reversal is still 1-up-1-down
            reversal_levels = (*reversal_levels, trial_level)
            reversal_trials = (*reversal_trials, trial_index)

        if len(reversal_levels) >= s.n_reversals:
            return replace(
                self,
                levels_db=levels,
                responses=responses,
                reversal_levels_db=reversal_levels,
                reversal_trials=reversal_trials,
                run=run,
                direction=direction,
                status="completed",
                _initial_step_pending=False,
            )

        up = s.up_step_db(len(reversal_levels))
        if (initial_phase or initial_step_pending) and s.initial_one_down_one_up:
            initial_step_pending = False
            step = -up * s.down_up_ratio if correct else up
        elif run >= s.n_down:
            step = -up * s.down_up_ratio
        elif run <= -s.n_up:
            step = up
        else:
            step = 0.0
        # One copy per trial (each ``replace`` is a few µs of a simulated trial's CPU).
        state = replace(
            self,
            levels_db=levels,
            responses=responses,
            reversal_levels_db=reversal_levels,
            reversal_trials=reversal_trials,
            run=run,
            direction=direction,
            _initial_step_pending=initial_step_pending,
        )

        if step != 0.0:
            state = state._apply_step(trial_level, step)
            if state.finished:
                return state
        if s.max_trials is not None and len(levels) >= s.max_trials:
            return replace(state, status="trial_cap")
        return state

    def _apply_step(self, trial_level: float, step: float) -> Staircase:
        s = self.settings
        target = trial_level + step
        bound: float | None = s.max_level_db if step > 0 else s.min_level_db
        beyond = bound is not None and (target > bound if step > 0 else target < bound)
        ended: Status = "ceiling" if step > 0 else "floor"
        if not beyond:
            return replace(self, level_db=target, run=0, bound_hits=0)
        assert bound is not None
        if s.bound_policy == "stop":
            return replace(self, level_db=trial_level, run=0, status=ended)
        at_bound = trial_level == bound
        hits = self.bound_hits + 1 if at_bound else 0
        status: Status = ended if hits >= s.max_bound_hits else "running"
        return replace(self, level_db=bound, run=0, bound_hits=hits, status=status)

    @property
    def at_bound(self) -> Literal["upper", "lower"] | None:
        """Which bound the next level sits on, if any."""
        if self.settings.max_level_db is not None and self.level_db >= self.settings.max_level_db:
            return "upper"
        if self.settings.min_level_db is not None and self.level_db <= self.settings.min_level_db:
            return "lower"
        return None


def start(settings: StaircaseSettings) -> Staircase:
    """A fresh staircase at ``settings.start_level_db``."""
    return Staircase(settings=settings, level_db=float(settings.start_level_db))


def replay(settings: StaircaseSettings, responses: Iterable[bool]) -> Staircase:
    """Rebuild a staircase from its responses (the resume path; see
    :func:`masking_lab.procedures.base.replay`).

    Raises
    ------
    StaircaseError
        If there are more responses than the track accepts (it finished earlier).
    """
    state = _replay(settings, responses)
    assert isinstance(state, Staircase)
    return state


def implied_target_p(settings: StaircaseSettings) -> float:
    """p(correct) at which the track has zero expected drift (where it converges).

    Solves ``up_step·P(up step) = down_step·P(down step)`` per trial for the run-counter Markov
    chain of this rule (Kaernbach 1991; García-Pérez 1998). For equal steps this is Levitt's
    target, e.g. 0.5^(1/3) = 0.794 for 1-up 3-down; a down/up ratio of 0.7393 (García-Pérez's
    2AFC value) gives 0.8315.
    This is the asymptote for steps small against the psychometric spread; with larger steps the
    reversal mean settles elsewhere (simulated in docs/speed-accuracy.md).
    """
    return implied_target_p_for(settings.n_up, settings.n_down, settings.down_up_ratio)


def implied_target_p_for(n_up: int, n_down: int, down_up_ratio: float = 1.0) -> float:
    """:func:`implied_target_p` for a rule given by its numbers (see there)."""

    def drift(p: float) -> float:
        p_up, p_down = _step_rates(n_up, n_down, p)
        return p_up * 1.0 - p_down * down_up_ratio

    return float(brentq(drift, 1e-9, 1 - 1e-9, xtol=1e-13))


def _step_rates(n_up: int, n_down: int, p: float) -> tuple[float, float]:
    """Stationary per-trial probabilities of an up step and a down step at p(correct) = p."""
    import numpy as np

    # States: run counter after a trial, −(n_up−1)…(n_down−1); 0 means "just stepped".
    states = list(range(-(n_up - 1), n_down))
    index = {c: i for i, c in enumerate(states)}
    n = len(states)
    T = np.zeros((n, n))
    up_from = np.zeros(n)
    down_from = np.zeros(n)
    for c in states:
        i = index[c]
        nxt_c = c + 1 if c > 0 else 1
        if nxt_c >= n_down:
            T[i, index[0]] += p
            down_from[i] += p
        else:
            T[i, index[nxt_c]] += p
        nxt_w = c - 1 if c < 0 else -1
        if nxt_w <= -n_up:
            T[i, index[0]] += 1 - p
            up_from[i] += 1 - p
        else:
            T[i, index[nxt_w]] += 1 - p
    # Stationary distribution: left eigenvector for eigenvalue 1.
    A = np.vstack([T.T - np.eye(n), np.ones(n)])
    b = np.zeros(n + 1)
    b[-1] = 1.0
    pi = np.linalg.lstsq(A, b, rcond=None)[0]
    return float(pi @ up_from), float(pi @ down_from)
