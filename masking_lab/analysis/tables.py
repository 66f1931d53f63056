"""The output tables of an analysis as rows (one mapping per CSV line), with their columns.

``anova.csv``, ``sphericity.csv``, ``posthoc.csv`` (:func:`effect_rows`), ``one_sample.csv`` and
``ramp_fits.csv``: each ``*_rows`` function turns
:class:`~masking_lab.analysis.experiment.ExperimentResult` objects into tidy rows (one
observation a row, one variable a column) whose keys are the names in the matching
``*_COLUMNS`` list; :func:`masking_lab.formats.csv_table.csv_text` writes them and
``pandas.DataFrame(rows, columns=...)`` reads them into a frame.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any, Literal

from masking_lab.analysis.experiment import ExperimentResult

__all__ = [
    "ANOVA_COLUMNS",
    "FIT_COLUMNS",
    "ONE_SAMPLE_COLUMNS",
    "POSTHOC_COLUMNS",
    "SPHERICITY_COLUMNS",
    "EffectTable",
    "effect_rows",
    "fit_rows",
    "one_sample_rows",
]

# Column → attribute of the per-experiment item the row is made from.
_ANOVA_FIELDS = {
    "effect": "name",
    "F": "F",
    "df1": "df1",
    "df2": "df2",
    "p": "p",
    "eps_gg": "eps_gg",
    "p_gg": "p_gg",
    "np2": "np2",
}
_SPHERICITY_FIELDS = {
    "effect": "name",
    "mauchly_w": "mauchly_w",
    "chi2": "mauchly_chi2",
    "df": "mauchly_df",
    "p": "mauchly_p",
    "eps_gg": "eps_gg",
    "note": "note",
}
_POSTHOC_FIELDS = {
    "a": "a",
    "b": "b",
    "n": "n",
    "mean_diff_db": "mean_diff",
    "t": "t",
    "df": "df",
    "p": "p",
    "p_bonf": "p_bonf",
    "dz": "dz",
    "note": "note",
}

ANOVA_COLUMNS = ["experiment", *_ANOVA_FIELDS]
SPHERICITY_COLUMNS = ["experiment", *_SPHERICITY_FIELDS]
POSTHOC_COLUMNS = ["experiment", "factor", *_POSTHOC_FIELDS]
ONE_SAMPLE_COLUMNS = [
    "experiment",
    "target",
    "masker",
    "mv_stimulus",
    "mv_frequency_hz",
    "masker_level_db_sl",
    "n",
    "mean_shift_db",
    "sd_db",
    "se_db",
    "t",
    "df",
    "p",
    "masking",
    "note",
]
FIT_COLUMNS = [
    "experiment",
    "group",
    "pairs",
    "mv_frequencies_hz",
    "pooling_rule",
    "n_points",
    "n_participants",
    "intercept_db",
    "intercept_se_db",
    "intercept_ci_lo_db",
    "intercept_ci_hi_db",
    "slope",
    "slope_se",
    "slope_ci_lo",
    "slope_ci_hi",
    "knee_db_sl",
    "fitted_lo_db_sl",
    "fitted_hi_db_sl",
    "adj_r2",
    "adj_r2_active",
    "uncertainty",
    "status",
    "message",
]


# Table → (attribute of ExperimentResult holding its items, column → item attribute, constants).
_EFFECT_TABLES: dict[str, tuple[str, Mapping[str, str], Mapping[str, Any]]] = {
    "anova": ("anova", _ANOVA_FIELDS, {}),
    "sphericity": ("anova", _SPHERICITY_FIELDS, {}),
    "posthoc": ("posthoc", _POSTHOC_FIELDS, {"factor": "frequency"}),
}
EffectTable = Literal["anova", "sphericity", "posthoc"]


def effect_rows(results: Iterable[ExperimentResult], table: EffectTable) -> list[dict[str, Any]]:
    """Rows of anova.csv, sphericity.csv or posthoc.csv: one per effect or comparison.

    Parameters
    ----------
    results : iterable of ExperimentResult
        Per-experiment results (an experiment without ANOVA or comparisons adds no row).
    table : {"anova", "sphericity", "posthoc"}
        ``anova``: the two-way repeated-measures ANOVA (keys :data:`ANOVA_COLUMNS`; ``F`` and
        ``np2`` have no unit, ``df1``/``df2`` are degrees of freedom, ``eps_gg`` the
        Greenhouse–Geisser epsilon and ``p_gg`` its corrected p). ``sphericity``: Mauchly's
        test per effect (:data:`SPHERICITY_COLUMNS`; ``mauchly_w`` and ``chi2`` have no unit).
        ``posthoc``: Bonferroni paired comparisons between frequency levels
        (:data:`POSTHOC_COLUMNS`; ``mean_diff_db`` in dB, ``dz`` is Cohen's d_z).

    Returns
    -------
    list of dict
        One mapping per CSV line, keys in column order.

    Examples
    --------
    Four participants, two MV frequencies, two masker levels (dB SL):

    >>> import itertools
    >>> import pandas as pd
    >>> from masking_lab.analysis.experiment import analyze_shifts
    >>> from masking_lab.analysis.settings import AnalysisSettings
    >>> shifts = pd.DataFrame(
    ...     dict(experiment="e1", participant=f"P{p}", target="EV270", masker=f"MV{hz}",
    ...          mv_stimulus=f"MV{hz}", mv_frequency_hz=float(hz), masker_level_db_sl=lv,
    ...          shift_db=0.4 * lv + (hz == 120) + (p * hz + lv) % 7 / 4)
    ...     for p, hz, lv in itertools.product(range(4), (120, 180), (10.0, 20.0))
    ... )
    >>> results = analyze_shifts(shifts, AnalysisSettings())
    >>> [(row["effect"], row["df1"], row["df2"]) for row in effect_rows(results, "anova")]
    [('frequency', 1, 3), ('level', 1, 3), ('frequency:level', 1, 3)]
    >>> (row,) = effect_rows(results, "posthoc")
    >>> row["a"], row["b"], row["mean_diff_db"], round(row["p_bonf"], 4)
    ('MV120', 'MV180', 1.03125, 0.0082)
    """
    items, fields, constants = _EFFECT_TABLES[table]
    return [
        {
            "experiment": r.experiment,
            **constants,
            **{col: getattr(item, attr) for col, attr in fields.items()},
        }
        for r in results
        for item in (getattr(r, items) or ())
    ]


def one_sample_rows(
    results: Iterable[ExperimentResult], alpha: float = 0.05
) -> list[dict[str, Any]]:
    """Rows of one_sample.csv: every cell's shift against 0 (two-tailed).

    Parameters
    ----------
    results : iterable of ExperimentResult
        Per-experiment results.
    alpha : float
        Level below which a positive mean shift counts as masking (``masking`` = ``yes``).

    Returns
    -------
    list of dict
        Keys :data:`ONE_SAMPLE_COLUMNS`; shifts, SD and SE in dB, levels in dB SL, carriers in
        Hz.

    Examples
    --------
    >>> one_sample_rows([], alpha=0.05)
    []
    """
    rows = []
    for r in results:
        for c in r.cells:
            t = c.test
            masking = ""
            if t is not None and t.p is not None:
                masking = "yes" if (t.p < alpha and t.mean > 0) else "no"
            rows.append(
                {
                    "experiment": r.experiment,
                    "target": c.target,
                    "masker": c.masker,
                    "mv_stimulus": c.mv_stimulus,
                    "mv_frequency_hz": c.mv_frequency_hz,
                    "masker_level_db_sl": c.masker_level_db_sl,
                    "n": c.n,
                    "mean_shift_db": c.mean_shift_db,
                    "sd_db": None if t is None else t.sd,
                    "se_db": None if t is None else t.se,
                    "t": None if t is None else t.t,
                    "df": None if t is None else t.df,
                    "p": None if t is None else t.p,
                    "masking": masking,
                    "note": "no participant data: not tested" if t is None else t.note,
                }
            )
    return rows


def fit_rows(results: Iterable[ExperimentResult]) -> list[dict[str, Any]]:
    """Rows of ramp_fits.csv: one per pooled group.

    Parameters
    ----------
    results : iterable of ExperimentResult
        Per-experiment results.

    Returns
    -------
    list of dict
        Keys :data:`FIT_COLUMNS`; intercepts in dB, slopes in dB per dB SL, knees and fitted
        ranges in dB SL, carriers in Hz.

    Examples
    --------
    >>> fit_rows([])
    []
    """
    rows = []
    for r in results:
        for g in r.fits:
            f = g.fit
            rows.append(
                {
                    "experiment": r.experiment,
                    "group": g.label,
                    "pairs": " ".join(g.pairs),
                    "mv_frequencies_hz": "+".join(f"{v:g}" for v in g.frequencies_hz),
                    "pooling_rule": r.pooling.rule,
                    "n_points": f.n_points,
                    "n_participants": g.n_participants,
                    "intercept_db": f.intercept_db,
                    "intercept_se_db": f.intercept_se_db,
                    "intercept_ci_lo_db": f.intercept_ci_db[0] if f.intercept_ci_db else None,
                    "intercept_ci_hi_db": f.intercept_ci_db[1] if f.intercept_ci_db else None,
                    "slope": f.slope,
                    "slope_se": f.slope_se,
                    "slope_ci_lo": f.slope_ci[0] if f.slope_ci else None,
                    "slope_ci_hi": f.slope_ci[1] if f.slope_ci else None,
                    "knee_db_sl": f.knee_db_sl,
                    "fitted_lo_db_sl": f.fitted_range_db_sl[0],
                    "fitted_hi_db_sl": f.fitted_range_db_sl[1],
                    "adj_r2": f.adj_r2,
                    "adj_r2_active": f.adj_r2_active,
                    "uncertainty": f.uncertainty,
                    "status": f.status,
                    "message": f.message,
                }
            )
    return rows
