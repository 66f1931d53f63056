"""ALs of sets run by a Bayesian procedure (QUEST+), re-estimated from the logged trials (pure).

The staircase's AL is the mean of its last reversals (:mod:`masking_lab.analysis.thresholds`).
A QUEST+ set (``set_start.procedure.kind == "quest_plus"``) is estimated from its logged levels
and answers under the model and prior its ``set_start`` record states:

``reversals`` (the analysis default, named for the staircase)
    the **posterior mean** of the threshold, with the posterior SD and the central 95 %
    credible interval (2.5 % and 97.5 % quantiles of the threshold's marginal posterior);
``ml``
    the maximum-likelihood fit over the trials (:func:`masking_lab.procedures.estimators.
    ml_threshold`, the staircase's ML estimator, with the set's guess rate and threshold
    definition), with the posterior's SD and interval beside it.

The posterior is recomputed from the logged levels (not by replaying the placement), so the
estimate holds even for a log whose levels a newer version would place differently. Levels and
SDs are dB in the set's ``level_unit``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from masking_lab.core.errors import StaircaseError
from masking_lab.procedures.estimators import ml_threshold
from masking_lab.procedures.quest_plus import QuestPlusSettings, tables
from masking_lab.procedures.quest_plus_model import psychometric_table

__all__ = ["ProcedureEstimate", "posterior_summary", "procedure_estimate"]


@dataclass(frozen=True)
class ProcedureEstimate:
    """A Bayesian set's AL and its interval, or why there is none.

    Attributes
    ----------
    al_db : float or None
        The AL, dB in the set's level unit.
    sd_db : float or None
        Posterior SD of the threshold, dB.
    ci_low_db, ci_high_db : float or None
        Central 95 % credible interval of the threshold, dB.
    method : str
        ``posterior_mean`` or ``ml``.
    status : str
        ``completed``, ``invalid`` or ``estimator_failed``.
    note : str or None
        Why there is no AL.
    """

    al_db: float | None
    sd_db: float | None
    ci_low_db: float | None
    ci_high_db: float | None
    method: str
    status: str
    note: str | None = None


def posterior_summary(
    settings: QuestPlusSettings, levels_db: Sequence[float], correct: Sequence[bool]
) -> tuple[float, float, float, float]:
    """Posterior (mean, SD, 2.5 % quantile, 97.5 % quantile) of the threshold, dB.

    Parameters
    ----------
    settings : QuestPlusSettings
        Model, grids and prior the set ran under.
    levels_db, correct : sequences
        Every trial's level (dB, any value: off-grid levels are evaluated exactly) and answer.

    Examples
    --------
    >>> s = QuestPlusSettings(-20.0, 45.0, max_trials=40)
    >>> mean, sd, lo, hi = posterior_summary(s, [10.0] * 20 + [0.0] * 20,
    ...                                      [True] * 20 + [False, True, False] * 6 + [False] * 2)
    >>> lo < mean < hi and sd > 0
    True
    """
    t = tables(settings)
    x = np.asarray(levels_db, dtype=float)
    r = np.asarray(correct, dtype=bool)
    p_c, p_w = psychometric_table(
        x, t.thresholds_db, t.nuisance, settings.guess, settings.p_at_threshold
    )
    log_post = np.log(t.prior) + np.where(r[:, None, None], np.log(p_c), np.log(p_w)).sum(axis=0)
    post = np.exp(log_post - log_post.max())
    marginal = post.sum(axis=1)
    marginal /= marginal.sum()
    grid = t.thresholds_db
    mean = float(marginal @ grid)
    sd = float(np.sqrt(max(float(marginal @ (grid - mean) ** 2), 0.0)))
    cdf = np.cumsum(marginal)
    lo, hi = (float(np.interp(q, cdf, grid)) for q in (0.025, 0.975))
    return mean, sd, lo, hi


def procedure_estimate(
    procedure: Mapping[str, Any],
    levels_db: Sequence[float],
    correct: Sequence[bool],
    *,
    estimator: str = "reversals",
    lapse: float | None = 0.02,
) -> ProcedureEstimate:
    """Estimate a completed set that ran ``procedure`` (its logged ``set_start.procedure``).

    Never raises for bad data: problems come back as a status and a note.

    Examples
    --------
    >>> proc = {"kind": "quest_plus", "min_level_db": -20, "max_level_db": 45, "max_trials": 30}
    >>> est = procedure_estimate(proc, [12.0, 4.0, 8.0], [True, False, True])
    >>> est.method, est.status, est.ci_low_db < est.al_db < est.ci_high_db
    ('posterior_mean', 'completed', True)
    """
    kind = procedure.get("kind")
    method = "ml" if estimator == "ml" else "posterior_mean"
    if kind != "quest_plus":
        note = f"procedure kind {kind!r} has no estimator here (known: staircase, quest_plus)"
        return ProcedureEstimate(None, None, None, None, method, "invalid", note)
    try:
        settings = QuestPlusSettings.from_mapping(procedure)
    except StaircaseError as exc:
        return ProcedureEstimate(
            None, None, None, None, method, "invalid", f"set_start.procedure: {exc}"
        )
    if not levels_db:
        return ProcedureEstimate(
            None, None, None, None, method, "estimator_failed", "no trials to estimate from"
        )
    mean, sd, lo, hi = posterior_summary(settings, levels_db, correct)
    if estimator != "ml":
        return ProcedureEstimate(mean, sd, lo, hi, method, "completed")
    fit = ml_threshold(
        levels_db,
        correct,
        guess=settings.guess,
        lapse=lapse,
        p_target=settings.p_at_threshold,
    )
    if not fit.ok:
        return ProcedureEstimate(None, sd, lo, hi, method, "estimator_failed", fit.message)
    return ProcedureEstimate(float(fit.threshold_db), sd, lo, hi, method, "completed")  # type: ignore[arg-type]
