"""Batch analysis (paper §2.4): session logs or a table of AL shifts → statistics, pooling,
ramp fits and ``masking_params.json``.

The science is in pure functions (:func:`analyze_shifts` and the modules it calls: ``stats``,
``pooling``, ``ramp_fit``, ``thresholds``); :func:`run_analyze` and :func:`run_fit` are the
imperative shell that reads files, reports progress and writes outputs.

Per experiment (the protocol's ``experiment`` id, or in ``fit`` the direction ``EV270|MV`` /
``MV|EV270`` derived from the stimulus names) the "frequency" factor is the MV stimulus of each
pair — the masker in Experiment I, the target in Experiment II (paper Table 2's "Frequency of
MV") — and the "level" factor is the masker level in dB SL.

Outputs are deterministic: same inputs and settings, same bytes (sorted inputs, fixed float
formats, seeded bootstrap with a seed per experiment and group, no wall-clock time anywhere;
``created_utc`` comes from a setting or from the data, see docs/analysis.md).
"""

from __future__ import annotations

import csv
import hashlib
import io
import math
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import pandas as pd

from masking_lab import __version__
from masking_lab.analysis.pooling import (
    RULES,
    PoolingDecision,
    decide_pooling,
    level_sort_key,
    parse_pool_spec,
)
from masking_lab.analysis.ramp_fit import RampFit, fit_ramp, participant_bootstrap, with_bootstrap
from masking_lab.analysis.stats import (
    Effect,
    OneSampleT,
    PairedTest,
    one_sample_t,
    paired_comparisons,
    rm_anova,
    rm_design,
)
from masking_lab.analysis.thresholds import (
    COLUMNS as THRESHOLD_COLUMNS,
)
from masking_lab.analysis.thresholds import (
    UNMASKED_SOURCES,
    EstimatorSettings,
    session_rows,
    shifts_long,
    thresholds_table,
)
from masking_lab.core.errors import AnalysisError, LogError
from masking_lab.core.stimulus import is_stimulus_name, parse_stimulus
from masking_lab.formats.fileio import write_text_atomic
from masking_lab.formats.masking_params import masking_params_json
from masking_lab.procedures.estimators import ESTIMATORS

UNCERTAINTY = ("bootstrap", "asymptotic")
FIGURES = ("all", "summary", "none")
ANOVA_COLUMNS = ["experiment", "effect", "F", "df1", "df2", "p", "eps_gg", "p_gg", "np2"]
EPOCH_UTC = "1970-01-01T00:00:00Z"
_UTC_RE = re.compile(r"^\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}Z$")


@dataclass(frozen=True)
class AnalysisSettings:
    """Every setting of an analysis; all of them are recorded in the export's provenance.

    Attributes
    ----------
    estimator : {"reversals", "ml"}
        AL estimator (``analyze`` only).
    n_reversals_averaged : int or None
        Last reversals averaged (None: as logged, 8 in the paper).
    lapse : float or None
        Lapse rate of the ML estimator (None: fitted).
    unmasked_al : {"auto", "baseline", "calibration"}
        Source of unmasked ALs (see :mod:`masking_lab.analysis.thresholds`).
    pooling : {"paired", "none", "all"}
        Pooling rule (see :mod:`masking_lab.analysis.pooling`).
    pool_alpha : float
        Significance level of the ``paired`` rule (on Bonferroni-corrected p).
    pool_groups : tuple[str, ...]
        Explicit groups, ``[EXPERIMENT:]LEVEL+LEVEL``; they override the rule.
    uncertainty : {"bootstrap", "asymptotic"}
        Ramp uncertainty: participant bootstrap, or asymptotic least-squares SEs.
    n_boot : int
        Bootstrap replicates.
    ci_level : float
        Confidence level of the intervals.
    seed : int
        Bootstrap seed.
    test_alpha : float
        Level at which a one-sample t-test marks a cell as masked.
    created_utc : str or None
        Value for ``created_utc`` in the export (None: derived, see docs).
    figures : {"all", "summary", "none"}
        Figures to draw (``all`` adds one staircase-track figure per session).
    """

    estimator: str = "reversals"
    n_reversals_averaged: int | None = None
    lapse: float | None = 0.02
    unmasked_al: str = "auto"
    pooling: str = "paired"
    pool_alpha: float = 0.05
    pool_groups: tuple[str, ...] = ()
    uncertainty: str = "bootstrap"
    n_boot: int = 2000
    ci_level: float = 0.95
    seed: int = 0
    test_alpha: float = 0.05
    created_utc: str | None = None
    figures: str = "all"

    def __post_init__(self) -> None:
        checks = [
            (self.estimator in ESTIMATORS, f"estimator must be one of {ESTIMATORS}"),
            (
                self.unmasked_al in UNMASKED_SOURCES,
                f"unmasked_al must be one of {UNMASKED_SOURCES}",
            ),
            (self.pooling in RULES, f"pooling must be one of {RULES}"),
            (self.uncertainty in UNCERTAINTY, f"uncertainty must be one of {UNCERTAINTY}"),
            (self.figures in FIGURES, f"figures must be one of {FIGURES}"),
            (0 < self.pool_alpha < 1, "the pooling alpha must lie in (0, 1)"),
            (0 < self.test_alpha < 1, "the test alpha must lie in (0, 1)"),
            (0 < self.ci_level < 1, "the confidence level must lie in (0, 1)"),
            (self.n_boot >= 100, "use at least 100 bootstrap replicates"),
            (
                self.created_utc is None or bool(_UTC_RE.match(self.created_utc)),
                "created_utc must look like 2024-05-01T12:00:00Z",
            ),
        ]
        for ok, msg in checks:
            if not ok:
                raise AnalysisError(f"analysis settings: {msg}")
        if self.lapse is not None and not 0 <= self.lapse < 2 / 3:
            raise AnalysisError(f"analysis settings: lapse must lie in [0, 2/3), got {self.lapse}")
        parse_pool_spec(self.pool_groups)  # fail early on a malformed --pool

    def as_dict(self, source: str = "analyze") -> dict[str, Any]:
        """Settings that shape the numbers, for provenance (JSON types only).

        ``figures`` is left out (it changes no number); ``fit`` also leaves out the settings
        that only apply to logs.
        """
        d = asdict(self)
        d["pool_groups"] = list(self.pool_groups)
        d.pop("figures")  # drawing figures changes no number
        if source == "fit":
            for key in ("estimator", "n_reversals_averaged", "lapse", "unmasked_al"):
                d.pop(key)
        return d


# --------------------------------------------------------------------------------------------
# Pure analysis of a shifts table


@dataclass(frozen=True)
class CellResult:
    """One cell (pair × masker level) of an experiment.

    Attributes
    ----------
    target, masker, mv_stimulus : str
        The pair and its frequency-factor level.
    mv_frequency_hz : float
        Carrier of the MV stimulus, Hz.
    masker_level_db_sl : float
        Masker level, dB SL.
    n : int
        Participants (or 1 for a table of means).
    mean_shift_db : float
        Mean AL shift, dB.
    test : OneSampleT or None
        Two-tailed one-sample t-test against 0 (None without participants).
    """

    target: str
    masker: str
    mv_stimulus: str
    mv_frequency_hz: float
    masker_level_db_sl: float
    n: int
    mean_shift_db: float
    test: OneSampleT | None

    @property
    def pair(self) -> str:
        return f"{self.target}|{self.masker}"


@dataclass(frozen=True)
class GroupFit:
    """The ramp fitted to one pooled group of an experiment.

    Attributes
    ----------
    levels : tuple[str, ...]
        MV stimuli pooled.
    pairs : tuple[str, ...]
        ``target|masker`` of the pooled pairs.
    frequencies_hz : tuple[float, ...]
        Carriers of the MV stimuli, Hz.
    fit : RampFit
        The fit (cell means of the group's pairs as points).
    n_participants : int or None
        Participants behind the cell means (None for a table of means).
    """

    levels: tuple[str, ...]
    pairs: tuple[str, ...]
    frequencies_hz: tuple[float, ...]
    fit: RampFit
    n_participants: int | None

    @property
    def label(self) -> str:
        return "+".join(self.levels)


@dataclass(frozen=True)
class ExperimentResult:
    """Everything computed for one experiment."""

    experiment: str
    levels: tuple[str, ...]
    pair_of_level: Mapping[str, tuple[str, str]]
    participants: tuple[str, ...]
    anova: tuple[Effect, ...]
    anova_participants: tuple[str, ...]
    dropped: tuple[tuple[str, str], ...]
    posthoc: tuple[PairedTest, ...] | None
    cells: tuple[CellResult, ...]
    pooling: PoolingDecision
    fits: tuple[GroupFit, ...]
    notes: tuple[str, ...] = field(default_factory=tuple)


def analyze_shifts(
    shifts: pd.DataFrame, settings: AnalysisSettings, *, has_participants: bool = True
) -> list[ExperimentResult]:
    """Statistics, pooling and ramp fits for every experiment of a long shift table.

    Parameters
    ----------
    shifts : DataFrame
        Columns ``experiment, target, masker, mv_stimulus, mv_frequency_hz,
        masker_level_db_sl, shift_db`` and (with ``has_participants``) ``participant``.
    settings : AnalysisSettings
        Pooling, uncertainty and seed settings.
    has_participants : bool
        False for a table of cell means: tests are skipped (and the results say so).

    Raises
    ------
    AnalysisError
        If the table is empty.
    """
    if shifts.empty:
        raise AnalysisError("there are no AL shifts to analyse (no completed masked sets)")
    explicit = parse_pool_spec(settings.pool_groups)
    known = set(shifts["experiment"])
    for exp in explicit:
        if exp is not None and exp not in known:
            raise AnalysisError(
                f"--pool names experiment {exp!r}, which is not in the data "
                f"(experiments: {', '.join(sorted(known))})"
            )
    return [
        _analyze_experiment(str(exp), sub, settings, has_participants, explicit)
        for exp, sub in sorted(shifts.groupby("experiment"), key=lambda kv: str(kv[0]))
    ]


def _analyze_experiment(
    experiment: str,
    sub: pd.DataFrame,
    settings: AnalysisSettings,
    has_participants: bool,
    explicit: Mapping[str | None, list[list[str]]],
) -> ExperimentResult:
    notes: list[str] = []
    pairs = sub.groupby("mv_stimulus")[["target", "masker"]].apply(
        lambda g: sorted({(t, m) for t, m in zip(g["target"], g["masker"], strict=True)})
    )
    mixed = {lv: p for lv, p in pairs.items() if len(p) > 1}
    if mixed:
        lv, p = next(iter(mixed.items()))
        raise AnalysisError(
            f"experiment {experiment}: frequency level {lv} belongs to several pairs "
            f"({', '.join('|'.join(x) for x in p)}); give each direction its own experiment id"
        )
    levels = tuple(sorted(pairs.index, key=level_sort_key))
    pair_of_level = {lv: pairs[lv][0] for lv in levels}
    participants = tuple(sorted(sub["participant"].unique())) if has_participants else ()

    anova: list[Effect] = []
    anova_participants: tuple[str, ...] = ()
    dropped: tuple[tuple[str, str], ...] = ()
    posthoc: list[PairedTest] | None = None
    if not has_participants:
        notes.append(
            "no participant column: the repeated-measures ANOVA, Mauchly's test, the paired "
            "comparisons and the one-sample t-tests need per-participant shifts and were not run"
        )
    else:
        try:
            design = rm_design(
                sub,
                subject="participant",
                factor_a="mv_stimulus",
                factor_b="masker_level_db_sl",
                dv="shift_db",
            )
            # rm_design sorts levels alphabetically; reorder frequency levels by carrier.
            order = [design.levels_a.index(lv) for lv in levels]
            data = design.data[:, order, :]
            anova_participants, dropped = design.subjects, design.dropped
            for subj, why in dropped:
                notes.append(f"participant {subj} left out of the ANOVA and paired tests: {why}")
        except AnalysisError as exc:
            data = None
            notes.append(f"ANOVA not run: {exc}")
        if data is not None:
            try:
                anova = rm_anova(data)
            except AnalysisError as exc:
                notes.append(f"ANOVA not run: {exc}")
            if len(levels) >= 2:
                try:
                    posthoc = paired_comparisons(data.mean(axis=2), list(levels))
                except AnalysisError as exc:
                    notes.append(f"paired comparisons not run: {exc}")
            else:
                notes.append("one frequency level only: no paired comparisons")

    cells = []
    for (lv, level), g in sorted(
        sub.groupby(["mv_stimulus", "masker_level_db_sl"]),
        key=lambda kv: (level_sort_key(kv[0][0]), kv[0][1]),
    ):
        values = g["shift_db"].to_numpy(dtype=float)
        test = one_sample_t(values) if has_participants else None
        t, m = pair_of_level[lv]
        cells.append(
            CellResult(
                t,
                m,
                lv,
                float(g["mv_frequency_hz"].iloc[0]),
                float(level),
                int(values.size),
                float(values.mean()),
                test,
            )
        )

    pooling = decide_pooling(
        experiment,
        list(levels),
        rule=settings.pooling,
        alpha=settings.pool_alpha,
        tests=posthoc,
        explicit=explicit,
    )
    fits = tuple(
        _fit_group(experiment, group, sub, cells, pair_of_level, settings, has_participants)
        for group in pooling.groups
    )
    return ExperimentResult(
        experiment=experiment,
        levels=levels,
        pair_of_level=pair_of_level,
        participants=participants,
        anova=tuple(anova),
        anova_participants=anova_participants,
        dropped=dropped,
        posthoc=None if posthoc is None else tuple(posthoc),
        cells=tuple(cells),
        pooling=pooling,
        fits=fits,
        notes=tuple(notes),
    )


def _fit_group(
    experiment: str,
    group: tuple[str, ...],
    sub: pd.DataFrame,
    cells: Sequence[CellResult],
    pair_of_level: Mapping[str, tuple[str, str]],
    settings: AnalysisSettings,
    has_participants: bool,
) -> GroupFit:
    mine = [c for c in cells if c.mv_stimulus in group]
    x = np.array([c.masker_level_db_sl for c in mine])
    y = np.array([c.mean_shift_db for c in mine])
    fit = fit_ramp(x, y, ci_level=settings.ci_level)
    members = sub[sub["mv_stimulus"].isin(group)]
    n_part = int(members["participant"].nunique()) if has_participants else None
    if settings.uncertainty == "bootstrap" and fit.status == "fitted":
        if not has_participants:
            fit = _add_message(
                fit, "bootstrap needs per-participant shifts; asymptotic uncertainty reported"
            )
        elif (n_part or 0) < 2:
            fit = _add_message(
                fit, "one participant: no bootstrap; asymptotic uncertainty reported"
            )
        else:
            wide = members.pivot_table(
                index="participant",
                columns=["mv_stimulus", "masker_level_db_sl"],
                values="shift_db",
                aggfunc="mean",
            )
            cols = [(c.mv_stimulus, c.masker_level_db_sl) for c in mine]
            wide = wide.reindex(columns=pd.MultiIndex.from_tuples(cols)).sort_index()
            rng = _rng_for(settings.seed, experiment, "+".join(group))
            a, b, failed = participant_bootstrap(
                x, wide.to_numpy(dtype=float), n_boot=settings.n_boot, rng=rng
            )
            fit = with_bootstrap(fit, a, b, n_failed=failed)
            if n_part is not None and n_part < 5:
                fit = _add_message(
                    fit, f"only {n_part} participants: bootstrap intervals are optimistic"
                )
    pairs = tuple("|".join(pair_of_level[lv]) for lv in group)
    freqs = tuple(sorted({c.mv_frequency_hz for c in mine}))
    return GroupFit(tuple(group), pairs, freqs, fit, n_part)


def _add_message(fit: RampFit, text: str) -> RampFit:
    return replace(fit, message=f"{fit.message}; {text}" if fit.message else text)


def _rng_for(seed: int, experiment: str, group: str) -> np.random.Generator:
    """A generator per (seed, experiment, group): results do not depend on processing order."""
    digest = hashlib.sha256(f"{experiment}\x00{group}".encode()).digest()
    words = [int.from_bytes(digest[i : i + 4], "little") for i in range(0, 16, 4)]
    return np.random.default_rng(np.random.SeedSequence([int(seed), *words]))


# --------------------------------------------------------------------------------------------
# Export


def masking_params_document(
    results: Sequence[ExperimentResult],
    settings: AnalysisSettings,
    *,
    source: str,
    inputs: Sequence[Mapping[str, str]],
    skipped: Sequence[Mapping[str, str]] = (),
    created_utc: str,
) -> tuple[dict[str, Any], list[str]]:
    """The masking_params.json document, and notes on pairs dropped as duplicates."""
    entries: dict[tuple[str, str], dict[str, Any]] = {}
    notes = []
    for res in results:
        for gf in res.fits:
            f = gf.fit
            for lv in gf.levels:
                target, masker = res.pair_of_level[lv]
                if (target, masker) in entries:
                    notes.append(
                        f"{target}|{masker} is fitted in experiment "
                        f"{entries[(target, masker)]['experiment']} and {res.experiment}; "
                        f"the export keeps {entries[(target, masker)]['experiment']}"
                    )
                    continue
                entries[(target, masker)] = {
                    "target": target,
                    "masker": masker,
                    "masker_frequencies_hz": list(gf.frequencies_hz),
                    "intercept_db": f.intercept_db,
                    "slope": f.slope,
                    "intercept_se_db": f.intercept_se_db,
                    "slope_se": f.slope_se,
                    "intercept_ci_db": None
                    if f.intercept_ci_db is None
                    else list(f.intercept_ci_db),
                    "slope_ci": None if f.slope_ci is None else list(f.slope_ci),
                    "fitted_range_db_sl": list(f.fitted_range_db_sl),
                    "knee_db_sl": f.knee_db_sl,
                    "adj_r2": f.adj_r2,
                    "n_points": f.n_points,
                    "pooled_pairs": list(gf.pairs),
                    "status": f.status,
                    "message": f.message,
                    "experiment": res.experiment,
                    "uncertainty": f.uncertainty,
                    "ci_level": f.ci_level,
                    "n_participants": gf.n_participants,
                }
    provenance: dict[str, Any] = {
        "source": source,
        "inputs": [dict(i) for i in inputs],
        "settings": settings.as_dict(source),
    }
    if skipped:
        provenance["skipped_inputs"] = [dict(s) for s in skipped]
    doc = {
        "schema_version": 1,
        "software_version": __version__,
        "created_utc": created_utc,
        "provenance": provenance,
        "functions": [entries[k] for k in sorted(entries)],
    }
    return doc, notes


# --------------------------------------------------------------------------------------------
# Tables


def anova_rows(results: Iterable[ExperimentResult]) -> list[dict[str, Any]]:
    """Rows of anova.csv (columns :data:`ANOVA_COLUMNS`)."""
    return [
        {
            "experiment": r.experiment,
            "effect": e.name,
            "F": e.F,
            "df1": e.df1,
            "df2": e.df2,
            "p": e.p,
            "eps_gg": e.eps_gg,
            "p_gg": e.p_gg,
            "np2": e.np2,
        }
        for r in results
        for e in r.anova
    ]


SPHERICITY_COLUMNS = ["experiment", "effect", "mauchly_w", "chi2", "df", "p", "eps_gg", "note"]
POSTHOC_COLUMNS = [
    "experiment",
    "factor",
    "a",
    "b",
    "n",
    "mean_diff_db",
    "t",
    "df",
    "p",
    "p_bonf",
    "dz",
    "note",
]
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


def sphericity_rows(results: Iterable[ExperimentResult]) -> list[dict[str, Any]]:
    """Rows of sphericity.csv: Mauchly's test per effect."""
    return [
        {
            "experiment": r.experiment,
            "effect": e.name,
            "mauchly_w": e.mauchly_w,
            "chi2": e.mauchly_chi2,
            "df": e.mauchly_df,
            "p": e.mauchly_p,
            "eps_gg": e.eps_gg,
            "note": e.note,
        }
        for r in results
        for e in r.anova
    ]


def posthoc_rows(results: Iterable[ExperimentResult]) -> list[dict[str, Any]]:
    """Rows of posthoc.csv: Bonferroni paired comparisons between frequency levels."""
    return [
        {
            "experiment": r.experiment,
            "factor": "frequency",
            "a": t.a,
            "b": t.b,
            "n": t.n,
            "mean_diff_db": t.mean_diff,
            "t": t.t,
            "df": t.df,
            "p": t.p,
            "p_bonf": t.p_bonf,
            "dz": t.dz,
            "note": t.note,
        }
        for r in results
        for t in (r.posthoc or ())
    ]


def one_sample_rows(
    results: Iterable[ExperimentResult], alpha: float = 0.05
) -> list[dict[str, Any]]:
    """Rows of one_sample.csv: every cell's shift against 0 (two-tailed)."""
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
    """Rows of ramp_fits.csv: one per pooled group."""
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


def csv_text(columns: Sequence[str], rows: Iterable[Mapping[str, Any]]) -> str:
    """CSV with fixed formatting: floats to 6 significant digits, empty for None."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for row in rows:
        w.writerow([_cell(row.get(c)) for c in columns])
    return buf.getvalue()


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool | np.bool_):
        return "true" if v else "false"
    if isinstance(v, float | np.floating):
        if isinstance(v, float) and math.isnan(v):
            return ""
        return f"{float(v):.6g}"
    return str(v)


# --------------------------------------------------------------------------------------------
# Report


def report_text(
    results: Sequence[ExperimentResult],
    settings: AnalysisSettings,
    *,
    source: str,
    inputs_summary: Sequence[str],
    thresholds: pd.DataFrame | None,
    export_notes: Sequence[str],
) -> str:
    """The readable text report."""
    out: list[str] = []
    add = out.append
    add(f"masking-lab {source} report (software {__version__})")
    add("=" * 72)
    add("")
    add("Inputs")
    add("------")
    out.extend(inputs_summary)
    add("")
    add("Settings")
    add("--------")
    for k, v in settings.as_dict(source).items():
        add(f"  {k}: {v}")
    if thresholds is not None:
        add("")
        add("Thresholds")
        add("----------")
        counts = thresholds["status"].value_counts().sort_index()
        add("  sets by status: " + ", ".join(f"{k} {v}" for k, v in counts.items()))
        excluded = thresholds[thresholds["status"] != "completed"]
        if len(excluded):
            add("  excluded from the statistics (never averaged into a threshold):")
            for _, r in excluded.iterrows():
                what = r["target"] if r["masker"] is None else f"{r['target']}|{r['masker']}"
                lvl = (
                    ""
                    if r["masker_level_db_sl"] is None
                    else f" @ {r['masker_level_db_sl']:g} dB SL"
                )
                add(
                    f"    {r['participant']} {r['experiment']} {r['set_id']} ({what}{lvl}): "
                    f"{r['status']} — {r['note'] or ''}".rstrip(" —")
                )
        src = thresholds["unmasked_source"].dropna().value_counts().sort_index()
        if len(src):
            add("  unmasked ALs from: " + ", ".join(f"{k} ({v} sets)" for k, v in src.items()))
    for r in results:
        add("")
        title = f"Experiment {r.experiment}"
        add(title)
        add("-" * len(title))
        pairs = ", ".join(f"{lv} → {'|'.join(r.pair_of_level[lv])}" for lv in r.levels)
        add(f"  frequency factor (MV stimulus of each pair): {pairs}")
        if r.participants:
            add(f"  participants: {len(r.participants)} ({', '.join(r.participants)})")
        for note in r.notes:
            add(f"  NOTE: {note}")
        if r.anova:
            add("")
            add(f"  Two-way repeated-measures ANOVA on AL shift (n = {len(r.anova_participants)})")
            add(
                f"    {'effect':<16}{'F':>9}{'df1':>5}{'df2':>5}{'p':>11}{'eps_GG':>8}"
                f"{'p_GG':>11}{'np2':>7}   Mauchly W, p"
            )
            for e in r.anova:
                mw = "—" if e.mauchly_w is None else f"{e.mauchly_w:.3f}"
                mp = "—" if e.mauchly_p is None else _p(e.mauchly_p)
                add(
                    f"    {e.name:<16}{e.F:9.3f}{e.df1:5d}{e.df2:5d}{_p(e.p):>11}"
                    f"{e.eps_gg:8.3f}{_p(e.p_gg):>11}{e.np2:7.3f}   {mw}, {mp}"
                )
                if e.note:
                    add(f"      ({e.note})")
        if r.posthoc:
            add("")
            add("  Paired comparisons between frequency levels (Bonferroni)")
            for t in r.posthoc:
                if t.t is None:
                    add(f"    {t.a} vs {t.b}: mean diff {t.mean_diff:+.3f} dB; {t.note}")
                else:
                    add(
                        f"    {t.a} vs {t.b}: mean diff {t.mean_diff:+.3f} dB, "
                        f"t({t.df}) = {t.t:.3f}, {_p_eq(t.p)}, Bonferroni {_p_eq(t.p_bonf)}"
                    )
        add("")
        tested = any(c.test is not None for c in r.cells)
        add(
            "  Mean AL shift per cell (dB); * = not different from 0 (two-tailed t-test)"
            if tested
            else "  Mean AL shift per cell (dB; not tested against 0: no participant data)"
        )
        lvls = sorted({c.masker_level_db_sl for c in r.cells})
        add("    " + f"{'':<10}" + "".join(f"{v:>11g}" for v in lvls) + "  dB SL")
        for lv in r.levels:
            line = f"    {lv:<10}"
            for x in lvls:
                c = next(
                    (c for c in r.cells if c.mv_stimulus == lv and c.masker_level_db_sl == x), None
                )
                if c is None:
                    line += f"{'—':>11}"
                    continue
                star = ""
                if c.test is not None:
                    star = (
                        "?"
                        if c.test.p is None
                        else ("*" if c.test.p >= settings.test_alpha else "")
                    )
                line += f"{star + format(c.mean_shift_db, '.3f'):>11}"
            add(line)
        add("")
        add(f"  Pooling ({r.pooling.rule}): " + "; ".join("+".join(g) for g in r.pooling.groups))
        for reason in r.pooling.reasons:
            add(f"    {reason}")
        add("")
        add("  Ramp fits: shift = max(0, a + b·x), x = masker level (dB SL)")
        for g in r.fits:
            f = g.fit
            add(f"    {g.label} [{', '.join(g.pairs)}]: {f.status}")
            if f.intercept_db is not None and f.slope is not None:
                a_unc = _unc(f.intercept_se_db, f.intercept_ci_db)
                b_unc = _unc(f.slope_se, f.slope_ci)
                add(f"      a = {f.intercept_db:.3f} dB {a_unc}")
                add(f"      b = {f.slope:.4f} {b_unc}")
                knee = "none" if f.knee_db_sl is None else f"{f.knee_db_sl:.2f} dB SL"
                adj = "—" if f.adj_r2 is None else f"{f.adj_r2:.4f}"
                adj_a = "—" if f.adj_r2_active is None else f"{f.adj_r2_active:.4f}"
                add(
                    f"      knee −a/b = {knee}; fitted {f.fitted_range_db_sl[0]:g}–"
                    f"{f.fitted_range_db_sl[1]:g} dB SL on {f.n_points} cell means; "
                    f"adj. R² = {adj} (above the knee only: {adj_a}); "
                    f"uncertainty: {f.uncertainty}"
                )
            if f.message:
                add(f"      note: {f.message}")
    if export_notes:
        add("")
        add("Export")
        add("------")
        for n in export_notes:
            add(f"  {n}")
    add("")
    return "\n".join(out)


def _p(p: float | None) -> str:
    if p is None:
        return "—"
    return "< 0.001" if p < 0.001 else f"{p:.3f}"


def _p_eq(p: float | None) -> str:
    """``p = 0.123`` or ``p < 0.001`` for running text."""
    text = _p(p)
    return f"p {text}" if text.startswith("<") else f"p = {text}"


def _unc(se: float | None, ci: tuple[float, float] | None) -> str:
    parts = []
    if se is not None:
        parts.append(f"SE {se:.3f}")
    if ci is not None:
        parts.append(f"CI [{ci[0]:.3f}, {ci[1]:.3f}]")
    return f"({', '.join(parts)})" if parts else "(no uncertainty)"


# --------------------------------------------------------------------------------------------
# Shell: analyze DATA_DIR


@dataclass
class RunSummary:
    """What a run wrote and what it warns about."""

    out_dir: Path
    files: list[Path]
    warnings: list[str]


def find_logs(data_dir: Path) -> list[Path]:
    """Every ``*.jsonl`` under ``data_dir`` (hidden files skipped), sorted by relative path."""
    if not data_dir.is_dir():
        raise AnalysisError(f"{data_dir}: no such folder; give the folder holding session logs")
    found = [
        p
        for p in data_dir.rglob("*.jsonl")
        if p.is_file() and not any(part.startswith(".") for part in p.relative_to(data_dir).parts)
    ]
    return sorted(found, key=lambda p: p.relative_to(data_dir).as_posix())


def run_analyze(
    data_dir: str | Path,
    out_dir: str | Path,
    settings: AnalysisSettings,
    *,
    progress: Callable[[int, int], None] | None = None,
) -> RunSummary:
    """Analyse every session log under ``data_dir`` and write every output into ``out_dir``.

    Unreadable or truncated logs are reported (report, ``problems.csv``, provenance) and the run
    continues.

    Raises
    ------
    AnalysisError
        If the folder has no readable log or no completed masked set (``thresholds.csv`` and the
        report are written first in the latter case).
    """
    from masking_lab.formats.session_log import read_log

    data = Path(data_dir)
    out = Path(out_dir)
    paths = find_logs(data)
    if not paths:
        raise AnalysisError(f"{data}: no session logs (*.jsonl) found")
    est = EstimatorSettings(settings.estimator, settings.n_reversals_averaged, settings.lapse)
    rows: list[dict] = []
    inputs: list[dict[str, str]] = []
    skipped: list[dict[str, str]] = []
    problems: list[dict[str, str]] = []
    created: list[str] = []
    figure_jobs = settings.figures == "all"
    files: list[Path] = []
    for i, path in enumerate(paths, start=1):
        rel = path.relative_to(data).as_posix()
        try:
            raw = path.read_bytes()
            log = read_log(path)
        except (OSError, LogError) as exc:
            reason = str(exc)
            skipped.append({"path": rel, "reason": reason})
            problems.append({"log": rel, "problem": reason, "action": "file skipped"})
            if progress:
                progress(i, len(paths))
            continue
        for pr in log.problems:
            problems.append({"log": rel, "problem": pr, "action": "line ignored"})
        h = log.header
        if (
            not isinstance(h.get("protocol"), dict)
            or "experiment" not in h["protocol"]
            or ("participant" not in h)
        ):
            reason = "header lacks participant or protocol.experiment"
            skipped.append({"path": rel, "reason": reason})
            problems.append({"log": rel, "problem": reason, "action": "file skipped"})
            if progress:
                progress(i, len(paths))
            continue
        if h.get("kind") == "usertest":
            reason = "a user-test log (no staircases): analyse it with masking-lab usertest-report"
            skipped.append({"path": rel, "reason": reason})
            problems.append({"log": rel, "problem": reason, "action": "file skipped"})
            if progress:
                progress(i, len(paths))
            continue
        inputs.append({"path": rel, "sha256": hashlib.sha256(raw).hexdigest()})
        if isinstance(h.get("created_utc"), str) and _UTC_RE.match(h["created_utc"]):
            created.append(h["created_utc"])
        new_rows = session_rows(log, rel, est)
        rows.extend(new_rows)
        if figure_jobs:
            from masking_lab.analysis.figures import track_figure

            als = {
                r["set_id"]: (r.get("al_db_sl") if r.get("masker") else r.get("al_db_v"))
                for r in new_rows
            }
            name = _safe(
                f"{h['participant']}_{h['protocol']['experiment']}_{h.get('session_id', '')}"
            )
            files.append(track_figure(out / "figures" / "tracks" / f"{name}.png", log, als))
        if progress:
            progress(i, len(paths))
    if not inputs:
        raise AnalysisError(
            f"{data}: none of the {len(paths)} log file(s) could be read; first problem: "
            f"{problems[0]['log']}: {problems[0]['problem']}"
        )
    thresholds = thresholds_table(rows, unmasked_al=settings.unmasked_al)
    shifts = shifts_long(thresholds)
    created_utc = settings.created_utc or (max(created) if created else EPOCH_UTC)
    n_sessions = len(inputs)
    summary = [
        f"  data folder: {data}",
        f"  logs found: {len(paths)}; analysed: {n_sessions}; skipped: {len(skipped)}",
    ]
    summary += [f"  SKIPPED {s['path']}: {s['reason']}" for s in skipped]
    summary += [
        f"  {p['log']}: {p['problem']} ({p['action']})"
        for p in problems
        if p["action"] != "file skipped"
    ]
    files.append(
        write_text_atomic(
            out / "thresholds.csv", csv_text(THRESHOLD_COLUMNS, thresholds.to_dict("records"))
        )
    )
    files.append(
        write_text_atomic(out / "problems.csv", csv_text(["log", "problem", "action"], problems))
    )
    warnings = [f"{p['log']}: {p['problem']} ({p['action']})" for p in problems]
    if shifts.empty:
        text = report_text(
            [],
            settings,
            source="analyze",
            inputs_summary=summary,
            thresholds=thresholds,
            export_notes=[],
        )
        files.append(write_text_atomic(out / "report.txt", text))
        raise AnalysisError(
            f"{data}: no completed masked set to analyse ({len(thresholds)} sets, none with an "
            f"AL shift); see {out / 'report.txt'} for the status of each set"
        )
    results = analyze_shifts(shifts, settings, has_participants=True)
    files += _write_results(
        out,
        results,
        settings,
        source="analyze",
        inputs=inputs,
        skipped=skipped,
        created_utc=created_utc,
        summary=summary,
        thresholds=thresholds,
    )
    warnings += _result_warnings(results)
    return RunSummary(out, files, warnings)


def _result_warnings(results: Sequence[ExperimentResult]) -> list[str]:
    out = [f"{r.experiment}: {n}" for r in results for n in r.notes]
    for r in results:
        for g in r.fits:
            if g.fit.status != "fitted":
                out.append(f"{r.experiment}: {g.label}: {g.fit.status}: {g.fit.message}")
    return out


def _write_results(
    out: Path,
    results: Sequence[ExperimentResult],
    settings: AnalysisSettings,
    *,
    source: str,
    inputs: Sequence[Mapping[str, str]],
    skipped: Sequence[Mapping[str, str]],
    created_utc: str,
    summary: Sequence[str],
    thresholds: pd.DataFrame | None,
) -> list[Path]:
    doc, export_notes = masking_params_document(
        results, settings, source=source, inputs=inputs, skipped=skipped, created_utc=created_utc
    )
    files = [
        write_text_atomic(out / "anova.csv", csv_text(ANOVA_COLUMNS, anova_rows(results))),
        write_text_atomic(
            out / "sphericity.csv", csv_text(SPHERICITY_COLUMNS, sphericity_rows(results))
        ),
        write_text_atomic(out / "posthoc.csv", csv_text(POSTHOC_COLUMNS, posthoc_rows(results))),
        write_text_atomic(
            out / "one_sample.csv",
            csv_text(ONE_SAMPLE_COLUMNS, one_sample_rows(results, settings.test_alpha)),
        ),
        write_text_atomic(out / "ramp_fits.csv", csv_text(FIT_COLUMNS, fit_rows(results))),
        write_text_atomic(out / "masking_params.json", masking_params_json(doc)),
        write_text_atomic(
            out / "report.txt",
            report_text(
                results,
                settings,
                source=source,
                inputs_summary=summary,
                thresholds=thresholds,
                export_notes=export_notes,
            ),
        ),
    ]
    if settings.figures != "none":
        from masking_lab.analysis.figures import masking_function_figure

        for r in results:
            cells = [
                {
                    "mv_stimulus": c.mv_stimulus,
                    "pair": c.pair,
                    "masker_level_db_sl": c.masker_level_db_sl,
                    "mean_shift_db": c.mean_shift_db,
                    "se_db": None if c.test is None else c.test.se,
                }
                for c in r.cells
            ]
            fits = [
                {
                    "label": g.label,
                    "levels": g.levels,
                    "intercept_db": g.fit.intercept_db if g.fit.status == "fitted" else None,
                    "slope": g.fit.slope,
                    "fitted_range_db_sl": g.fit.fitted_range_db_sl,
                    "status": g.fit.status,
                }
                for g in r.fits
            ]
            files.append(
                masking_function_figure(
                    out / "figures" / f"masking_{_safe(r.experiment)}.png",
                    experiment=r.experiment,
                    cells=cells,
                    fits=fits,
                )
            )
    return files


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("_") or "unnamed"


# --------------------------------------------------------------------------------------------
# Shell: fit SHIFTS.csv

FIT_REQUIRED = ("target", "masker", "masker_level_db_sl", "shift_db")
FIT_OPTIONAL = ("participant", "masker_frequency_hz", "mv_frequency_hz", "experiment")


def read_shifts_csv(path: str | Path) -> tuple[pd.DataFrame, bool]:
    """Read a long CSV of AL shifts for ``fit``.

    Columns: ``target, masker, masker_level_db_sl, shift_db`` (required), ``participant``,
    ``masker_frequency_hz`` (the masker's carrier, checked against its name), ``experiment``
    (default: the direction, ``EV270|MV`` or ``MV|EV270``) (optional). Lines starting with
    ``#`` are comments.

    Returns
    -------
    shifts : DataFrame
        The long table :func:`analyze_shifts` takes.
    has_participants : bool
        Whether a participant column with values is present.

    Raises
    ------
    AnalysisError
        Naming the file, line and column of the first problem.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise AnalysisError(f"{p}: cannot read the file ({exc.strerror or exc})") from exc
    lines = [
        (n, line)
        for n, line in enumerate(text.splitlines(), start=1)
        if line.strip() and not line.lstrip().startswith("#")
    ]
    if not lines:
        raise AnalysisError(f"{p}: the file is empty; expected a header line and shift rows")
    reader = csv.reader([line for _, line in lines])
    header = [h.strip() for h in next(reader)]
    missing = [c for c in FIT_REQUIRED if c not in header]
    if missing:
        raise AnalysisError(
            f"{p}: line {lines[0][0]}: missing column(s) {', '.join(missing)}; the header must "
            f"name {', '.join(FIT_REQUIRED)} (and optionally {', '.join(FIT_OPTIONAL)})"
        )
    unknown = [c for c in header if c not in FIT_REQUIRED + FIT_OPTIONAL]
    if unknown:
        raise AnalysisError(
            f"{p}: line {lines[0][0]}: unknown column(s) {', '.join(unknown)}; allowed: "
            f"{', '.join(FIT_REQUIRED + FIT_OPTIONAL)}"
        )
    has_participants = "participant" in header
    records = []
    seen: dict[tuple, int] = {}
    for (lineno, _), values in zip(lines[1:], reader, strict=True):
        if len(values) != len(header):
            raise AnalysisError(
                f"{p}: line {lineno}: {len(values)} fields, expected {len(header)} "
                f"({', '.join(header)})"
            )
        row = dict(zip(header, (v.strip() for v in values), strict=True))
        rec = _shift_record(p, lineno, row, has_participants)
        key = (
            rec["experiment"],
            rec["participant"],
            rec["target"],
            rec["masker"],
            rec["masker_level_db_sl"],
        )
        if key in seen:
            who = f"participant {rec['participant']}, " if has_participants else ""
            raise AnalysisError(
                f"{p}: line {lineno}: {who}{rec['target']}|{rec['masker']} at "
                f"{rec['masker_level_db_sl']:g} dB SL repeats line {seen[key]}; give one shift per "
                "cell"
                + (" and participant" if has_participants else " (or add a participant column)")
            )
        seen[key] = lineno
        records.append(rec)
    if not records:
        raise AnalysisError(f"{p}: no data rows after the header")
    return pd.DataFrame(records), has_participants


def _shift_record(p: Path, lineno: int, row: Mapping[str, str], has_participants: bool) -> dict:
    where = f"{p}: line {lineno}"
    names = {}
    for col in ("target", "masker"):
        if not is_stimulus_name(row[col]):
            raise AnalysisError(
                f"{where}: {col} {row[col]!r} is not a stimulus name; write e.g. EV270 or MV120"
            )
        names[col] = parse_stimulus(row[col])
    target, masker = names["target"], names["masker"]
    numbers = {}
    for col in ("masker_level_db_sl", "shift_db", "masker_frequency_hz", "mv_frequency_hz"):
        if col not in row or (col not in FIT_REQUIRED and row[col] == ""):
            continue
        try:
            numbers[col] = float(row[col])
        except ValueError:
            raise AnalysisError(f"{where}: {col} {row[col]!r} is not a number") from None
        if not math.isfinite(numbers[col]):
            raise AnalysisError(f"{where}: {col} must be a finite number, got {row[col]!r}")
    mv = masker if masker.channel == "MV" or target.channel != "MV" else target
    if "masker_frequency_hz" in numbers and numbers["masker_frequency_hz"] != masker.carrier_hz:
        raise AnalysisError(
            f"{where}: masker_frequency_hz {numbers['masker_frequency_hz']:g} does not match the "
            f"masker {masker.name} ({masker.carrier_hz:g} Hz); the column is the masker's carrier "
            "(the frequency factor is taken from the MV stimulus name)"
        )
    if "mv_frequency_hz" in numbers and numbers["mv_frequency_hz"] != mv.carrier_hz:
        raise AnalysisError(
            f"{where}: mv_frequency_hz {numbers['mv_frequency_hz']:g} does not match the pair's "
            f"MV stimulus {mv.name}"
        )
    participant = row.get("participant", "") if has_participants else ""
    if has_participants and not participant:
        raise AnalysisError(f"{where}: participant is empty; fill it in or drop the column")
    experiment = row.get("experiment") or (
        f"{target.name}|MV" if mv is masker else f"MV|{masker.name}"
    )
    return {
        "experiment": experiment,
        "participant": participant,
        "target": target.name,
        "masker": masker.name,
        "mv_stimulus": mv.name,
        "mv_frequency_hz": mv.carrier_hz,
        "masker_level_db_sl": numbers["masker_level_db_sl"],
        "shift_db": numbers["shift_db"],
    }


def run_fit(csv_path: str | Path, out_dir: str | Path, settings: AnalysisSettings) -> RunSummary:
    """Statistics, pooling, ramp fits and export from a long CSV of AL shifts.

    Raises
    ------
    AnalysisError
        For an unreadable or malformed table (naming the line).
    """
    path = Path(csv_path)
    out = Path(out_dir)
    shifts, has_participants = read_shifts_csv(path)
    results = analyze_shifts(shifts, settings, has_participants=has_participants)
    inputs = [{"path": str(csv_path), "sha256": hashlib.sha256(path.read_bytes()).hexdigest()}]
    summary = [
        f"  shifts table: {csv_path} ({len(shifts)} rows, "
        + (
            f"{shifts['participant'].nunique()} participants)"
            if has_participants
            else "cell means without participants)"
        )
    ]
    files = _write_results(
        out,
        results,
        settings,
        source="fit",
        inputs=inputs,
        skipped=(),
        created_utc=settings.created_utc or EPOCH_UTC,
        summary=summary,
        thresholds=None,
    )
    return RunSummary(out, files, _result_warnings(results))


def progress_printer(stream: TextIO, label: str) -> Callable[[int, int], None]:
    """A progress callback drawing ``[ 340/1000] logs read`` in place on ``stream``."""
    last = {"shown": -1}

    def show(i: int, n: int) -> None:
        step = max(1, n // 200)
        if i != n and i % step and i - last["shown"] < step:
            return
        last["shown"] = i
        width = len(str(n))
        stream.write(f"\r[{i:>{width}}/{n}] {label}")
        if i == n:
            stream.write("\n")
        stream.flush()

    return show
