"""The analysis report as fixed-width plain text (``report.txt``), from the report model.

Reads only :class:`masking_lab.analysis.report.ReportModel`, so the same inputs and settings give
the same bytes. :mod:`masking_lab.analysis.report_html` renders the same model as HTML.
"""

from __future__ import annotations

from collections.abc import Sequence

from masking_lab.analysis.experiment import GroupFit
from masking_lab.analysis.pooling import PoolingDecision
from masking_lab.analysis.report import (
    ExperimentSection,
    LogsInput,
    ReportModel,
    ShiftsTableInput,
    ThresholdsSection,
    experiment_heading,
)
from masking_lab.analysis.report_lab import lab_text_sections
from masking_lab.analysis.t_tests import PairedTest

__all__ = ["render_text"]


def render_text(model: ReportModel) -> str:
    """The report as fixed-width plain text (``report.txt``).

    Parameters
    ----------
    model : ReportModel
        From :func:`build_report`.

    Returns
    -------
    str
        Lines joined by ``\\n``, ending with a newline; shifts and intercepts in dB, levels in
        dB SL.

    Examples
    --------
    >>> from masking_lab.analysis.report import ShiftsTableInput, build_report
    >>> from masking_lab.analysis.settings import AnalysisSettings
    >>> model = build_report(
    ...     [], AnalysisSettings(), source="fit", inputs=ShiftsTableInput("s.csv", 4, None)
    ... )
    >>> render_text(model).splitlines()[5]
    '  shifts table: s.csv (4 rows, cell means without participants)'
    """
    out = [f"masking-lab {model.source} report (software {model.software_version})", "=" * 72]
    if model.created_utc:
        out.append(f"export created: {model.created_text}")
    out += _section("Inputs", _input_lines(model.inputs))
    out += _section("Settings", [f"  {k}: {v}" for k, v in model.settings])
    if model.thresholds is not None:
        out += _section("Thresholds", _threshold_lines(model.thresholds))
    for e in model.experiments:
        out += _section(experiment_heading(e.experiment), _experiment_lines(e))
    if model.lab is not None:
        for title, lines in lab_text_sections(model.lab):
            out += _section(title, lines)
    if model.export_notes:
        out += _section("Export", [f"  {n}" for n in model.export_notes])
    out.append("")
    return "\n".join(out)


def _section(title: str, lines: list[str]) -> list[str]:
    return ["", title, "-" * len(title), *lines]


def _input_lines(inputs: LogsInput | ShiftsTableInput) -> list[str]:
    if isinstance(inputs, ShiftsTableInput):
        who = (
            "cell means without participants)"
            if inputs.n_participants is None
            else f"{inputs.n_participants} participants)"
        )
        return [f"  shifts table: {inputs.path} ({inputs.n_rows} rows, " + who]
    out = [
        f"  data folder: {inputs.data_dir}",
        f"  logs found: {inputs.n_found}; analysed: {inputs.n_analysed}; "
        f"skipped: {len(inputs.skipped)}",
    ]
    out += [f"  SKIPPED {path}: {reason}" for path, reason in inputs.skipped]
    out += [f"  {log}: {problem} ({action})" for log, problem, action in inputs.line_problems]
    out += [f"  RIG CHANGED {w}" for w in inputs.rig_warnings]
    return out


def _threshold_lines(t: ThresholdsSection) -> list[str]:
    out = ["  sets by status: " + ", ".join(f"{k} {v}" for k, v in t.status_counts)]
    if t.excluded:
        out.append("  excluded from the statistics (never averaged into a threshold):")
        for s in t.excluded:
            what = s.target if s.masker is None else f"{s.target}|{s.masker}"
            lvl = "" if s.masker_level_db_sl is None else f" @ {s.masker_level_db_sl:g} dB SL"
            out.append(
                f"    {s.participant} {s.experiment} {s.set_id} ({what}{lvl}): "
                f"{s.status} — {s.note}".rstrip(" —")
            )
    if t.unmasked_sources:
        out.append(
            "  masked sets' unmasked ALs (the reference of each shift) from: "
            + ", ".join(f"{k} ({v} masked sets)" for k, v in t.unmasked_sources)
        )
    for note, n in t.model_notes:  # the caveat beside the intervals (al_ci95_* columns)
        out.append(f"  intervals of {n} set(s): {note}")
    return out


def _experiment_lines(e: ExperimentSection) -> list[str]:
    pairs = ", ".join(f"{lv} → {t}|{m}" for lv, t, m in e.frequency_levels)
    out = [f"  frequency factor (MV stimulus of each pair): {pairs}"]
    if e.participants:
        out.append(f"  participants: {len(e.participants)} ({', '.join(e.participants)})")
    out += [f"  NOTE: {note}" for note in e.notes]
    if e.anova:
        out += ["", *_anova_lines(e)]
    if e.posthoc:
        out += ["", *_posthoc_lines(e.posthoc)]
    out += ["", *_shift_grid_lines(e)]
    out += ["", *_pooling_lines(e.pooling)]
    out += ["", *_fit_lines(e.fits)]
    return out


def _anova_lines(e: ExperimentSection) -> list[str]:
    out = [
        f"  Two-way repeated-measures ANOVA on AL shift (n = {e.anova_n})",
        f"    {'effect':<16}{'F':>9}{'df1':>5}{'df2':>5}{'p':>11}{'eps_GG':>8}"
        f"{'p_GG':>11}{'np2':>7}   Mauchly W, p",
    ]
    for a in e.anova:
        mw = "—" if a.mauchly_w is None else f"{a.mauchly_w:.3f}"
        mp = "—" if a.mauchly_p is None else _p(a.mauchly_p)
        out.append(
            f"    {a.name:<16}{a.F:9.3f}{a.df1:5d}{a.df2:5d}{_p(a.p):>11}"
            f"{a.eps_gg:8.3f}{_p(a.p_gg):>11}{a.np2:7.3f}   {mw}, {mp}"
        )
        if a.note:
            out.append(f"      ({a.note})")
    return out


def _posthoc_lines(tests: Sequence[PairedTest]) -> list[str]:
    out = ["  Paired comparisons between frequency levels (Bonferroni)"]
    for t in tests:
        if t.t is None:
            out.append(f"    {t.a} vs {t.b}: mean diff {t.mean_diff:+.3f} dB; {t.note}")
        else:
            out.append(
                f"    {t.a} vs {t.b}: mean diff {t.mean_diff:+.3f} dB, "
                f"t({t.df}) = {t.t:.3f}, {_p_eq(t.p)}, Bonferroni {_p_eq(t.p_bonf)}"
            )
    return out


def _shift_grid_lines(e: ExperimentSection) -> list[str]:
    legend = "* = not different from 0 (two-tailed t-test)"
    if e.untestable:
        legend += "; ? = test not computable (zero variance or one participant)"
    out = [
        f"  Mean AL shift per cell (dB); {legend}"
        if e.tested
        else "  Mean AL shift per cell (dB; not tested against 0: no participant data)",
        "    " + f"{'':<10}" + "".join(f"{v:>11g}" for v in e.masker_levels_db_sl) + "  dB SL",
    ]
    for row in e.shifts:
        line = f"    {row.mv_stimulus:<10}"
        for c in row.cells:
            if c is None:
                line += f"{'—':>11}"
                continue
            star = ""
            if c.tested:
                star = "?" if c.differs_from_zero is None else ("" if c.differs_from_zero else "*")
            line += f"{star + format(c.mean_shift_db, '.3f'):>11}"
        out.append(line)
    return out


def _pooling_lines(pooling: PoolingDecision) -> list[str]:
    groups = "; ".join("+".join(g) for g in pooling.groups)
    lines = [f"  Pooling ({pooling.rule}): {groups}", *(f"    {r}" for r in pooling.reasons)]
    if pooling.model_comparison:
        lines.append("    Model comparison (likelihood ratio, AIC, BIC; reported, not used):")
        lines += [f"      {r}" for r in pooling.model_comparison]
    return lines


def _fit_lines(fits: Sequence[GroupFit]) -> list[str]:
    out = ["  Ramp fits: shift = max(0, a + b·x), x = masker level (dB SL)"]
    for g in fits:
        f = g.fit
        out.append(f"    {g.label} [{', '.join(g.pairs)}]: {f.status}")
        if f.intercept_db is not None and f.slope is not None:
            knee = "none" if f.knee_db_sl is None else f"{f.knee_db_sl:.2f} dB SL"
            adj = "—" if f.adj_r2 is None else f"{f.adj_r2:.4f}"
            adj_a = "—" if f.adj_r2_active is None else f"{f.adj_r2_active:.4f}"
            out += [
                f"      a = {f.intercept_db:.3f} dB {_unc(f.intercept_se_db, f.intercept_ci_db)}",
                f"      b = {f.slope:.4f} {_unc(f.slope_se, f.slope_ci)}",
                f"      knee −a/b = {knee}; fitted {f.fitted_range_db_sl[0]:g}–"
                f"{f.fitted_range_db_sl[1]:g} dB SL on {f.n_points} cell means; "
                f"adj. R² = {adj} (above the knee only: {adj_a}); "
                f"uncertainty: {f.uncertainty}",
            ]
        if f.message:
            out.append(f"      note: {f.message}")
    return out


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
