"""The imperative shell of the analysis: read inputs, run the analysis, write the outputs.

:func:`run_analyze` reads every session log under a folder (``masking-lab analyze``);
:func:`run_fit` reads a long CSV of AL shifts (``masking-lab fit``). Both hand the shifts to
:func:`masking_lab.analysis.experiment.analyze_shifts` and write through
:func:`masking_lab.analysis.export.write_outputs`; :func:`progress_printer` shows how many logs
have been read.

Outputs are deterministic: same inputs and settings, same bytes (sorted inputs, fixed float
formats, seeded bootstrap with a seed per experiment and group, no wall-clock time anywhere;
``created_utc`` comes from a setting or from the data, see docs/analysis.md).
"""

from __future__ import annotations

import gc
import hashlib
import os
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from masking_lab.analysis import freed_memory
from masking_lab.analysis.data_folder import data_folder, find_logs
from masking_lab.analysis.figure_pool import FigurePool
from masking_lab.analysis.log_checks import duplicate_sessions, refused_sets, repeated_sessions
from masking_lab.analysis.log_reading import PARALLEL_FROM, read_logs
from masking_lab.analysis.rig_check import RigUse, rig_changes, rig_use
from masking_lab.analysis.settings import EPOCH_UTC, AnalysisSettings, is_utc_stamp
from masking_lab.analysis.thresholds import COLUMNS as THRESHOLD_COLUMNS
from masking_lab.analysis.thresholds import (
    EstimatorSettings,
    shifts_long,
    thresholds_table,
    unpacked,
)
from masking_lab.core.blas_threads import one_blas_thread
from masking_lab.core.errors import AnalysisError
from masking_lab.core.worker_processes import Beside
from masking_lab.formats.csv_table import csv_column_blocks, csv_text
from masking_lab.formats.fileio import write_text_atomic, write_text_chunks_atomic
from masking_lab.formats.output_dir import staged_output

if TYPE_CHECKING:
    import pandas as pd

    from masking_lab.analysis.lab_outputs import LabOutputs, ShiftFigures
    from masking_lab.analysis.track_figures import TrackJob
    from masking_lab.formats.session_log import SessionLog

__all__ = ["RunSummary", "find_logs", "progress_printer", "run_analyze", "run_fit"]


@dataclass
class RunSummary:
    """What a run wrote and what it warns about."""

    out_dir: Path
    files: list[Path]
    warnings: list[str]


def _skip_reason(header: dict) -> str | None:
    """Why a readable log is not analysed, or None."""
    protocol = header.get("protocol")
    if (
        not isinstance(protocol, dict)
        or "experiment" not in protocol
        or "participant" not in header
    ):
        return "header lacks participant or protocol.experiment"
    if header.get("kind") == "usertest":
        return "a user-test log (no staircases): analyse it with masking-lab usertest-report"
    return None


def run_analyze(
    data_dir: str | Path,
    out_dir: str | Path,
    settings: AnalysisSettings,
    *,
    progress: Callable[[int, int], None] | None = None,
    fit_progress: Callable[[int, int], None] | None = None,
    figure_pool: FigurePool | None = None,
    on_params: Callable[[str], None] | None = None,
) -> RunSummary:
    """Analyse every session log under ``data_dir`` and write every output into ``out_dir``.

    Unreadable or truncated logs are reported (report, ``problems.csv``, provenance) and the run
    continues. The outputs are written into a fresh sibling folder that replaces ``out_dir``
    only when the run completes (:func:`masking_lab.formats.output_dir.staged_output`).

    Parameters
    ----------
    data_dir : str or Path
        Folder of session logs (searched recursively).
    out_dir : str or Path
        Output folder: missing, empty or a previous run's outputs (replaced as a whole).
    settings : AnalysisSettings
        Estimation, statistics, export and figure settings.
    progress : callable or None
        Called with (logs read, logs found).
    fit_progress : callable or None
        Called with (sets fitted, sets to fit) for ``psychometric.csv``.
    figure_pool : FigurePool, optional
        The worker drawing the summary figures, started early by the caller so that it loads
        matplotlib while this process loads the analysis (default: started here); closed
        when the run ends.
    on_params : callable, optional
        Called once with the text of ``masking_params.json`` (the bytes the run will write)
        as soon as the ramp fits are done, before the psychometric fits: the demo renders its
        scene from it while the rest is written. For a small study with trial tables, the
        statistics and ramp fits run in a worker of their own while this process reads the
        logs again for the per-trial outputs (the same numbers: every bootstrap has its own
        seed). Not called when there is no masked set to export.

    Returns
    -------
    RunSummary
        Files written (paths inside ``out_dir``) and warnings.

    Raises
    ------
    AnalysisError
        If the folder has no readable log or no completed masked set (``thresholds.csv`` and the
        report are written first in the latter case); the previous results stay in place.

    Examples
    --------
    >>> run_analyze("data", "analysis", AnalysisSettings())  # doctest: +SKIP
    """
    data, out = data_folder(data_dir), Path(out_dir)
    if figure_pool is None:
        figure_pool = FigurePool(settings.figures != "none")
    try:
        with staged_output(out, protect=[data]) as staging:
            summary = _analyze_into(
                data, staging, settings, progress, fit_progress, figure_pool, on_params
            )
    except BaseException:  # a failed run does not wait for its figures
        figure_pool.close(cancel=True)
        raise
    finally:  # what the run froze is collectable again for a caller that goes on
        gc.unfreeze()
    figure_pool.close()
    return _moved(summary, staging, out)


def _moved(summary: RunSummary, staging: Path, out: Path) -> RunSummary:
    """The summary with paths pointing into ``out`` instead of the staging folder."""
    files = [out / p.relative_to(staging) for p in summary.files]
    return RunSummary(out, files, summary.warnings)


def _analyze_into(
    data: Path,
    out: Path,
    settings: AnalysisSettings,
    progress: Callable[[int, int], None] | None,
    fit_progress: Callable[[int, int], None] | None = None,
    figure_pool: FigurePool | None = None,
    on_params: Callable[[str], None] | None = None,
) -> RunSummary:
    """The analysis of :func:`run_analyze`, writing into ``out`` (the staging folder)."""
    from masking_lab.formats.session_log import read_log

    paths = find_logs(data)
    if not paths:
        raise AnalysisError(f"{data}: no session logs (*.jsonl) found")
    est = EstimatorSettings(settings.estimator, settings.n_reversals_averaged, settings.lapse)
    rows: list[tuple] = []  # packed (thresholds.packed): a third of the memory of dicts
    inputs: list[dict[str, str]] = []
    skipped: list[dict[str, str]] = []
    problems: list[dict[str, str]] = []
    created: list[str] = []
    files: list[Path] = []
    tracks: list[TrackJob] = []
    rigs: list[RigUse] = []
    analysed: set[str] = set()  # rel paths, for the cross-log checks
    analysed_logs: list[Path] = []  # paths that may hold functional-procedure sets
    sessions: list[Any] = []  # each analysed log's session, for the study matrix
    if figure_pool is not None and len(paths) >= PARALLEL_FROM and settings.figures != "none":
        # A large study's shift figures take seconds each and are drawn by two workers (the
        # second forked from the first; a second pool where processes cannot be forked).
        figure_pool.widen(2)
    # One read per log (hashed and parsed from the same bytes), in parallel for many logs: the
    # workers start at once, forked before the statistics' modules (pandas, SciPy) are loaded,
    # and this process loads those while they read.
    reading = read_logs(paths, data, est, progress=progress)
    if len(paths) >= PARALLEL_FROM:  # loaded while the workers read
        _load_statistics()
        freed_memory.return_early()  # after the workers are forked: only this process's
        gc.freeze()  # the modules' objects live to the end: no collection need visit them
    results = list(reading)
    gc.freeze()  # nor the read results' (at 10,000 sessions ~0.2 s of collections after this)
    copies = duplicate_sessions(results)
    for res in results:
        rel = res.rel
        if res.error is not None:
            reason: str | None = res.error
        else:
            problems += [
                {"log": rel, "problem": pr, "action": "line ignored"} for pr in res.line_problems
            ]
            reason = copies.get(rel) or _skip_reason(res.header)
        if reason is not None:
            skipped.append({"path": rel, "reason": reason})
            problems.append({"log": rel, "problem": reason, "action": "file skipped"})
        else:
            h = res.header
            problems += [
                {"log": rel, "problem": pr, "action": "records kept; check the log"}
                for pr in res.continuity
            ]
            problems += refused_sets(res)
            inputs.append({"path": rel, "sha256": res.sha256})
            analysed.add(rel)
            rigs.append(rig_use(h, rel))
            if isinstance(h.get("created_utc"), str) and is_utc_stamp(h["created_utc"]):
                created.append(h["created_utc"])
            rows.extend(res.rows)
            if res.may_hold_functional:  # read off the records of the one read
                analysed_logs.append(res.path)
            sessions.append(res.session)
            if settings.figures == "all":
                tracks.append(_track_job(out, read_log(res.path), unpacked(res.rows)))
        # The rows live on in ``rows`` only, so thresholds_table(consume=True) can free them
        # (at 10,000 sessions the result kept them: ~50 MB held to the end of the run); of the
        # header, only what the cross-log check below reads (the whole header: ~20 MB).
        res.rows = []
        res.header = _cross_log_fields(res.header)
    problems += repeated_sessions([r for r in results if r.rel in analysed])
    del results, reading  # each log's result (at 10,000 sessions ~10 MB): what is kept is above
    if not inputs:
        raise AnalysisError(
            f"{data}: none of the {len(paths)} log file(s) could be read; first problem: "
            f"{problems[0]['log']}: {problems[0]['problem']}"
        )
    track_files: list[Path] = []
    if tracks:
        from masking_lab.analysis.track_figures import draw_tracks

        track_files = draw_tracks(tracks, workers=min(4, os.cpu_count() or 1))
        files += track_files
    thresholds = thresholds_table(rows, unmasked_al=settings.unmasked_al, consume=True)
    freed_memory.trim()  # the rows' and the read results' memory, before the tables grow
    # The AL-shift figures need only the thresholds: their drawing starts before the
    # statistics' modules load (a small study reads its logs here, with nothing to overlap).
    from masking_lab.analysis.lab_outputs import start_shift_figures

    shift_figures = start_shift_figures(thresholds, settings.figures, figure_pool)
    _load_statistics()
    from masking_lab.analysis.experiment import result_warnings
    from masking_lab.analysis.export import write_outputs
    from masking_lab.analysis.report import LogsInput, build_report
    from masking_lab.analysis.report_html import render_html
    from masking_lab.analysis.report_text import render_text

    shifts = shifts_long(thresholds)
    created_utc = settings.created_utc or (max(created) if created else EPOCH_UTC)
    report_inputs = LogsInput(
        data_dir=str(data),
        n_found=len(paths),
        n_analysed=len(inputs),
        skipped=tuple((s["path"], s["reason"]) for s in skipped),
        line_problems=tuple(
            (p["log"], p["problem"], p["action"]) for p in problems if p["action"] != "file skipped"
        ),
        rig_warnings=tuple(rig_changes(rigs)),
    )
    # The statistics and ramp fits (~0.5 s for the demo's study) run in a worker of their own
    # while this process writes thresholds.csv and reads the logs again for the per-trial
    # outputs; the result is taken when that read is done, before the psychometric fits, so
    # the masking-function figures and a caller's export still come before those. Only where
    # a core is free for that worker: a large study's second read has workers of its own on
    # every core, and without trial tables there is nothing to read (at 10,000 sessions the
    # worker only added memory). Masker levels too close to tell apart are refused first.
    statistics: Beside[list[Any]] | None = None
    if not shifts.empty:
        from masking_lab.formats.shifts_csv import levels_told_apart

        levels_told_apart(shifts, str(data))
        beside = settings.trial_tables and len(inputs) < PARALLEL_FROM
        statistics = Beside(_statistics, shifts, settings, worker=beside)
    experiments: list[Any] | None = None
    masking_figures = params_json = None

    def statistics_done() -> None:
        """Take the statistics' result and start what follows it (``write_lab_outputs`` calls
        this once, after its read)."""
        nonlocal experiments, masking_figures, params_json
        if statistics is None:
            return
        from masking_lab.analysis.export import start_masking_figures

        experiments = statistics.result()
        masking_figures = start_masking_figures(experiments, settings, figure_pool)
        if on_params is not None:
            params_json = _params_text(experiments, settings, inputs, skipped, created_utc)
            on_params(params_json)

    with statistics or nullcontext():
        # Formatted column-wise and written a block of rows at a time; neither the column
        # lists (at 10,000 sessions ~25 MB) nor the whole text (~21 MB, twice while encoded)
        # is kept.
        columns = [thresholds[c].tolist() for c in THRESHOLD_COLUMNS]
        blocks = csv_column_blocks(THRESHOLD_COLUMNS, columns)
        files.append(write_text_chunks_atomic(out / "thresholds.csv", blocks))
        del columns, blocks
        problem_rows = csv_text(["log", "problem", "action"], problems)
        files.append(write_text_atomic(out / "problems.csv", problem_rows))
        warnings = [f"{p['log']}: {p['problem']} ({p['action']})" for p in problems]
        warnings += report_inputs.rig_warnings
        # Only the track figures are listed as such (files also holds thresholds.csv, ...).
        lab = _lab_outputs(
            data,
            out,
            [i["path"] for i in inputs],
            thresholds,
            settings,
            track_files,
            fit_progress,
            sessions,
            figure_pool,
            shift_figures,
            after_read=statistics_done,
        )
    files += lab.files
    warnings += lab.warnings
    if shifts.empty:
        ramp_files, ramp_problems = _functional_ramps(
            out, analysed_logs, inputs, settings, created_utc
        )
        report = build_report(
            [],
            settings,
            source="analyze",
            inputs=report_inputs,
            thresholds=thresholds,
            lab=lab.finished(),
        )
        files.append(write_text_atomic(out / "report.txt", render_text(report)))
        files.append(write_text_atomic(out / "report.html", render_html(report)))
        if ramp_files:  # functional-procedure logs: their ramps are the result
            return RunSummary(out, files + ramp_files, warnings + ramp_problems)
        raise AnalysisError(
            f"{data}: no completed masked set to analyse ({len(thresholds)} sets, none with an "
            "AL shift); see report.txt for the status of each set"
        )
    assert experiments is not None  # computed above: the shifts are not empty
    files += write_outputs(
        out,
        experiments,
        settings,
        source="analyze",
        inputs=inputs,
        skipped=skipped,
        created_utc=created_utc,
        report_inputs=report_inputs,
        thresholds=thresholds,
        lab=lab.section,
        figure_pool=figure_pool,
        lab_embedded=lambda: lab.finished().embedded,
        masking_figures=masking_figures,
        params_json=params_json,
    )
    warnings += result_warnings(experiments)
    ramp_files, ramp_problems = _functional_ramps(out, analysed_logs, inputs, settings, created_utc)
    return RunSummary(out, files + ramp_files, warnings + ramp_problems)


def _statistics(shifts: pd.DataFrame, settings: AnalysisSettings) -> list[Any]:
    """The per-experiment statistics and ramp fits of the AL shifts (dB), whose masker levels
    are told apart (:func:`~masking_lab.formats.shifts_csv.levels_told_apart`)."""
    from masking_lab.analysis.experiment import analyze_shifts

    freed_memory.trim()  # before the statistics' bootstrap
    with one_blas_thread():
        return analyze_shifts(shifts, settings, has_participants=True)


def _params_text(
    experiments: list[Any],
    settings: AnalysisSettings,
    inputs: list[dict[str, str]],
    skipped: list[dict[str, str]],
    created_utc: str,
) -> str:
    """The text of ``masking_params.json``, as :func:`~masking_lab.analysis.export.write_outputs`
    writes it."""
    from masking_lab.analysis.export import masking_params_document
    from masking_lab.formats.masking_params import masking_params_json

    doc, _ = masking_params_document(
        experiments, settings, source="analyze", inputs=inputs, skipped=skipped,
        created_utc=created_utc,
    )  # fmt: skip
    return masking_params_json(doc)


def _load_statistics() -> None:
    """Import the statistics, export and report modules (pandas, the fits, the templates)."""
    import masking_lab.analysis.experiment
    import masking_lab.analysis.export
    import masking_lab.analysis.report
    import masking_lab.analysis.report_html
    import masking_lab.analysis.report_text
    import masking_lab.formats.shifts_csv  # noqa: F401


def _cross_log_fields(header: dict[str, Any]) -> dict[str, Any]:
    """The header fields :func:`~masking_lab.analysis.log_checks.repeated_sessions` reads."""
    kept: dict[str, Any] = {
        k: header[k] for k in ("participant", "session_id", "created_utc") if k in header
    }
    protocol = header.get("protocol")
    if isinstance(protocol, dict):
        kept["protocol"] = {k: protocol[k] for k in ("experiment",) if k in protocol}
    return kept


def _functional_ramps(
    out: Path,
    logs: list[Path],
    inputs: list[dict[str, str]],
    settings: AnalysisSettings,
    created_utc: str,
) -> tuple[list[Path], list[str]]:
    """Ramp posteriors and group ramps of functional-procedure sets, if any (the procedures
    hook: analysis/functional_outputs.py)."""
    from masking_lab.analysis.functional_outputs import write_functional_outputs

    # ``logs``: only those with a functional set (LogResult.may_hold_functional, from the one read):
    # parsing every log again only to find no functional set would be a third read of the study.
    return write_functional_outputs(
        out, logs, inputs=inputs, settings=settings.as_dict("analyze"), created_utc=created_utc
    )


def _lab_outputs(
    data: Path,
    out: Path,
    logs: list[str],
    thresholds: pd.DataFrame,
    settings: AnalysisSettings,
    drawn: list[Path],
    fit_progress: Callable[[int, int], None] | None = None,
    sessions: list[Any] | None = None,
    figure_pool: FigurePool | None = None,
    shift_figures: ShiftFigures | None = None,
    *,
    after_read: Callable[[], None] | None = None,
) -> LabOutputs:
    """trials.csv, psychometric.csv, participants.tsv, the study status and their figures;
    ``after_read`` is called once the logs are read, before the psychometric fits."""
    from dataclasses import replace

    from masking_lab.analysis.lab_outputs import write_lab_outputs

    lab = write_lab_outputs(
        data,
        out,
        logs,
        thresholds,
        figures=settings.figures,
        n_boot=settings.pf_boot,
        trial_tables=settings.trial_tables,
        progress=fit_progress,
        sessions=sessions,
        figure_pool=figure_pool,
        shift_figures=shift_figures,
        after_read=after_read,
    )
    tracks = tuple(
        (p.relative_to(out).as_posix(), "staircase tracks of one session") for p in drawn
    )
    lab.section = replace(lab.section, figures=lab.section.figures + tracks)
    return lab


def _track_job(out: Path, log: SessionLog, rows: list[dict]) -> TrackJob:
    """The track figure of one session, to draw into ``out/figures/tracks``."""
    from masking_lab.analysis.figures import safe_stem
    from masking_lab.analysis.track_figures import track_job

    h = log.header
    als = {r["set_id"]: (r.get("al_db_sl") if r.get("masker") else r.get("al_db_v")) for r in rows}
    name = safe_stem(f"{h['participant']}_{h['protocol']['experiment']}_{h.get('session_id', '')}")
    return track_job(out / "figures" / "tracks" / f"{name}.png", log, als)


def run_fit(csv_path: str | Path, out_dir: str | Path, settings: AnalysisSettings) -> RunSummary:
    """Statistics, pooling, ramp fits and export from a long CSV of AL shifts.

    Parameters
    ----------
    csv_path : str or Path
        The long table of AL shifts (dB) against masker level (dB SL).
    out_dir : str or Path
        Output folder: missing, empty or a previous run's outputs (replaced as a whole when
        the run completes).
    settings : AnalysisSettings
        Pooling, uncertainty, export and figure settings.

    Returns
    -------
    RunSummary
        Files written (paths inside ``out_dir``) and warnings.

    Raises
    ------
    AnalysisError
        For an unreadable or malformed table (naming the line).

    Examples
    --------
    >>> run_fit("shifts.csv", "fit_out", AnalysisSettings(pooling="paired"))  # doctest: +SKIP
    """
    from masking_lab.analysis.experiment import analyze_shifts, result_warnings
    from masking_lab.analysis.export import write_outputs
    from masking_lab.analysis.report import ShiftsTableInput
    from masking_lab.formats.shifts_csv import read_shifts_csv

    path = Path(csv_path)
    out = Path(out_dir)
    with staged_output(out, protect=[path]) as staging:
        shifts, has_participants = read_shifts_csv(path)
        with one_blas_thread():  # as analyze: the same numbers on any machine
            results = analyze_shifts(shifts, settings, has_participants=has_participants)
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
        table = ShiftsTableInput(
            path=str(csv_path),
            n_rows=len(shifts),
            n_participants=int(shifts["participant"].nunique()) if has_participants else None,
        )
        files = write_outputs(
            staging,
            results,
            settings,
            source="fit",
            inputs=[{"path": str(csv_path), "sha256": digest}],
            skipped=(),
            created_utc=settings.created_utc or EPOCH_UTC,
            report_inputs=table,
            thresholds=None,
        )
    return _moved(RunSummary(out, files, result_warnings(results)), staging, out)


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
