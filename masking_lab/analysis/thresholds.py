"""Session logs → a tidy table of thresholds and AL shifts (pure: works on parsed logs).

One row per participant × experiment × set attempt. Masked sets run their staircase in dB SL
relative to the target's unmasked AL in the session header (the calibration), so their AL in
dB re 1 V is ``al_db_sl + calibration``; the AL *shift* is that minus the participant's unmasked
AL of the target, taken from (``unmasked_al`` setting):

``auto`` (default)
    the participant's baseline session in the analysed logs, re-estimated with the same
    estimator, or the header calibration if there is no such session (``unmasked_source`` says
    which);
``baseline``
    the baseline session only; without one the set is ``no_baseline`` and left out;
``calibration``
    the header calibration (then the shift is just ``al_db_sl``).

A set whose staircase did not complete (``ceiling``, ``floor``, ``aborted``, ``trial_cap``, or
``incomplete`` when the log stops mid-set) is listed with that status and never averaged into a
threshold; so are ``superseded`` attempts (a later session completed the same set),
``no_baseline``, ``estimator_failed`` and ``invalid`` ones. Only ``completed`` rows carry a
shift and enter the statistics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import pandas as pd

from masking_lab.core.errors import AnalysisError
from masking_lab.core.psychometric import GUESS_3IFC
from masking_lab.core.stimulus import parse_stimulus
from masking_lab.formats.session_log import SessionLog, SetRecords
from masking_lab.procedures.estimators import ESTIMATORS, ml_threshold, reversal_mean_al
from masking_lab.procedures.staircase import implied_target_p_for

UNMASKED_SOURCES = ("auto", "baseline", "calibration")

COLUMNS = [
    "participant",
    "experiment",
    "set_id",
    "target",
    "masker",
    "masker_frequency_hz",
    "mv_stimulus",
    "mv_frequency_hz",
    "masker_level_db_sl",
    "al_db_v",
    "unmasked_al_db_v",
    "shift_db",
    "al_db_sl",
    "unmasked_source",
    "trials",
    "reversals",
    "status",
    "estimator",
    "session_id",
    "created_utc",
    "log",
    "note",
]


@dataclass(frozen=True)
class EstimatorSettings:
    """How ALs are re-estimated from the logged trials.

    Attributes
    ----------
    estimator : {"reversals", "ml"}
        Mean of the last k reversal levels, or a maximum-likelihood psychometric fit.
    n_reversals_averaged : int or None
        k for ``reversals``; None uses each set's logged staircase setting (8 in the paper).
    lapse : float or None
        Lapse rate of the ML fit; None fits it.
    """

    estimator: str = "reversals"
    n_reversals_averaged: int | None = None
    lapse: float | None = 0.02

    def __post_init__(self) -> None:
        if self.estimator not in ESTIMATORS:
            raise AnalysisError(
                f"unknown estimator {self.estimator!r}; use one of {', '.join(ESTIMATORS)}"
            )
        if self.n_reversals_averaged is not None and self.n_reversals_averaged < 1:
            raise AnalysisError(f"reversals averaged must be ≥ 1, got {self.n_reversals_averaged}")


@dataclass(frozen=True)
class SetEstimate:
    """The AL of one set in its staircase's unit, or why there is none."""

    al_db: float | None
    status: str
    trials: int
    reversals: int
    note: str | None


def estimate_set(records: SetRecords, settings: EstimatorSettings) -> SetEstimate:
    """Re-estimate one set's AL from its logged trials.

    Returns the AL in the set's level unit (dB SL for masked sets, dB re 1 V for baseline
    sets). Never raises for bad data: problems come back as a status and a note.
    """
    start, trials, end = records.start, records.trials, records.end
    n_trials = len(trials)
    if end is None:
        return SetEstimate(
            None, "incomplete", n_trials, 0, "no set_end record: the session stopped mid-set"
        )
    status = str(end.get("status"))
    unit_key = "level_db_sl" if start.get("level_unit") == "db_sl" else "level_db_v"
    try:
        levels = [float(t[unit_key]) for t in trials]
        correct = [bool(t["correct"]) for t in trials]
        flagged = [float(t[unit_key]) for t in trials if t.get("reversal")]
    except (KeyError, TypeError, ValueError) as exc:
        return SetEstimate(
            None, "invalid", n_trials, 0, f"a trial record lacks a usable {exc} value"
        )
    logged_reversals = end.get("reversal_levels_db")
    reversals = flagged
    notes = []
    if isinstance(logged_reversals, list) and [float(v) for v in logged_reversals] != flagged:
        # The set_end list is the staircase's own record; flags can miss a skipped line.
        reversals = [float(v) for v in logged_reversals]
        notes.append("trial reversal flags disagree with set_end; used set_end's reversals")
    index = [t.get("trial_index") for t in trials]
    if index != list(range(n_trials)):
        notes.append("trial indices are not 0..n-1 (lines lost or repeated)")
    if status != "completed":
        reason = end.get("reason")
        return SetEstimate(
            None,
            status,
            n_trials,
            len(reversals),
            f"staircase ended as {status}"
            + (f" ({reason})" if reason else "")
            + ": not a threshold",
        )
    staircase = start.get("staircase") or {}
    if settings.estimator == "reversals":
        k = settings.n_reversals_averaged or int(staircase.get("n_reversals_averaged", 8))
        try:
            al = reversal_mean_al(reversals, k)
        except AnalysisError as exc:
            return SetEstimate(None, "estimator_failed", n_trials, len(reversals), str(exc))
    else:
        p_target = implied_target_p_for(
            int(staircase.get("n_up", 1)),
            int(staircase.get("n_down", 3)),
            float(staircase.get("down_up_ratio", 1.0)),
        )
        fit = ml_threshold(
            levels, correct, guess=GUESS_3IFC, lapse=settings.lapse, p_target=p_target
        )
        if not fit.ok:
            return SetEstimate(None, "estimator_failed", n_trials, len(reversals), fit.message)
        al = float(fit.threshold_db)  # type: ignore[arg-type]
    return SetEstimate(al, "completed", n_trials, len(reversals), "; ".join(notes) or None)


def session_rows(log: SessionLog, log_name: str, settings: EstimatorSettings) -> list[dict]:
    """One raw row per set of a parsed log (before unmasked ALs are joined).

    Parameters
    ----------
    log : SessionLog
        The parsed log.
    log_name : str
        How the log is named in the table (path relative to the data folder).
    settings : EstimatorSettings
        Re-estimation settings.
    """
    h = log.header
    protocol = h.get("protocol") if isinstance(h.get("protocol"), dict) else {}
    calibration = h.get("calibration") if isinstance(h.get("calibration"), dict) else {}
    base = {
        "participant": str(h.get("participant", "?")),
        "experiment": str(protocol.get("experiment", "?")),
        "session_id": str(h.get("session_id", log_name)),
        "created_utc": str(h.get("created_utc", "")),
        "log": log_name,
        "estimator": settings.estimator,
    }
    rows = []
    for set_id, records in log.sets().items():
        start = records.start
        row: dict[str, Any] = {**base, "set_id": str(set_id)}
        try:
            target = parse_stimulus(start["target"]).name
            masker = start.get("masker")
            masker = parse_stimulus(masker).name if masker else None
            level = start.get("masker_level_db_sl")
            row |= {
                "target": target,
                "masker": masker,
                "masker_level_db_sl": None if masker is None else float(level),
            }
        except (KeyError, TypeError, ValueError) as exc:
            rows.append(row | {"status": "invalid", "note": f"set_start unusable ({exc})"})
            continue
        est = estimate_set(records, settings)
        row |= {
            "trials": est.trials,
            "reversals": est.reversals,
            "status": est.status,
            "note": est.note,
        }
        if start.get("level_unit") == "db_sl":
            cal = start.get("unmasked_al_db_v")
            if cal is None:
                cal = calibration.get(target)
            row["calibration_al_db_v"] = None if cal is None else float(cal)
            row["al_db_sl"] = est.al_db
            if est.al_db is not None and cal is not None:
                row["al_db_v"] = est.al_db + float(cal)
            elif est.al_db is not None:
                row |= {
                    "status": "no_baseline",
                    "note": f"the session header has no calibration for {target}, so the AL "
                    "cannot be placed in dB re 1 V",
                }
        else:
            row["al_db_v"] = est.al_db
        rows.append(row)
    return rows


def thresholds_table(rows: list[dict], *, unmasked_al: str = "auto") -> pd.DataFrame:
    """Join unmasked ALs, compute shifts, mark superseded attempts; sorted, one row per set.

    Parameters
    ----------
    rows : list of dict
        From :func:`session_rows` over every log.
    unmasked_al : {"auto", "baseline", "calibration"}
        Where a masked set's unmasked AL comes from (module docstring).
    """
    if unmasked_al not in UNMASKED_SOURCES:
        raise AnalysisError(
            f"unknown unmasked-AL source {unmasked_al!r}; use one of {', '.join(UNMASKED_SOURCES)}"
        )
    table = [{col: r.get(col) for col in [*COLUMNS, "calibration_al_db_v"]} for r in rows]
    order = sorted(
        range(len(table)),
        key=lambda i: (
            table[i]["created_utc"] or "",
            table[i]["session_id"] or "",
            table[i]["log"] or "",
        ),
    )

    def set_key(r: dict) -> tuple:
        return (
            r["participant"],
            r["experiment"],
            r["target"],
            r["masker"],
            r["masker_level_db_sl"],
        )

    # Later attempts at the same set supersede earlier completed ones.
    latest: dict[tuple, dict] = {}
    for i in order:
        r = table[i]
        if r["status"] == "completed":
            key = set_key(r)
            if key in latest:
                latest[key]["status"] = "superseded"
                latest[key]["note"] = f"a later session ({r['session_id']}) completed this set"
            latest[key] = r
    baseline: dict[tuple[str, str], float] = {}
    for i in order:  # latest baseline session wins
        r = table[i]
        if r["status"] == "completed" and r["masker"] is None and r["al_db_v"] is not None:
            baseline[(r["participant"], r["target"])] = float(r["al_db_v"])

    for r in table:
        if r["masker"] is None or r["target"] is None:
            continue
        target, masker = parse_stimulus(r["target"]), parse_stimulus(r["masker"])
        # The ANOVA's frequency factor is the MV stimulus of the pair (paper Table 2).
        mv = masker if masker.channel == "MV" or target.channel != "MV" else target
        r["masker_frequency_hz"] = masker.carrier_hz
        r["mv_stimulus"] = mv.name
        r["mv_frequency_hz"] = mv.carrier_hz
        if r["status"] != "completed":
            continue
        from_base = baseline.get((r["participant"], r["target"]))
        cal = r["calibration_al_db_v"]
        if unmasked_al == "calibration" or (unmasked_al == "auto" and from_base is None):
            unmasked, source = cal, "calibration"
        else:
            unmasked, source = from_base, "baseline"
        if unmasked is None:
            r["status"] = "no_baseline"
            r["note"] = (
                f"participant {r['participant']} has no completed baseline AL for {r['target']}"
                + (
                    "; run the baseline protocol or use --unmasked-al calibration"
                    if unmasked_al == "baseline"
                    else ""
                )
            )
            continue
        r["unmasked_al_db_v"] = float(unmasked)
        r["unmasked_source"] = source
        r["shift_db"] = float(r["al_db_v"]) - float(unmasked)

    def sort_key(r: dict) -> tuple:
        lvl = r["masker_level_db_sl"]
        return (
            r["participant"] or "",
            r["experiment"] or "",
            r["target"] or "",
            r["masker"] or "",
            -math.inf if lvl is None else lvl,
            r["created_utc"] or "",
            r["log"] or "",
            r["set_id"] or "",
        )

    table.sort(key=sort_key)
    # object dtype keeps None as None (pandas would turn missing strings into NaN)
    return pd.DataFrame(table, columns=COLUMNS, dtype=object)


def shifts_long(thresholds: pd.DataFrame) -> pd.DataFrame:
    """The completed masked rows as the long shift table the statistics use.

    Columns: participant, experiment, target, masker, mv_stimulus, mv_frequency_hz,
    masker_level_db_sl, shift_db.
    """
    used = thresholds[(thresholds["status"] == "completed") & thresholds["masker"].notna()]
    cols = [
        "participant",
        "experiment",
        "target",
        "masker",
        "mv_stimulus",
        "mv_frequency_hz",
        "masker_level_db_sl",
        "shift_db",
    ]
    out = used[cols].copy()
    for c in ("mv_frequency_hz", "masker_level_db_sl", "shift_db"):
        out[c] = out[c].astype(float)
    return out.reset_index(drop=True)
