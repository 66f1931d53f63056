"""The trade users ask about: trials per participant for a masking function at the paper's
precision, by the paper's route, QUEST+ per set, and the functional procedure (pure).

One stimulus pair and direction (a target, a masker, its ramp a + b·x above the knee), one
simulated participant per replicate. Every route starts from the same calibration: the
participant's unmasked AL measured by the paper's staircase, whose error e shifts every
level the session plays (dB SL of the *calibrated* AL). Then:

``paper``
    five 1-up-3-down staircases (the paper's 11/8 reversals, steps 4, 4, 4, 2 dB) at the
    masker levels ``levels_db_sl``; shifts = the five ALs (already relative to the calibrated
    AL); the least-squares ramp (:func:`masking_lab.analysis.ramp_fit.ramp_least_squares_batch`).
``quest_plus``
    the same with a QUEST+ track per level (psi-marginal, slope and lapse marginalised, stop
    at posterior SD 1.6 dB after 10 trials, cap 120: ``protocols/experiment1_questplus.yaml``).
``functional``
    one functional_ramp track over the same masker range (``protocols/experiment1_functional
    .yaml``'s grids), run to ``max(checkpoints)`` trials; its posterior means at each
    checkpoint (a shorter cap is a prefix of the same track: nothing else stops it).

Precision of one participant's fitted ramp, over replicates: SD of the intercept (dB), SD of
the slope (dB/dB), and RMS error of the predicted masked AL over the masker range (dB), each
against the participant's true ramp. The Cramér–Rao bound of the two-dimensional design (slope
and lapse known, every trial above the knee at the most informative target level, half at
each end of the masker range) gives the fewest trials any unbiased procedure needs for each.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from masking_lab.analysis.ramp_fit import ramp_least_squares_batch
from masking_lab.core.errors import AnalysisError
from masking_lab.core.masking import ramp
from masking_lab.core.psychometric import Psychometric
from masking_lab.procedures.fisher import max_information
from masking_lab.procedures.functional import FunctionalRampSettings
from masking_lab.procedures.functional_lockstep import run_lockstep
from masking_lab.procedures.quest_plus import QuestPlusSettings
from masking_lab.procedures.quest_plus_batch import simulate_quest_plus
from masking_lab.procedures.staircase import StaircaseSettings
from masking_lab.procedures.staircase_batch import Observer, simulate

__all__ = [
    "RouteResult",
    "TradeEstimates",
    "TradeSettings",
    "cramer_rao_ramp",
    "format_trade",
    "precision_ratios",
    "ramp_precision",
    "run_trade",
    "summarize_trade",
    "trade_estimates",
    "trade_for_protocol",
]

PAPER_STAIRCASE = StaircaseSettings(
    20.0, step_sizes_db=(4.0, 4.0, 4.0, 2.0), min_level_db=-20.0, max_level_db=45.0,
    max_trials=150,
)  # fmt: skip
# protocols/experiment1_questplus.yaml's settings: slope and lapse marginalised (the defaults).
PAPER_QUEST = QuestPlusSettings(-20.0, 45.0, target_sd_db=1.6, min_trials=10, max_trials=120)


@dataclass(frozen=True)
class TradeSettings:
    """One pair and direction to compare the routes on.

    Attributes
    ----------
    intercept_db, slope : float
        The participants' true ramp (a dB, b dB/dB); default EV270 by MV120 (ground truth).
    levels_db_sl : tuple of float
        The paper's masker levels, dB SL.
    scale_db, lapse : float
        The observers' psychometric scale (dB) and lapse.
    replicates : int
        Simulated participants per route.
    checkpoints : tuple of int
        Trial counts at which the functional track's ramp is read.
    seconds_per_trial : float
        Time per trial, s (the paper's timing: 7.8 s of stimuli, ~1 s answer, 0.5 s pause).
    functional : FunctionalRampSettings
        Its grids (``max_trials`` is set to the largest checkpoint).
    """

    intercept_db: float = -7.442
    slope: float = 0.711
    levels_db_sl: tuple[float, ...] = (5.0, 10.0, 15.0, 20.0, 25.0)
    scale_db: float = 1.5
    lapse: float = 0.02
    replicates: int = 60
    checkpoints: tuple[int, ...] = (45, 60, 87, 120, 150)
    seconds_per_trial: float = 9.3
    functional: FunctionalRampSettings = field(default_factory=FunctionalRampSettings)


@dataclass(frozen=True)
class RouteResult:
    """One route's precision and cost per participant and masking function.

    Attributes
    ----------
    route : str
    trials_mean : float
        Trials per participant for this masking function (masked sets only).
    minutes : float
    sd_intercept_db, sd_slope, rms_al_db : float
        Spread of the fitted intercept (dB) and slope (dB/dB), RMS error of the predicted
        masked AL over the masker range (dB).
    n : int
        Replicates that gave a ramp.
    """

    route: str
    trials_mean: float
    minutes: float
    sd_intercept_db: float
    sd_slope: float
    rms_al_db: float
    n: int


def ramp_precision(
    a_hat: NDArray[np.float64],
    b_hat: NDArray[np.float64],
    a: float,
    b: float,
    levels_db_sl: tuple[float, ...],
) -> tuple[float, float, float]:
    """(SD of intercepts dB, SD of slopes, RMS error of predicted masked AL dB over the range).

    SDs are root-mean-square errors against the truth (bias included).

    Examples
    --------
    >>> ramp_precision(np.array([-7.0, -8.0]), np.array([0.7, 0.72]), -7.5, 0.71, (5.0, 25.0))[0]
    0.5
    """
    sd_a, sd_b, rms = np.sqrt(_squared_errors(a_hat, b_hat, a, b, levels_db_sl).mean(axis=0))
    return float(sd_a), float(sd_b), float(rms)


def _squared_errors(
    a_hat: NDArray[np.float64],
    b_hat: NDArray[np.float64],
    a: float,
    b: float,
    levels_db_sl: tuple[float, ...],
) -> NDArray[np.float64]:
    """Per participant: squared intercept error, squared slope error, mean squared AL error
    over the masker range (the predicted AL floored at 0 dB SL, as the ramp is)."""
    x = np.linspace(min(levels_db_sl), max(levels_db_sl), 41)
    pred = np.maximum(0.0, a_hat[:, None] + b_hat[:, None] * x[None, :])
    err_al = pred - ramp(x, a, b)[None, :]
    return np.stack([(a_hat - a) ** 2, (b_hat - b) ** 2, np.mean(err_al**2, axis=1)], axis=1)


def cramer_rao_ramp(
    n_trials: float, levels_db_sl: tuple[float, ...], *, scale_db: float = 1.5, lapse: float = 0.02
) -> tuple[float, float, float]:
    """Cramér–Rao SDs (intercept dB, slope, RMS of predicted AL dB) for ``n_trials`` trials.

    The design: half the trials at each end of the masker range, each at the target level of
    peak Fisher information I* (:func:`masking_lab.procedures.fisher.max_information`), all
    above the knee, slope and lapse known: Cov = (n·I*·M)⁻¹ with M = mean of [1, x; x, x²].

    Examples
    --------
    >>> sd_a, sd_b, rms = cramer_rao_ramp(100, (5.0, 25.0))
    >>> round(sd_b, 3)
    0.043
    """
    info, _, _ = max_information(scale_db=scale_db, guess=1 / 3, lapse=lapse)
    ends = np.array([min(levels_db_sl), max(levels_db_sl)])
    m = np.array([[1.0, ends.mean()], [ends.mean(), (ends**2).mean()]])
    cov = np.linalg.inv(m) / (n_trials * info)
    x = np.linspace(ends[0], ends[1], 41)
    design = np.stack([np.ones_like(x), x], axis=1)
    var_pred = np.einsum("ij,jk,ik->i", design, cov, design)
    return math.sqrt(cov[0, 0]), math.sqrt(cov[1, 1]), float(math.sqrt(var_pred.mean()))


def _calibration_errors(s: TradeSettings, rng: np.random.Generator) -> NDArray[np.float64]:
    sim = simulate(
        PAPER_STAIRCASE, np.zeros(s.replicates), Observer(scale_db=s.scale_db, lapse=s.lapse), rng
    )
    return np.nan_to_num(sim.al_db, nan=0.0)


def _per_level_fits(
    s: TradeSettings, name: str, errors: NDArray[np.float64], rng: np.random.Generator
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Every replicate's (intercept, slope), NaN where it gave fewer than five ALs, and trials."""
    truth = np.array([float(ramp(x, s.intercept_db, s.slope)) for x in s.levels_db_sl])
    als, trials = [], np.zeros(s.replicates)
    for k in range(len(s.levels_db_sl)):
        thresholds = truth[k] - errors  # dB SL of the calibrated AL
        if name == "paper":
            sim = simulate(
                PAPER_STAIRCASE, thresholds, Observer(scale_db=s.scale_db, lapse=s.lapse), rng
            )
            als.append(sim.al_db)
            trials += sim.n_trials
        else:
            q = simulate_quest_plus(
                PAPER_QUEST, thresholds, scale_db=s.scale_db, lapse=s.lapse, rng=rng
            )
            als.append(q.estimate_db)
            trials += q.n_trials
    shifts = np.stack(als, axis=1)
    ok = np.all(np.isfinite(shifts), axis=1)
    a_hat, b_hat = np.full(s.replicates, np.nan), np.full(s.replicates, np.nan)
    if ok.any():
        a_hat[ok], b_hat[ok] = ramp_least_squares_batch(np.array(s.levels_db_sl), shifts[ok])
    return a_hat, b_hat, trials


def _functional_fits(
    s: TradeSettings, errors: NDArray[np.float64], rng: np.random.Generator
) -> dict[int, tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """Per checkpoint, every replicate's posterior-mean intercept and slope."""
    settings = replace(s.functional, max_trials=max(s.checkpoints))
    psy = Psychometric(0.0, s.scale_db, 1 / 3, s.lapse)
    draws = rng.random((max(s.checkpoints), s.replicates))

    def answer(i: int, k: int, masker_db_sl: float, target_db: float) -> bool:
        theta = float(ramp(masker_db_sl, s.intercept_db, s.slope))
        return bool(draws[k, i] < psy.p_correct(target_db - (theta - errors[i])))

    # The replicates' tracks advance together (one pass over the table serves them all),
    # each exactly as a scalar track would run.
    run = run_lockstep(settings, answer, s.replicates, checkpoints=s.checkpoints)
    return {
        c: (
            np.array([m["intercept_db"] for m in run.at_trials[c]]),
            np.array([m["slope"] for m in run.at_trials[c]]),
        )
        for c in s.checkpoints
    }


def simulate_chunk(
    s: TradeSettings, replicates: int, seed: np.random.SeedSequence
) -> dict[str, Any]:
    """One chunk of simulated participants through every route (what a worker runs).

    Its result depends only on its arguments: the same chunk gives the same numbers on any
    worker.
    """
    rng = np.random.default_rng(seed)
    sub = replace(s, replicates=replicates)
    errors = _calibration_errors(sub, rng)
    return {
        "paper": _per_level_fits(sub, "paper", errors, rng),
        "quest_plus": _per_level_fits(sub, "quest_plus", errors, rng),
        "functional": _functional_fits(sub, errors, rng),
    }


def _route(s: TradeSettings, name: str, a_hat: Any, b_hat: Any, trials: float) -> RouteResult:
    ok = np.isfinite(a_hat) & np.isfinite(b_hat)
    sd_a, sd_b, rms = ramp_precision(a_hat[ok], b_hat[ok], s.intercept_db, s.slope, s.levels_db_sl)
    return RouteResult(
        name, trials, trials * s.seconds_per_trial / 60, sd_a, sd_b, rms, int(ok.sum())
    )


@dataclass(frozen=True)
class TradeEstimates:
    """Every simulated participant's fitted ramp by every route, in participant order.

    Attributes
    ----------
    intercepts_db, slopes : dict of str to ndarray
        Per route (``"paper"``, ``"quest_plus"``, ``"functional (N)"``), one intercept (dB) and
        slope (dB/dB) per participant; NaN where the route gave no ramp. Index i is the same
        participant (the same calibration error) in every route.
    trials : dict of str to float
        Mean trials per participant for the route's masking function.
    """

    intercepts_db: dict[str, NDArray[np.float64]]
    slopes: dict[str, NDArray[np.float64]]
    trials: dict[str, float]


def trade_estimates(
    s: TradeSettings, seed: int = 0, *, scheduler: str | None = "synchronous", chunk: int = 10
) -> TradeEstimates:
    """Simulate the three routes on the same participants; their fitted ramps.

    Participants are simulated in chunks of ``chunk`` (:mod:`masking_lab.planning.parallel`):
    ``scheduler`` ``"synchronous"`` in this process, None on worker processes of this machine,
    or a Dask scheduler's address; the same seed gives the same results whichever.

    Examples
    --------
    >>> est = trade_estimates(TradeSettings(replicates=3, checkpoints=(10,)))
    >>> list(est.intercepts_db), est.slopes["paper"].shape
    (['paper', 'quest_plus', 'functional (10)'], (3,))
    """
    from masking_lab.planning.parallel import chunk_plan, run_chunks

    plan = chunk_plan(
        int(np.random.SeedSequence([seed, 0x7A1D]).generate_state(1)[0]), s.replicates, chunk
    )
    parts = run_chunks(simulate_chunk, [(s, n, ss) for n, ss in plan], scheduler=scheduler)
    a: dict[str, NDArray[np.float64]] = {}
    b: dict[str, NDArray[np.float64]] = {}
    trials: dict[str, float] = {}
    for name in ("paper", "quest_plus"):
        a[name] = np.concatenate([p[name][0] for p in parts])
        b[name] = np.concatenate([p[name][1] for p in parts])
        trials[name] = float(np.concatenate([p[name][2] for p in parts]).mean())
    for c in s.checkpoints:
        name = f"functional ({c})"
        a[name] = np.concatenate([p["functional"][c][0] for p in parts])
        b[name] = np.concatenate([p["functional"][c][1] for p in parts])
        trials[name] = float(c)
    return TradeEstimates(a, b, trials)


def summarize_trade(s: TradeSettings, est: TradeEstimates) -> list[RouteResult]:
    """One :class:`RouteResult` per route, the paper's first.

    Examples
    --------
    >>> small = TradeSettings(replicates=3, checkpoints=(10,))
    >>> [r.n for r in summarize_trade(small, trade_estimates(small))]
    [3, 3, 3]
    """
    return [
        _route(s, name, est.intercepts_db[name], est.slopes[name], est.trials[name])
        for name in est.intercepts_db
    ]


def run_trade(
    s: TradeSettings, seed: int = 0, *, scheduler: str | None = "synchronous", chunk: int = 10
) -> list[RouteResult]:
    """The three routes on the same simulated participants (same calibration errors).

    :func:`trade_estimates` then :func:`summarize_trade`.

    Examples
    --------
    >>> small = TradeSettings(replicates=3, checkpoints=(10,))
    >>> [r.route for r in run_trade(small)]
    ['paper', 'quest_plus', 'functional (10)']
    """
    return summarize_trade(s, trade_estimates(s, seed, scheduler=scheduler, chunk=chunk))


def precision_ratios(
    s: TradeSettings, est: TradeEstimates, *, n_boot: int = 2000, seed: int = 0
) -> dict[str, NDArray[np.float64]]:
    """Each route's precision over the paper's, with a paired bootstrap 95 % interval.

    The participants are resampled together (every route measured the same participants, so
    their errors are paired), and for each resample each route's RMS errors (intercept, slope,
    predicted AL) are divided by the paper route's. A ratio below 1 is better than the paper.

    Returns
    -------
    dict of str to ndarray, shape (3, 3)
        Per route other than ``"paper"``: rows intercept, slope, RMS AL; columns the ratio on
        all participants, the 2.5th and the 97.5th percentile of the resampled ratios.

    Examples
    --------
    >>> small = TradeSettings(replicates=4, checkpoints=(10,))
    >>> r = precision_ratios(small, trade_estimates(small), n_boot=50)
    >>> sorted(r), r["quest_plus"].shape
    (['functional (10)', 'quest_plus'], (3, 3))
    """
    rng = np.random.default_rng(seed)
    n = est.intercepts_db["paper"].size
    idx = rng.integers(0, n, size=(n_boot, n))

    def rms(sq: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        # NaN rows (no ramp) drop out of their route's mean, as in summarize_trade.
        ok = np.isfinite(sq[:, 0]) & np.isfinite(sq[:, 1])
        sq0 = np.where(ok[:, None], sq, 0.0)
        whole = np.sqrt(sq0.sum(axis=0) / max(1, ok.sum()))
        counts = np.maximum(1, ok[idx].sum(axis=1))[:, None]
        return whole, np.sqrt(sq0[idx].sum(axis=1) / counts)

    paper_whole, paper_boot = rms(
        _squared_errors(
            est.intercepts_db["paper"], est.slopes["paper"], s.intercept_db, s.slope, s.levels_db_sl
        )
    )
    out = {}
    for name in est.intercepts_db:
        if name == "paper":
            continue
        whole, boot = rms(
            _squared_errors(
                est.intercepts_db[name], est.slopes[name], s.intercept_db, s.slope, s.levels_db_sl
            )
        )
        ratios = boot / paper_boot
        lo, hi = np.percentile(ratios, [2.5, 97.5], axis=0)
        out[name] = np.stack([whole / paper_whole, lo, hi], axis=1)
    return out


def trade_for_protocol(
    protocol: Any,
    truth: Any,
    *,
    replicates: int,
    seed: int,
    scheduler: str | None = "synchronous",
) -> tuple[TradeSettings, list[RouteResult], dict[str, NDArray[np.float64]]]:
    """The trade for the first set of a protocol whose procedure places the masker level:
    its settings, each route's result and its precision ratios (:func:`precision_ratios`).

    The pair's true ramp and the observers' psychometric function come from the ground truth;
    the functional grids, masker range and the checkpoints (up to the protocol's trial cap)
    from the protocol.

    Raises
    ------
    AnalysisError
        If the ground truth has no masking function for the pair.
    """
    spec = protocol.sets[0]
    fn = truth.masking_function(spec.target.name, spec.masker.name)
    if fn is None:
        raise AnalysisError(
            f"the ground truth has no masking function for {spec.target.name} by "
            f"{spec.masker.name}; add it, or pass another with --ground-truth"
        )
    settings = spec.settings
    lo, hi = settings.masker_min_db_sl, settings.masker_max_db_sl
    cap = settings.max_trials
    checkpoints = tuple(sorted({max(10, cap // 2), max(10, (2 * cap) // 3), cap}))
    trade = TradeSettings(
        intercept_db=fn.intercept_db,
        slope=fn.slope,
        levels_db_sl=tuple(float(v) for v in np.linspace(lo, hi, 5)),
        scale_db=truth.scale_db,
        lapse=truth.lapse,
        replicates=replicates,
        checkpoints=checkpoints,
        functional=settings,
    )
    est = trade_estimates(trade, seed, scheduler=scheduler)
    return trade, summarize_trade(trade, est), precision_ratios(trade, est, seed=seed)


def format_trade(
    trade: TradeSettings,
    results: Sequence[RouteResult],
    ratios: dict[str, NDArray[np.float64]] | None = None,
) -> str:
    """The trade as a text table with the Cramér–Rao trials for the paper's precision, and,
    given ``ratios`` (:func:`precision_ratios`), each route's precision over the paper's.

    Examples
    --------
    >>> r = RouteResult("paper", 260.0, 40.3, 3.1, 0.13, 1.1, 60)
    >>> print(format_trade(TradeSettings(), [r]).splitlines()[1])
    route                trials  minutes  SD a (dB)  SD b (dB/dB)  RMS AL (dB)
    """
    paper = results[0]
    lines = [
        f"masking function {trade.intercept_db:g} + {trade.slope:g}·x dB over "
        f"{min(trade.levels_db_sl):g}-{max(trade.levels_db_sl):g} dB SL, "
        f"{trade.replicates} simulated participants per route",
        f"{'route':<20} {'trials':>6} {'minutes':>8} {'SD a (dB)':>10} {'SD b (dB/dB)':>13} "
        f"{'RMS AL (dB)':>12}",
    ]
    for r in results:
        ok = (
            r.sd_intercept_db <= paper.sd_intercept_db
            and r.sd_slope <= paper.sd_slope
            and r.rms_al_db <= paper.rms_al_db
        )
        mark = "" if r is paper else ("  at the paper's precision" if ok else "")
        lines.append(
            f"{r.route:<20} {r.trials_mean:>6.0f} {r.minutes:>8.1f} {r.sd_intercept_db:>10.2f} "
            f"{r.sd_slope:>13.3f} {r.rms_al_db:>12.2f}{mark}"
        )
    if ratios:
        lines.append(
            "RMS error over the paper route's (below 1 is better; paired bootstrap 95 % interval "
            "over the participants):"
        )
        for name, ratio in ratios.items():
            cells = ", ".join(
                f"{what} {v:.2f} ({lo:.2f}-{hi:.2f})"
                for what, (v, lo, hi) in zip(("intercept", "slope", "RMS AL"), ratio, strict=True)
            )
            lines.append(f"  {name:<18} {cells}")
    need = []
    for k, target in enumerate((paper.sd_intercept_db, paper.sd_slope, paper.rms_al_db)):
        n = 1.0
        while (
            cramer_rao_ramp(n, trade.levels_db_sl, scale_db=trade.scale_db, lapse=trade.lapse)[k]
            > target
            and n < 1e6
        ):
            n *= 1.01
        need.append(math.ceil(n))
    lines.append(
        f"Cramér-Rao bound of the 2-D design (slope and lapse known): {max(need)} trials for "
        f"the paper's precision ({need[0]} intercept, {need[1]} slope, {need[2]} RMS AL)"
    )
    return "\n".join(lines) + "\n"
