"""ALs of sets run by a Bayesian procedure (QUEST+), re-estimated from the logged trials (pure).

The staircase's AL is the mean of its last reversals (:mod:`masking_lab.analysis.thresholds`).
A set run by another procedure (``set_start.procedure`` with its ``kind``) is estimated by its
kind's estimator (:mod:`masking_lab.procedures.registry`); for QUEST+, from its logged levels
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

from masking_lab.core.errors import ProcedureError
from masking_lab.procedures.registry import kind_named

__all__ = ["ProcedureEstimate", "procedure_estimate"]


def __getattr__(name: str) -> Any:
    # ``posterior_summary`` (QUEST+'s, still importable from here) is imported when asked for:
    # its module loads numpy and QUEST+, which a study of staircases never needs.
    if name == "posterior_summary":
        from masking_lab.procedures.quest_plus_kind import posterior_summary

        return posterior_summary
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


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
    method = "ml" if estimator == "ml" else "posterior_mean"
    try:
        kind = kind_named(procedure.get("kind"))
    except ProcedureError as exc:
        return ProcedureEstimate(None, None, None, None, method, "invalid", str(exc))
    if kind.estimate_log is None:
        note = f"procedure kind {kind.name!r} is estimated from its reversals, not here"
        return ProcedureEstimate(None, None, None, None, method, "invalid", note)
    return ProcedureEstimate(*kind.estimate_log(procedure, levels_db, correct, estimator, lapse))


def places_masker(procedure: Any) -> bool:
    """Whether a logged ``set_start.procedure`` chooses the masker level trial by trial.

    Such a set (``functional_ramp``) has no single masker level, so its ``set_start`` names none.

    Examples
    --------
    >>> places_masker({"kind": "functional_ramp"}), places_masker({"kind": "quest_plus"})
    (True, False)
    >>> places_masker(None), places_masker({"kind": "no such kind"})
    (False, False)
    """
    if not isinstance(procedure, Mapping):
        return False
    try:
        return kind_named(procedure.get("kind")).places_masker
    except ProcedureError:
        return False
