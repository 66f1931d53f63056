"""How well a scene will render after a measurement budget (participants × trials), predicted by
simulation (issue 19.4; pure: the caller seeds the generator).

Two stages, so that the slow one runs once:

1. **Participants** (:func:`participant_errors`). For each masking function to be measured,
   ``tracks`` simulated participants run the procedure the plan's protocol uses over its masker
   range — the functional track (read after every trial budget: a shorter budget is a prefix of
   the same track) or QUEST+ per masker level with a least-squares ramp — each with their own
   ramp (the population's intercept plus the ground truth's between-participant shift SD) and
   their own calibration error (the paper's baseline staircase). Their estimates' errors against
   the population ramp give the per-participant covariance of (intercept, slope) per budget.
2. **Studies** (:func:`budget_table`). A study of N participants estimates the ramp as their
   mean, so its error is drawn from a normal with that covariance over N (the same standard
   normals for every budget: common random numbers, so budgets differ by their budget only).
   Functions already fitted within range keep their exported standard errors. The scene is
   rendered with the estimated ramps exactly as ``render`` does (ratings, gamut mapping) and
   felt under the true ones; the error is perceived − intended, dB, over every point and
   playing channel.

Simplifications (docs/scenes.md): the mean of N participants stands for ``analyze``'s pooled
ramp; a function measured beyond its fitted range is simulated as if refitted from the new
sessions alone (conservative: the old data would pin it inside its range); the simulated
procedure's bias is left out (a handful of tracks estimates it worse than it matters).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from masking_lab.analysis.ramp_fit import ramp_least_squares_batch
from masking_lab.core.errors import AnalysisError, SolverError
from masking_lab.core.masking import ramp
from masking_lab.core.psychometric import Psychometric
from masking_lab.planning.ramp_trade import PAPER_STAIRCASE
from masking_lab.procedures.functional import FunctionalRampSettings
from masking_lab.procedures.quest_plus import QuestPlusSettings
from masking_lab.procedures.quest_plus_batch import simulate_quest_plus
from masking_lab.procedures.staircase_batch import Observer, simulate
from masking_lab.rendering.pair import MutualMasking
from masking_lab.rendering.render import render_scene
from masking_lab.rendering.scene import Scene
from masking_lab.rendering.solver import forward

__all__ = [
    "BudgetRow",
    "Observers",
    "budget_table",
    "participant_errors",
    "participant_errors_chunked",
    "scene_error",
]

#: Simulated participants per chunk of :func:`participant_errors_chunked`.
PARTICIPANTS_PER_CHUNK = 25


@dataclass(frozen=True)
class Observers:
    """The simulated population's psychometric function and spread.

    Attributes
    ----------
    scale_db, lapse : float
        Logistic scale (dB) and lapse rate.
    shift_sd_db : float
        Between-participant SD of the ramp's intercept, dB.
    """

    scale_db: float = 1.5
    lapse: float = 0.02
    shift_sd_db: float = 1.0


def _calibration_errors(n: int, obs: Observers, rng: np.random.Generator) -> NDArray[np.float64]:
    """Each participant's unmasked-AL error from the paper's baseline staircase, dB."""
    sim = simulate(PAPER_STAIRCASE, np.zeros(n), Observer(obs.scale_db, obs.lapse), rng)
    return np.nan_to_num(sim.al_db, nan=0.0)


def participant_errors(
    procedure: Mapping[str, Any],
    kind: str,
    ramp_ab: tuple[float, float],
    trials: Sequence[int],
    *,
    tracks: int,
    observers: Observers,
    rng: np.random.Generator,
    masker_levels_db_sl: Sequence[float] = (),
) -> dict[int, NDArray[np.float64]]:
    """Per trial budget, each simulated participant's (intercept, slope) error, shape (n, 2).

    Parameters
    ----------
    procedure : mapping
        The protocol's ``procedure`` block (functional_ramp or quest_plus settings).
    kind : {"functional", "quest_plus"}
        Which procedure.
    ramp_ab : (float, float)
        The population ramp: intercept dB, slope dB/dB.
    trials : sequence of int
        Trial budgets per participant for this function (QUEST+: split over the levels).
    tracks : int
        Simulated participants.
    observers : Observers
    rng : numpy.random.Generator
    masker_levels_db_sl : sequence of float
        QUEST+'s masker levels, dB SL.

    Examples
    --------
    >>> from masking_lab.planning.scene_protocols import measurement_protocol
    >>> from masking_lab.planning.scene_needs import FunctionNeed
    >>> n = FunctionNeed("EV270", "MV180", (25, 30), "missing", None, 0, 0, "missing", -5.9, 0.66)
    >>> doc = measurement_protocol(n, 25.0, 30.0, procedure="quest_plus")
    >>> e = participant_errors(doc["procedure"], "quest_plus", (-5.9, 0.66), [20, 40], tracks=8,
    ...     observers=Observers(), rng=np.random.default_rng(0), masker_levels_db_sl=[25, 30])
    >>> sorted(e), e[40].shape
    ([20, 40], (8, 2))
    """
    a, b = ramp_ab
    intercepts = a + observers.shift_sd_db * rng.standard_normal(tracks)
    calib = _calibration_errors(tracks, observers, rng)
    want = sorted({int(t) for t in trials})
    if kind == "functional":
        settings = FunctionalRampSettings.from_mapping(
            {**procedure, "max_trials": max(want), "kind": "functional_ramp"}
        )
        psy = Psychometric(0.0, observers.scale_db, settings.guess, observers.lapse)
        draws = rng.random((max(want), tracks))
        out: dict[int, list[tuple[float, float]]] = {t: [] for t in want}
        for i in range(tracks):
            state = settings.start()
            read: dict[int, tuple[float, float]] = {}
            while not state.finished:
                theta = calib[i] + float(ramp(state.next_masker_level_db_sl(), intercepts[i], b))
                p = psy.p_correct(state.next_level() - theta)
                state = state.update(bool(draws[state.n_trials, i] < p))
                if state.n_trials in out:
                    m = state.moments()
                    read[state.n_trials] = (m["intercept_db"] - a, m["slope"] - b)
            m = state.moments()
            for t in want:  # a track that stopped early keeps its last estimate
                out[t].append(read.get(t, (m["intercept_db"] - a, m["slope"] - b)))
        return {t: np.array(v) for t, v in out.items()}
    levels = np.asarray(masker_levels_db_sl, dtype=float)
    if levels.size < 2:
        raise AnalysisError("QUEST+ per set needs at least two masker levels to fit a ramp")
    caps = {t: max(1, t // levels.size) for t in want}
    qp_settings = QuestPlusSettings.from_mapping(
        {**procedure, "max_trials": max(caps.values()), "kind": "quest_plus"}
    )
    means = []
    for x in levels:
        thr = calib + np.array([float(ramp(x, ai, b)) for ai in intercepts])
        sim = simulate_quest_plus(
            qp_settings, thr, scale_db=observers.scale_db, lapse=observers.lapse, rng=rng
        )
        means.append(sim)
    result = {}
    for t, cap in caps.items():
        shifts = np.stack(
            [s.mean_db[np.arange(tracks), np.minimum(cap, s.n_trials) - 1] for s in means], axis=1
        )
        ok = np.all(np.isfinite(shifts), axis=1)
        a_hat, b_hat = ramp_least_squares_batch(levels, shifts[ok])
        result[t] = np.stack([a_hat - a, b_hat - b], axis=1)
    return result


def _errors_chunk(
    procedure: dict[str, Any],
    kind: str,
    ramp_ab: tuple[float, float],
    trials: tuple[int, ...],
    tracks: int,
    observers: Observers,
    seed: np.random.SeedSequence,
    masker_levels_db_sl: tuple[float, ...],
) -> dict[int, NDArray[np.float64]]:
    """One chunk of :func:`participant_errors_chunked` (what a worker runs)."""
    return participant_errors(
        procedure, kind, ramp_ab, trials, tracks=tracks, observers=observers,
        rng=np.random.default_rng(seed), masker_levels_db_sl=masker_levels_db_sl,
    )  # fmt: skip


def participant_errors_chunked(
    procedure: Mapping[str, Any],
    kind: str,
    ramp_ab: tuple[float, float],
    trials: Sequence[int],
    *,
    tracks: int,
    observers: Observers,
    seed: Sequence[int],
    masker_levels_db_sl: Sequence[float] = (),
    scheduler: str | None = "synchronous",
    chunk: int = PARTICIPANTS_PER_CHUNK,
) -> dict[int, NDArray[np.float64]]:
    """:func:`participant_errors` in chunks of ``chunk`` participants, each seeded from
    ``seed`` (:func:`masking_lab.planning.parallel.chunk_plan`), run wherever ``scheduler``
    says (``"synchronous"``, ``"local"`` or a Dask address): the same seed gives the same
    errors on any number of workers.

    Examples
    --------
    >>> from masking_lab.planning.scene_protocols import measurement_protocol
    >>> from masking_lab.planning.scene_needs import FunctionNeed
    >>> n = FunctionNeed("EV270", "MV180", (25, 30), "missing", None, 0, 0, "missing", -5.9, 0.66)
    >>> doc = measurement_protocol(n, 25.0, 30.0, procedure="quest_plus")
    >>> e = participant_errors_chunked(doc["procedure"], "quest_plus", (-5.9, 0.66), [20],
    ...     tracks=7, observers=Observers(), seed=[0, 1], masker_levels_db_sl=[25, 30], chunk=3)
    >>> e[20].shape
    (7, 2)
    """
    from masking_lab.planning.parallel import chunk_plan, run_tasks

    args = (dict(procedure), kind, (float(ramp_ab[0]), float(ramp_ab[1])), tuple(trials))
    levels = tuple(float(x) for x in masker_levels_db_sl)
    tasks = [
        (_errors_chunk, (*args, n, observers, ss, levels))
        for n, ss in chunk_plan(list(seed), tracks, chunk)
    ]
    parts = run_tasks(tasks, scheduler=scheduler)
    return {t: np.concatenate([p[t] for p in parts]) for t in parts[0]}


@dataclass(frozen=True)
class BudgetRow:
    """The scene's predicted rendering error after one budget.

    Attributes
    ----------
    participants, trials : int
        Participants, and trials per participant per measured function.
    trials_per_participant : int
        Over every measured function.
    hours : float
        Testing time of the whole study, h (trials × seconds per trial).
    rms_db, rms_p90_db, max_db : float
        Over simulated studies: mean and 90th percentile of the scene's RMS perceived error, and
        mean of its maximum, dB (perceived − intended, every point and playing channel).
    measurement_rms_db : float
        Mean RMS of the part due to the measurement: perceived − what the true ramps would give,
        dB.
    unrendered_share : float
        Mean share of points without a unique input (b·d ≥ 1 in a study's estimate).
    """

    participants: int
    trials: int
    trials_per_participant: int
    hours: float
    rms_db: float
    rms_p90_db: float
    max_db: float
    measurement_rms_db: float
    unrendered_share: float

    def as_dict(self) -> dict[str, Any]:
        """CSV/JSON row (levels dB, time h)."""
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def scene_error(
    scene: Scene,
    estimate: MutualMasking,
    truth: MutualMasking,
    *,
    max_mv_db_sl: float | None,
    max_ev_db_sl: float | None,
    gamut_map: str,
    reference: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None, float]:
    """Perceived − intended per point and playing channel (dB), the same against ``reference``
    (what the true ramps give), and the share of points without an input.

    The scene is rendered with ``estimate`` as ``render`` would (ratings, gamut mapping) and felt
    under ``truth``.

    Examples
    --------
    >>> from masking_lab.rendering.scene import GeometrySpec, PathSpec, TextureSpec
    >>> scene = Scene("bump_rough", PathSpec(n_points=91), GeometrySpec("bump"),
    ...               TextureSpec("rough", "MV180", 6.0))
    >>> truth = MutualMasking(1.304, 1.062, -5.927, 0.658, mv="MV180", ev="EV270")
    >>> err, _, lost = scene_error(scene, truth, truth, max_mv_db_sl=None, max_ev_db_sl=None,
    ...                            gamut_map="none")
    >>> float(np.max(np.abs(err))) < 1e-9, lost
    (True, 0.0)
    """
    mapping = gamut_map if (max_mv_db_sl is not None and max_ev_db_sl is not None) else "none"
    r = render_scene(
        scene, estimate, max_mv_db_sl=max_mv_db_sl, max_ev_db_sl=max_ev_db_sl, gamut_map=mapping
    )
    mv_t, ev_t = scene.targets()[1:]
    with np.errstate(invalid="ignore"):
        mp, ep = forward(truth, r.mv_input_db_sl, r.ev_input_db_sl)
    errs, refs = [], []
    for felt, want, k in ((mp, mv_t, 0), (ep, ev_t, 1)):
        plays = np.isfinite(want)
        errs.append((felt - want)[plays])
        if reference is not None:
            refs.append((felt - reference[k])[plays])
    err = np.concatenate(errs)
    lost = float(np.mean(~np.isfinite(r.mv_input_db_sl) & np.isfinite(mv_t)))
    return err, (np.concatenate(refs) if reference is not None else None), lost


def _rms(x: NDArray[np.float64]) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x**2))) if x.size else math.nan


def _max_abs(x: NDArray[np.float64]) -> float:
    x = x[np.isfinite(x)]
    return float(np.max(np.abs(x))) if x.size else math.nan


def _mean(values: Sequence[float], q: float | None = None) -> float:
    """Mean (or the ``q``-th percentile) of the finite values; NaN, without a warning, if none."""
    x = np.asarray(values, dtype=float)
    x = x[np.isfinite(x)]
    if not x.size:
        return math.nan
    return float(np.mean(x) if q is None else np.percentile(x, q))


def budget_table(
    scene: Scene,
    truth: MutualMasking,
    measured: Mapping[str, dict[int, NDArray[np.float64]]],
    known_sd: Mapping[str, tuple[float, float]],
    *,
    participants: Sequence[int],
    trials: Sequence[int],
    studies: int,
    seconds_per_trial: float,
    max_mv_db_sl: float | None,
    max_ev_db_sl: float | None,
    gamut_map: str,
    rng: np.random.Generator,
) -> tuple[list[BudgetRow], dict[str, float]]:
    """The scene's rendering error for every budget (participants × trials).

    Parameters
    ----------
    scene : Scene
    truth : MutualMasking
        The ramps the simulated participants have.
    measured : mapping
        ``"f"`` (MV masked by EV) and/or ``"g"`` (EV masked by MV) → :func:`participant_errors`.
    known_sd : mapping
        ``"f"``/``"g"`` → (intercept SE dB, slope SE) of functions not measured again.
    participants, trials : sequence of int
        The budgets (trials per participant per measured function).
    studies : int
        Simulated studies per budget.
    seconds_per_trial : float
        For the testing time, s.
    max_mv_db_sl, max_ev_db_sl : float or None
        Ratings, dB SL.
    gamut_map : str
    rng : numpy.random.Generator

    Returns
    -------
    rows, floor
        One :class:`BudgetRow` per budget (participants outer), and the error with the ramps
        known exactly (``rms_db``, ``max_db``): what no budget can beat.
    """
    kw: dict[str, Any] = {
        "max_mv_db_sl": max_mv_db_sl,
        "max_ev_db_sl": max_ev_db_sl,
        "gamut_map": gamut_map,
    }
    err0, _, _ = scene_error(scene, truth, truth, **kw)
    mv_t, ev_t = scene.targets()[1:]
    reference = (mv_t + _unfold(err0, mv_t, ev_t, 0), ev_t + _unfold(err0, mv_t, ev_t, 1))
    floor = {"rms_db": _rms(err0), "max_db": _max_abs(err0)}
    base = {"f": np.array([truth.a_db, truth.b]), "g": np.array([truth.c_db, truth.d])}
    z = {k: rng.standard_normal((studies, 2)) for k in ("f", "g")}
    n_measured = len(measured)
    rows = []
    for n in participants:
        for t in trials:
            draws = {}
            for k in ("f", "g"):
                if k in measured:
                    dev = measured[k][t]
                    cov = np.cov(dev, rowvar=False) if len(dev) > 1 else np.zeros((2, 2))
                    chol = np.linalg.cholesky(cov + 1e-12 * np.eye(2))
                    draws[k] = base[k] + z[k] @ chol.T / math.sqrt(n)
                else:
                    draws[k] = base[k] + z[k] * np.asarray(known_sd.get(k, (0.0, 0.0)))
            rms, mx, meas, lost = [], [], [], []
            for s in range(studies):
                (a, b), (c, d) = draws["f"][s], draws["g"][s]
                try:
                    est = replace(truth, a_db=a, b=max(b, 0.0), c_db=c, d=max(d, 0.0))
                except SolverError:
                    continue
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    err, dref, share = scene_error(scene, est, truth, reference=reference, **kw)
                rms.append(_rms(err))
                mx.append(_max_abs(err))
                meas.append(_rms(dref) if dref is not None else math.nan)
                lost.append(share)
            rows.append(
                BudgetRow(
                    participants=int(n),
                    trials=int(t),
                    trials_per_participant=int(t) * n_measured,
                    hours=n * t * n_measured * seconds_per_trial / 3600,
                    rms_db=_mean(rms),
                    rms_p90_db=_mean(rms, 90),
                    max_db=_mean(mx),
                    measurement_rms_db=_mean(meas),
                    unrendered_share=_mean(lost),
                )
            )
    return rows, floor


def _unfold(
    err: NDArray[np.float64], mv_t: NDArray[np.float64], ev_t: NDArray[np.float64], k: int
) -> NDArray[np.float64]:
    """Put the per-channel errors of :func:`scene_error` back on the points (NaN elsewhere)."""
    out = np.full(mv_t.shape, np.nan)
    n_mv = int(np.count_nonzero(np.isfinite(mv_t)))
    if k == 0:
        out[np.isfinite(mv_t)] = err[:n_mv]
    else:
        out[np.isfinite(ev_t)] = err[n_mv:]
    return out
