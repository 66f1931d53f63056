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

import functools
import itertools
import math
import operator
import zlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from msgspec import UNSET

from masking_lab.analysis.procedure_estimates import places_masker, procedure_estimate
from masking_lab.analysis.psychometric import fit_pf
from masking_lab.analysis.settings import UNMASKED_SOURCES
from masking_lab.core.errors import AnalysisError, LevelError
from masking_lab.core.psychometric import GUESS_3IFC
from masking_lab.core.stimulus import Stimulus, parse_stimulus
from masking_lab.formats.log_records import ATrial
from masking_lab.formats.session_log import SessionLog, SetRecords
from masking_lab.procedures.estimators import ESTIMATORS, ml_threshold, reversal_mean_al
from masking_lab.procedures.staircase import implied_target_p_for

if TYPE_CHECKING:
    import pandas as pd

ML_BOOTSTRAP = 200  # parametric-bootstrap refits behind an ML AL's SD and interval

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
    "al_sd_db",
    "al_ci95_low_db",
    "al_ci95_high_db",
    "session_id",
    "created_utc",
    "log",
    "note",
]
# The keys of a raw row (session_rows) that the table uses, in the order of packed rows.
ROW_KEYS = (*COLUMNS, "calibration_al_db_v")


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
    # Bayesian sets (QUEST+): posterior SD and 95 % credible interval, dB in the set's unit.
    sd_db: float | None = None
    ci95_db: tuple[float, float] | None = None


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
        levels, correct, flagged, index = _trial_columns(trials, unit_key, records.counted)
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        return SetEstimate(
            None, "invalid", n_trials, 0, f"a trial record lacks a usable {exc} value"
        )
    bad = _first_non_finite(levels)
    if bad is not None:
        # Refused before any estimator sees it, so every estimator answers alike.
        return SetEstimate(None, "invalid", n_trials, 0, f"trial {bad} has a non-finite level")
    logged_reversals = end.get("reversal_levels_db")
    reversals = flagged
    notes = []
    if isinstance(logged_reversals, list):
        try:
            logged_reversals = [float(v) for v in logged_reversals]
        except (TypeError, ValueError, OverflowError):
            return SetEstimate(None, "invalid", n_trials, 0, "set_end reversal levels unusable")
        if _first_non_finite(logged_reversals) is not None:
            return SetEstimate(
                None, "invalid", n_trials, 0, "set_end has a non-finite reversal level"
            )
    if isinstance(logged_reversals, list) and logged_reversals != flagged:
        # The set_end list is the staircase's own record; flags can miss a skipped line.
        reversals = [float(v) for v in logged_reversals]
        notes.append("trial reversal flags disagree with set_end; used set_end's reversals")
    if index is not None and index != list(range(n_trials)):
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
    if start.get("procedure"):
        est = procedure_estimate(
            start["procedure"], levels, correct, estimator=settings.estimator, lapse=settings.lapse
        )
        ci = (
            None
            if est.ci_low_db is None or est.ci_high_db is None
            else (est.ci_low_db, est.ci_high_db)
        )
        note = est.note or ("; ".join(notes) or None)
        return SetEstimate(est.al_db, est.status, n_trials, 0, note, est.sd_db, ci)
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
        threshold_db, s = fit.threshold_db, fit.scale_db
        if threshold_db is None or s is None or not math.isfinite(threshold_db):
            return SetEstimate(
                None, "estimator_failed", n_trials, len(reversals),
                f"the estimate is {fit.threshold_db}",
            )  # fmt: skip
        # Its SD and 95 % interval from a parametric bootstrap (analysis.psychometric), seeded
        # by the set so reruns give the same bytes.
        q = (p_target - GUESS_3IFC) / (1.0 - GUESS_3IFC - fit.lapse)
        alpha = threshold_db - s * math.log(q / (1.0 - q))
        boot = fit_pf(
            levels,
            correct,
            guess=GUESS_3IFC,
            lapse=settings.lapse,
            p_target=p_target,
            n_boot=ML_BOOTSTRAP,
            seed=zlib.crc32(str(start.get("set_id")).encode()),
            estimate=(alpha, 1.0 / s, float(fit.lapse)),
        )
        if boot.ok and boot.message:  # e.g. few refits inside the bounds
            notes.append(boot.message)
        return SetEstimate(
            float(threshold_db),
            "completed",
            n_trials,
            len(reversals),
            "; ".join(notes) or None,
            boot.al_sd_db,
            boot.al_ci_db,
        )
    if not math.isfinite(al):  # finite levels near the float limit can still overflow a mean
        return SetEstimate(
            None, "estimator_failed", n_trials, len(reversals), f"the estimate is {al}"
        )
    return SetEstimate(al, "completed", n_trials, len(reversals), "; ".join(notes) or None)


def _first_non_finite(values: list[Any]) -> int | None:
    """Index of the first value that is not a finite number, or None."""
    if all(map(math.isfinite, values)):  # the common case, in C
        return None
    for k, v in enumerate(values):
        if not math.isfinite(v):
            return k
    return None


# A study names a handful of stimuli, thousands of times; bounded, as names come from files.
_cached_stimulus = functools.lru_cache(maxsize=1024)(parse_stimulus)


def _stimulus(name: Any) -> Stimulus:
    # Only strings are cached: anything else must fail exactly as parse_stimulus fails.
    return _cached_stimulus(name) if isinstance(name, str) else parse_stimulus(name)


_CORRECT = operator.attrgetter("correct")
_REVERSAL = operator.attrgetter("reversal")
_TRIAL_INDEX = operator.attrgetter("trial_index")
_TRUE = itertools.repeat(True)  # flags compared by identity: `is True`, as JSON true decodes


def _trial_columns(
    trials: list[Any], unit_key: str, counted: bool = False
) -> tuple[list[float], list[bool], list[float], list[Any] | None]:
    """Levels (dB in the set's unit), answers, levels of flagged reversals and trial indices.

    Typed trial records (the analysis view of :mod:`masking_lab.formats.log_records`) are read
    by attribute; anything else, or a typed record lacking a value, by key, which raises
    ``KeyError``/``TypeError``/``ValueError`` for a missing or unusable value. ``counted``:
    the trials are typed and their indices count 0..n-1 (:class:`SetRecords`), so neither is
    looked at again and the indices come back as None.
    """
    if trials and (counted or set(map(type, trials)) == {ATrial}):
        levels = list(map(operator.attrgetter(unit_key), trials))
        correct = list(map(_CORRECT, trials))
        if None not in levels and UNSET not in levels and UNSET not in correct:
            flagged = list(
                itertools.compress(levels, map(operator.is_, map(_REVERSAL, trials), _TRUE))
            )
            # An absent index (UNSET) differs from every int, as None does for dicts.
            return levels, correct, flagged, None if counted else list(map(_TRIAL_INDEX, trials))
    levels = [float(t[unit_key]) for t in trials]
    correct = [bool(t["correct"]) for t in trials]
    flagged = [float(t[unit_key]) for t in trials if t.get("reversal")]
    return levels, correct, flagged, [t.get("trial_index") for t in trials]


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
            target = _stimulus(start["target"]).name
            masker = start.get("masker")
            masker = _stimulus(masker).name if masker else None
            level = start.get("masker_level_db_sl")
            # A procedure that places the masker trial by trial logs no level for the set.
            one_level = masker is not None and not (
                level is None and places_masker(start.get("procedure"))
            )
            row |= {
                "target": target,
                "masker": masker,
                "masker_level_db_sl": _finite(level, "masker level") if one_level else None,
            }
        except (KeyError, TypeError, ValueError, OverflowError) as exc:
            rows.append(row | {"status": "invalid", "note": f"set_start unusable ({exc})"})
            continue
        est = estimate_set(records, settings)
        if start.get("procedure"):  # a Bayesian set: say which estimate its AL is
            row["estimator"] = "ml" if settings.estimator == "ml" else "posterior_mean"
        row |= {
            "trials": est.trials,
            "reversals": est.reversals,
            "status": est.status,
            "note": est.note,
            "al_sd_db": est.sd_db,
            "al_ci95_low_db": est.ci95_db[0] if est.ci95_db else None,
            "al_ci95_high_db": est.ci95_db[1] if est.ci95_db else None,
        }
        if start.get("level_unit") == "db_sl":
            cal = start.get("unmasked_al_db_v")
            if cal is None:
                cal = calibration.get(target)
            try:
                row["calibration_al_db_v"] = None if cal is None else _finite(cal, "calibration")
            except (TypeError, ValueError, OverflowError) as exc:
                rows.append(row | {"status": "invalid", "note": f"unusable calibration ({exc})"})
                continue
            row["al_db_sl"] = est.al_db
            if est.al_db is not None and cal is not None:
                row["al_db_v"] = est.al_db + row["calibration_al_db_v"]
                if not math.isfinite(row["al_db_v"]):
                    row |= {"al_db_v": None, "status": "invalid", "note": "AL overflows"}
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


def _finite(value: Any, what: str) -> float:
    """``value`` as a finite float (dB), or ValueError naming ``what``."""
    x = float(value)
    if not math.isfinite(x):
        raise LevelError(f"{what} {x} is not a finite number of dB")
    return x


def packed(rows: list[dict]) -> list[tuple]:
    """Rows as tuples in :data:`ROW_KEYS` order (None where a key is absent): ~3x smaller.

    What :mod:`masking_lab.analysis.log_reading` sends between processes and keeps for a large
    study; :func:`thresholds_table` takes either form.

    Examples
    --------
    >>> packed([{"participant": "P1", "status": "completed"}])[0][:2]
    ('P1', None)
    """
    return [tuple(map(r.get, ROW_KEYS)) for r in rows]


def unpacked(rows: list[tuple]) -> list[dict]:
    """The dicts of :func:`packed` rows (absent keys as None).

    Examples
    --------
    >>> unpacked(packed([{"set_id": "A"}]))[0]["set_id"]
    'A'
    """
    return [dict(zip(ROW_KEYS, r, strict=True)) for r in rows]


def thresholds_table(
    rows: list[dict] | list[tuple], *, unmasked_al: str = "auto", consume: bool = False
) -> pd.DataFrame:
    """Join unmasked ALs, compute shifts, mark superseded attempts; sorted, one row per set.

    Parameters
    ----------
    rows : list of dict, or list of tuple
        From :func:`session_rows` over every log, or those rows :func:`packed`.
    unmasked_al : {"auto", "baseline", "calibration"}
        Where a masked set's unmasked AL comes from (module docstring).
    consume : bool
        The caller gives ``rows`` up: the list is emptied once its values are taken, so a
        large study does not hold the rows and the table at once (about 1 kB per set).

    Returns
    -------
    pandas.DataFrame
        :data:`COLUMNS`, object dtype (None stays None).

    Examples
    --------
    >>> rows = [{"participant": "P1", "experiment": "baseline", "set_id": "EV", "target": "EV270",
    ...          "masker": None, "status": "completed", "al_db_v": -20.0, "log": "a.jsonl"}]
    >>> thresholds_table(rows)[["participant", "al_db_v", "status"]].values.tolist()
    [['P1', -20.0, 'completed']]
    """
    if unmasked_al not in UNMASKED_SOURCES:
        raise AnalysisError(
            f"unknown unmasked-AL source {unmasked_al!r}; use one of {', '.join(UNMASKED_SOURCES)}"
        )
    # Column lists (None where a row lacks the key), not a dict per row: ~8 bytes per cell.
    if rows and isinstance(rows[0], tuple):
        col = dict(zip(ROW_KEYS, map(list, zip(*rows, strict=True)), strict=True))
    else:
        # rows are dicts here (the tuple form was handled above)
        col = {c: [r.get(c) for r in rows] for c in ROW_KEYS}  # type: ignore[union-attr]
    if consume:
        rows.clear()
    n = len(col["status"])
    created, session, log = col["created_utc"], col["session_id"], col["log"]
    participant, experiment = col["participant"], col["experiment"]
    target, masker, level = col["target"], col["masker"], col["masker_level_db_sl"]
    status, note, al_db_v = col["status"], col["note"], col["al_db_v"]
    order = sorted(range(n), key=lambda i: (created[i] or "", session[i] or "", log[i] or ""))

    # Later attempts at the same set supersede earlier completed ones.
    latest: dict[tuple, int] = {}
    for i in order:
        if status[i] == "completed":
            key = (participant[i], experiment[i], target[i], masker[i], level[i])
            if key in latest:
                j = latest[key]
                status[j] = "superseded"
                note[j] = f"a later session ({session[i]}) completed this set"
            latest[key] = i
    baseline: dict[tuple[str, str], float] = {}
    for i in order:  # latest baseline session wins
        if status[i] == "completed" and masker[i] is None and al_db_v[i] is not None:
            baseline[(participant[i], target[i])] = float(al_db_v[i])

    # A study has a handful of (target, masker) pairs, named on ~10⁵ rows: each is parsed once.
    pairs: dict[tuple[str, str], tuple[Any, str, Any]] = {}
    masker_hz, mv_name, mv_hz = (
        col["masker_frequency_hz"],
        col["mv_stimulus"],
        col["mv_frequency_hz"],
    )
    for i in range(n):
        if masker[i] is None or target[i] is None:
            continue
        pair = (target[i], masker[i])
        cacheable = type(pair[0]) is str and type(pair[1]) is str  # others fail as they did
        known = pairs.get(pair) if cacheable else None
        if known is None:
            t_stim, m_stim = _stimulus(target[i]), _stimulus(masker[i])
            # The ANOVA's frequency factor is the MV stimulus of the pair (paper Table 2).
            mv = m_stim if m_stim.channel == "MV" or t_stim.channel != "MV" else t_stim
            known = (m_stim.carrier_hz, mv.name, mv.carrier_hz)
            if cacheable:
                pairs[pair] = known
        masker_hz[i], mv_name[i], mv_hz[i] = known
        if status[i] != "completed":
            continue
        from_base = baseline.get((participant[i], target[i]))
        cal = col["calibration_al_db_v"][i]
        if unmasked_al == "calibration" or (unmasked_al == "auto" and from_base is None):
            unmasked, source = cal, "calibration"
        else:
            unmasked, source = from_base, "baseline"
        if unmasked is None:
            status[i] = "no_baseline"
            note[i] = (
                f"participant {participant[i]} has no completed baseline AL for {target[i]}"
                + (
                    "; run the baseline protocol or use --unmasked-al calibration"
                    if unmasked_al == "baseline"
                    else ""
                )
            )
            continue
        col["unmasked_al_db_v"][i] = float(unmasked)
        col["unmasked_source"][i] = source
        col["shift_db"][i] = float(al_db_v[i]) - float(unmasked)

    set_id = col["set_id"]

    def sort_key(i: int) -> tuple:
        lvl = level[i]
        return (
            participant[i] or "",
            experiment[i] or "",
            target[i] or "",
            masker[i] or "",
            -math.inf if lvl is None else lvl,
            created[i] or "",
            log[i] or "",
            set_id[i] or "",
        )

    ranked = sorted(range(n), key=sort_key)  # stable, like sorting the rows themselves
    # object dtype keeps None as None (pandas would turn missing strings into NaN)
    import numpy as np
    import pandas as pd  # here: reading a log (this module, in every worker) needs no pandas

    # One object block filled a column at a time, each column list freed once copied: a
    # frame built from lists held the lists, a reordered copy, an array per column and the
    # consolidated block at once (at 10,000 sessions ~100 MB for a 23 MB table).
    order_idx = np.fromiter(ranked, dtype=np.intp, count=n)
    del ranked, order
    table = np.empty((n, len(COLUMNS)), dtype=object)
    for j, c in enumerate(COLUMNS):
        table[:, j] = np.fromiter(col.pop(c), dtype=object, count=n)[order_idx]
    return pd.DataFrame(table, columns=COLUMNS, dtype=object, copy=False)


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
