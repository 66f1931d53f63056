"""The model of the user-test report, and its plain-text rendering (``report.txt``).

:func:`build_usertest_model` gathers every number and sentence the report shows — inputs,
correct rates per condition and measure, paired tests, confusion matrices, chance levels and
clipping — from the collected logs and their analysis; :func:`render_usertest_text` and
:func:`masking_lab.usertest.report_html.render_usertest_html` read only the model. Pure.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from masking_lab.usertest.design import CONDITIONS, MEASURES

if TYPE_CHECKING:
    from masking_lab.usertest.report import UserTestData
    from masking_lab.usertest.stats import UserTestAnalysis

__all__ = [
    "ConfusionTable",
    "RateCell",
    "UserTestReportModel",
    "build_usertest_model",
    "chance_levels",
    "participants_text",
    "render_usertest_text",
]

MEASURE_LABELS = {
    "both": "geometry and texture",
    "geometry": "geometry",
    "texture": "texture",
}


@dataclass(frozen=True)
class RateCell:
    """Correct rate of one condition and measure.

    Attributes
    ----------
    condition, measure : str
        E.g. ``compensated``, ``geometry``.
    mean : float
        Mean correct rate over participants (0–1).
    sd : float or None
        Between-participant SD (ddof 1); None with one participant.
    n : int
        Participants.
    """

    condition: str
    measure: str
    mean: float
    sd: float | None
    n: int


@dataclass(frozen=True)
class ConfusionTable:
    """Counts of answers against what was presented.

    Attributes
    ----------
    condition, measure : str
        ``compensated``/``uncompensated`` and ``geometry``/``texture``.
    presented : str
        Header of the row labels (e.g. ``geometry presented``).
    columns : tuple of str
        Answers (the classes, then ``no answer``).
    rows : tuple of (label, counts)
        One per presented class.
    """

    condition: str
    measure: str
    presented: str
    columns: tuple[str, ...]
    rows: tuple[tuple[str, tuple[int, ...]], ...]


@dataclass(frozen=True)
class UserTestReportModel:
    """Everything the user-test report shows.

    Attributes
    ----------
    sessions : tuple of (log, participant, n_logged, n_trials, ended)
        The logs used.
    skipped : tuple of (log, reason)
        Files not used.
    notes : tuple of str
        Caveats (incomplete sessions, truncated lines, repeated participants, clipping).
    n_participants, n_trials : int
        Participants and trials analysed.
    conditions : tuple of str
        Conditions present, in design order.
    rates : tuple of RateCell
        Per condition × measure.
    tests : tuple of PairedComparison
        One per measure.
    confusion : tuple of ConfusionTable
        Per condition × (geometry, texture).
    chance : mapping of measure to float
        Correct rate by guessing (1 / classes; ``both``: 1 / (geometries × textures)).
    clipped_trials : mapping of condition to (clipped, total)
        Trials whose levels were clipped at the rig's limits.
    """

    sessions: tuple[tuple[str, str, int, int, bool], ...]
    skipped: tuple[tuple[str, str], ...]
    notes: tuple[str, ...]
    n_participants: int
    n_trials: int
    conditions: tuple[str, ...]
    rates: tuple[RateCell, ...]
    tests: tuple[Any, ...]
    confusion: tuple[ConfusionTable, ...]
    chance: Mapping[str, float]
    clipped_trials: Mapping[str, tuple[int, int]]

    def rate(self, condition: str, measure: str) -> RateCell | None:
        """The cell of ``condition`` and ``measure``, or None."""
        for r in self.rates:
            if r.condition == condition and r.measure == measure:
                return r
        return None


def participants_text(n: int) -> str:
    """``"1 participant"``, ``"3 participants"``.

    Examples
    --------
    >>> participants_text(1), participants_text(10)
    ('1 participant', '10 participants')
    """
    return f"{n} participant" + ("" if n == 1 else "s")


def _finite(v: Any) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def build_usertest_model(data: UserTestData, analysis: UserTestAnalysis) -> UserTestReportModel:
    """The report's numbers and sentences, from the collected logs and their analysis.

    Parameters
    ----------
    data : UserTestData
        From :func:`masking_lab.usertest.report.collect_usertest`.
    analysis : UserTestAnalysis
        From :func:`masking_lab.usertest.stats.analyze_usertest`.

    Returns
    -------
    UserTestReportModel

    Examples
    --------
    >>> model = build_usertest_model(data, analyze_usertest(data.records, ...))  # doctest: +SKIP
    """
    rates = tuple(
        RateCell(
            str(r["condition"]), str(r["measure"]), float(r["mean"]), _finite(r["sd"]), int(r["n"])
        )
        for r in analysis.summary.to_dict(orient="records")
        if r["measure"] in MEASURES
    )
    present = {r.condition for r in rates}
    confusion = []
    for cond, tables in sorted(analysis.confusion.items()):
        for measure in ("geometry", "texture"):
            t = tables[measure]
            confusion.append(
                ConfusionTable(
                    condition=cond,
                    measure=measure,
                    presented=str(t.index.name),
                    columns=tuple(str(c) for c in t.columns),
                    rows=tuple(
                        (str(idx), tuple(int(v) for v in row.tolist())) for idx, row in t.iterrows()
                    ),
                )
            )
    clipped: dict[str, tuple[int, int]] = {}
    for rec in data.records:
        cond = str(rec.get("condition"))
        k, n = clipped.get(cond, (0, 0))
        clipped[cond] = (k + (1 if rec.get("clipped") else 0), n + 1)
    notes = list(data.notes)
    for cond, (k, n) in sorted(clipped.items()):
        if k:
            notes.append(
                f"{cond}: {k} of {n} trials were clipped at the rig's limits (compensation is "
                "only partial there)"
            )
    return UserTestReportModel(
        sessions=tuple(
            (s.log, s.participant, s.n_logged, s.n_trials, s.ended) for s in data.sessions
        ),
        skipped=tuple((s["log"], s["reason"]) for s in data.skipped),
        notes=tuple(notes),
        n_participants=int(analysis.rates["participant"].nunique()),
        n_trials=len(data.records),
        conditions=tuple(c for c in CONDITIONS if c in present),
        rates=rates,
        tests=tuple(analysis.tests),
        confusion=tuple(confusion),
        chance=chance_levels(data.geometries, data.textures),
        clipped_trials={c: v for c, v in sorted(clipped.items()) if v[0]},
    )


def render_usertest_text(model: UserTestReportModel) -> str:
    """The text report: inputs, correct rates per condition, paired tests, confusion matrices.

    Parameters
    ----------
    model : UserTestReportModel
        From :func:`build_usertest_model`.

    Returns
    -------
    str
        Lines ending with a newline; rates are fractions (0–1).

    Examples
    --------
    >>> text = render_usertest_text(model)  # doctest: +SKIP
    """
    lines = ["User test (Ryu et al. 2020, section 3.3): identification of geometry and texture", ""]
    lines.append(
        f"Logs: {len(model.sessions)} user-test session(s), {model.n_participants} "
        f"participant(s), {model.n_trials} trials; {len(model.skipped)} other file(s) skipped."
    )
    for log, participant, n_logged, n_trials, ended in model.sessions:
        state = "completed" if ended else "INCOMPLETE"
        lines.append(f"  {log}: {participant}, {n_logged}/{n_trials} trials, {state}")
    lines += [f"  skipped {log}: {reason}" for log, reason in model.skipped]
    lines += [f"  note: {note}" for note in model.notes]
    lines += ["", "Correct rate, mean ± SD over participants (no answer counts as wrong):"]
    lines.append(f"  {'condition':<15}" + "".join(f"{m:>18}" for m in MEASURES))
    for cond in model.conditions:
        cells = []
        for m in MEASURES:
            r = model.rate(cond, m)
            cells.append(f"{_pm(r):>18}" if r else f"{'-':>18}")
        lines.append(f"  {cond:<15}" + "".join(cells))
    chance = ", ".join(f"{m} {model.chance[m]:.3f}" for m in MEASURES)
    lines.append(f"  chance (guessing): {chance}")
    lines += ["", "Paired t-tests, compensated vs uncompensated (two-sided):"]
    for t in model.tests:
        if t.t is None:
            lines.append(f"  {t.measure:<9} not tested: {t.note}")
            continue
        lines.append(
            f"  {t.measure:<9} {t.mean_compensated:.3f} vs {t.mean_uncompensated:.3f}, "
            f"difference {t.mean_difference:+.3f}, t({t.n - 1}) = {t.t:.3f}, {_p(t.p)}, "
            f"d_z = {t.dz:.2f}"
        )
    for c in model.confusion:
        lines += ["", f"Confusion, {c.measure}, {c.condition} (rows presented, columns answered):"]
        lines += ["  " + line for line in _grid(c)]
    lines.append("")
    return "\n".join(lines)


def _grid(c: ConfusionTable) -> list[str]:
    labels = [c.presented, *(label for label, _ in c.rows)]
    first = max(len(s) for s in labels)
    widths = [
        max(len(col), *(len(str(r[1][i])) for r in c.rows)) for i, col in enumerate(c.columns)
    ]
    out = [
        f"{'':<{first}}  "
        + "  ".join(f"{col:>{w}}" for col, w in zip(c.columns, widths, strict=True))
    ]
    out.append(c.presented)
    for label, counts in c.rows:
        out.append(
            f"{label:<{first}}  "
            + "  ".join(f"{v:>{w}}" for v, w in zip(counts, widths, strict=True))
        )
    return out


def _pm(r: RateCell) -> str:
    return f"{r.mean:.3f} ± {r.sd:.3f}" if r.sd is not None else f"{r.mean:.3f} (n = 1)"


def _p(p: float | None) -> str:
    if p is None:
        return "p n/a"
    return "p < 0.001" if p < 0.001 else f"p = {p:.3f}"


def chance_levels(geometries: Sequence[str], textures: Sequence[str]) -> dict[str, float]:
    """Correct rate by guessing per measure (1 / classes; ``both`` needs both right).

    Examples
    --------
    >>> chance_levels(["bump", "hole"], ["smooth", "rough", "fine"])["both"]
    0.16666666666666666
    """
    return {
        "both": 1.0 / max(1, len(geometries) * len(textures)),
        "geometry": 1.0 / max(1, len(geometries)),
        "texture": 1.0 / max(1, len(textures)),
    }
