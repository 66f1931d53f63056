"""The functional procedure: a masking function's ramp measured directly (pure: no I/O, no RNG).

Instead of one threshold per masker level, one track per target/masker pair chooses, on every
3IFC trial, the masker level *and* the target level whose answer is expected to leave the least
entropy in the posterior of the ramp's two parameters (as the quick TvC of Lesmes et al. 2006
does for threshold-versus-contrast functions). The model is the paper's ramp
(:func:`masking_lab.core.masking.ramp`, Eq. 1–2): the masked threshold at masker level x (dB SL
of the masker) is

    θ(x) = u + max(0, a + b·x)    (dB SL of the target),

a the ramp's intercept (dB), b its slope (dB/dB), u the error of the participant's calibrated
unmasked AL (dB; 0 if the baseline were exact). The answer follows the project's forced-choice
logistic around θ(x) (:mod:`masking_lab.core.psychometric`) with scale s and lapse λ. u, s and λ
are nuisance parameters on small grids with flat priors, marginalised as psi-marginal does
(Prins 2013): placement minimises the expected entropy of the *marginal* posterior of (a, b).

The likelihood table (stimuli × (a, b) × nuisance) and the first stimulus depend on the
settings only and are cached per settings object (:func:`ramp_tables`); an update is a
multiply-normalise, a placement one batched product over the table.

References: Lesmes L.A., Jeon S.-T., Lu Z.-L., Dosher B.A. (2006) Bayesian adaptive estimation
of threshold versus contrast external noise functions: the quick TvC method. Vision Res 46.
Prins N. (2013) The psi-marginal adaptive method. J Vis 13(7):3.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from masking_lab.core.errors import ProcedureError
from masking_lab.core.masking import ramp
from masking_lab.core.psychometric import LEVITT_1U3D
from masking_lab.procedures.base import ThresholdEstimate, settings_from_mapping
from masking_lab.procedures.fused import nuisance_sums, wrong_and_totals
from masking_lab.procedures.limits import grid_memory_problem, grid_points
from masking_lab.procedures.quest_plus_model import PosteriorTrack, grid_db

Status = Literal["running", "completed", "trial_cap", "ceiling"]

__all__ = ["FunctionalRamp", "FunctionalRampSettings", "RampTables", "ramp_tables", "stop_status"]


@dataclass(frozen=True)
class FunctionalRampSettings:
    """Settings of a functional (ramp) track. Levels in dB SL; slopes in dB per dB.

    Attributes
    ----------
    masker_min_db_sl, masker_max_db_sl, masker_step_db : float
        The masker levels the track may play, dB SL of the masker (the rig's rating lowers
        the top).
    min_level_db, max_level_db, level_step_db : float
        The target levels it may play, dB SL of the target (the device limit lowers the top).
    intercept_min_db, intercept_max_db, intercept_step_db : float
        The grid of the ramp intercept a, dB.
    slope_min, slope_max, slope_step : float
        The grid of the ramp slope b, dB/dB.
    unmasked_offsets_db : tuple of float
        Nuisance grid of u, the error of the calibrated unmasked AL, dB.
    scales_db, lapses : tuple of float
        Nuisance grids of the logistic scale (dB) and the lapse rate.
    n_intervals : int
        Intervals per trial (guess rate 1/n).
    p_at_threshold : float
        p(correct) at the threshold θ(x) (0.794, the 1-up-3-down point, as every procedure).
    max_trials : int
        Trials of the track (its stop rule, and its cap when a precision target is set).
    target_sd_intercept_db, target_sd_slope : float or None
        Stop once both posterior SDs are at most these (after ``min_trials``).
    min_trials : int
        Trials before the precision rule may stop the track.
    """

    masker_min_db_sl: float = 5.0
    masker_max_db_sl: float = 25.0
    masker_step_db: float = 5.0
    min_level_db: float = -10.0
    max_level_db: float = 35.0
    level_step_db: float = 1.0
    intercept_min_db: float = -20.0
    intercept_max_db: float = 10.0
    intercept_step_db: float = 1.0
    slope_min: float = 0.2
    slope_max: float = 1.6
    slope_step: float = 0.05
    unmasked_offsets_db: tuple[float, ...] = (-1.5, 0.0, 1.5)
    scales_db: tuple[float, ...] = (0.75, 1.5, 3.0)
    lapses: tuple[float, ...] = (0.0, 0.06, 0.12)
    n_intervals: int = 3
    p_at_threshold: float = LEVITT_1U3D
    max_trials: int = 90
    target_sd_intercept_db: float | None = None
    target_sd_slope: float | None = None
    min_trials: int = 0

    def __post_init__(self) -> None:
        for name in ("unmasked_offsets_db", "scales_db", "lapses"):
            value = getattr(self, name)
            items = (value,) if isinstance(value, int | float) else value
            object.__setattr__(self, name, tuple(float(v) for v in items))
        for name, problem in self._problems():
            raise ProcedureError(f"functional_ramp setting {name}: {problem}")

    def _problems(self) -> Iterable[tuple[str, str]]:
        def finite(v: object) -> bool:
            return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)

        ranges = (
            ("masker_min_db_sl", "masker_max_db_sl", "masker_step_db"),
            ("min_level_db", "max_level_db", "level_step_db"),
            ("intercept_min_db", "intercept_max_db", "intercept_step_db"),
            ("slope_min", "slope_max", "slope_step"),
        )
        for lo, hi, step in ranges:
            a, b, c = getattr(self, lo), getattr(self, hi), getattr(self, step)
            if not (finite(a) and finite(b)):
                yield lo, f"{lo} and {hi} must be finite numbers, got {a!r}, {b!r}"
                return
            if not a < b:
                yield lo, f"must be below {hi} ({a} ≥ {b})"
                return
            if not (finite(c) and c > 0):
                yield step, f"must be a positive number, got {c!r}"
                return
        for name in ("unmasked_offsets_db", "scales_db", "lapses"):
            if not getattr(self, name):
                yield name, "needs at least one value"
                return
            if not all(math.isfinite(v) for v in getattr(self, name)):
                yield name, "every value must be finite"
                return
        if not all(s > 0 for s in self.scales_db):
            yield "scales_db", "every scale must be a positive number of dB"
        if not (isinstance(self.n_intervals, int) and self.n_intervals >= 2):
            yield "n_intervals", f"must be an integer ≥ 2, got {self.n_intervals!r}"
            return
        guess = 1.0 / self.n_intervals
        for lam in self.lapses:
            if not 0.0 <= lam < 1.0 - guess:
                yield "lapses", f"every lapse rate must lie in [0, {1 - guess:.3f}), got {lam}"
                return
        top = 1.0 - max(self.lapses)
        if not (finite(self.p_at_threshold) and guess < self.p_at_threshold < top):
            yield (
                "p_at_threshold",
                f"must lie between the guess rate {guess:.3f} and {top:.3f}, "
                f"got {self.p_at_threshold!r}",
            )
        if not (isinstance(self.max_trials, int) and 1 <= self.max_trials <= 5000):
            yield "max_trials", f"must be an integer in 1..5000, got {self.max_trials!r}"
        if not (isinstance(self.min_trials, int) and self.min_trials >= 0):
            yield "min_trials", f"must be an integer ≥ 0, got {self.min_trials!r}"
        elif isinstance(self.max_trials, int) and self.min_trials > self.max_trials:
            yield "min_trials", f"{self.min_trials} exceeds max_trials={self.max_trials}"
        for name in ("target_sd_intercept_db", "target_sd_slope"):
            v = getattr(self, name)
            if v is not None and not (finite(v) and v > 0):
                yield name, f"must be a positive number or null, got {v!r}"
        problem = grid_memory_problem(self.table_cells, "functional_ramp table")
        if problem is not None:
            yield "level_step_db", problem

    @property
    def table_cells(self) -> int:
        """Cells of one likelihood table (stimuli × (a, b) × nuisance), without building it."""
        s = grid_points(self.masker_min_db_sl, self.masker_max_db_sl, self.masker_step_db)
        s *= grid_points(self.min_level_db, self.max_level_db, self.level_step_db)
        p = grid_points(self.intercept_min_db, self.intercept_max_db, self.intercept_step_db)
        p *= grid_points(self.slope_min, self.slope_max, self.slope_step)
        n = len(self.unmasked_offsets_db) * len(self.scales_db) * len(self.lapses)
        return s * p * n

    @property
    def guess(self) -> float:
        """Guess rate γ = 1/``n_intervals``."""
        return 1.0 / self.n_intervals

    @property
    def kind(self) -> str:
        """The protocol's name for this procedure: ``"functional_ramp"``."""
        return "functional_ramp"

    def start(self) -> FunctionalRamp:
        """A fresh track: the prior and its first stimulus.

        Examples
        --------
        >>> s = FunctionalRampSettings(max_trials=10)
        >>> track = s.start()
        >>> track.n_trials, 5.0 <= track.next_masker_level_db_sl() <= 25.0
        (0, True)
        """
        t = ramp_tables(self)
        return FunctionalRamp(self, t.prior, t.first_stimulus)

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any]) -> FunctionalRampSettings:
        """Settings from a protocol's ``procedure:`` mapping (keys = attribute names).

        Raises
        ------
        ProcedureError
            On an unknown key (listing the valid ones) or an invalid value.

        Examples
        --------
        >>> s = FunctionalRampSettings.from_mapping({"kind": "functional_ramp", "max_trials": 60})
        >>> s.max_trials
        60
        """
        return settings_from_mapping(
            cls, mapping, "functional_ramp", tuples=("unmasked_offsets_db", "scales_db", "lapses")
        )


@dataclass(frozen=True, eq=False)
class RampTables:
    """Everything about a :class:`FunctionalRampSettings` that does not depend on the answers.

    Attributes
    ----------
    maskers_db_sl, targets_db : ndarray, shape (S,)
        Masker level and target level of every stimulus, dB SL.
    intercepts_db, slopes : ndarray, shape (A,)
        (a, b) of every grid point of interest (A = intercepts × slopes).
    nuisance : ndarray, shape (N, 3)
        Every (u dB, scale dB, lapse) triple.
    p_correct : ndarray, shape (N, A, S), float32
        p(correct) of every stimulus under every parameter point (the placement's table).
    prior : ndarray, shape (A, N)
        Flat prior, summing to 1.
    first_stimulus : int
        The stimulus the prior places first.
    """

    maskers_db_sl: NDArray[np.float64]
    targets_db: NDArray[np.float64]
    intercepts_db: NDArray[np.float64]
    slopes: NDArray[np.float64]
    nuisance: NDArray[np.float64]
    p_correct: NDArray[np.float32]
    prior: NDArray[np.float64]
    first_stimulus: int


_P_FLOOR = 1e-12


def likelihood(
    maskers_db_sl: NDArray[np.float64],
    targets_db: NDArray[np.float64],
    intercepts_db: NDArray[np.float64],
    slopes: NDArray[np.float64],
    nuisance: NDArray[np.float64],
    guess: float,
    p_at_threshold: float,
) -> NDArray[np.float64]:
    """p(correct), shape (A, S, N), of trials (masker x, target y) under the ramp model.

    Examples
    --------
    >>> p = likelihood(np.array([10.0]), np.array([4.0]), np.array([-4.0]), np.array([0.8]),
    ...                np.array([[0.0, 1.5, 0.02]]), 1 / 3, LEVITT_1U3D)
    >>> round(float(p[0, 0, 0]), 4)   # the target at the masked threshold 4 dB SL
    0.7937
    """
    u, scale, lapse = nuisance[:, 0], nuisance[:, 1], nuisance[:, 2]
    rise = 1.0 - guess - lapse
    q = (p_at_threshold - guess) / rise
    # The paper's ramp (core.masking.ramp), broadcast over (a, b) × stimuli: shape (A, S).
    shift = ramp(maskers_db_sl[None, :], intercepts_db[:, None], slopes[:, None])
    theta = shift[:, :, None] + u[None, None, :]  # (A, S, N)
    z = (targets_db[None, :, None] - theta) / scale + np.log(q / (1.0 - q))
    # Kept off 0 and 1 by 1e-12: with a lapse of 0 a wrong answer far above threshold would
    # otherwise make every point impossible (a 0/0 posterior).
    return np.clip(guess + rise / (1.0 + np.exp(-z)), _P_FLOOR, 1.0 - _P_FLOOR)


def _xlogx_sum(m: NDArray[np.float32]) -> NDArray[np.float32]:
    """Σ m·log m over the first axis (cells that underflowed to 0 add 0)."""
    return np.einsum("as,as->s", m, np.log(np.maximum(m, _TINY32)))


_TINY32 = np.float32(np.finfo(np.float32).tiny)


def expected_entropy(t: RampTables, posterior: NDArray[np.float64]) -> NDArray[np.float64]:
    """Expected entropy (nats) of the (a, b) marginal posterior after each stimulus, shape (S,).

    The placement's arithmetic is float32 (the table is stored so, half the memory traffic);
    the posterior itself is updated in float64 with exact likelihoods.

    Parameters
    ----------
    t : RampTables
    posterior : ndarray, shape (A, N)

    Examples
    --------
    >>> t = ramp_tables(FunctionalRampSettings(max_trials=5))
    >>> expected_entropy(t, t.prior).shape == t.targets_db.shape
    True
    """
    post = posterior.astype(np.float32)
    # m_c[a, s] = Σ_n post[a, n]·p_c[n, a, s]; the wrong answer's is the marginal minus it.
    m_c = nuisance_sums(t.p_correct, post[None])[0]
    return _entropy_after(m_c, post.sum(axis=1))


def _entropy_after(m_c: NDArray[np.float32], row_sums: NDArray[np.float32]) -> NDArray[np.float64]:
    """Expected entropy per stimulus from the correct answer's joint table ``m_c`` (A, S) and
    the posterior's (a, b) marginal ``row_sums`` (A,), nats."""
    m_w, pk_c, pk_w = wrong_and_totals(m_c, row_sums)
    out = np.zeros(m_c.shape[1])
    for m, pk in ((m_c, pk_c), (m_w, pk_w)):
        out += pk * np.log(np.maximum(pk, 1e-300)) - _xlogx_sum(m)
    return out


@functools.lru_cache(maxsize=8)
def ramp_tables(settings: FunctionalRampSettings) -> RampTables:
    """The grids, likelihood table, prior and first stimulus of ``settings`` (cached).

    Examples
    --------
    >>> t = ramp_tables(FunctionalRampSettings(max_trials=5))
    >>> t.p_correct.shape, t.p_correct.dtype.name
    ((27, 899, 230), 'float32')
    """
    s = settings
    maskers = grid_db(s.masker_min_db_sl, s.masker_max_db_sl, s.masker_step_db)
    targets = grid_db(s.min_level_db, s.max_level_db, s.level_step_db)
    mx, ty = (a.ravel() for a in np.meshgrid(maskers, targets, indexing="ij"))
    a_grid = grid_db(s.intercept_min_db, s.intercept_max_db, s.intercept_step_db)
    b_grid = grid_db(s.slope_min, s.slope_max, s.slope_step)
    aa, bb = (g.ravel() for g in np.meshgrid(a_grid, b_grid, indexing="ij"))
    nuisance = np.array(
        [(u, sc, lam) for u in s.unmasked_offsets_db for sc in s.scales_db for lam in s.lapses]
    )
    p_c = np.empty((nuisance.shape[0], aa.size, mx.size), dtype=np.float32)
    for i in range(nuisance.shape[0]):  # one nuisance point at a time bounds the temporaries
        one = likelihood(mx, ty, aa, bb, nuisance[i : i + 1], s.guess, s.p_at_threshold)
        p_c[i] = one[:, :, 0]
    prior = np.full((aa.size, nuisance.shape[0]), 1.0 / (aa.size * nuisance.shape[0]))
    partial = RampTables(mx, ty, aa, bb, nuisance, p_c, prior, 0)
    first = int(np.argmin(expected_entropy(partial, prior)))
    for arr in (mx, ty, aa, bb, nuisance, p_c, prior):
        arr.flags.writeable = False
    return replace(partial, first_stimulus=first)


def stimulus_likelihood(
    t: RampTables, settings: FunctionalRampSettings, stimulus: int
) -> NDArray[np.float64]:
    """p(correct) of one stimulus under every parameter point, shape (A, N), in float64."""
    one = likelihood(
        t.maskers_db_sl[stimulus : stimulus + 1],
        t.targets_db[stimulus : stimulus + 1],
        t.intercepts_db,
        t.slopes,
        t.nuisance,
        settings.guess,
        settings.p_at_threshold,
    )
    return one[:, 0, :]


def ramp_moments(t: RampTables, posterior: NDArray[np.float64]) -> dict[str, float]:
    """Posterior mean and SD of the intercept (dB) and slope (dB/dB), and their correlation.

    Examples
    --------
    >>> t = ramp_tables(FunctionalRampSettings(max_trials=5))
    >>> sorted(ramp_moments(t, t.prior))
    ['intercept_db', 'intercept_sd_db', 'rho', 'slope', 'slope_sd']
    """
    w = posterior.sum(axis=1)
    ma, mb = float(w @ t.intercepts_db), float(w @ t.slopes)
    da, db = t.intercepts_db - ma, t.slopes - mb
    va, vb = float(w @ da**2), float(w @ db**2)
    cov = float(w @ (da * db))
    rho = min(1.0, max(-1.0, cov / math.sqrt(va * vb))) if va > 0 and vb > 0 else 0.0
    return {
        "intercept_db": ma,
        "intercept_sd_db": math.sqrt(max(va, 0.0)),
        "slope": mb,
        "slope_sd": math.sqrt(max(vb, 0.0)),
        "rho": rho,
    }


def stop_status(settings: FunctionalRampSettings, n: int, m: dict[str, float]) -> Status:
    """A track's stop rule after ``n`` trials with posterior moments ``m`` (SDs in dB, dB/dB).

    Examples
    --------
    >>> stop_status(FunctionalRampSettings(max_trials=3), 3, {})
    'completed'
    >>> stop_status(FunctionalRampSettings(max_trials=3, target_sd_slope=0.1), 3, {"slope_sd": 0.2})
    'trial_cap'
    """
    s = settings
    precise = s.target_sd_intercept_db is not None or s.target_sd_slope is not None
    if precise and n >= s.min_trials:
        sd_a, sd_b = s.target_sd_intercept_db, s.target_sd_slope
        ok_a = sd_a is None or m["intercept_sd_db"] <= sd_a
        ok_b = sd_b is None or m["slope_sd"] <= sd_b
        if ok_a and ok_b:
            return "completed"
    if n >= s.max_trials:
        return "trial_cap" if precise else "completed"
    return "running"


@dataclass(frozen=True, eq=False)
class FunctionalRamp(PosteriorTrack):
    """Immutable state of one functional (ramp) track.

    Attributes
    ----------
    settings : FunctionalRampSettings
    posterior : ndarray, shape (A, N)
        Posterior over ((a, b), nuisance) grid points, summing to 1 (read-only).
    stimulus : int
        Index of the next trial's stimulus in :func:`ramp_tables`.
    levels_db, maskers_db_sl : tuple of float
        Target level (dB SL) and masker level (dB SL) of every trial so far.
    responses : tuple of bool
    status : {"running", "completed", "trial_cap"}
    """

    settings: FunctionalRampSettings
    posterior: NDArray[np.float64]
    stimulus: int
    levels_db: tuple[float, ...] = ()
    maskers_db_sl: tuple[float, ...] = ()
    responses: tuple[bool, ...] = ()
    status: Status = "running"

    def next_level(self) -> float:
        """Target level of the next trial, dB SL."""
        return float(ramp_tables(self.settings).targets_db[self.stimulus])

    def next_masker_level_db_sl(self) -> float:
        """Masker level of the next trial, dB SL of the masker."""
        return float(ramp_tables(self.settings).maskers_db_sl[self.stimulus])

    def moments(self) -> dict[str, float]:
        """Posterior mean and SD of intercept (dB) and slope (dB/dB), and their correlation."""
        return ramp_moments(ramp_tables(self.settings), self.posterior)

    def update(self, correct: bool) -> FunctionalRamp:
        """The track after the next trial answered ``correct``.

        Raises
        ------
        ProcedureError
            If the track has finished.

        Examples
        --------
        >>> track = FunctionalRampSettings(max_trials=2).start()
        >>> track.update(True).update(False).status
        'completed'
        """
        if self.finished:
            raise ProcedureError(
                f"the functional_ramp track has finished ({self.status}); it takes no more "
                "responses"
            )
        t = ramp_tables(self.settings)
        correct = bool(correct)
        like = stimulus_likelihood(t, self.settings, self.stimulus)
        post = self.posterior * (like if correct else 1.0 - like)
        post /= post.sum()
        post.flags.writeable = False
        n = self.n_trials + 1
        status = stop_status(self.settings, n, ramp_moments(t, post))
        nxt = self.stimulus
        if status == "running":
            nxt = int(np.argmin(expected_entropy(t, post)))
        return FunctionalRamp(
            self.settings,
            post,
            nxt,
            (*self.levels_db, self.next_level()),
            (*self.maskers_db_sl, self.next_masker_level_db_sl()),
            (*self.responses, correct),
            status,
        )

    def estimate(self) -> ThresholdEstimate:
        """No single threshold: the ramp is in :meth:`moments`; ``method`` says so.

        Examples
        --------
        >>> FunctionalRampSettings(max_trials=3).start().estimate().method
        'ramp_posterior'
        """
        return ThresholdEstimate(
            level_db=None, sd_db=None, method="ramp_posterior", status=self.status
        )
