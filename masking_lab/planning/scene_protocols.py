"""The measurement protocols a scene's plan writes: one per masking function and masker range
still to be measured (pure: documents only; ``masking-lab plan --scene`` writes them).

The functional procedure (``functional_ramp``, docs/procedures.md) measures a ramp directly over
a masker range, so it is the default: one set, the masker range exactly the one missing, its
grids those of ``protocols/experiment1_functional.yaml`` (widened where the prior's ramp or the
masked ALs fall outside them). ``quest_plus`` writes the per-set alternative: one QUEST+ set per
masker level (at most 5 dB apart over the same range), the settings of
``protocols/experiment1_questplus.yaml`` with the trials split over the sets. One protocol per
function and range: ``analyze`` pools an experiment's sets by frequency, so the two directions
never share an experiment id (as experiments I and II). Levels in dB SL.
"""

from __future__ import annotations

import math
from functools import cache
from typing import Any

import numpy as np
import yaml

from masking_lab.core.errors import SolverError
from masking_lab.formats.resources import shipped
from masking_lab.planning.scene_needs import FunctionNeed

__all__ = ["PROCEDURES", "masker_levels", "measurement_protocol", "protocol_name"]

PROCEDURES = ("functional", "quest_plus")


@cache
def _template(name: str) -> dict[str, Any]:
    return yaml.safe_load(shipped("protocols", name).read_text(encoding="utf-8"))


def masker_levels(lo: float, hi: float) -> list[float]:
    """Masker levels from ``lo`` to ``hi`` dB SL, evenly spaced at most 5 dB apart (≥ 2).

    Examples
    --------
    >>> masker_levels(25.0, 30.0), masker_levels(23.0, 30.0)
    ([25.0, 30.0], [23.0, 26.5, 30.0])
    """
    n = max(2, math.ceil((hi - lo) / 5.0 - 1e-9) + 1)
    return [round(float(v), 6) for v in np.linspace(lo, hi, n)]


def protocol_name(need: FunctionNeed, lo: float, hi: float) -> str:
    """The experiment id: ``measure_<target>_by_<masker>_<lo>-<hi>dB``.

    Examples
    --------
    >>> n = FunctionNeed("EV270", "MV180", (23.3, 30.0), "missing", None, 0, 0, "missing", 0, 1)
    >>> protocol_name(n, 23.0, 30.0)
    'measure_EV270_by_MV180_23-30dB'
    """
    return f"measure_{need.target}_by_{need.masker}_{lo:g}-{hi:g}dB"


def measurement_protocol(
    need: FunctionNeed,
    lo: float,
    hi: float,
    *,
    procedure: str = "functional",
    trials: int = 90,
    scene_name: str = "",
) -> dict[str, Any]:
    """The protocol that measures ``need`` over masker levels ``lo``–``hi`` dB SL.

    Parameters
    ----------
    need : FunctionNeed
        The function (target and masker stimuli; its ramp sizes the level grids).
    lo, hi : float
        Masker range, dB SL of the masker.
    procedure : {"functional", "quest_plus"}
        One functional track over the range, or QUEST+ per masker level.
    trials : int
        Trials per participant for this function (split over the sets for QUEST+).
    scene_name : str
        Named in the description.

    Returns
    -------
    dict
        A protocol document that ``masking-lab validate`` accepts.

    Examples
    --------
    >>> n = FunctionNeed("MV180", "EV270", (9.4, 19.5), "missing", None, 0, 0, "missing",
    ...                  1.3, 1.06)
    >>> doc = measurement_protocol(n, 9.0, 20.0)
    >>> proc = doc["procedure"]
    >>> doc["target"], proc["masker_min_db_sl"], round(proc["masker_step_db"], 3)
    ('MV180', 9.0, 3.667)
    >>> [s["masker_level_db_sl"] for s in measurement_protocol(
    ...     n, 9.0, 20.0, procedure="quest_plus")["sets"]]
    [9.0, 12.666667, 16.333333, 20.0]
    """
    if procedure not in PROCEDURES:
        raise SolverError(
            f"procedure {procedure!r}: choose one of {', '.join(PROCEDURES)} for the "
            "measurement protocols"
        )
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo < hi):
        raise SolverError(f"masker range {lo}-{hi} dB SL: need 0 ≤ lo < hi")
    levels = masker_levels(lo, hi)
    # The masked AL at the top of the range, by the ramp the plan starts from, sizes the
    # target levels: 15 dB of headroom above it, as the shipped protocols leave.
    top_al = max(0.0, need.intercept_db + need.slope * hi)
    max_level = float(max(35, math.ceil(top_al + 15)))
    why = (
        f"the masker range {lo:g}-{hi:g} dB SL that scene {scene_name!r} plays and the "
        f"parameters {'lack' if need.status == 'missing' else 'do not cover'}"
    )
    name = protocol_name(need, lo, hi)
    if procedure == "functional":
        tpl = _template("experiment1_functional.yaml")
        proc: dict[str, Any] = dict(tpl["procedure"])
        proc.update(
            masker_min_db_sl=float(lo),
            masker_max_db_sl=float(hi),
            masker_step_db=(hi - lo) / (len(levels) - 1),
            max_level_db=max_level,
            intercept_min_db=float(
                min(proc["intercept_min_db"], math.floor(need.intercept_db - 10))
            ),
            intercept_max_db=float(
                max(proc["intercept_max_db"], math.ceil(need.intercept_db + 10))
            ),
            slope_max=float(max(proc["slope_max"], round(need.slope + 0.5, 2))),
            max_trials=int(trials),
        )
        sets: list[dict[str, Any]] = [{"id": need.masker, "masker": need.masker}]
        how = f"one functional_ramp track of {trials} trials over the range"
        order: dict[str, Any] = {"randomize": True}
    else:
        tpl = _template("experiment1_questplus.yaml")
        proc = dict(tpl["procedure"])
        per_set = max(10, trials // len(levels))
        proc.update(max_level_db=float(max(proc["max_level_db"], max_level)), max_trials=per_set)
        proc.pop("target_sd_db", None)
        proc.pop("min_trials", None)
        sets = [
            {"id": f"{need.masker}_{k + 1:02d}", "masker": need.masker, "masker_level_db_sl": lv}
            for k, lv in enumerate(levels)
        ]
        how = f"QUEST+ at {len(levels)} masker levels, {per_set} trials each"
        order = {"randomize": True}
    timing = dict(tpl["timing"])
    return {
        "schema_version": 1,
        "experiment": name,
        "description": f"Measures {need.label} over {why}: {how}. Written by masking-lab plan "
        "--scene; run after the baseline of both stimuli, analyse with the rest of the study.",
        "kind": "masked",
        "target": need.target,
        "procedure": proc,
        "timing": timing,
        "order": order,
        "sets": sets,
    }
