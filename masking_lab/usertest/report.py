"""User-test logs under a folder → correct rates, paired tests, confusion matrices, Figure 8a.

:func:`collect_usertest` reads every session log under a folder and keeps the user-test ones
(header ``kind: usertest``); threshold logs and unreadable files are listed as skipped, with why.
:func:`masking_lab.usertest.design.analyze_usertest` does the arithmetic (paper §3.4: "both",
"geometry"
and "texture" correct rates per participant and condition, a two-sided paired t-test per measure,
confusion matrices). :func:`write_usertest_report` writes the tables, a text report and a bar
chart like the paper's Figure 8a (mean correct rate per measure and condition, SD error bars,
asterisks for the paired tests).

Every output is deterministic: the same logs give the same bytes (sorted inputs, fixed number
formats, no dates or software versions in the PNG), written atomically.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from masking_lab.core.errors import AnalysisError, LogError
from masking_lab.formats.fileio import write_bytes_atomic, write_text_atomic
from masking_lab.usertest.design import CONDITIONS, MEASURES
from masking_lab.usertest.stats import UserTestAnalysis, analyze_usertest

RECORD = "usertest_trial"
COMPENSATED_COLOUR = "tab:blue"
UNCOMPENSATED_COLOUR = "tab:gray"


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
    from masking_lab.analysis.batch import find_logs
    from masking_lab.formats.session_log import read_log

    data = Path(data_dir)
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


def report_text(data: UserTestData, analysis: UserTestAnalysis) -> str:
    """The text report: inputs, correct rates per condition, paired tests, confusion matrices."""
    lines = ["User test (Ryu et al. 2020, section 3.3): identification of geometry and texture", ""]
    n_part = analysis.rates["participant"].nunique()
    lines.append(
        f"Logs: {len(data.sessions)} user-test session(s), {n_part} participant(s), "
        f"{len(data.records)} trials; {len(data.skipped)} other file(s) skipped."
    )
    for s in data.sessions:
        state = "completed" if s.ended else "INCOMPLETE"
        lines.append(f"  {s.log}: {s.participant}, {s.n_logged}/{s.n_trials} trials, {state}")
    for s in data.skipped:
        lines.append(f"  skipped {s['log']}: {s['reason']}")
    for note in data.notes:
        lines.append(f"  note: {note}")
    lines += ["", "Correct rate, mean ± SD over participants (no answer counts as wrong):"]
    summary = {(r["condition"], r["measure"]): r for r in summary_rows(analysis)}
    lines.append(f"  {'condition':<15}" + "".join(f"{m:>18}" for m in MEASURES))
    for cond in CONDITIONS:
        if not any((cond, m) in summary for m in MEASURES):
            continue
        cells = []
        for m in MEASURES:
            r = summary.get((cond, m))
            cells.append(f"{_pm(r['mean'], r['sd']):>18}" if r else f"{'-':>18}")
        lines.append(f"  {cond:<15}" + "".join(cells))
    lines += ["", "Paired t-tests, compensated vs uncompensated (two-sided):"]
    for t in analysis.tests:
        if t.t is None:
            lines.append(f"  {t.measure:<9} not tested: {t.note}")
            continue
        lines.append(
            f"  {t.measure:<9} {t.mean_compensated:.3f} vs {t.mean_uncompensated:.3f}, "
            f"difference {t.mean_difference:+.3f}, t({t.n - 1}) = {t.t:.3f}, {_p(t.p)}, "
            f"d_z = {t.dz:.2f}"
        )
    for cond, tables in sorted(analysis.confusion.items()):
        for measure in ("geometry", "texture"):
            lines += ["", f"Confusion, {measure}, {cond} (rows presented, columns answered):"]
            lines += ["  " + line for line in tables[measure].to_string().splitlines()]
    lines.append("")
    return "\n".join(lines)


def figure8a_png(analysis: UserTestAnalysis, *, dpi: int = 110) -> bytes:
    """Bar chart like the paper's Figure 8a: mean correct rate per measure and condition.

    Error bars are the between-participant SD; ``*`` marks p < 0.05 and ``**`` p < 0.01 in the
    paired t-test of a measure.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary = {(r["condition"], r["measure"]): r for r in summary_rows(analysis)}
    conditions = [c for c in CONDITIONS if any((c, m) in summary for m in MEASURES)]
    colours = {"compensated": COMPENSATED_COLOUR, "uncompensated": UNCOMPENSATED_COLOUR}
    labels = {"compensated": "with compensation", "uncompensated": "without compensation"}
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    width = 0.8 / max(1, len(conditions))
    for j, cond in enumerate(conditions):
        xs = [i + (j - (len(conditions) - 1) / 2) * width for i in range(len(MEASURES))]
        means = [_finite(summary.get((cond, m), {}).get("mean")) for m in MEASURES]
        sds = [_finite(summary.get((cond, m), {}).get("sd")) for m in MEASURES]
        ax.bar(
            xs,
            means,
            width * 0.95,
            yerr=sds,
            capsize=4,
            color=colours[cond],
            label=labels[cond],
            edgecolor="black",
            linewidth=0.6,
        )
    tests = {t.measure: t for t in analysis.tests}
    for i, m in enumerate(MEASURES):
        t = tests.get(m)
        if t is None or t.p is None or t.p >= 0.05:
            continue
        top = max(
            _finite(summary.get((c, m), {}).get("mean"))
            + _finite(summary.get((c, m), {}).get("sd"))
            for c in conditions
        )
        ax.text(i, min(top + 0.03, 1.08), "**" if t.p < 0.01 else "*", ha="center", fontsize=13)
    ax.set_xticks(range(len(MEASURES)))
    ax.set_xticklabels(["geometry and texture", "geometry", "texture"])
    ax.set_ylabel("correct rate")
    ax.set_ylim(0.0, 1.15)
    ax.set_yticks([0.0, 0.2, 0.4, 0.6, 0.8, 1.0])
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.09), ncol=2, fontsize=9, frameon=False)
    n = analysis.rates["participant"].nunique()
    ax.set_title(f"User test: correct answers (mean ± SD, {n} participants)", fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, metadata={"Software": None})
    plt.close(fig)
    return buf.getvalue()


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
    texture>.csv``, ``sessions.csv``, ``report.txt`` and (unless ``figure`` is False)
    ``figure8a.png``.

    Raises
    ------
    AnalysisError
        No user-test logs, inconsistent designs, or records that do not fit the design.
    """
    from masking_lab.formats.csv_table import csv_text

    data = collect_usertest(data_dir)
    analysis = analyze_usertest(data.records, data.geometries, data.textures)
    out = Path(out_dir)
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
    written.append(write_text_atomic(out / "report.txt", report_text(data, analysis)))
    if figure:
        written.append(write_bytes_atomic(out / "figure8a.png", figure8a_png(analysis)))
    return UserTestReport(data, analysis, written)


def _repeated_trial(trials: list[dict[str, Any]]) -> Any:
    """The first trial index logged twice, or None."""
    seen: set[Any] = set()
    for rec in trials:
        index = rec.get("trial")
        if index in seen:
            return index
        seen.add(index)
    return None


def _pm(mean: Any, sd: Any) -> str:
    m = float(mean)
    s = float(sd) if sd is not None else math.nan
    return f"{m:.3f} ± {s:.3f}" if math.isfinite(s) else f"{m:.3f} (n = 1)"


def _p(p: float | None) -> str:
    if p is None:
        return "p n/a"
    return "p < 0.001" if p < 0.001 else f"p = {p:.3f}"


def _finite(value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return 0.0
    return v if math.isfinite(v) else 0.0


__all__ = [
    "UserTestData",
    "UserTestReport",
    "UserTestSession",
    "collect_usertest",
    "confusion_csv",
    "figure8a_png",
    "report_text",
    "write_usertest_report",
]
