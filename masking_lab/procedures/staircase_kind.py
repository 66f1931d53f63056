"""The transformed up-down staircase as a registered procedure kind (pure).

The paper's procedure: a protocol's ``staircase:`` block (a set may override its start level),
logged under ``set_start.staircase``; its progress counts reversals; its pace is trials per
reversal; ``analyze`` averages its last reversals (:mod:`masking_lab.analysis.thresholds`).
Levels in dB of the set's level unit.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from masking_lab.core.errors import StaircaseError
from masking_lab.procedures.registry import ProcedureKind, ProtocolContext, SettingsProblem
from masking_lab.procedures.staircase import Staircase, StaircaseSettings
from masking_lab.procedures.staircase_batch import Observer, replay_many, simulate

__all__ = ["KIND", "default_trial_cap", "staircase_trials_left"]

#: 1-up-3-down tracks take about 6 trials per reversal before any is observed.
PRIOR_TRIALS_PER_REVERSAL = 6.0

_KEYS = {f.name for f in dataclasses.fields(StaircaseSettings)}


def default_trial_cap(settings: StaircaseSettings) -> int:
    """The trial cap of a staircase whose protocol gives none: 25 trials per reversal.

    The paper's 11-reversal track (median 52, 90th percentile 63 trials) never reaches it; a
    track that does has lost its threshold.

    Examples
    --------
    >>> default_trial_cap(StaircaseSettings(0.0))
    275
    """
    return 25 * int(settings.n_reversals)


def _from_protocol(ctx: ProtocolContext) -> StaircaseSettings:
    block = ctx.protocol.get("staircase")
    if block is None:
        raise SettingsProblem(
            ctx.set_key,
            "this set runs the staircase (the default procedure) but the protocol has no "
            "`staircase:` block; add one, or give `procedure: {kind: quest_plus, ...}`",
        )
    data = {k: v for k, v in dict(block).items() if k in _KEYS}
    if "step_sizes_db" in data:
        data["step_sizes_db"] = tuple(data["step_sizes_db"])
    try:
        base = StaircaseSettings(**data)
    except StaircaseError as exc:
        key = str(exc).split(":")[0].replace("staircase setting ", "").split("[")[0]
        raise SettingsProblem(f"staircase.{key}", str(exc).split(": ", 1)[1]) from None
    if base.max_trials is None:
        base = replace(base, max_trials=default_trial_cap(base))
    if "start_level_db" in ctx.set_data:
        try:
            return replace(base, start_level_db=float(ctx.set_data["start_level_db"]))
        except StaircaseError as exc:
            raise SettingsProblem(f"{ctx.set_key}.start_level_db", str(exc)) from None
    return base


def _from_record(record: Mapping[str, Any], fallback: Any) -> StaircaseSettings:
    data = {k: v for k, v in dict(record).items() if k in _KEYS}
    default = fallback.step_sizes_db if isinstance(fallback, StaircaseSettings) else (4.0,)
    data["step_sizes_db"] = tuple(data.get("step_sizes_db", default))
    return StaircaseSettings(**data)


def _within_limit(settings: StaircaseSettings, max_db: float) -> StaircaseSettings:
    top = settings.max_level_db if settings.max_level_db is not None else math.inf
    # A start level within rounding of the limit is the limit itself.
    return replace(settings, max_level_db=max(min(top, max_db), settings.start_level_db))


def _trial_fields(before: Staircase, after: Staircase) -> dict[str, Any]:
    return {
        "reversal": len(after.reversal_levels_db) > len(before.reversal_levels_db),
        "step_db": before.step_db,
        "at_bound": after.at_bound,
    }


def _end_fields(state: Staircase) -> dict[str, Any]:
    return {"reversal_levels_db": list(state.reversal_levels_db)}


def _progress(state: Staircase, unit: str) -> str:
    return f"reversals {len(state.reversal_levels_db)}/{state.settings.n_reversals}"


def staircase_trials_left(state: Staircase, finished_set_trials: Sequence[int] = ()) -> float:
    """Expected trials before a running staircase stops, from its pace in reversals.

    This set's trials per reversal once it has 2 reversals, else the finished sets' pace, else
    :data:`PRIOR_TRIALS_PER_REVERSAL`; at most the trials left to its cap.

    Examples
    --------
    >>> staircase_trials_left(StaircaseSettings(0.0, max_trials=50).start())
    50.0
    """
    sc = state.settings
    if finished_set_trials:
        per_reversal = float(np.mean(finished_set_trials)) / sc.n_reversals
    else:
        per_reversal = PRIOR_TRIALS_PER_REVERSAL
    done = len(state.reversal_levels_db)
    if done >= 2:
        per_reversal = state.n_trials / done
    left = max(0, sc.n_reversals - done) * per_reversal
    return float(min(left, max(0, _cap(sc) - state.n_trials)))


def _cap(settings: StaircaseSettings) -> int:
    return settings.max_trials if settings.max_trials is not None else default_trial_cap(settings)


def _no_al_reason(state: Staircase, unit: str, target_max_v: float) -> str:
    sc = state.settings
    if state.status == "ceiling":
        return (
            f"pinned at the upper bound {sc.max_level_db:.2f} {unit} (protocol max ∩ device "
            f"limit {target_max_v:g} V): a ceiling, not a threshold"
        )
    if state.status == "floor":
        return f"pinned at the lower bound {sc.min_level_db} {unit}: a floor, not a threshold"
    return f"reached the trial cap ({sc.max_trials} trials) before {sc.n_reversals} reversals"


def _replay_batch(settings: StaircaseSettings, answers: Any) -> Any:
    return replay_many(settings, answers)


def _simulate_batch(
    settings: StaircaseSettings,
    true_threshold_db: Any,
    *,
    scale_db: float,
    lapse: float,
    rng: np.random.Generator,
) -> Any:
    return simulate(
        settings,
        true_threshold_db,
        Observer(scale_db=scale_db, lapse=lapse),
        rng,
        trial_limit=_cap(settings),
    )


def _examples() -> list[StaircaseSettings]:
    return [
        StaircaseSettings(20.0, min_level_db=-20.0, max_level_db=45.0, max_trials=150),
        StaircaseSettings(
            10.0, step_sizes_db=(2.0,), n_reversals=6, n_reversals_averaged=4, max_trials=40
        ),
    ]


_SCHEMA: dict[str, Any] = {}  # the staircase's keys live in the protocol's `staircase:` block

KIND = ProcedureKind(
    name="staircase",
    settings_type=StaircaseSettings,
    state_type=Staircase,
    log_key="staircase",
    schema=_SCHEMA,
    from_protocol=_from_protocol,
    from_record=_from_record,
    start_level_db=lambda s: s.start_level_db,
    within_limit=_within_limit,
    trial_fields=_trial_fields,
    end_fields=_end_fields,
    progress=_progress,
    trials_left=staircase_trials_left,
    trial_cap=_cap,
    no_al_reason=_no_al_reason,
    estimate_log=None,
    replay_batch=_replay_batch,
    simulate_batch=_simulate_batch,
    examples=_examples,
    summary="1-up-3-down from the `staircase` block (the paper's)",
    start_key="staircase.start_level_db",
)
