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

import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from masking_lab.analysis.experiment import analyze_shifts, result_warnings
from masking_lab.analysis.export import write_outputs
from masking_lab.analysis.report import LogsInput, ShiftsTableInput, build_report
from masking_lab.analysis.report_text import render_text
from masking_lab.analysis.settings import EPOCH_UTC, AnalysisSettings, is_utc_stamp
from masking_lab.analysis.thresholds import COLUMNS as THRESHOLD_COLUMNS
from masking_lab.analysis.thresholds import (
    EstimatorSettings,
    session_rows,
    shifts_long,
    thresholds_table,
)
from masking_lab.core.errors import AnalysisError, LogError
from masking_lab.formats.csv_table import csv_text
from masking_lab.formats.fileio import write_text_atomic
from masking_lab.formats.shifts_csv import read_shifts_csv

if TYPE_CHECKING:
    from masking_lab.formats.session_log import SessionLog

__all__ = ["RunSummary", "find_logs", "progress_printer", "run_analyze", "run_fit"]


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
    files: list[Path] = []
    for i, path in enumerate(paths, start=1):
        rel = path.relative_to(data).as_posix()
        try:
            raw = path.read_bytes()
            log = read_log(path)
        except (OSError, LogError) as exc:
            reason: str | None = str(exc)
        else:
            problems += [
                {"log": rel, "problem": pr, "action": "line ignored"} for pr in log.problems
            ]
            reason = _skip_reason(log.header)
        if reason is not None:
            skipped.append({"path": rel, "reason": reason})
            problems.append({"log": rel, "problem": reason, "action": "file skipped"})
        else:
            h = log.header
            inputs.append({"path": rel, "sha256": hashlib.sha256(raw).hexdigest()})
            if isinstance(h.get("created_utc"), str) and is_utc_stamp(h["created_utc"]):
                created.append(h["created_utc"])
            new_rows = session_rows(log, rel, est)
            rows.extend(new_rows)
            if settings.figures == "all":
                files.append(_track_figure(out, log, new_rows))
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
    report_inputs = LogsInput(
        data_dir=str(data),
        n_found=len(paths),
        n_analysed=len(inputs),
        skipped=tuple((s["path"], s["reason"]) for s in skipped),
        line_problems=tuple(
            (p["log"], p["problem"], p["action"]) for p in problems if p["action"] != "file skipped"
        ),
    )
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
        report = build_report(
            [], settings, source="analyze", inputs=report_inputs, thresholds=thresholds
        )
        files.append(write_text_atomic(out / "report.txt", render_text(report)))
        raise AnalysisError(
            f"{data}: no completed masked set to analyse ({len(thresholds)} sets, none with an "
            f"AL shift); see {out / 'report.txt'} for the status of each set"
        )
    results = analyze_shifts(shifts, settings, has_participants=True)
    files += write_outputs(
        out,
        results,
        settings,
        source="analyze",
        inputs=inputs,
        skipped=skipped,
        created_utc=created_utc,
        report_inputs=report_inputs,
        thresholds=thresholds,
    )
    warnings += result_warnings(results)
    return RunSummary(out, files, warnings)


def _track_figure(out: Path, log: SessionLog, rows: list[dict]) -> Path:
    """Draw the staircase tracks of one session into ``out/figures/tracks``."""
    from masking_lab.analysis.figures import safe_stem, track_figure

    h = log.header
    als = {r["set_id"]: (r.get("al_db_sl") if r.get("masker") else r.get("al_db_v")) for r in rows}
    name = safe_stem(f"{h['participant']}_{h['protocol']['experiment']}_{h.get('session_id', '')}")
    return track_figure(out / "figures" / "tracks" / f"{name}.png", log, als)


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
    table = ShiftsTableInput(
        path=str(csv_path),
        n_rows=len(shifts),
        n_participants=int(shifts["participant"].nunique()) if has_participants else None,
    )
    files = write_outputs(
        out,
        results,
        settings,
        source="fit",
        inputs=inputs,
        skipped=(),
        created_utc=settings.created_utc or EPOCH_UTC,
        report_inputs=table,
        thresholds=None,
    )
    return RunSummary(out, files, result_warnings(results))


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
