"""The functional (ramp) procedure as a registered procedure kind (pure).

Chosen by ``procedure: {kind: functional_ramp, ...}`` in a masked protocol whose sets name a
masker but no masker level (one set per target/masker pair, e.g. per masker frequency; sets
interleave like any). Each trial record holds the trial's ``masker_level_db_sl`` and the ramp's
posterior after it (``ramp``: intercept and slope with their SDs); ``set_end`` holds the ramp's
posterior summary. Levels are dB SL; slopes dB per dB.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from masking_lab.core.errors import LevelError, ProcedureError
from masking_lab.procedures.batch import TrackBatch
from masking_lab.procedures.functional import FunctionalRamp, FunctionalRampSettings
from masking_lab.procedures.functional_batch import simulate_ramps
from masking_lab.procedures.limits import grid_top
from masking_lab.procedures.registry import ProcedureKind, ProtocolContext, SettingsProblem

__all__ = ["KIND", "replay_ramps"]


def _from_protocol(ctx: ProtocolContext) -> FunctionalRampSettings:
    try:
        settings = FunctionalRampSettings.from_mapping(ctx.block)
    except ProcedureError as exc:
        raise SettingsProblem.of(exc, "functional_ramp", ctx.block_key) from None
    for key in ("start_level_db", "masker_level_db_sl"):
        if ctx.set_data.get(key) is not None:
            raise SettingsProblem(
                f"{ctx.set_key}.{key}",
                "a functional_ramp set chooses every trial's masker and target level itself "
                "within procedure.masker_min_db_sl..masker_max_db_sl and min_level_db.."
                "max_level_db; remove the key",
            )
    if ctx.set_data.get("masker") is None:
        raise SettingsProblem(
            ctx.set_key, "a functional_ramp set measures a masking function: name its `masker`"
        )
    return settings


def _within_limit(settings: FunctionalRampSettings, max_db: float) -> FunctionalRampSettings:
    """Target levels stop at the device limit, on the protocol's grid."""
    if max_db >= settings.max_level_db:
        return settings
    top = grid_top(settings.min_level_db, settings.level_step_db, max_db)
    if top <= settings.min_level_db:
        raise LevelError(
            f"the device limit ({max_db:.2f} dB SL) leaves the functional_ramp less than one "
            f"target step above procedure.min_level_db ({settings.min_level_db:g} dB SL)"
        )
    return replace(settings, max_level_db=top)


def _within_masker_limit(
    settings: FunctionalRampSettings, max_db_sl: float
) -> FunctionalRampSettings:
    """Masker levels stop at the rig's rating for the masker, on the protocol's grid."""
    if max_db_sl >= settings.masker_max_db_sl:
        return settings
    top = grid_top(settings.masker_min_db_sl, settings.masker_step_db, max_db_sl)
    if top <= settings.masker_min_db_sl:
        raise LevelError(
            f"the rig's rating for the masker ({max_db_sl:.2f} dB SL) leaves the "
            f"functional_ramp less than two masker levels from procedure.masker_min_db_sl "
            f"({settings.masker_min_db_sl:g} dB SL); a ramp needs at least two"
        )
    return replace(settings, masker_max_db_sl=top)


def _trial_fields(before: FunctionalRamp, after: FunctionalRamp) -> dict[str, Any]:
    m = after.moments()
    return {
        "masker_level_db_sl": before.next_masker_level_db_sl(),
        "ramp": {k: m[k] for k in ("intercept_db", "intercept_sd_db", "slope", "slope_sd")},
        "next_masker_level_db_sl": None if after.finished else after.next_masker_level_db_sl(),
    }


def _end_fields(state: FunctionalRamp) -> dict[str, Any]:
    return {"reversal_levels_db": [], "ramp": state.moments()}


def _progress(state: FunctionalRamp, unit: str) -> str:
    masker = f"masker {state.next_masker_level_db_sl():.1f} dB SL"
    if not state.n_trials:
        return f"ramp: prior | {masker}"
    m = state.moments()
    return (
        f"ramp a {m['intercept_db']:.1f} ± {m['intercept_sd_db']:.1f} dB, "
        f"b {m['slope']:.2f} ± {m['slope_sd']:.2f} | {masker}"
    )


def _result_text(state: FunctionalRamp, unit: str) -> str:
    m = state.moments()
    return (
        f"ramp a {m['intercept_db']:.2f} ± {m['intercept_sd_db']:.2f} dB, "
        f"b {m['slope']:.3f} ± {m['slope_sd']:.3f} dB/dB (posterior mean ± SD)"
    )


def _no_al_reason(state: FunctionalRamp, unit: str, target_max_v: float) -> str:
    m = state.moments()
    return (
        f"reached the trial cap ({state.settings.max_trials} trials) with the ramp's posterior "
        f"SDs {m['intercept_sd_db']:.2f} dB (intercept) and {m['slope_sd']:.3f} (slope), above "
        "the targets"
    )


def _estimate_log(
    record: Mapping[str, Any],
    levels_db: Sequence[float],
    correct: Sequence[bool],
    estimator: str,
    lapse: float | None,
) -> tuple[None, None, None, None, str, str, str]:
    return (
        None,
        None,
        None,
        None,
        "ramp_posterior",
        "no_threshold",
        "a functional_ramp set measures a masking function, not one AL: its ramp posterior is "
        "in ramp_posteriors.csv",
    )


def replay_ramps(settings: FunctionalRampSettings, answers: Any) -> TrackBatch[Any]:
    """One track per row of an answer matrix (R × T), by the scalar track (the reference).

    Examples
    --------
    >>> s = FunctionalRampSettings(max_trials=3)
    >>> replay_ramps(s, [[True, False, True, True]]).n_trials.tolist()
    [3]
    """
    m = np.asarray(answers, dtype=bool)
    if m.ndim != 2:
        raise ProcedureError(f"answers must be a 2-D matrix (tracks × trials), got {m.shape}")
    width = min(m.shape[1], settings.max_trials)
    levels = np.full((m.shape[0], width), np.nan)
    correct = np.zeros((m.shape[0], width), dtype=bool)
    n = np.zeros(m.shape[0], dtype=np.int64)
    for i, row in enumerate(m):
        state = settings.start()
        for r in row[:width]:
            if state.finished:
                break
            state = state.update(bool(r))
        k = state.n_trials
        levels[i, :k] = state.levels_db
        correct[i, :k] = state.responses
        n[i] = k
    return TrackBatch(settings=settings, levels_db=levels, correct=correct, n_trials=n)


def _simulate_batch(
    settings: FunctionalRampSettings,
    truth: Any,
    *,
    scale_db: float,
    lapse: float,
    rng: np.random.Generator,
) -> Any:
    t = np.asarray(truth, dtype=float)
    if t.ndim == 1:  # thresholds alone: a flat ramp at that level (a = level, b = 0)
        t = np.column_stack([t, np.zeros_like(t)])
    return simulate_ramps(settings, t[:, 0], t[:, 1], scale_db=scale_db, lapse=lapse, rng=rng)


def _examples() -> list[FunctionalRampSettings]:
    return [
        FunctionalRampSettings(max_trials=12),
        FunctionalRampSettings(
            masker_min_db_sl=0.0,
            masker_max_db_sl=20.0,
            masker_step_db=10.0,
            min_level_db=-5.0,
            max_level_db=25.0,
            level_step_db=2.0,
            intercept_step_db=2.0,
            slope_step=0.1,
            unmasked_offsets_db=(0.0,),
            scales_db=(1.5,),
            lapses=(0.02,),
            max_trials=15,
            target_sd_intercept_db=6.0,
            target_sd_slope=0.3,
            min_trials=4,
        ),
    ]


def _num(lo: float | None = None, hi: float | None = None, **extra: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"type": "number", **extra}
    if lo is not None:
        out["minimum"] = lo
    if hi is not None:
        out["maximum"] = hi
    return out


_POS = {"type": "number", "exclusiveMinimum": 0}
_SCHEMA: dict[str, Any] = {
    "masker_min_db_sl": _num(-50, 100, description="functional_ramp: lowest masker level, dB SL."),
    "masker_max_db_sl": _num(
        -50, 100, description="functional_ramp: highest masker level, dB SL (the rig lowers it)."
    ),
    "masker_step_db": {
        **_POS,
        "maximum": 150,
        "description": "functional_ramp: masker level grid step, dB.",
    },
    "intercept_min_db": _num(-100, 100),
    "intercept_max_db": _num(-100, 100),
    "intercept_step_db": {**_POS, "maximum": 200},
    "slope_min": _num(-5, 5),
    "slope_max": _num(-5, 5),
    "slope_step": {**_POS, "maximum": 10},
    "unmasked_offsets_db": {
        "oneOf": [_num(-20, 20), {"type": "array", "minItems": 1, "items": _num(-20, 20)}],
        "description": "functional_ramp: nuisance grid of the calibrated unmasked AL's error, dB.",
    },
    "target_sd_intercept_db": {"type": ["number", "null"], "exclusiveMinimum": 0, "maximum": 100},
    "target_sd_slope": {"type": ["number", "null"], "exclusiveMinimum": 0, "maximum": 10},
}

KIND = ProcedureKind(
    name="functional_ramp",
    settings_type=FunctionalRampSettings,
    state_type=FunctionalRamp,
    log_key="procedure",
    schema=_SCHEMA,
    from_protocol=_from_protocol,
    from_record=lambda record, _fallback: FunctionalRampSettings.from_mapping(record),
    start_level_db=lambda s: s.min_level_db,
    within_limit=_within_limit,
    trial_fields=_trial_fields,
    end_fields=_end_fields,
    progress=_progress,
    trials_left=lambda state, _f: float(state.settings.max_trials - state.n_trials),
    trial_cap=lambda s: int(s.max_trials),
    no_al_reason=_no_al_reason,
    estimate_log=_estimate_log,
    replay_batch=replay_ramps,
    simulate_batch=_simulate_batch,
    examples=_examples,
    masker_level_db_sl=lambda state: state.next_masker_level_db_sl(),
    within_masker_limit=_within_masker_limit,
    masker_range_db_sl=lambda s: (s.masker_min_db_sl, s.masker_max_db_sl),
    places_masker=True,
    result_text=_result_text,
    summary="masking function (ramp intercept and slope) measured directly, masker and target "
    "level chosen per trial",
)
