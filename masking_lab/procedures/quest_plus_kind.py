"""QUEST+ / psi-marginal as a registered procedure kind (pure).

Chosen by ``procedure: {kind: quest_plus, ...}``, logged under ``set_start.procedure``; each
trial record holds the posterior's mean and SD; its trials left come from the precision stop
rule; ``analyze`` recomputes the posterior from the logged levels and answers
(:func:`posterior_summary`). Levels in dB of the set's level unit.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from masking_lab.core.errors import LevelError, ProcedureError
from masking_lab.procedures.estimators import ml_threshold
from masking_lab.procedures.fisher import max_information
from masking_lab.procedures.limits import DEFAULT_BAYES_TRIAL_CAP, grid_top
from masking_lab.procedures.model_note import stated_model_note
from masking_lab.procedures.quest_plus import QuestPlus, QuestPlusSettings, tables
from masking_lab.procedures.quest_plus_batch import replay_many, simulate_quest_plus
from masking_lab.procedures.quest_plus_model import psychometric_table
from masking_lab.procedures.registry import ProcedureKind, ProtocolContext, SettingsProblem

__all__ = [
    "KIND",
    "PSI_MARGINAL_EFFICIENCY",
    "QUEST_EFFICIENCY",
    "posterior_summary",
    "quest_trials_left",
]

#: QUEST+'s measured efficiency against the Cramér-Rao bound (docs/procedures.md: 59 %).
QUEST_EFFICIENCY = 0.6
#: The same for psi-marginal on the default scale and lapse grids: the posterior SD also
#: carries the slope and lapse the trials have not pinned down (median 65 trials to SD 1.08 dB
#: for the 1.5 dB / 0.02 observer, docs/procedures.md).
PSI_MARGINAL_EFFICIENCY = 0.27


def _from_mapping(block: Mapping[str, Any], key: str) -> QuestPlusSettings:
    try:
        return QuestPlusSettings.from_mapping(block)
    except ProcedureError as exc:
        raise SettingsProblem.of(exc, "quest_plus", key) from None


def _from_protocol(ctx: ProtocolContext) -> QuestPlusSettings:
    settings = _from_mapping(ctx.block, ctx.block_key)
    if settings.max_trials is None:
        # Every track has a finite cap; `validate` shows this one in the protocol's summary.
        block = {**ctx.block, "max_trials": max(DEFAULT_BAYES_TRIAL_CAP, settings.min_trials)}
        settings = _from_mapping(block, ctx.block_key)
    if "start_level_db" in ctx.set_data:
        raise SettingsProblem(
            f"{ctx.set_key}.start_level_db",
            "start_level_db belongs to a staircase; QUEST+ places its first trial itself "
            "(remove the key or run this set as a staircase)",
        )
    return settings


def _within_limit(settings: QuestPlusSettings, max_db: float) -> QuestPlusSettings:
    """QUEST+ under a device limit: the stimulus grid stops at the limit, on the protocol's
    grid so the levels stay round numbers. A threshold grid that follows the stimulus range
    (the default) follows it down, so a threshold above what the rig can play ends the track
    as ``ceiling`` rather than as an extrapolated number."""
    if max_db >= settings.max_level_db:
        return settings
    step = settings.level_step_db
    top = grid_top(settings.min_level_db, step, max_db)
    if top <= settings.min_level_db:
        raise LevelError(
            f"the device limit ({max_db:.2f} dB) leaves QUEST+ less than one grid step "
            f"({step:g} dB) above procedure.min_level_db ({settings.min_level_db:g} dB)"
        )
    return replace(settings, max_level_db=top)


def _trial_fields(_before: QuestPlus, after: QuestPlus) -> dict[str, Any]:
    return {"posterior": {"mean_db": after.posterior_mean_db, "sd_db": after.posterior_sd_db}}


def _progress(state: QuestPlus, unit: str) -> str:
    if not state.n_trials:
        return f"posterior: prior {unit}"
    return f"posterior {state.posterior_mean_db:.1f} ± {state.posterior_sd_db:.1f} {unit}"


@functools.lru_cache(maxsize=32)
def _information(settings: QuestPlusSettings) -> float:
    """I* of the settings' model (the middle scale and lapse of its grids) times the
    procedure's efficiency, dB⁻² per trial."""
    info, _, _ = max_information(
        scale_db=float(np.median(settings.scales_db)),
        guess=settings.guess,
        lapse=float(np.median(settings.lapses)),
    )
    known = len(settings.scales_db) * len(settings.lapses) == 1
    return info * (QUEST_EFFICIENCY if known else PSI_MARGINAL_EFFICIENCY)


def quest_trials_left(
    settings: QuestPlusSettings, n_trials: int, sd_db: float | None = None
) -> float:
    """Expected trials before a QUEST+ track stops.

    Each trial adds to the posterior precision 1/SD² about ``QUEST_EFFICIENCY`` × I* (the
    Fisher information of the most informative trial, at the grids' middle scale and lapse),
    so a track at SD σ needs about (1/target² − 1/σ²)/(0.6·I*) more; with slope or lapse
    marginalised the efficiency is ``PSI_MARGINAL_EFFICIENCY``.

    Parameters
    ----------
    settings : QuestPlusSettings
        The track's rules.
    n_trials : int
        Trials answered so far.
    sd_db : float or None
        The posterior SD now, dB (None before the track starts: the prior counts as no
        information).

    Returns
    -------
    float
        Trials, ≥ 0: the trials left to the cap without a precision rule; otherwise the
        information still missing for ``target_sd_db`` over what a trial brings, at least
        ``min_trials − n_trials``, at most the trials left to the cap.

    Examples
    --------
    >>> s = QuestPlusSettings(-20.0, 45.0, target_sd_db=1.08, max_trials=80)
    >>> round(quest_trials_left(s, 0))   # slope and lapse marginalised (the default)
    70
    >>> round(quest_trials_left(QuestPlusSettings(-20.0, 45.0, scales_db=1.5, lapses=0.02,
    ...                                            target_sd_db=1.08, max_trials=80), 0))
    27
    >>> quest_trials_left(s, 20, 1.0)
    0.0
    """
    s = settings
    cap = max(0.0, float(_cap(s) - n_trials))
    if s.target_sd_db is None:
        return cap
    have = 0.0 if sd_db is None or not sd_db > 0 else 1.0 / sd_db**2
    missing = max(0.0, 1.0 / s.target_sd_db**2 - have)
    left = missing / _information(s)
    left = max(left, float(s.min_trials - n_trials))
    return float(min(left, cap))


def _trials_left(state: QuestPlus, _finished: Sequence[int]) -> float:
    sd = state.posterior_sd_db if state.n_trials else None
    return quest_trials_left(state.settings, state.n_trials, sd)


def _cap(settings: QuestPlusSettings) -> int:
    # The protocol reader fills in the default cap; settings built by hand may still lack one.
    return settings.max_trials if settings.max_trials is not None else DEFAULT_BAYES_TRIAL_CAP


def _no_al_reason(state: QuestPlus, unit: str, target_max_v: float) -> str:
    qs = state.settings
    lo, hi = qs.threshold_range_db
    where = f"{state.posterior_mean_db:.2f} ± {state.posterior_sd_db:.2f} {unit}"
    if state.status == "ceiling":
        return (
            f"stopped with its posterior mean {where} at the top of the threshold grid "
            f"({hi:g} {unit}, protocol max ∩ device limit {target_max_v:g} V): a ceiling"
        )
    if state.status == "floor":
        return f"stopped with its posterior mean {where} at the grid's bottom ({lo:g} {unit})"
    return (
        f"reached the trial cap ({qs.max_trials} trials) with posterior SD "
        f"{state.posterior_sd_db:.2f} {unit}, above the target {qs.target_sd_db}"
    )


def posterior_summary(
    settings: QuestPlusSettings, levels_db: Sequence[float], correct: Sequence[bool]
) -> tuple[float, float, float, float]:
    """Posterior (mean, SD, 2.5 % quantile, 97.5 % quantile) of the threshold, dB.

    Recomputed from the logged levels (off-grid levels are evaluated exactly), not by
    replaying the placement.

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


def _estimate_log(
    record: Mapping[str, Any],
    levels_db: Sequence[float],
    correct: Sequence[bool],
    estimator: str,
    lapse: float | None,
) -> tuple[float | None, float | None, float | None, float | None, str, str, str | None]:
    method = "ml" if estimator == "ml" else "posterior_mean"
    try:
        settings = QuestPlusSettings.from_mapping(record)
    except ProcedureError as exc:
        return None, None, None, None, method, "invalid", f"set_start.procedure: {exc}"
    if not len(levels_db):
        return None, None, None, None, method, "estimator_failed", "no trials to estimate from"
    mean, sd, lo, hi = posterior_summary(settings, levels_db, correct)
    # A stated slope or lapse: the interval holds for that observer only; say so beside it.
    caveat = stated_model_note(record)
    if estimator != "ml":
        return mean, sd, lo, hi, method, "completed", caveat
    fit = ml_threshold(
        levels_db, correct, guess=settings.guess, lapse=lapse, p_target=settings.p_at_threshold
    )
    if not fit.ok or fit.threshold_db is None:
        return None, sd, lo, hi, method, "estimator_failed", fit.message
    return float(fit.threshold_db), sd, lo, hi, method, "completed", caveat


def _simulate_batch(
    settings: QuestPlusSettings,
    true_threshold_db: Any,
    *,
    scale_db: float,
    lapse: float,
    rng: np.random.Generator,
) -> Any:
    return simulate_quest_plus(
        settings,
        true_threshold_db,
        scale_db=scale_db,
        lapse=lapse,
        rng=rng,
        n_trials=_cap(settings),
    )


def _examples() -> list[QuestPlusSettings]:
    return [
        QuestPlusSettings(-20.0, 45.0, target_sd_db=1.5, min_trials=5, max_trials=40),
        QuestPlusSettings(
            -10.0,
            30.0,
            level_step_db=1.0,
            scales_db=(0.75, 1.5, 3.0),
            lapses=(0.0, 0.04),
            max_trials=20,
        ),
        QuestPlusSettings(
            -10.0,
            30.0,
            level_step_db=1.0,
            prior="normal",
            prior_mean_db=8.0,
            prior_sd_db=5.0,
            entropy_over="all",
            scales_db=(1.0, 2.0),
            max_trials=15,
        ),
    ]


_NUM_OR_NULL = ["number", "null"]
# Upper bounds keep what validate accepts within what a session can compute (issue 21).
_SCALE = {"type": "number", "exclusiveMinimum": 0, "maximum": 100}
_LAPSE = {"type": "number", "minimum": 0, "exclusiveMaximum": 0.5}
_SCHEMA: dict[str, Any] = {
    "min_level_db": {
        "type": "number",
        "minimum": -200,
        "maximum": 200,
        "description": "QUEST+ stimulus range bottom (protocol's level unit, dB).",
    },
    "max_level_db": {
        "type": "number",
        "minimum": -200,
        "maximum": 200,
        "description": "QUEST+ stimulus range top, dB (the device limit lowers it).",
    },
    "level_step_db": {
        "type": "number",
        "exclusiveMinimum": 0,
        "maximum": 100,
        "description": "Stimulus grid spacing, dB.",
    },
    "threshold_min_db": {"type": _NUM_OR_NULL, "minimum": -200, "maximum": 200},
    "threshold_max_db": {"type": _NUM_OR_NULL, "minimum": -200, "maximum": 200},
    "threshold_step_db": {"type": _NUM_OR_NULL, "exclusiveMinimum": 0, "maximum": 100},
    "scales_db": {
        "oneOf": [
            _SCALE,
            {"type": "array", "minItems": 1, "items": _SCALE},
        ],
        "description": "Logistic scale(s), dB; a list makes the slope a nuisance parameter "
        "(psi-marginal).",
    },
    "lapses": {
        "oneOf": [
            _LAPSE,
            {"type": "array", "minItems": 1, "items": _LAPSE},
        ]
    },
    "n_intervals": {
        "type": "integer",
        "minimum": 2,
        "maximum": 10,
        "description": "Intervals per trial; guess rate 1/n (3 for the paper's 3IFC).",
    },
    "p_at_threshold": {"type": "number", "exclusiveMinimum": 0, "exclusiveMaximum": 1},
    "prior": {"enum": ["flat", "normal"]},
    "prior_mean_db": {"type": _NUM_OR_NULL, "minimum": -200, "maximum": 200},
    "prior_sd_db": {"type": _NUM_OR_NULL, "exclusiveMinimum": 0, "maximum": 400},
    "entropy_over": {"enum": ["threshold", "all"]},
    "max_trials": {
        "type": ["integer", "null"],
        "minimum": 1,
        "maximum": 5000,
        "description": "Trial cap of a track; null takes the default cap (the protocol "
        "summary shows it).",
    },
    "target_sd_db": {
        "type": _NUM_OR_NULL,
        "exclusiveMinimum": 0,
        "maximum": 100,
        "description": "Stop when the posterior SD of the threshold is at most this, dB.",
    },
    "min_trials": {"type": "integer", "minimum": 0, "maximum": 5000},
    "bound_margin_db": {"type": "number", "minimum": 0, "maximum": 100},
}

KIND = ProcedureKind(
    name="quest_plus",
    settings_type=QuestPlusSettings,
    state_type=QuestPlus,
    log_key="procedure",
    schema=_SCHEMA,
    from_protocol=_from_protocol,
    from_record=lambda record, _fallback: QuestPlusSettings.from_mapping(record),
    start_level_db=lambda s: s.min_level_db,
    within_limit=_within_limit,
    trial_fields=_trial_fields,
    end_fields=lambda _state: {"reversal_levels_db": []},
    progress=_progress,
    trials_left=_trials_left,
    trial_cap=_cap,
    no_al_reason=_no_al_reason,
    estimate_log=_estimate_log,
    replay_batch=replay_many,
    simulate_batch=_simulate_batch,
    examples=_examples,
    summary="QUEST+ / psi-marginal threshold track",
)
