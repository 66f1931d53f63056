"""The per-trial and per-participant outputs of ``analyze`` (*shell*: reads logs, writes files).

:func:`write_lab_outputs` reads every analysed log once more with the general reader (it needs
fields the analysis view leaves out: intervals, response times, onsets, the participant's
``info``) and writes

* ``trials.csv`` — one row per trial (:mod:`masking_lab.analysis.trials_table`), streamed log
  by log so a large study never sits in memory; ``trials.parquet`` too when pyarrow is
  installed (``pip install masking-lab[parquet]``);
* ``psychometric.csv`` — a psychometric function per participant × completed set
  (:mod:`masking_lab.analysis.psychometric`);
* ``participants.tsv`` and ``participants.json`` — one row per participant with the
  protocol's ``info`` fields from the session headers, and the sidecar describing each column
  (BIDS / Psych-DS style);
* ``study_status.csv`` — the participant × protocol matrix
  (:mod:`masking_lab.analysis.study_status`);
* figures: ``figures/shifts_<experiment>.png`` (unless ``--figures none``) and, with
  ``--figures all``, ``figures/psychometric/<participant>_<experiment>.png``; the HTML report
  draws every set's psychometric function itself (inline SVG, see
  :mod:`masking_lab.analysis.report_lab`).

It returns the :class:`~masking_lab.analysis.report_lab.LabSection` the reports show.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, TextIO

import pandas as pd

from masking_lab.analysis.figure_pool import FigurePool
from masking_lab.analysis.log_reading import PARALLEL_FROM
from masking_lab.analysis.pf_table import (
    PF_BOOTSTRAP,
    PF_COLUMNS,
    SetTrials,
    fit_all,
    fit_all_with,
    pf_job,
    pf_row,
    pf_seed,
)
from masking_lab.analysis.psychometric import PFFit, PFJob
from masking_lab.analysis.report_lab import LabSection, PFPlot, PFRow, pf_plot
from masking_lab.analysis.study_reading import LogPart, ParquetSink, StudyLogs, read_parts
from masking_lab.analysis.study_status import (
    SessionInfo,
    outliers,
    status_matrix,
    unmasked_als,
)
from masking_lab.analysis.trials_table import TRIAL_COLUMNS
from masking_lab.formats.csv_table import csv_text
from masking_lab.formats.fileio import write_bytes_atomic, write_text_atomic
from masking_lab.formats.html_report import data_uri

__all__ = [
    "PF_COLUMNS",
    "LabOutputs",
    "ShiftFigures",
    "fit_all",
    "pf_job",
    "pf_row",
    "read_study",
    "start_shift_figures",
    "write_lab_outputs",
]

_UNIT_TEXT = {"db_sl": "dB SL", "db_v": "dB re 1 V"}


@dataclass
class LabOutputs:
    """What :func:`write_lab_outputs` wrote and what the reports show."""

    files: list[Path]
    section: LabSection
    warnings: list[str]
    #: Writes the AL-shift figures that the figure pool is still drawing and gives their
    #: (path, data URI) pairs; None once they are in ``section.embedded``.
    embed_shifts: Callable[[], tuple[tuple[str, str], ...]] | None = None

    def finished(self) -> LabSection:
        """The section with the shift figures written and embedded (waits for their worker).

        The run asks for them as late as it can, just before the HTML report that embeds them,
        so their drawing overlaps the statistics and the other outputs.
        """
        if self.embed_shifts is not None:
            self.section = replace(self.section, embedded=self.embed_shifts())
            self.embed_shifts = None
        return self.section


def read_study(
    data: Path,
    logs: Sequence[str],
    set_status: Mapping[tuple[str, str], str] | None = None,
    *,
    trials_csv: TextIO | None = None,
    parquet: ParquetSink | None = None,
) -> StudyLogs:
    """Read the analysed logs (relative paths under ``data``) with the general reader.

    With ``trials_csv`` (and ``parquet``), each log's trial rows are written there as it comes
    in (``set_status``: ``(log, set_id)`` → status), so a large study never sits in memory.
    Many logs are read in parallel (:func:`~masking_lab.analysis.study_reading.read_parts`).
    """
    study = StudyLogs()
    rows = parquet is not None and parquet.enabled
    for part in read_parts(data, logs, set_status, csv=trials_csv is not None, rows=rows):
        if part is None:
            continue  # already reported by the analysis' own read
        study.add(part)
        if trials_csv is not None:
            trials_csv.write(part.trials_csv)
        if rows and part.trial_batch is not None:
            parquet.add(part.trial_batch)  # type: ignore[union-attr]
    return study


def write_lab_outputs(
    data: Path,
    out: Path,
    logs: Sequence[str],
    thresholds: pd.DataFrame,
    *,
    figures: str = "summary",
    n_boot: int = PF_BOOTSTRAP,
    progress: Callable[[int, int], None] | None = None,
    trial_tables: bool = True,
    sessions: Sequence[tuple[SessionInfo, Mapping[str, Any] | None, list[dict]]] | None = None,
    figure_pool: FigurePool | None = None,
    shift_figures: ShiftFigures | None = None,
    after_read: Callable[[], None] | None = None,
) -> LabOutputs:
    """Write the per-trial and per-participant outputs of ``analyze`` into ``out``.

    Parameters
    ----------
    data : Path
        The data folder.
    out : Path
        The (staging) output folder.
    logs : sequence of str
        The analysed logs, relative to ``data``.
    thresholds : DataFrame
        The thresholds table (its ``status`` goes into every trial row).
    figures : {"all", "summary", "none"}
        ``none`` draws no figure.
    n_boot : int
        Bootstrap data sets per psychometric function.
    progress : callable, optional
        Called with (sets fitted, sets to fit).
    trial_tables : bool
        Write ``trials.csv``/``.parquet`` and ``psychometric.csv`` (False: only the study
        status, ``participants.tsv`` and the shift plots).
    sessions : sequence, optional
        Each log's :attr:`~masking_lab.analysis.log_reading.LogResult.session`, in the order
        of ``logs``, from the analysis' own read: without trial tables nothing is read again.
    figure_pool : FigurePool, optional
        Where the shift figures are drawn (default: a worker of their own for a large study,
        else in-process).
    shift_figures : ShiftFigures, optional
        The thresholds' outlier flags and shift figures, already started
        (:func:`start_shift_figures`; default: started here).
    after_read : callable, optional
        Called once the logs are read, before the psychometric fits (``analyze`` takes the
        statistics computed beside the read then).

    Returns
    -------
    LabOutputs
    """
    files: list[Path] = []
    # each trial row's set status (trials.csv only): a key per set of the study
    status: dict[tuple[str, str], str] = {}
    if trial_tables:
        keys = [thresholds[c].tolist() for c in ("log", "set_id", "status")]
        status = {(str(log), str(sid)): str(st) for log, sid, st in zip(*keys, strict=True)}
    # The shift figures need only the thresholds: they are drawn in a worker process while
    # the logs are read and fitted.
    own_pool = figure_pool is None
    if figure_pool is None:
        figure_pool = FigurePool(figures != "none" and len(logs) >= PARALLEL_FROM)
    if len(logs) >= PARALLEL_FROM:  # a shift figure of hundreds of participants takes seconds
        figure_pool.widen(2)
    early = shift_figures or start_shift_figures(thresholds, figures, figure_pool)
    flags = early.flags
    if trial_tables:
        trials_path = out / "trials.csv"
        parquet = ParquetSink(out / "trials.parquet")
        with trials_path.open("w", encoding="utf-8", newline="") as fh:
            fh.write(",".join(TRIAL_COLUMNS) + "\n")
            study = read_study(data, logs, status, trials_csv=fh, parquet=parquet)
        files.append(trials_path)
        files += parquet.close()
    elif sessions is not None:
        study = StudyLogs()
        for session, info, specs in sessions:
            study.add(LogPart(session, info, specs, {}))
    else:
        study = read_study(data, logs)
    if after_read is not None:
        after_read()

    # Psychometric functions of the sets whose threshold is used (completed attempts).
    used = thresholds[thresholds["status"] == "completed"] if trial_tables else thresholds[:0]
    wanted: list[tuple[dict, SetTrials, int]] = []
    for r in used.itertuples(index=False):
        st = study.sets.get((str(r.log), str(r.set_id)))
        if st is not None:
            base = {
                "participant": r.participant,
                "experiment": r.experiment,
                "set_id": r.set_id,
                "target": r.target,
                "masker": r.masker,
                "masker_level_db_sl": r.masker_level_db_sl,
                "session_id": r.session_id,
                "log": r.log,
            }
            seed = pf_seed(r.participant, r.experiment, r.set_id, str(r.log))
            wanted.append((base, st, seed))
    # Every fit at once (batched, in parallel for many sets): the same numbers as one by one.
    # Each set's report plot is made where its fit was (at 1,000 sessions 11,000 plots, ~4 s
    # in this process alone).
    jobs = [pf_job(st, seed, n_boot) for _, st, seed in wanted]
    made = fit_all_with(jobs, _plot, progress=progress)
    pf_rows = [
        pf_row(base, st, seed, n_boot, fit)
        for (base, st, seed), (fit, _) in zip(wanted, made, strict=True)
    ]
    if trial_tables:
        files.append(write_text_atomic(out / "psychometric.csv", csv_text(PF_COLUMNS, pf_rows)))
    files += _write_participants(out, study)

    matrix = status_matrix(study.sessions, thresholds)
    status_cols = [
        "participant", "experiment", "status", "sets_done", "sets_planned", "trials", "sessions",
    ]  # fmt: skip
    status_csv = csv_text(status_cols, [vars(c) for c in matrix])
    files.append(write_text_atomic(out / "study_status.csv", status_csv))
    figure_links: list[tuple[str, str]] = []
    if figures != "none":
        drawn = _draw(out, study, pf_rows, figures) + early.paths(out)
        files += [p for p, _ in drawn]
        figure_links = [(p.relative_to(out).as_posix(), c) for p, c in drawn]
    section = LabSection(
        experiments=tuple(sorted({s.experiment for s in study.sessions})),
        matrix=tuple(matrix),
        unmasked=tuple(
            (p, tuple(sorted(als.items()))) for p, als in sorted(unmasked_als(thresholds).items())
        ),
        outliers=tuple(flags),
        pf=tuple(_pf_report_row(r, plot) for r, (_, plot) in zip(pf_rows, made, strict=True)),
        figures=tuple(figure_links),
    )
    warnings = [
        f"outlier: {o.participant} {o.what} = {o.value_db:.2f} dB (z {o.z:+.1f})" for o in flags
    ]
    lab = LabOutputs(files, section, warnings, embed_shifts=lambda: early.write(out))
    if own_pool:  # nothing later to overlap with: collect the figures now
        lab.finished()
        figure_pool.close()
    return lab


def _plot(job: PFJob, fit: PFFit) -> PFPlot:
    """A set's report plot, from its fit's trials (run beside the fit, in a worker too)."""
    return pf_plot(job.levels_db, job.correct, fit)


def _pf_report_row(r: Mapping[str, Any], plot: PFPlot | None) -> PFRow:
    fit: PFFit = r["_fit"]
    assert plot is not None  # fit_all_with made one beside every fit
    what = r["target"] if r["masker"] is None else f"{r['target']}|{r['masker']}"
    lvl = "" if r["masker_level_db_sl"] is None else f" @ {r['masker_level_db_sl']:g} dB SL"
    return PFRow(
        participant=str(r["participant"]),
        experiment=str(r["experiment"]),
        set_id=str(r["set_id"]),
        unit=_UNIT_TEXT[r["level_unit"]],
        n_trials=fit.n_trials,
        threshold_db=fit.threshold_db,
        threshold_ci_db=fit.threshold_ci_db,
        slope_per_db=fit.slope_per_db,
        lapse=fit.lapse,
        deviance=fit.deviance,
        deviance_p=fit.deviance_p,
        note=fit.message or "",
        label=f"{what}{lvl}",
        plot=plot,
    )


def _draw(
    out: Path,
    study: StudyLogs,
    pf_rows: Sequence[Mapping[str, Any]],
    figures: str,
) -> list[tuple[Path, str]]:
    """The psychometric figures (``--figures all``), drawn here."""
    from masking_lab.analysis.figures import safe_stem
    from masking_lab.analysis.lab_figures import pf_figure_png

    drawn: list[tuple[Path, str]] = []
    groups: dict[tuple[str, str], list[Mapping[str, Any]]] = {}
    for r in pf_rows:
        groups.setdefault((str(r["participant"]), str(r["experiment"])), []).append(r)
    for (p, e), rows in sorted(groups.items()) if figures == "all" else ():
        panels = []
        for r in rows:
            st = study.sets[(str(r["log"]), str(r["set_id"]))]
            what = r["target"] if r["masker"] is None else f"{r['target']}|{r['masker']}"
            lvl = "" if r["masker_level_db_sl"] is None else f" @ {r['masker_level_db_sl']:g} dB SL"
            panels.append(
                {"label": f"{what}{lvl}", "levels_db": st.levels, "correct": st.correct,
                 "unit": r["level_unit"], "fit": r["_fit"]}
            )  # fmt: skip
        path = out / "figures" / "psychometric" / f"{safe_stem(f'{p}_{e}')}.png"
        write_bytes_atomic(path, pf_figure_png(f"Psychometric functions: {p}, {e}", panels))
        drawn.append((path, f"psychometric functions of {p} in {e}, one panel per set"))
    return drawn


def start_shift_figures(
    thresholds: pd.DataFrame, figures: str, pool: FigurePool | None
) -> ShiftFigures:
    """The thresholds' outlier flags, and their AL-shift figures started in ``pool`` at once
    (drawn in-process when asked for without a pool)."""
    wanted = figures != "none"
    return ShiftFigures(thresholds, outliers(thresholds), wanted, pool or FigurePool(False))


class ShiftFigures:
    """``figures/shifts_<experiment>.png`` of the thresholds, started in ``pool`` at once;
    ``flags``: the outliers (:func:`~masking_lab.analysis.study_status.outliers`)."""

    def __init__(
        self, thresholds: pd.DataFrame, flags: Sequence[Any], wanted: bool, pool: FigurePool
    ):
        self.flags = list(flags)
        self.jobs: list[tuple[str, str, dict[str, list], set]] = []
        self.results: list[Callable[[], bytes]] = []
        if not wanted:
            return
        names = ["participant", "mv_stimulus", "target", "masker", "masker_level_db_sl", "shift_db"]
        ok = (thresholds["status"] == "completed") & thresholds["shift_db"].notna()
        done = thresholds.loc[ok, ["experiment", *names]]  # not the table's other columns
        flagged = set()
        for o in flags:
            if "(AL shift)" in o.what:
                head, _, rest = o.what.partition(" @ ")
                flagged.add((o.participant, head.split(" ", 1)[1], float(rest.split(" ")[0])))
        # Column lists, not a dict per set (at 10,000 sessions ~40 MB, left fragmented once
        # freed); the worker makes the rows (lab_figures.shift_figure_png_columns).
        for e, g in done.groupby("experiment", sort=True):
            p, mv, t, m, lv, sh = (g[c].tolist() for c in names)
            pairs: dict[tuple[Any, Any], str] = {}
            pair = [pairs.setdefault((a, b), f"{a}|{b}") for a, b in zip(t, m, strict=True)]
            columns = {"participant": p, "mv_stimulus": mv, "pair": pair,
                       "masker_level_db_sl": lv, "shift_db": sh}  # fmt: skip
            self.jobs.append((str(e), f"Individual AL shifts: {e}", columns, flagged))
        if self.jobs:
            from masking_lab.analysis.lab_figures import shift_figure_png_columns

            self.results = [pool.submit(shift_figure_png_columns, *job[1:]) for job in self.jobs]
            # The figures' data is the pool's now, freed when drawn; only the experiments'
            # names are kept here.
            self.jobs = [(e, title, {}, set()) for e, title, *_ in self.jobs]

    def result(self) -> list[tuple[str, bytes]]:
        """(experiment, PNG bytes) per experiment, sorted by experiment."""
        return [(job[0], get()) for job, get in zip(self.jobs, self.results, strict=True)]

    def paths(self, out: Path) -> list[tuple[Path, str]]:
        """(file, caption) of each experiment's figure in ``out``, before it is drawn."""
        from masking_lab.analysis.figures import safe_stem

        return [
            (
                out / "figures" / f"shifts_{safe_stem(e)}.png",
                f"each participant's AL shift in {e} against masker level",
            )
            for e, *_ in self.jobs
        ]

    def write(self, out: Path) -> tuple[tuple[str, str], ...]:
        """Wait for the figures, write them into ``out``; (path, data URI) of each."""
        embedded = []
        for (path, _), (_, png) in zip(self.paths(out), self.result(), strict=True):
            write_bytes_atomic(path, png)
            embedded.append((path.relative_to(out).as_posix(), data_uri(png)))
        return tuple(embedded)


def _write_participants(out: Path, study: StudyLogs) -> list[Path]:
    """``participants.tsv`` (one row per participant) and its JSON sidecar."""
    # The protocols' order of fields, then any other key found in a header.
    extra = {k for v in study.info.values() for k in v} - set(study.info_fields)
    names = [*study.info_fields, *sorted(extra)]
    cols = ["participant_id", "n_sessions", *names]
    lines = ["\t".join(cols)]
    for p in sorted(study.sessions_of):
        info = study.info.get(p, {})
        vals = [p, str(study.sessions_of[p])] + [_tsv(info.get(n)) for n in names]
        lines.append("\t".join(vals))
    sidecar: dict[str, Any] = {
        "participant_id": {"Description": "Participant code as given to masking-lab run."},
        "n_sessions": {"Description": "Session logs of this participant in the data folder."},
    }
    for n in names:
        spec = study.info_fields.get(n, {})
        entry: dict[str, Any] = {"Description": spec.get("description") or n}
        if spec.get("choices"):
            entry["Levels"] = {str(c): str(c) for c in spec["choices"]}
        if spec.get("unit"):
            entry["Units"] = spec["unit"]
        if spec.get("type"):
            entry["DataType"] = spec["type"]
        sidecar[n] = entry
    return [
        write_text_atomic(out / "participants.tsv", "\n".join(lines) + "\n"),
        write_text_atomic(
            out / "participants.json", json.dumps(sidecar, indent=2, ensure_ascii=False) + "\n"
        ),
    ]


def _tsv(v: Any) -> str:
    """A TSV cell: ``n/a`` for a missing value (BIDS), tabs and newlines replaced."""
    if v is None or v == "":
        return "n/a"
    text = json.dumps(v) if isinstance(v, bool) else str(v)
    return text.replace("\t", " ").replace("\n", " ")


def study_at_a_glance(data: str | Path) -> tuple[LabSection, list[str]]:
    """The study status of a data folder, read without writing anything (``masking-lab status``).

    Returns the report section (matrix, unmasked ALs, outlier flags; no psychometric fits)
    and the problems met (unreadable logs, headers without a participant), one line each.

    Raises
    ------
    AnalysisError
        If ``data`` is not a folder or holds no session log.
    """
    from masking_lab.analysis.batch import _skip_reason
    from masking_lab.analysis.data_folder import data_folder, find_logs
    from masking_lab.analysis.log_reading import read_logs
    from masking_lab.analysis.thresholds import EstimatorSettings, thresholds_table
    from masking_lab.core.errors import AnalysisError

    root = data_folder(data)
    paths = find_logs(root)
    if not paths:
        raise AnalysisError(f"{root}: no session logs (*.jsonl) found")
    rows: list[tuple] = []
    study = StudyLogs()  # from the one read of each log (LogResult.session)
    problems: list[str] = []
    for res in read_logs(paths, root, EstimatorSettings()):
        reason = res.error or _skip_reason(res.header)
        if reason or res.session is None:
            problems.append(f"{res.rel}: {reason}")
            continue
        study.add(LogPart(*res.session, {}))
        rows.extend(res.rows)
    thresholds = thresholds_table(rows, consume=True)
    section = LabSection(
        experiments=tuple(sorted({s.experiment for s in study.sessions})),
        matrix=tuple(status_matrix(study.sessions, thresholds)),
        unmasked=tuple(
            (p, tuple(sorted(als.items()))) for p, als in sorted(unmasked_als(thresholds).items())
        ),
        outliers=tuple(outliers(thresholds)),
        pf=(),
    )
    return section, problems
