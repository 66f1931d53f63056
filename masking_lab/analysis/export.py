"""What an analysis writes: the ``masking_params.json`` document and every output file.

:func:`masking_params_document` turns the ramp fits into the export (one entry per pair, with
provenance); :func:`write_outputs` writes the tables, the export, the report and the
masking-function figures through :mod:`masking_lab.formats` (atomic, byte-stable writes).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import pandas as pd

from masking_lab import __version__
from masking_lab.analysis.experiment import ExperimentResult
from masking_lab.analysis.figure_pool import FigurePool
from masking_lab.analysis.report import LogsInput, ShiftsTableInput, build_report
from masking_lab.analysis.report_html import prepare_html, render_html
from masking_lab.analysis.report_lab import LabSection
from masking_lab.analysis.report_text import render_text
from masking_lab.analysis.settings import AnalysisSettings
from masking_lab.analysis.tables import (
    ANOVA_COLUMNS,
    FIT_COLUMNS,
    ONE_SAMPLE_COLUMNS,
    POSTHOC_COLUMNS,
    SPHERICITY_COLUMNS,
    effect_rows,
    fit_rows,
    one_sample_rows,
)
from masking_lab.formats.csv_table import csv_text
from masking_lab.formats.fileio import write_bytes_atomic, write_text_atomic
from masking_lab.formats.masking_params import draws_field, masking_params_json

__all__ = ["determination", "masking_params_document", "start_masking_figures", "write_outputs"]


# A fitted ramp is "poorly determined" when its slope interval reaches 0 (masking not shown to
# grow with the masker) or an interval is wider than these limits (dB; dB/dB).
MAX_INTERCEPT_CI_WIDTH_DB = 10.0
MAX_SLOPE_CI_WIDTH = 1.0


def determination(
    status: str,
    intercept_ci_db: tuple[float, float] | None,
    slope_ci: tuple[float, float] | None,
) -> dict[str, Any]:
    """``poorly_determined`` and ``determination`` (why, or None) of an exported function.

    Examples
    --------
    >>> determination("fitted", (1.0, 3.0), (-0.34, 1.36))["determination"]
    'slope interval [-0.34, 1.36] includes 0; slope interval 1.7 wider than 1'
    >>> determination("fitted", (1.0, 3.0), (0.4, 0.6))
    {'poorly_determined': False, 'determination': None}
    """
    why = []
    if status == "fitted":
        if slope_ci is not None and slope_ci[0] <= 0.0 <= slope_ci[1]:
            why.append(f"slope interval [{slope_ci[0]:.2f}, {slope_ci[1]:.2f}] includes 0")
        if slope_ci is not None and slope_ci[1] - slope_ci[0] > MAX_SLOPE_CI_WIDTH:
            why.append(
                f"slope interval {slope_ci[1] - slope_ci[0]:.2g} wider than {MAX_SLOPE_CI_WIDTH:g}"
            )
        if (
            intercept_ci_db is not None
            and intercept_ci_db[1] - intercept_ci_db[0] > MAX_INTERCEPT_CI_WIDTH_DB
        ):
            width = intercept_ci_db[1] - intercept_ci_db[0]
            why.append(
                f"intercept interval {width:.3g} dB wider than {MAX_INTERCEPT_CI_WIDTH_DB:g} dB"
            )
    return {"poorly_determined": bool(why), "determination": "; ".join(why) or None}


def masking_params_document(
    results: Sequence[ExperimentResult],
    settings: AnalysisSettings,
    *,
    source: str,
    inputs: Sequence[Mapping[str, str]],
    skipped: Sequence[Mapping[str, str]] = (),
    created_utc: str,
) -> tuple[dict[str, Any], list[str]]:
    """The masking_params.json document, and notes on pairs dropped as duplicates.

    Parameters
    ----------
    results : sequence of ExperimentResult
        Per-experiment results; a pair fitted in two experiments is kept from the first.
    settings : AnalysisSettings
        Recorded in the provenance.
    source : {"analyze", "fit"}
        The command.
    inputs, skipped : sequence of mapping
        Files read (``path``, ``sha256``) and files left out (``path``, ``reason``).
    created_utc : str
        ``YYYY-MM-DDTHH:MM:SSZ``.

    Returns
    -------
    doc : dict
        The document (JSON types); intercepts in dB, slopes in dB per dB SL, ranges in dB SL.
    notes : list of str
        One per pair dropped as a duplicate.

    Examples
    --------
    >>> doc, notes = masking_params_document(
    ...     [], AnalysisSettings(), source="fit", inputs=[], created_utc="1970-01-01T00:00:00Z"
    ... )
    >>> doc["functions"], notes
    ([], [])
    """
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
                    "estimate": "paper_route",
                    **determination(f.status, f.intercept_ci_db, f.slope_ci),
                    **_joint_uncertainty(f.intercept_slope_cov, f.draws, f.n_boot_failed, settings),
                }
                if entries[(target, masker)]["poorly_determined"]:
                    why = entries[(target, masker)]["determination"]
                    note = f"{target}|{masker} is poorly determined: {why}"
                    if note not in notes:
                        notes.append(note)
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


def _joint_uncertainty(
    cov: float | None,
    draws: Sequence[tuple[float, float]],
    n_failed: int,
    settings: AnalysisSettings,
) -> dict[str, Any]:
    """The optional ``intercept_slope_cov`` and ``draws`` keys (absent when unknown)."""
    out: dict[str, Any] = {}
    if cov is not None and math.isfinite(cov):
        out["intercept_slope_cov"] = cov
    if draws:
        n_replicates = max(settings.n_boot - n_failed, len(draws))
        field = draws_field("bootstrap", settings.seed, n_replicates, draws)
        if field is not None:
            out["draws"] = field
    return out


def start_masking_figures(
    results: Sequence[ExperimentResult],
    settings: AnalysisSettings,
    figure_pool: FigurePool | None = None,
) -> dict[str, Callable[[], bytes]]:
    """Start drawing each experiment's masking-function figure (``figures/masking_<e>.png``).

    Parameters
    ----------
    results : sequence of ExperimentResult
        Per-experiment results.
    settings : AnalysisSettings
        ``figures`` = ``"none"`` draws nothing (an empty mapping).
    figure_pool : FigurePool, optional
        Where they are drawn (default: in-process, when asked for).

    Returns
    -------
    dict
        Experiment id → a callable giving the figure's PNG bytes (waits for its worker).
    """
    if settings.figures == "none":
        return {}
    from masking_lab.analysis.figures import experiment_figure_data, masking_function_png

    pool = figure_pool or FigurePool(enabled=False)
    return {
        r.experiment: pool.submit(masking_function_png, **experiment_figure_data(r))
        for r in results
    }


def write_outputs(
    out: Path,
    results: Sequence[ExperimentResult],
    settings: AnalysisSettings,
    *,
    source: str,
    inputs: Sequence[Mapping[str, str]],
    skipped: Sequence[Mapping[str, str]],
    created_utc: str,
    report_inputs: LogsInput | ShiftsTableInput,
    thresholds: pd.DataFrame | None,
    lab: LabSection | None = None,
    figure_pool: FigurePool | None = None,
    lab_embedded: Callable[[], tuple[tuple[str, str], ...]] | None = None,
    masking_figures: Mapping[str, Callable[[], bytes]] | None = None,
    params_json: str | None = None,
) -> list[Path]:
    """Write the statistics tables, ``masking_params.json``, the reports and the figures.

    The reports are ``report.txt`` and ``report.html`` (the same model; the HTML embeds the
    figures).

    Parameters
    ----------
    out : Path
        Output folder (made if missing).
    results : sequence of ExperimentResult
        Per-experiment results.
    settings : AnalysisSettings
        Settings of the run (``figures`` = ``"none"`` draws nothing).
    source : {"analyze", "fit"}
        The command.
    inputs, skipped : sequence of mapping
        Provenance of the export (see :func:`masking_params_document`).
    created_utc : str
        ``created_utc`` of the export.
    report_inputs : LogsInput or ShiftsTableInput
        What the report says was read.
    thresholds : DataFrame or None
        The thresholds table (``analyze``), for the report.
    lab : LabSection, optional
        The per-participant sections of ``analyze`` (the masking figures join its figure list).
    figure_pool : FigurePool, optional
        Where the masking-function figures are drawn, while the tables and reports are
        written (default: in-process).
    lab_embedded : callable, optional
        Gives the ``lab`` section's embedded figures, (path, data URI) pairs, when
        ``report.html`` is rendered (:meth:`~masking_lab.analysis.lab_outputs.LabOutputs.finished`:
        the AL-shift figures are still being drawn while the statistics are written).
    masking_figures : mapping, optional
        The masking-function figures, already started by :func:`start_masking_figures` for
        these ``results`` and ``settings`` (default: started here).
    params_json : str, optional
        The text of ``masking_params.json`` for these arguments, already made (``analyze``
        hands it to its caller early; default: made here).

    Returns
    -------
    list of Path
        The files written, in order.

    Examples
    --------
    >>> write_outputs(  # doctest: +SKIP
    ...     Path("out"), results, settings, source="fit", inputs=inputs, skipped=(),
    ...     created_utc="1970-01-01T00:00:00Z", report_inputs=table, thresholds=None,
    ... )
    """
    drawing = masking_figures
    if drawing is None:
        drawing = start_masking_figures(results, settings, figure_pool)
    doc, export_notes = masking_params_document(
        results, settings, source=source, inputs=inputs, skipped=skipped, created_utc=created_utc
    )
    if lab is not None and settings.figures != "none":
        from masking_lab.analysis.figures import safe_stem

        masking = tuple(
            (
                f"figures/masking_{safe_stem(r.experiment)}.png",
                f"masking functions of {r.experiment}",
            )
            for r in results
        )
        lab = replace(lab, figures=masking + lab.figures)
    report = build_report(
        results,
        settings,
        source=source,
        inputs=report_inputs,
        thresholds=thresholds,
        export_notes=export_notes,
        provenance=inputs,
        created_utc=created_utc,
        lab=lab,
    )
    tables = [
        ("anova.csv", ANOVA_COLUMNS, effect_rows(results, "anova")),
        ("sphericity.csv", SPHERICITY_COLUMNS, effect_rows(results, "sphericity")),
        ("posthoc.csv", POSTHOC_COLUMNS, effect_rows(results, "posthoc")),
        ("one_sample.csv", ONE_SAMPLE_COLUMNS, one_sample_rows(results, settings.test_alpha)),
        ("ramp_fits.csv", FIT_COLUMNS, fit_rows(results)),
    ]
    files = [write_text_atomic(out / name, csv_text(cols, rows)) for name, cols, rows in tables]
    if params_json is None:
        params_json = masking_params_json(doc)
    files.append(write_text_atomic(out / "masking_params.json", params_json))
    files.append(write_text_atomic(out / "report.txt", render_text(report)))
    figures: dict[str, bytes] = {}
    if settings.figures != "none":
        from masking_lab.analysis.figures import safe_stem

        prepare_html()  # while the figures are drawn

        for r in results:
            figures[r.experiment] = drawing[r.experiment]()
            path = out / "figures" / f"masking_{safe_stem(r.experiment)}.png"
            files.append(write_bytes_atomic(path, figures[r.experiment]))
    if lab_embedded is not None and report.lab is not None:
        report = replace(report, lab=replace(report.lab, embedded=lab_embedded()))
    files.append(write_text_atomic(out / "report.html", render_html(report, figures)))
    return files
