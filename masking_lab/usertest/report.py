"""User-test logs under a folder → correct rates, paired tests, confusion matrices, Figure 8a.

:func:`collect_usertest` reads every session log under a folder and keeps the user-test ones
(header ``kind: usertest``); threshold logs and unreadable files are listed as skipped, with why.
:func:`masking_lab.usertest.design.analyze_usertest` does the arithmetic (paper §3.4: "both",
"geometry"
and "texture" correct rates per participant and condition, a two-sided paired t-test per measure,
confusion matrices). :func:`write_usertest_report` writes the tables, the report (a model from
:mod:`masking_lab.usertest.report_model`, rendered as text and as HTML) and a bar chart like the
paper's Figure 8a (:mod:`masking_lab.usertest.figures`).

Every output is deterministic: the same logs give the same bytes (sorted inputs, fixed number
formats, no dates or software versions in the PNG), written atomically.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from masking_lab.core.errors import AnalysisError, LogError
from masking_lab.formats.fileio import write_bytes_atomic, write_text_atomic
from masking_lab.formats.output_dir import staged_output
from masking_lab.usertest.design import MEASURES
from masking_lab.usertest.figures import figure8a_png
from masking_lab.usertest.report_html import render_usertest_html
from masking_lab.usertest.report_model import build_usertest_model, render_usertest_text
from masking_lab.usertest.stats import UserTestAnalysis, analyze_usertest

RECORD = "usertest_trial"


@dataclass(frozen=True)
class UserTestSession:
    """One user-test log found under the folder.

    Attributes
    ----------
    log : str
        Path relative to the data folder.
    participant : str
        Participant id.
    n_logged, n_trials : int
        Trials logged, and in the design.
    ended : bool
        The log has a ``session_end`` record.
    """

    log: str
    participant: str
    n_logged: int
    n_trials: int
    ended: bool


@dataclass(frozen=True)
class UserTestData:
    """The user-test trials of a folder of logs.

    Attributes
    ----------
    records : list[dict]
        Every ``usertest_trial`` record, logs in path order.
    geometries, textures : tuple[str, ...]
        The design's answer keys (the same in every log).
    sessions : list[UserTestSession]
        The logs used.
    skipped : list[dict]
        ``{"log", "reason"}`` of files not used.
    notes : list[str]
        Caveats worth reading (incomplete sessions, truncated lines, repeated participants).
    """

    records: list[dict[str, Any]]
    geometries: tuple[str, ...]
    textures: tuple[str, ...]
    sessions: list[UserTestSession]
    skipped: list[dict[str, str]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def collect_usertest(data_dir: str | Path) -> UserTestData:
    """Read the user-test logs under ``data_dir`` (recursively, ``*.jsonl``).

    Raises
    ------
    AnalysisError
        No such folder, no user-test log in it, or logs of designs with different answer keys.
    """
    from masking_lab.analysis.data_folder import data_folder, find_logs
    from masking_lab.formats.session_log import read_log

    data = data_folder(data_dir)
    paths = find_logs(data)
    records: list[dict[str, Any]] = []
    sessions: list[UserTestSession] = []
    skipped: list[dict[str, str]] = []
    notes: list[str] = []
    keys: tuple[tuple[str, ...], tuple[str, ...]] | None = None
    keys_from = ""
    for path in paths:
        rel = path.relative_to(data).as_posix()
        try:
            log = read_log(path)
        except LogError as exc:
            skipped.append({"log": rel, "reason": str(exc)})
            continue
        h = log.header
        if h.get("kind") != "usertest":
            skipped.append({"log": rel, "reason": "not a user-test log (a threshold session)"})
            continue
        content = (h.get("protocol") or {}).get("content") or {}
        try:
            these = (tuple(content["geometries"]), tuple(content["textures"]))
        except (KeyError, TypeError):
            skipped.append(
                {"log": rel, "reason": "header lacks the protocol's geometries/textures"}
            )
            continue
        trials = [r for r in log.records if r.get("record") == RECORD]
        twice = _repeated_trial(trials)
        if twice is not None:
            skipped.append(
                {
                    "log": rel,
                    "reason": f"trial {twice} is logged twice; the log was edited or merged",
                }
            )
            continue
        if keys is None:
            keys, keys_from = these, rel
        elif these != keys:
            raise AnalysisError(
                f"{rel} uses geometries {list(these[0])} and textures {list(these[1])} but "
                f"{keys_from} uses {list(keys[0])} and {list(keys[1])}; analyse the two designs "
                "from separate folders"
            )
        participant = str(h.get("participant", ""))
        n_trials = int((h.get("usertest") or {}).get("n_trials", len(trials)))
        sessions.append(UserTestSession(rel, participant, len(trials), n_trials, log.ended))
        if not log.ended:
            notes.append(
                f"{rel}: incomplete session ({len(trials)} of {n_trials} trials logged); its "
                "trials are included — resume it to finish"
            )
        for problem in log.problems:
            notes.append(f"{rel}: {problem}")
        mapped = (h.get("usertest") or {}).get("gamut_map", "none")
        if mapped != "none":
            notes.append(f"{rel}: scenes mapped into the rig's gamut ({mapped}) before rendering")
        records.extend(trials)
    if keys is None:
        what = f"{len(paths)} log(s), none of them a user test" if paths else "no session logs"
        raise AnalysisError(
            f"{data}: {what}; point at the folder holding the user-test logs "
            "(masking-lab run protocols/usertest.yaml ... writes them)"
        )
    by_participant: dict[str, int] = {}
    for s in sessions:
        by_participant[s.participant] = by_participant.get(s.participant, 0) + 1
    for participant, n in sorted(by_participant.items()):
        if n > 1:
            notes.append(
                f"participant {participant} has {n} user-test sessions; their trials are pooled"
            )
    return UserTestData(records, keys[0], keys[1], sessions, skipped, notes)


# --------------------------------------------------------------------------------------------
# Outputs


def rates_rows(analysis: UserTestAnalysis) -> list[dict[str, Any]]:
    """Per participant × condition: trials, unanswered, correct rates."""
    return [dict(row) for row in analysis.rates.to_dict(orient="records")]


def summary_rows(analysis: UserTestAnalysis) -> list[dict[str, Any]]:
    """Per condition × measure: mean, SD, n (participants)."""
    return [dict(row) for row in analysis.summary.to_dict(orient="records")]


def tests_rows(analysis: UserTestAnalysis) -> list[dict[str, Any]]:
    """One paired comparison per measure."""
    return [
        {
            "measure": t.measure,
            "n": t.n,
            "mean_compensated": t.mean_compensated,
            "mean_uncompensated": t.mean_uncompensated,
            "mean_difference": t.mean_difference,
            "t": t.t,
            "df": t.n - 1 if t.t is not None else None,
            "p": t.p,
            "dz": t.dz,
            "note": t.note,
        }
        for t in analysis.tests
    ]


def confusion_csv(table: Any) -> str:
    """A confusion matrix as CSV: first column the presented class, then one per answer."""
    from masking_lab.formats.csv_table import csv_text

    columns = [str(table.index.name), *[str(c) for c in table.columns]]
    rows = [
        {columns[0]: str(idx), **{str(c): int(v) for c, v in row.items()}}
        for idx, row in table.iterrows()
    ]
    return csv_text(columns, rows)


@dataclass(frozen=True)
class UserTestReport:
    """What :func:`write_usertest_report` produced.

    Attributes
    ----------
    data : UserTestData
        The logs read.
    analysis : UserTestAnalysis
        The results.
    written : list[Path]
        Files written, in order.
    """

    data: UserTestData
    analysis: UserTestAnalysis
    written: list[Path]


def write_usertest_report(
    data_dir: str | Path, out_dir: str | Path, *, figure: bool = True
) -> UserTestReport:
    """Analyse the user-test logs under ``data_dir`` and write every output into ``out_dir``.

    Writes ``rates.csv``, ``summary.csv``, ``tests.csv``, ``confusion_<condition>_<geometry|
    texture>.csv``, ``sessions.csv``, ``report.html``, ``report.txt`` and (unless ``figure`` is
    False) ``figure8a.png``, into a fresh folder that replaces ``out_dir`` only when every file
    is written (:func:`masking_lab.formats.output_dir.staged_output`).

    Parameters
    ----------
    data_dir : str or Path
        Folder holding the logs (searched recursively).
    out_dir : str or Path
        Output folder: missing, empty or a previous report (replaced as a whole).
    figure : bool
        Draw Figure 8a.

    Returns
    -------
    UserTestReport
        The data, the analysis and the files written (paths inside ``out_dir``).

    Raises
    ------
    AnalysisError
        No user-test logs, inconsistent designs, or records that do not fit the design; the
        previous report stays in place.

    Examples
    --------
    >>> write_usertest_report("data", "usertest_report")  # doctest: +SKIP
    """
    final = Path(out_dir)
    with staged_output(final, protect=[Path(data_dir)]) as staging:
        data = collect_usertest(data_dir)
        analysis = analyze_usertest(data.records, data.geometries, data.textures)
        written = _write_report(data, analysis, staging, figure=figure)
    return UserTestReport(data, analysis, [final / p.relative_to(staging) for p in written])


def _write_report(
    data: UserTestData, analysis: UserTestAnalysis, out: Path, *, figure: bool
) -> list[Path]:
    """Every output file of :func:`write_usertest_report`, into ``out``."""
    from masking_lab.formats.csv_table import csv_text

    rate_cols = ["participant", "condition", "n_trials", "n_no_answer", *MEASURES]
    test_cols = [
        "measure",
        "n",
        "mean_compensated",
        "mean_uncompensated",
        "mean_difference",
        "t",
        "df",
        "p",
        "dz",
        "note",
    ]
    session_cols = ["log", "participant", "n_logged", "n_trials", "ended"]
    sessions = [
        {
            "log": s.log,
            "participant": s.participant,
            "n_logged": s.n_logged,
            "n_trials": s.n_trials,
            "ended": s.ended,
        }
        for s in data.sessions
    ]
    written = [
        write_text_atomic(out / "rates.csv", csv_text(rate_cols, rates_rows(analysis))),
        write_text_atomic(
            out / "summary.csv",
            csv_text(["condition", "measure", "mean", "sd", "n"], summary_rows(analysis)),
        ),
        write_text_atomic(out / "tests.csv", csv_text(test_cols, tests_rows(analysis))),
    ]
    for cond, tables in sorted(analysis.confusion.items()):
        for measure in ("geometry", "texture"):
            written.append(
                write_text_atomic(
                    out / f"confusion_{cond}_{measure}.csv", confusion_csv(tables[measure])
                )
            )
    written.append(write_text_atomic(out / "sessions.csv", csv_text(session_cols, sessions)))
    model = build_usertest_model(data, analysis)
    png = figure8a_png(model) if figure else None
    written.append(write_text_atomic(out / "report.html", render_usertest_html(model, png)))
    written.append(write_text_atomic(out / "report.txt", render_usertest_text(model)))
    if png is not None:
        written.append(write_bytes_atomic(out / "figure8a.png", png))
    return written


def _repeated_trial(trials: list[dict[str, Any]]) -> Any:
    """The first trial index logged twice, or None."""
    seen: set[Any] = set()
    for rec in trials:
        index = rec.get("trial")
        if index in seen:
            return index
        seen.add(index)
    return None


__all__ = [
    "UserTestData",
    "UserTestReport",
    "UserTestSession",
    "collect_usertest",
    "confusion_csv",
    "write_usertest_report",
]
