"""The model of the analysis report: a tree of frozen dataclasses holding its numbers.

:func:`build_report` gathers what the report shows — inputs, settings, the status of every
threshold, and per experiment the ANOVA, paired comparisons, the grid of mean shifts, pooling
and ramp fits — from the analysis results. Renderers read only the model:
:func:`masking_lab.analysis.report_text.render_text` writes ``report.txt``; an HTML renderer can
read the same model.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import pandas as pd

from masking_lab import __version__
from masking_lab.analysis.experiment import ExperimentResult, GroupFit, result_warnings
from masking_lab.analysis.pooling import PoolingDecision
from masking_lab.analysis.report_lab import LabSection
from masking_lab.analysis.settings import EPOCH_UTC, AnalysisSettings
from masking_lab.analysis.stats import Effect
from masking_lab.analysis.t_tests import PairedTest

__all__ = [
    "ExcludedSet",
    "ExperimentSection",
    "LogsInput",
    "ReportModel",
    "ShiftCell",
    "ShiftRow",
    "ShiftsTableInput",
    "ThresholdsSection",
    "build_report",
    "experiment_heading",
    "setting_text",
]


@dataclass(frozen=True)
class LogsInput:
    """The inputs of ``analyze``: a folder of session logs.

    Attributes
    ----------
    data_dir : str
        The folder searched.
    n_found, n_analysed : int
        Logs found, and logs read into the analysis.
    skipped : tuple of (path, reason)
        Logs left out, paths relative to ``data_dir``.
    line_problems : tuple of (log, problem, action)
        Problems inside logs that were read (e.g. a truncated last line).
    rig_warnings : tuple of str
        Participants whose sessions ran on different rig records
        (:func:`masking_lab.analysis.rig_check.rig_changes`).
    """

    data_dir: str
    n_found: int
    n_analysed: int
    skipped: tuple[tuple[str, str], ...]
    line_problems: tuple[tuple[str, str, str], ...]
    rig_warnings: tuple[str, ...] = ()


@dataclass(frozen=True)
class ShiftsTableInput:
    """The input of ``fit``: a table of AL shifts.

    Attributes
    ----------
    path : str
        The CSV file as given.
    n_rows : int
        Data rows.
    n_participants : int or None
        Distinct participants (None: a table of cell means without participants).
    """

    path: str
    n_rows: int
    n_participants: int | None


@dataclass(frozen=True)
class ExcludedSet:
    """A staircase set that is not averaged into any threshold (``analyze`` only).

    Attributes
    ----------
    participant, experiment, set_id : str
        Where the set comes from.
    target : str
        Target stimulus.
    masker : str or None
        Masker stimulus (None for an unmasked set).
    masker_level_db_sl : float or None
        Masker level, dB SL (None for an unmasked set).
    status : str
        Why it is excluded (``incomplete``, ``superseded``, ...).
    note : str
        Details (may be empty).
    """

    participant: str
    experiment: str
    set_id: str
    target: str
    masker: str | None
    masker_level_db_sl: float | None
    status: str
    note: str


@dataclass(frozen=True)
class ThresholdsSection:
    """The status of every set's threshold (``analyze`` only).

    Attributes
    ----------
    status_counts : tuple of (status, count)
        Sets by status, sorted by status.
    excluded : tuple of ExcludedSet
        Sets that are not ``completed``, in table order.
    unmasked_sources : tuple of (source, count)
        Where the unmasked ALs of the masked sets come from, sorted by source.
    model_notes : tuple of (note, count)
        What the 95 % intervals of completed sets assume (a Bayesian procedure with a stated
        slope or lapse: :func:`masking_lab.procedures.model_note.stated_model_note`), with the
        number of sets, sorted by note.
    """

    status_counts: tuple[tuple[str, int], ...]
    excluded: tuple[ExcludedSet, ...]
    unmasked_sources: tuple[tuple[str, int], ...]
    model_notes: tuple[tuple[str, int], ...] = ()


@dataclass(frozen=True)
class ShiftCell:
    """The mean AL shift of one cell (frequency level × masker level).

    Attributes
    ----------
    mean_shift_db : float
        Mean AL shift, dB.
    tested : bool
        Whether a one-sample t-test against 0 was run (it needs participants).
    p : float or None
        Its two-tailed p (None if untested or not computable).
    differs_from_zero : bool or None
        ``p < test_alpha`` (None if there is no p).
    se_db : float or None
        Standard error of the mean shift, dB (None without participants or for n < 2).
    note : str or None
        Why a test could not be computed (e.g. zero variance), if it could not.
    """

    mean_shift_db: float
    tested: bool
    p: float | None
    differs_from_zero: bool | None
    se_db: float | None = None
    note: str | None = None


@dataclass(frozen=True)
class ShiftRow:
    """One frequency level's row of the shift grid.

    Attributes
    ----------
    mv_stimulus : str
        The frequency level (MV stimulus of the pair).
    cells : tuple of ShiftCell or None
        One per masker level of :attr:`ExperimentSection.masker_levels_db_sl` (None: no data).
    """

    mv_stimulus: str
    cells: tuple[ShiftCell | None, ...]


@dataclass(frozen=True)
class ExperimentSection:
    """Everything the report shows about one experiment.

    Attributes
    ----------
    experiment : str
        Experiment id.
    frequency_levels : tuple of (mv_stimulus, target, masker)
        The frequency factor's levels and the pair each belongs to.
    participants : tuple of str
        Participants with shifts (empty for a table of means).
    notes : tuple of str
        What could not be run, and why.
    anova_n : int
        Participants in the ANOVA and paired tests.
    anova : tuple of Effect
        ANOVA effects with Mauchly's test (empty if not run).
    posthoc : tuple of PairedTest
        Bonferroni paired comparisons between frequency levels (empty if not run).
    tested : bool
        Whether the cells were tested against 0.
    masker_levels_db_sl : tuple of float
        Columns of the shift grid, dB SL, ascending.
    shifts : tuple of ShiftRow
        The shift grid, one row per frequency level.
    pooling : PoolingDecision
        Groups pooled into one ramp, the rule and the reasons.
    fits : tuple of GroupFit
        One ramp per pooled group.
    """

    experiment: str
    frequency_levels: tuple[tuple[str, str, str], ...]
    participants: tuple[str, ...]
    notes: tuple[str, ...]
    anova_n: int
    anova: tuple[Effect, ...]
    posthoc: tuple[PairedTest, ...]
    tested: bool
    masker_levels_db_sl: tuple[float, ...]
    shifts: tuple[ShiftRow, ...]
    pooling: PoolingDecision
    fits: tuple[GroupFit, ...]

    @property
    def untestable(self) -> bool:
        """Whether a tested cell has no p (its test could not be computed)."""
        return any(c is not None and c.tested and c.p is None for r in self.shifts for c in r.cells)


@dataclass(frozen=True)
class ReportModel:
    """The whole report.

    Attributes
    ----------
    source : {"analyze", "fit"}
        The command that made it.
    software_version : str
        masking-lab version.
    inputs : LogsInput or ShiftsTableInput
        What was read.
    settings : tuple of (name, text)
        Settings that shape the numbers (as in the export's provenance), as display text: a
        setting left at its default says what the default does (never ``None``).
    thresholds : ThresholdsSection or None
        Threshold status (None for ``fit``).
    experiments : tuple of ExperimentSection
        One per experiment, sorted by id.
    export_notes : tuple of str
        Notes on the export (pairs fitted in two experiments).
    warnings : tuple of str
        What the experimenter should look at (notes, ramps not fitted).
    provenance : tuple of (path, sha256)
        Every input file read, as recorded in ``masking_params.json``.
    created_utc : str
        ``created_utc`` of the export (``YYYY-MM-DDTHH:MM:SSZ``; empty if not exported).
    lab : LabSection or None
        Study status, participants, psychometric functions and the figure list (``analyze``).
    """

    source: str
    software_version: str
    inputs: LogsInput | ShiftsTableInput
    settings: tuple[tuple[str, str], ...]
    thresholds: ThresholdsSection | None
    experiments: tuple[ExperimentSection, ...]
    export_notes: tuple[str, ...]
    warnings: tuple[str, ...] = ()
    provenance: tuple[tuple[str, str], ...] = ()
    created_utc: str = ""
    lab: LabSection | None = None

    @property
    def created_text(self) -> str:
        """``created_utc`` as a reader should take it: the fixed placeholder is not a date.

        Examples
        --------
        >>> from masking_lab.analysis.settings import EPOCH_UTC, AnalysisSettings
        >>> m = build_report([], AnalysisSettings(), source="fit",
        ...                  inputs=ShiftsTableInput("s.csv", 0, None), created_utc=EPOCH_UTC)
        >>> m.created_text.split(";")[0]
        'undated (a shifts table has no session dates)'
        """
        if not self.created_utc:
            return "—"
        if self.created_utc == EPOCH_UTC:
            why = "a shifts table has no session dates" if self.source == "fit" else "no dates"
            return (
                f"undated ({why}); created_utc holds the fixed placeholder {EPOCH_UTC} so "
                "reruns give the same bytes: pass --created-utc to date the export"
            )
        return self.created_utc


def experiment_heading(experiment: str) -> str:
    """The heading of an experiment's section: ``Experiment II`` or ``experiment1``, never
    ``Experiment experiment1``.

    Examples
    --------
    >>> experiment_heading("experiment1"), experiment_heading("EV270|MV")
    ('experiment1', 'Experiment EV270|MV')
    """
    return experiment if experiment.lower().startswith("experiment") else f"Experiment {experiment}"


# --------------------------------------------------------------------------------------------
# Building the model


def build_report(
    results: Sequence[ExperimentResult],
    settings: AnalysisSettings,
    *,
    source: str,
    inputs: LogsInput | ShiftsTableInput,
    thresholds: pd.DataFrame | None = None,
    export_notes: Sequence[str] = (),
    provenance: Sequence[Mapping[str, str]] = (),
    created_utc: str = "",
    lab: LabSection | None = None,
) -> ReportModel:
    """Gather the numbers of the report from the analysis results.

    Parameters
    ----------
    results : sequence of ExperimentResult
        Per-experiment results (may be empty when no masked set was completed).
    settings : AnalysisSettings
        The settings of the run (``test_alpha`` marks the shift grid).
    source : {"analyze", "fit"}
        The command.
    inputs : LogsInput or ShiftsTableInput
        What was read.
    thresholds : DataFrame or None
        The thresholds table of ``analyze`` (columns of :mod:`masking_lab.analysis.thresholds`).
    export_notes : sequence of str
        Notes from :func:`masking_lab.analysis.export.masking_params_document`.
    provenance : sequence of mapping
        Input files read (``path``, ``sha256``).
    created_utc : str
        ``created_utc`` of the export.
    lab : LabSection, optional
        The per-participant sections (``analyze``).

    Returns
    -------
    ReportModel

    Examples
    --------
    >>> from masking_lab.analysis.settings import EPOCH_UTC, AnalysisSettings
    >>> model = build_report(
    ...     [], AnalysisSettings(), source="fit", inputs=ShiftsTableInput("s.csv", 0, None)
    ... )
    >>> model.experiments, model.thresholds
    ((), None)
    """
    return ReportModel(
        source=source,
        software_version=__version__,
        inputs=inputs,
        settings=tuple(
            (
                k,
                _created_text(source, created_utc)
                if k == "created_utc" and v is None
                else setting_text(k, v),
            )
            for k, v in settings.as_dict(source).items()
        ),
        thresholds=None if thresholds is None else _thresholds_section(thresholds),
        experiments=tuple(_experiment_section(r, settings.test_alpha) for r in results),
        export_notes=tuple(export_notes),
        warnings=tuple(result_warnings(results))
        + (inputs.rig_warnings if isinstance(inputs, LogsInput) else ()),
        provenance=tuple((str(i["path"]), str(i["sha256"])) for i in provenance),
        created_utc=created_utc,
        lab=lab,
    )


def _created_text(source: str, created_utc: str) -> str:
    """What ``created_utc`` left at its default became, and why."""
    if source == "fit":
        return f"{created_utc or 'fixed'} (fixed default, so reruns give the same bytes)"
    return (
        f"{created_utc} (derived from the data: latest session header)"
        if created_utc
        else (_DEFAULT_MEANING["created_utc"])
    )


# What a setting left at None means, so the report never prints "None".
_DEFAULT_MEANING = {
    "n_reversals_averaged": "as logged (the n_reversals_averaged of each set)",
    "created_utc": "derived from the data (latest session header)",
}


def setting_text(name: str, value: Any) -> str:
    """A setting's value as the report shows it.

    Parameters
    ----------
    name : str
        Setting name (a key of :meth:`AnalysisSettings.as_dict`).
    value : object
        Its value (JSON types).

    Returns
    -------
    str
        ``None`` becomes what the default does, an empty list ``none``, a list its items joined
        by ``, ``.

    Examples
    --------
    >>> setting_text("n_reversals_averaged", None), setting_text("pool_groups", [])
    ('as logged (the n_reversals_averaged of each set)', 'none')
    >>> setting_text("n_boot", 2000)
    '2000'
    """
    if value is None:
        return _DEFAULT_MEANING.get(name, "default")
    if isinstance(value, list | tuple):
        return ", ".join(str(v) for v in value) or "none"
    return str(value)


def _thresholds_section(thresholds: pd.DataFrame) -> ThresholdsSection:
    counts = thresholds["status"].value_counts().sort_index()
    sources = thresholds["unmasked_source"].dropna().value_counts().sort_index()
    excluded = thresholds[thresholds["status"] != "completed"]
    return ThresholdsSection(
        status_counts=tuple((str(k), int(v)) for k, v in counts.items()),
        excluded=tuple(
            ExcludedSet(
                participant=str(r["participant"]),
                experiment=str(r["experiment"]),
                set_id=str(r["set_id"]),
                target=str(r["target"]),
                masker=None if r["masker"] is None else str(r["masker"]),
                masker_level_db_sl=(
                    None if r["masker_level_db_sl"] is None else float(r["masker_level_db_sl"])
                ),
                status=str(r["status"]),
                note=str(r["note"] or ""),
            )
            for _, r in excluded.iterrows()
        ),
        unmasked_sources=tuple((str(k), int(v)) for k, v in sources.items()),
        model_notes=_model_notes(thresholds),
    )


def _model_notes(thresholds: pd.DataFrame) -> tuple[tuple[str, int], ...]:
    """Distinct interval caveats of sets that have an interval, with their counts."""
    from masking_lab.procedures.model_note import STATED_MODEL

    if not {"al_ci95_low_db", "note"} <= set(thresholds.columns):
        return ()
    notes = thresholds.loc[thresholds["al_ci95_low_db"].notna(), "note"].dropna().astype(str)
    counts = notes[notes.str.startswith(STATED_MODEL)].value_counts().sort_index()
    return tuple((str(k), int(v)) for k, v in counts.items())


def _experiment_section(r: ExperimentResult, test_alpha: float) -> ExperimentSection:
    levels_db = tuple(sorted({c.masker_level_db_sl for c in r.cells}))
    by_key = {(c.mv_stimulus, c.masker_level_db_sl): c for c in reversed(r.cells)}
    rows = []
    for lv in r.levels:
        cells: list[ShiftCell | None] = []
        for x in levels_db:
            c = by_key.get((lv, x))
            if c is None:
                cells.append(None)
                continue
            p = None if c.test is None else c.test.p
            cells.append(
                ShiftCell(
                    mean_shift_db=c.mean_shift_db,
                    tested=c.test is not None,
                    p=p,
                    differs_from_zero=None if p is None else bool(p < test_alpha),
                    se_db=None if c.test is None else c.test.se,
                    note=None if c.test is None else c.test.note,
                )
            )
        rows.append(ShiftRow(lv, tuple(cells)))
    return ExperimentSection(
        experiment=r.experiment,
        frequency_levels=tuple((lv, *r.pair_of_level[lv]) for lv in r.levels),
        participants=r.participants,
        notes=r.notes,
        anova_n=len(r.anova_participants),
        anova=r.anova,
        posthoc=r.posthoc or (),
        tested=any(c.test is not None for c in r.cells),
        masker_levels_db_sl=levels_db,
        shifts=tuple(rows),
        pooling=r.pooling,
        fits=r.fits,
    )
