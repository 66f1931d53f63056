"""The output tables of an analysis as rows (one mapping per CSV line), with their columns.

``anova.csv``, ``sphericity.csv``, ``posthoc.csv``, ``one_sample.csv`` and ``ramp_fits.csv``:
each ``*_rows`` function turns :class:`~masking_lab.analysis.experiment.ExperimentResult`
objects into tidy rows (one observation a row, one variable a column) whose keys are the names
in the matching ``*_COLUMNS`` list; :func:`masking_lab.formats.csv_table.csv_text` writes them
and ``pandas.DataFrame(rows, columns=...)`` reads them into a frame.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from masking_lab.analysis.experiment import ExperimentResult

__all__ = [
    "ANOVA_COLUMNS",
    "FIT_COLUMNS",
    "ONE_SAMPLE_COLUMNS",
    "POSTHOC_COLUMNS",
    "SPHERICITY_COLUMNS",
    "anova_rows",
    "fit_rows",
    "one_sample_rows",
    "posthoc_rows",
    "sphericity_rows",
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


def _attribute_rows(
    results: Iterable[ExperimentResult],
    items: str,
    fields: Mapping[str, str],
    extra: Mapping[str, Any] | None = None,
) -> list[dict[str, Any]]:
    """One row per element of ``getattr(result, items)``, columns read through ``fields``."""
    return [
        {
            "experiment": r.experiment,
            **(extra or {}),
            **{col: getattr(item, attr) for col, attr in fields.items()},
        }
        for r in results
        for item in (getattr(r, items) or ())
    ]


def anova_rows(results: Iterable[ExperimentResult]) -> list[dict[str, Any]]:
    """Rows of anova.csv: the two-way repeated-measures ANOVA, one row per effect.

    Parameters
    ----------
    results : iterable of ExperimentResult
        Per-experiment results.

    Returns
    -------
    list of dict
        Keys :data:`ANOVA_COLUMNS`; ``F`` and ``np2`` have no unit, ``df1``/``df2`` are degrees of
        freedom, ``eps_gg`` the Greenhouse–Geisser epsilon and ``p_gg`` its corrected p.

    Examples
    --------
    >>> anova_rows([])
    []
    """
    return _attribute_rows(results, "anova", _ANOVA_FIELDS)


def sphericity_rows(results: Iterable[ExperimentResult]) -> list[dict[str, Any]]:
    """Rows of sphericity.csv: Mauchly's test per effect.

    Parameters
    ----------
    results : iterable of ExperimentResult
        Per-experiment results.

    Returns
    -------
    list of dict
        Keys :data:`SPHERICITY_COLUMNS` (``mauchly_w`` and ``chi2`` have no unit).

    Examples
    --------
    >>> sphericity_rows([])
    []
    """
    return _attribute_rows(results, "anova", _SPHERICITY_FIELDS)


def posthoc_rows(results: Iterable[ExperimentResult]) -> list[dict[str, Any]]:
    """Rows of posthoc.csv: Bonferroni paired comparisons between frequency levels.

    Parameters
    ----------
    results : iterable of ExperimentResult
        Per-experiment results (an experiment without comparisons adds no row).

    Returns
    -------
    list of dict
        Keys :data:`POSTHOC_COLUMNS`; ``mean_diff_db`` in dB, ``dz`` is Cohen's d_z.

    Examples
    --------
    >>> posthoc_rows([])
    []
    """
    return _attribute_rows(results, "posthoc", _POSTHOC_FIELDS, {"factor": "frequency"})


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
