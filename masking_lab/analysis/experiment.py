"""Pure analysis of one table of AL shifts (paper §2.4): per experiment, the repeated-measures
ANOVA, paired comparisons, one-sample t-tests, pooling and the ramp fits.

Per experiment (the protocol's ``experiment`` id, or in ``fit`` the direction ``EV270|MV`` /
``MV|EV270`` derived from the stimulus names) the "frequency" factor is the MV stimulus of each
pair — the masker in Experiment I, the target in Experiment II (paper Table 2's "Frequency of
MV") — and the "level" factor is the masker level in dB SL. The bootstrap is seeded per
experiment and group, so results do not depend on processing order.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd

from masking_lab.analysis.pooling import (
    PoolingDecision,
    decide_pooling,
    level_sort_key,
    parse_pool_spec,
)
from masking_lab.analysis.pooling_lr import compare_pooling, comparison_lines
from masking_lab.analysis.ramp_fit import RampFit, fit_ramp, participant_bootstrap, with_bootstrap
from masking_lab.analysis.settings import AnalysisSettings
from masking_lab.analysis.stats import Effect, rm_anova, rm_design
from masking_lab.analysis.t_tests import OneSampleT, PairedTest, one_sample_t, paired_comparisons
from masking_lab.core.errors import AnalysisError

__all__ = [
    "CellResult",
    "ExperimentResult",
    "GroupFit",
    "analyze_shifts",
    "result_warnings",
]


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

    Returns
    -------
    list of ExperimentResult
        One per experiment, sorted by id.

    Raises
    ------
    AnalysisError
        If the table is empty.

    Examples
    --------
    >>> from masking_lab.analysis.settings import AnalysisSettings
    >>> shifts = pd.DataFrame(
    ...     {
    ...         "experiment": "e1",
    ...         "target": "EV270",
    ...         "masker": "MV120",
    ...         "mv_stimulus": "MV120",
    ...         "mv_frequency_hz": 120.0,
    ...         "masker_level_db_sl": [5.0, 10.0, 15.0, 20.0, 25.0],
    ...         "shift_db": [0.0, 2.0, 4.5, 7.0, 9.5],
    ...     }
    ... )
    >>> (result,) = analyze_shifts(shifts, AnalysisSettings(), has_participants=False)
    >>> fit = result.fits[0].fit
    >>> fit.status, round(fit.intercept_db, 2), round(fit.slope, 2)
    ('fitted', -3.0, 0.5)
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
    for (lv, _), g in sorted(
        sub.groupby(["mv_stimulus", "masker_level_db_sl"]),
        key=lambda kv: (level_sort_key(str(kv[0][0])), kv[0][1]),
    ):
        values = g["shift_db"].to_numpy(dtype=float)
        test = one_sample_t(values) if has_participants else None
        t, m = pair_of_level[str(lv)]
        cells.append(
            CellResult(
                t,
                m,
                str(lv),
                float(g["mv_frequency_hz"].iloc[0]),
                float(g["masker_level_db_sl"].iloc[0]),  # the group's level (a number, not key)
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
    pooling = replace(pooling, model_comparison=_model_comparison(sub, levels, settings))
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


def _model_comparison(
    sub: pd.DataFrame, levels: Sequence[str], settings: AnalysisSettings
) -> tuple[str, ...]:
    """Pooled against separate ramps over every shift (issue 13), beside the paper's rule."""
    points = {
        str(lv): (g["masker_level_db_sl"].to_numpy(float), g["shift_db"].to_numpy(float))
        for lv, g in sub.groupby("mv_stimulus")
    }
    return tuple(comparison_lines(compare_pooling(points, levels), settings.pool_alpha))


def _add_message(fit: RampFit, text: str) -> RampFit:
    return replace(fit, message=f"{fit.message}; {text}" if fit.message else text)


def _rng_for(seed: int, experiment: str, group: str) -> np.random.Generator:
    """A generator per (seed, experiment, group): results do not depend on processing order."""
    digest = hashlib.sha256(f"{experiment}\x00{group}".encode()).digest()
    words = [int.from_bytes(digest[i : i + 4], "little") for i in range(0, 16, 4)]
    return np.random.default_rng(np.random.SeedSequence([int(seed), *words]))


def result_warnings(results: Sequence[ExperimentResult]) -> list[str]:
    """What the experimenter should look at: every note, and every ramp that was not fitted.

    Parameters
    ----------
    results : sequence of ExperimentResult
        The results of :func:`analyze_shifts`.

    Returns
    -------
    list of str
        One line each, prefixed by the experiment (and the group for a fit).

    Examples
    --------
    >>> result_warnings([])
    []
    """
    out = [f"{r.experiment}: {n}" for r in results for n in r.notes]
    for r in results:
        for g in r.fits:
            if g.fit.status != "fitted":
                out.append(f"{r.experiment}: {g.label}: {g.fit.status}: {g.fit.message}")
    return out
