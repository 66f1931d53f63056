"""The report sections on participants (pure): study status, psychometric functions, figures.

:class:`LabSection` is part of :class:`masking_lab.analysis.report.ReportModel`;
:func:`lab_text_sections` gives its ``report.txt`` sections (title, lines) and the template
``analysis.html.j2`` renders the same fields, under the same headings, in ``report.html``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike

from masking_lab.analysis.psychometric import PFFit, binned, pf_curve
from masking_lab.analysis.study_status import OUTLIER_RULE, CellStatus, Outlier

__all__ = [
    "LAB_HEADINGS",
    "LabSection",
    "PFPlot",
    "PFRow",
    "lab_text_sections",
    "pf_plot",
    "status_lines",
]

# Section titles, shared by both renderers (the heading-parity test reads them from the pages).
LAB_HEADINGS = {
    "status": "Study status",
    "unmasked": "Unmasked ALs per participant",
    "outliers": "Outlier flags",
    "pf": "Psychometric functions",
    "figures": "Figures",
}


@dataclass(frozen=True)
class PFPlot:
    """One set's psychometric function as an inline SVG draws it (pixels, y down).

    Attributes
    ----------
    width, height : int
        Size of the drawing, px.
    points : tuple of (x, y, radius, n)
        Proportion correct at each level run; the radius grows with the trials ``n`` there.
    curve : str
        The fitted function as SVG polyline points (empty without a fit).
    threshold_x, al_x : float or None
        α and the AL at the track's target p, px.
    guess_y : float
        The guess rate, px.
    x_ticks, y_ticks : tuple of (position px, label)
        Axis ticks (dB; p(correct)).
    """

    width: int
    height: int
    points: tuple[tuple[float, float, float, int], ...]
    curve: str
    threshold_x: float | None
    al_x: float | None
    guess_y: float
    x_ticks: tuple[tuple[float, str], ...]
    y_ticks: tuple[tuple[float, str], ...]


_W, _H, _L, _R, _T, _B = 250, 170, 38, 8, 8, 30  # size and margins of a PF plot, px


def pf_plot(levels_db: ArrayLike, correct: ArrayLike, fit: PFFit) -> PFPlot:
    """The geometry of one set's PF plot: binned proportions with n, the curve, α and AL.

    Examples
    --------
    >>> from masking_lab.analysis.psychometric import fit_pf
    >>> x, r = [0.0, 2.0, 4.0] * 10, [False, True, True] * 10
    >>> plot = pf_plot(x, r, fit_pf(x, r, n_boot=0))
    >>> len(plot.points), plot.points[0][3], plot.threshold_x is not None
    (3, 10, True)
    """
    x, n, k = binned(levels_db, correct)
    lo, hi = (float(x.min()), float(x.max())) if x.size else (0.0, 1.0)
    pad = max(1.0, 0.1 * (hi - lo))
    lo, hi = lo - pad, hi + pad

    def px(v: float) -> float:
        return round(_L + (v - lo) / (hi - lo) * (_W - _L - _R), 1)

    def py(p: float) -> float:
        return round(_T + (1.0 - p) * (_H - _T - _B), 1)

    pts = tuple(
        (px(float(xi)), py(float(ki / ni)), round(2.0 + 1.2 * float(np.sqrt(ni)), 1), int(ni))
        for xi, ni, ki in zip(x, n, k, strict=True)
    )
    curve, thr, al = "", None, None
    th, slope, lapse = fit.threshold_db, fit.slope_per_db, fit.lapse  # all set when fit.ok
    if fit.ok and th is not None and slope is not None and lapse is not None:
        xs = np.linspace(lo, hi, 60)
        ys = pf_curve(xs, th, slope, lapse, fit.guess)
        curve = " ".join(f"{px(float(a))},{py(float(b))}" for a, b in zip(xs, ys, strict=True))
        thr = px(th) if lo <= th <= hi else None
        al = px(fit.al_db) if fit.al_db is not None and lo <= fit.al_db <= hi else None
    step = max(1, int(np.ceil((hi - lo) / 5)))
    ticks = np.arange(np.ceil(lo / step) * step, hi + 1e-9, step)
    return PFPlot(
        _W,
        _H,
        pts,
        curve,
        thr,
        al,
        py(fit.guess),
        tuple((px(float(t)), f"{float(t) + 0.0:g}") for t in ticks),
        tuple((py(p), f"{p:g}") for p in (0.0, 0.5, 1.0)),
    )


@dataclass(frozen=True)
class PFRow:
    """One participant × set's psychometric function, as the report shows it.

    Attributes
    ----------
    participant, experiment, set_id, unit : str
        The set and its level unit (``dB SL`` or ``dB re 1 V``).
    n_trials : int
        Trials fitted.
    threshold_db, slope_per_db, lapse, deviance, deviance_p : float or None
        α (dB), β (1/dB), λ, deviance and its bootstrap p.
    threshold_ci_db : tuple or None
        95 % interval of α, dB.
    note : str
        Why there is no fit, or a caution.
    label : str
        The set as a reader names it (``EV270|MV120 @ 20 dB SL``).
    plot : PFPlot or None
        Its drawing in ``report.html``.
    """

    participant: str
    experiment: str
    set_id: str
    unit: str
    n_trials: int
    threshold_db: float | None
    threshold_ci_db: tuple[float, float] | None
    slope_per_db: float | None
    lapse: float | None
    deviance: float | None
    deviance_p: float | None
    note: str
    label: str = ""
    plot: PFPlot | None = None


@dataclass(frozen=True)
class LabSection:
    """What ``analyze`` reports per participant.

    Attributes
    ----------
    experiments : tuple of str
        Protocol columns of the matrix.
    matrix : tuple of CellStatus
        Participant × protocol cells, participant-major.
    unmasked : tuple of (participant, ((stimulus, AL dB re 1 V), ...))
        Completed baseline ALs.
    outliers : tuple of Outlier
        Values flagged by :data:`masking_lab.analysis.study_status.OUTLIER_RULE`.
    pf : tuple of PFRow
        One per fitted participant × set.
    figures : tuple of (path, caption)
        Every figure the run wrote, paths relative to the output folder.
    outlier_rule : str
        The rule of the outlier flags, in words.
    embedded : tuple of (path, data URI)
        Figures shown in ``report.html`` itself (the individual shift plots), so the page
        needs no file beside it.
    """

    experiments: tuple[str, ...]
    matrix: tuple[CellStatus, ...]
    unmasked: tuple[tuple[str, tuple[tuple[str, float], ...]], ...]
    outliers: tuple[Outlier, ...]
    pf: tuple[PFRow, ...]
    figures: tuple[tuple[str, str], ...] = ()
    outlier_rule: str = OUTLIER_RULE
    embedded: tuple[tuple[str, str], ...] = ()

    @property
    def participants(self) -> tuple[str, ...]:
        """Rows of the matrix, in order."""
        return tuple(dict.fromkeys(c.participant for c in self.matrix))

    def cell(self, participant: str, experiment: str) -> CellStatus | None:
        """The matrix cell of a participant and protocol (the first, if listed twice)."""
        return self._cells.get((participant, experiment))

    def pf_of(self, participant: str) -> tuple[PFRow, ...]:
        """The participant's rows of :attr:`pf`, in their order.

        Examples
        --------
        >>> r = PFRow("P1", "e1", "A", "dB SL", 30, 1.0, None, 0.5, 0.02, 3.0, 0.4, "")
        >>> lab = LabSection((), (), (), (), (r,))
        >>> lab.pf_of("P1") == (r,), lab.pf_of("P2")
        (True, ())
        """
        return self._pf_by_participant.get(participant, ())

    # Indexes built once: the report asks for every participant's cells and rows, and a scan
    # per question grows with the square of the study (hours at 10,000 sessions).
    @cached_property
    def _cells(self) -> dict[tuple[str, str], CellStatus]:
        cells: dict[tuple[str, str], CellStatus] = {}
        for c in self.matrix:
            cells.setdefault((c.participant, c.experiment), c)
        return cells

    @cached_property
    def _pf_by_participant(self) -> dict[str, tuple[PFRow, ...]]:
        groups: dict[str, list[PFRow]] = {}
        for r in self.pf:
            groups.setdefault(r.participant, []).append(r)
        return {p: tuple(rows) for p, rows in groups.items()}


def _f(v: float | None, fmt: str = ".2f") -> str:
    return "—" if v is None else format(v, fmt)


def status_lines(lab: LabSection) -> list[str]:
    """The participant × protocol matrix as fixed-width lines (``masking-lab status``).

    Examples
    --------
    >>> c = CellStatus("P1", "e1", "partial", 2, 15, 130, 1)
    >>> status_lines(LabSection(("e1",), (c,), (), (), ()))[1]
    '  P1          partial 2/15 sets, 130 trials'
    """
    width = max([len(c.text) for c in lab.matrix] + [len(e) for e in lab.experiments] + [8])
    out = [
        (
            "  " + f"{'participant':<12}" + "".join(f"{e:<{width + 2}}" for e in lab.experiments)
        ).rstrip()
    ]
    for p in lab.participants:
        cells = [lab.cell(p, e) for e in lab.experiments]
        out.append(
            "  "
            + f"{p:<12}"
            + "".join(f"{(c.text if c else 'missing'):<{width + 2}}" for c in cells).rstrip()
        )
    return out


def lab_text_sections(lab: LabSection) -> list[tuple[str, list[str]]]:
    """The sections of :class:`LabSection` in ``report.txt``: (title, lines).

    Examples
    --------
    >>> [t for t, _ in lab_text_sections(LabSection((), (), (), (), ()))][:3]
    ['Study status', 'Unmasked ALs per participant', 'Outlier flags']
    """
    h = LAB_HEADINGS
    unmasked = [
        f"  {p}: " + ", ".join(f"{t} {v:.2f} dB re 1 V" for t, v in als) for p, als in lab.unmasked
    ] or ["  none (no completed baseline set)"]
    outl = [f"  rule: {lab.outlier_rule}"]
    outl += [
        f"  {o.participant}: {o.what} = {o.value_db:.2f} dB (others' mean {o.others_mean_db:.2f}, "
        f"z {o.z:+.1f})"
        for o in lab.outliers
    ] or ["  none flagged"]
    pf = [
        "  p(correct) = γ + (1 − γ − λ)/(1 + exp(−β(x − α))); α threshold, β slope (1/dB), "
        "λ lapse; 95 % parametric-bootstrap intervals in psychometric.csv",
        f"  {'participant':<12}{'experiment':<14}{'set':<22}{'n':>4}{'α (dB)':>9}"
        f"{'α 95 %':>18}{'β':>7}{'λ':>7}{'deviance':>10}{'p':>7}",
    ]
    for r in lab.pf:
        ci = (
            "—"
            if r.threshold_ci_db is None
            else f"[{r.threshold_ci_db[0]:.1f}, {r.threshold_ci_db[1]:.1f}]"
        )
        pf.append(
            f"  {r.participant:<12}{r.experiment:<14}{r.set_id:<22}{r.n_trials:>4}"
            f"{_f(r.threshold_db):>9}{ci:>18}{_f(r.slope_per_db):>7}{_f(r.lapse, '.3f'):>7}"
            f"{_f(r.deviance):>10}{_f(r.deviance_p):>7}" + (f"  {r.note}" if r.note else "")
        )
    figs = [f"  {path}: {caption}" for path, caption in lab.figures] or ["  none drawn"]
    return [
        (h["status"], status_lines(lab)),
        (h["unmasked"], unmasked),
        (h["outliers"], outl),
        (h["pf"], pf),
        (h["figures"], figs),
    ]
