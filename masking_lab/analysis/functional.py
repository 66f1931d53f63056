"""Ramp posteriors of functional-procedure sets, and group masking functions from them (pure).

A ``functional_ramp`` set measures a masking function, not one AL. Its posterior over the
ramp's intercept a (dB) and slope b (dB/dB) is recomputed from the logged trials (masker level,
target level, answer; off-grid levels evaluated exactly) under the model and grids its
``set_start.procedure`` states, not by replaying the placement. Per participant that gives the
posterior means, SDs, correlation and central 95 % credible intervals.

Across participants, two group estimates per (target, masker):

``random_effects`` (partial pooling)
    a random-effects combination of the participants' posteriors (DerSimonian & Laird 1986):
    each participant's mean weighted by 1/(SD² + τ²), τ² the between-participant variance
    estimated from the spread of the means beyond their SDs; intercept and slope each.
``paper_route``
    the paper's route on the same data: each participant's predicted AL shift at the masker
    levels the procedure played (the posterior mean ramp), averaged across participants, and a
    least-squares ramp fit to those mean shifts (:func:`masking_lab.analysis.ramp_fit.fit_ramp`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from masking_lab.analysis.procedure_estimates import places_masker
from masking_lab.analysis.ramp_fit import fit_ramp
from masking_lab.core.errors import ProcedureError
from masking_lab.core.masking import ramp
from masking_lab.procedures.functional import FunctionalRampSettings, likelihood, ramp_tables
from masking_lab.procedures.functional_kind import KIND as FUNCTIONAL
from masking_lab.procedures.model_note import stated_model_note

__all__ = [
    "GroupRamp",
    "RampPosterior",
    "group_ramps",
    "ramp_posterior",
    "ramp_posteriors_from_logs",
]

#: Normal quantile of a central 95 % interval.
_Z95 = 1.959963984540054


@dataclass(frozen=True)
class RampPosterior:
    """One participant's ramp for one (target, masker), from one functional set.

    Attributes
    ----------
    participant, target, masker : str
    intercept_db, intercept_sd_db : float
        Posterior mean and SD of the intercept, dB.
    intercept_ci_db : (float, float)
        Central 95 % credible interval, dB.
    slope, slope_sd : float
        Posterior mean and SD of the slope, dB/dB.
    slope_ci : (float, float)
    rho : float
        Posterior correlation of intercept and slope.
    n_trials : int
    masker_levels_db_sl : tuple of float
        The masker levels the track played, dB SL.
    status : str
        The set's status (``completed``, ``trial_cap``, ...).
    """

    participant: str
    target: str
    masker: str
    intercept_db: float
    intercept_sd_db: float
    intercept_ci_db: tuple[float, float]
    slope: float
    slope_sd: float
    slope_ci: tuple[float, float]
    rho: float
    n_trials: int
    masker_levels_db_sl: tuple[float, ...]
    status: str


def _quantiles(grid: np.ndarray, weights: np.ndarray) -> tuple[float, float]:
    values = np.unique(grid)
    mass = np.array([weights[grid == v].sum() for v in values])
    cdf = np.cumsum(mass) / mass.sum()
    return float(np.interp(0.025, cdf, values)), float(np.interp(0.975, cdf, values))


def ramp_posterior(
    procedure: Mapping[str, Any],
    maskers_db_sl: Sequence[float],
    levels_db: Sequence[float],
    correct: Sequence[bool],
    *,
    participant: str = "",
    target: str = "",
    masker: str = "",
    status: str = "completed",
) -> RampPosterior:
    """The ramp posterior of one functional set from its logged trials.

    Raises
    ------
    ProcedureError
        If the logged settings are not valid functional_ramp settings or there are no trials.

    Examples
    --------
    >>> proc = {"kind": "functional_ramp", "max_trials": 4}
    >>> post = ramp_posterior(proc, [5.0, 25.0, 25.0, 15.0], [0.0, 12.0, 20.0, 8.0],
    ...                       [True, False, True, True])
    >>> post.intercept_ci_db[0] < post.intercept_db < post.intercept_ci_db[1]
    True
    """
    settings = FunctionalRampSettings.from_mapping(procedure)
    x = np.asarray(maskers_db_sl, dtype=float)
    y = np.asarray(levels_db, dtype=float)
    r = np.asarray(correct, dtype=bool)
    if x.size == 0 or not (x.shape == y.shape == r.shape):
        raise ProcedureError("a ramp posterior needs one masker level, level and answer per trial")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise ProcedureError("a logged masker or target level is not a finite number")
    t = ramp_tables(settings)
    p = likelihood(
        x, y, t.intercepts_db, t.slopes, t.nuisance, settings.guess, settings.p_at_threshold
    )  # (A, T, N)
    ll = np.log(np.where(r[None, :, None], p, 1.0 - p)).sum(axis=1)  # (A, N); p in (0, 1)
    post = np.exp(ll - ll.max())
    w = post.sum(axis=1)
    w /= w.sum()
    a, b = t.intercepts_db, t.slopes
    ma, mb = float(w @ a), float(w @ b)
    va, vb = float(w @ (a - ma) ** 2), float(w @ (b - mb) ** 2)
    cov = float(w @ ((a - ma) * (b - mb)))
    rho = min(1.0, max(-1.0, cov / math.sqrt(va * vb))) if va > 0 and vb > 0 else 0.0
    return RampPosterior(
        participant=participant,
        target=target,
        masker=masker,
        intercept_db=ma,
        intercept_sd_db=math.sqrt(max(va, 0.0)),
        intercept_ci_db=_quantiles(a, w),
        slope=mb,
        slope_sd=math.sqrt(max(vb, 0.0)),
        slope_ci=_quantiles(b, w),
        rho=rho,
        n_trials=int(x.size),
        masker_levels_db_sl=tuple(sorted({float(v) for v in x})),
        status=status,
    )


def ramp_posteriors_from_logs(logs: Iterable[Any]) -> tuple[list[RampPosterior], list[str]]:
    """Every finished functional set of these parsed session logs, and problems found.

    Parameters
    ----------
    logs : iterable of SessionLog
        Parsed logs (:func:`masking_lab.formats.session_log.read_log`); sets of other kinds
        are ignored.

    Returns
    -------
    posteriors : list of RampPosterior
    problems : list of str
        One line per functional set that could not be estimated (never an exception), then
        one per stated slope/lapse model whose ramp intervals assume it
        (:func:`masking_lab.procedures.model_note.stated_model_note`), with its set count.
    """
    out: list[RampPosterior] = []
    problems: list[str] = []
    caveats: dict[str, int] = {}
    for log in logs:
        participant = str(log.header.get("participant", ""))
        for set_id, rec in log.sets().items():
            procedure = rec.start.get("procedure") or {}
            if not places_masker(procedure) or rec.end is None:
                continue
            status = str(rec.end.get("status", ""))
            if status not in ("completed", "trial_cap"):
                continue
            try:
                out.append(
                    ramp_posterior(
                        procedure,
                        [t.get("masker_level_db_sl") for t in rec.trials],
                        [t.get("level_db_sl") for t in rec.trials],
                        [bool(t.get("correct")) for t in rec.trials],
                        participant=participant,
                        target=str(rec.start.get("target")),
                        masker=str(rec.start.get("masker")),
                        status=status,
                    )
                )
            except (ProcedureError, TypeError, ValueError) as exc:
                problems.append(f"{log.path.name}: set {set_id}: {str(exc)[:200]}")
                continue
            note = stated_model_note(procedure)
            if note is not None:
                caveats[note] = caveats.get(note, 0) + 1
    # Said once per distinct model, with how many ramps it concerns, as the report does.
    problems += [f"ramp intervals of {n} set(s): {note}" for note, n in sorted(caveats.items())]
    return out, problems


@dataclass(frozen=True)
class GroupRamp:
    """A group masking function for one (target, masker), and how it was formed.

    Attributes
    ----------
    target, masker : str
    estimate : {"random_effects", "paper_route"}
    procedure : str
        The procedure whose logs it comes from (``functional_ramp``).
    intercept_db, slope : float
    intercept_se_db, slope_se : float
    intercept_ci_db, slope_ci : (float, float)
    tau_intercept_db, tau_slope : float or None
        Between-participant SDs (random effects only).
    n_participants : int
    status, message : str
    intercept_slope_cov : float or None
        Covariance of the group intercept and slope, dB · dB/dB (random effects: the
        participants' mean posterior correlation times the two standard errors).
    """

    target: str
    masker: str
    estimate: str
    procedure: str
    intercept_db: float
    slope: float
    intercept_se_db: float
    slope_se: float
    intercept_ci_db: tuple[float, float]
    slope_ci: tuple[float, float]
    tau_intercept_db: float | None
    tau_slope: float | None
    n_participants: int
    status: str = "fitted"
    message: str = ""
    intercept_slope_cov: float | None = None


def random_effects(means: Sequence[float], sds: Sequence[float]) -> tuple[float, float, float]:
    """DerSimonian–Laird pooled mean, its SE and the between-unit SD τ.

    Examples
    --------
    >>> mu, se, tau = random_effects([1.0, 1.0, 1.0], [0.5, 0.5, 0.5])
    >>> mu, round(se, 4), tau
    (1.0, 0.2887, 0.0)
    """
    x = np.asarray(means, dtype=float)
    v = np.maximum(np.asarray(sds, dtype=float) ** 2, 1e-12)
    w = 1.0 / v
    mu_fixed = float(w @ x / w.sum())
    k = x.size
    q = float(w @ (x - mu_fixed) ** 2)
    denom = float(w.sum() - (w**2).sum() / w.sum())
    tau2 = max(0.0, (q - (k - 1)) / denom) if k > 1 and denom > 0 else 0.0
    ws = 1.0 / (v + tau2)
    mu = float(ws @ x / ws.sum())
    return mu, float(1.0 / math.sqrt(ws.sum())), math.sqrt(tau2)


def group_ramps(posteriors: Sequence[RampPosterior]) -> list[GroupRamp]:
    """Both group estimates for each (target, masker) of these participants' posteriors.

    Examples
    --------
    >>> one = RampPosterior("P1", "EV270", "MV120", -7.0, 1.0, (-9.0, -5.0), 0.7, 0.05,
    ...                     (0.6, 0.8), -0.9, 87, (5.0, 15.0, 25.0), "completed")
    >>> two = RampPosterior("P2", "EV270", "MV120", -6.0, 1.0, (-8.0, -4.0), 0.75, 0.05,
    ...                     (0.65, 0.85), -0.9, 87, (5.0, 15.0, 25.0), "completed")
    >>> [(g.estimate, round(g.intercept_db, 2)) for g in group_ramps([one, two])]
    [('random_effects', -6.5), ('paper_route', -6.5)]
    """
    by_pair: dict[tuple[str, str], list[RampPosterior]] = {}
    for p in posteriors:
        by_pair.setdefault((p.target, p.masker), []).append(p)
    out: list[GroupRamp] = []
    for (target, masker), ps in sorted(by_pair.items()):
        a, se_a, tau_a = random_effects(
            [p.intercept_db for p in ps], [p.intercept_sd_db for p in ps]
        )
        b, se_b, tau_b = random_effects([p.slope for p in ps], [p.slope_sd for p in ps])
        out.append(
            GroupRamp(
                target,
                masker,
                "random_effects",
                FUNCTIONAL.name,
                a,
                b,
                se_a,
                se_b,
                (a - _Z95 * se_a, a + _Z95 * se_a),
                (b - _Z95 * se_b, b + _Z95 * se_b),
                tau_a,
                tau_b,
                len(ps),
                # DerSimonian-Laird pools each parameter alone; their correlation is taken
                # as the participants' mean posterior one.
                intercept_slope_cov=float(np.mean([p.rho for p in ps])) * se_a * se_b,
            )
        )
        out.append(_paper_route(target, masker, ps))
    return out


def _paper_route(target: str, masker: str, ps: Sequence[RampPosterior]) -> GroupRamp:
    """Mean predicted shifts at the masker levels played, then the paper's least squares."""
    levels = np.array(sorted({v for p in ps for v in p.masker_levels_db_sl}))
    shifts = np.mean([ramp(levels, p.intercept_db, p.slope) for p in ps], axis=0)
    fit = fit_ramp(levels, shifts)
    nan = (math.nan, math.nan)
    return GroupRamp(
        target,
        masker,
        "paper_route",
        FUNCTIONAL.name,
        fit.intercept_db if fit.intercept_db is not None else math.nan,
        fit.slope if fit.slope is not None else math.nan,
        fit.intercept_se_db if fit.intercept_se_db is not None else math.nan,
        fit.slope_se if fit.slope_se is not None else math.nan,
        fit.intercept_ci_db if fit.intercept_ci_db is not None else nan,
        fit.slope_ci if fit.slope_ci is not None else nan,
        None,
        None,
        len(ps),
        fit.status,
        fit.message or "",
    )
