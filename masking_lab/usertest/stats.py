"""Analysis of a user test: correct rates, compensated vs uncompensated paired tests, confusion.

:func:`analyze_usertest` takes logged trial records (:func:`~masking_lab.usertest.design
.trial_record`): correct rates (0–1) per participant and condition, a paired t-test per measure
(both answers, geometry, texture) with Cohen's d_z — the one paired t-test of
:func:`masking_lab.analysis.t_tests.paired_t` — and confusion matrices (counts) per condition.
Pure: pandas is imported when it runs.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from masking_lab.analysis.t_tests import paired_t
from masking_lab.core.errors import AnalysisError
from masking_lab.usertest.design import CONDITIONS, MEASURES

__all__ = ["PairedComparison", "UserTestAnalysis", "analyze_usertest"]


@dataclass(frozen=True)
class PairedComparison:
    """Compensated vs uncompensated correct rate for one measure, paired by participant.

    Attributes
    ----------
    measure : {"both", "geometry", "texture"}
        Which answers had to be right.
    n : int
        Participants with both conditions.
    mean_compensated, mean_uncompensated : float or None
        Mean correct rate (0–1); None when no participant has both conditions.
    mean_difference : float or None
        Compensated minus uncompensated, mean over participants; None as above.
    t : float or None
        Paired t statistic (df = n − 1); None when it cannot be computed.
    p : float or None
        Two-sided p-value; None when it cannot be computed.
    dz : float or None
        Cohen's d_z (mean difference / SD of differences).
    note : str
        Why t/p are missing, if they are.
    """

    measure: str
    n: int
    mean_compensated: float | None
    mean_uncompensated: float | None
    mean_difference: float | None
    t: float | None
    p: float | None
    dz: float | None
    note: str = ""


@dataclass(frozen=True)
class UserTestAnalysis:
    """Results of :func:`analyze_usertest`.

    Attributes
    ----------
    rates : pandas.DataFrame
        Per participant × condition: ``n_trials``, ``n_no_answer`` and the correct rates
        ``both``, ``geometry``, ``texture`` (0–1; no answer counts as wrong).
    summary : pandas.DataFrame
        Per condition × measure: ``mean``, ``sd`` (between participants, ddof 1), ``n``.
    tests : list[PairedComparison]
        One per measure (needs both conditions).
    confusion : dict
        ``confusion[condition]["geometry" | "texture"]``: counts, rows presented, columns
        answered (plus a ``no answer`` column).
    """

    rates: Any
    summary: Any
    tests: list[PairedComparison]
    confusion: dict[str, dict[str, Any]]


def analyze_usertest(
    records: Iterable[Mapping[str, Any]],
    geometries: Sequence[str],
    textures: Sequence[str],
) -> UserTestAnalysis:
    """Correct rates per participant and condition, paired tests and confusion matrices.

    Parameters
    ----------
    records : iterable of mapping
        Logged trials (:func:`trial_record`); answers are 1-based keys or None.
    geometries, textures : sequence of str
        The design's answer keys, in order.

    Raises
    ------
    AnalysisError
        No records, a record without a required field, an unknown geometry/texture/condition,
        or an answer key out of range — naming the record.

    Returns
    -------
    UserTestAnalysis

    Examples
    --------
    Three participants, four objects per condition; geometry is identified better when the
    masking is compensated (P1: 4 of 4 against 2 of 4), textures always:

    >>> objects = [("bump", "smooth"), ("bump", "rough"), ("hole", "smooth"), ("hole", "rough")]
    >>> def trials(participant, condition, n_right):
    ...     return [dict(participant=participant, condition=condition, geometry=g, texture=t,
    ...                  geometry_answer=(1 if g == "bump" else 2) if k < n_right else
    ...                  (2 if g == "bump" else 1), texture_answer=1 if t == "smooth" else 2)
    ...             for k, (g, t) in enumerate(objects)]
    >>> records = [rec for p, comp, unc in [("P1", 4, 2), ("P2", 3, 1), ("P3", 4, 3)]
    ...            for rec in trials(p, "compensated", comp) + trials(p, "uncompensated", unc)]
    >>> result = analyze_usertest(records, ["bump", "hole"], ["smooth", "rough"])
    >>> both, geometry, texture = result.tests
    >>> print(f"geometry: {geometry.mean_compensated:.2f} vs {geometry.mean_uncompensated:.2f}, "
    ...       f"t({geometry.n - 1}) = {geometry.t:.2f}, p = {geometry.p:.4f}")
    geometry: 0.92 vs 0.50, t(2) = 5.00, p = 0.0377
    >>> texture.note
    "every participant's difference is the same; the paired t-test is undefined"
    >>> result.confusion["uncompensated"]["geometry"].to_numpy().tolist()
    [[5, 1, 0], [5, 1, 0]]
    """
    import pandas as pd

    rows = []
    for i, rec in enumerate(records):
        rows.append(_check_record(i, rec, geometries, textures))
    if not rows:
        raise AnalysisError("no user-test trial records to analyse; point at the session logs")
    df = pd.DataFrame(rows)
    df["geometry_ok"] = df["geometry_answer"] == df["geometry_key"]
    df["texture_ok"] = df["texture_answer"] == df["texture_key"]
    df["both_ok"] = df["geometry_ok"] & df["texture_ok"]
    grouped = df.groupby(["participant", "condition"], sort=True)
    rates = grouped.agg(
        n_trials=("both_ok", "size"),
        n_no_answer=("no_answer", "sum"),
        both=("both_ok", "mean"),
        geometry=("geometry_ok", "mean"),
        texture=("texture_ok", "mean"),
    ).reset_index()
    summary = (
        rates.melt(
            id_vars=["participant", "condition"], value_vars=list(MEASURES), var_name="measure"
        )
        .groupby(["condition", "measure"], sort=True)["value"]
        .agg(mean="mean", sd=_sd, n="size")
        .reset_index()
    )
    tests = []
    wide = rates.pivot(index="participant", columns="condition", values=list(MEASURES))
    for m in MEASURES:
        tests.append(_paired(wide, m))
    confusion: dict[str, dict[str, Any]] = {}
    for cond, part in df.groupby("condition", sort=True):
        confusion[str(cond)] = {
            "geometry": _confusion(part, "geometry", "geometry_answer", geometries),
            "texture": _confusion(part, "texture", "texture_answer", textures),
        }
    return UserTestAnalysis(rates=rates, summary=summary, tests=tests, confusion=confusion)


_REQUIRED = ("participant", "geometry", "texture", "condition", "geometry_answer", "texture_answer")


def _check_record(
    i: int, rec: Mapping[str, Any], geometries: Sequence[str], textures: Sequence[str]
) -> dict[str, Any]:
    for key in _REQUIRED:
        if key not in rec:
            raise AnalysisError(
                f"user-test record {i}: no {key!r}; records need {', '.join(_REQUIRED)}"
            )
    if rec["geometry"] not in geometries:
        raise AnalysisError(
            f"user-test record {i}: geometry {rec['geometry']!r} is not one of {list(geometries)}"
        )
    if rec["texture"] not in textures:
        raise AnalysisError(
            f"user-test record {i}: texture {rec['texture']!r} is not one of {list(textures)}"
        )
    if rec["condition"] not in CONDITIONS:
        raise AnalysisError(
            f"user-test record {i}: condition {rec['condition']!r} is not one of {CONDITIONS}"
        )
    answers = {}
    for key, n in (("geometry_answer", len(geometries)), ("texture_answer", len(textures))):
        a = rec[key]
        if a is not None and (isinstance(a, bool) or not isinstance(a, int) or not 1 <= a <= n):
            raise AnalysisError(
                f"user-test record {i}: {key} is {a!r}; it must be a key 1..{n} or null (no answer)"
            )
        answers[key] = a
    return {
        "participant": str(rec["participant"]),
        "condition": rec["condition"],
        "geometry": rec["geometry"],
        "texture": rec["texture"],
        "geometry_key": geometries.index(rec["geometry"]) + 1,
        "texture_key": textures.index(rec["texture"]) + 1,
        "geometry_answer": answers["geometry_answer"],
        "texture_answer": answers["texture_answer"],
        "no_answer": answers["geometry_answer"] is None or answers["texture_answer"] is None,
    }


def _sd(values: Any) -> float:
    # Between-participant SD; undefined for one participant.
    return float(np.std(values, ddof=1)) if len(values) > 1 else math.nan


def _paired(wide: Any, measure: str) -> PairedComparison:
    cols = [(measure, c) for c in CONDITIONS]
    if any(c not in wide.columns for c in cols):
        present = sorted({c for _, c in wide.columns})
        note = f"needs both conditions; the records have only {present}"
        return PairedComparison(measure, 0, None, None, None, None, None, None, note)
    both = wide[cols].dropna()
    comp = both[(measure, "compensated")].to_numpy(dtype=float)
    unc = both[(measure, "uncompensated")].to_numpy(dtype=float)
    n = comp.size
    if n == 0:
        note = "no participant has both conditions; a paired test needs ≥ 2 participants"
        return PairedComparison(measure, 0, None, None, None, None, None, None, note)
    res = paired_t(comp, unc)
    mean_c, mean_u = float(comp.mean()), float(unc.mean())
    if res.t is None:
        note = (
            f"a paired test needs ≥ 2 participants with both conditions, got {n}"
            if n < 2
            else "every participant's difference is the same; the paired t-test is undefined"
        )
        return PairedComparison(measure, n, mean_c, mean_u, res.mean, None, None, None, note)
    dz = res.mean / res.sd if res.sd else None
    return PairedComparison(measure, n, mean_c, mean_u, res.mean, res.t, res.p, dz)


def _confusion(part: Any, presented: str, answered: str, labels: Sequence[str]) -> Any:
    import pandas as pd

    columns = [*labels, "no answer"]
    table = pd.DataFrame(0, index=list(labels), columns=columns)
    for shown, ans in zip(part[presented], part[answered], strict=True):
        missing = ans is None or (isinstance(ans, float) and math.isnan(ans))
        col = "no answer" if missing else labels[int(ans) - 1]
        table.loc[shown, col] += 1
    table.index.name = f"{presented} presented"
    table.columns.name = "answered"
    return table
