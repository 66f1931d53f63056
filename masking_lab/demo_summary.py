"""The demo's closing summary: a model of numbers computed first, then rendered as text.

:func:`build_summary` computes what the summary shows — what ran, every exported masking
function beside the simulation's ground truth (:func:`sample_truth`), the rendered scene per
channel — and :func:`summary_text` renders that model. Pure: no files, no clock.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from masking_lab.core.errors import AnalysisError, MaskingLabError
from masking_lab.simulation.observer import GroundTruth

if TYPE_CHECKING:
    from masking_lab.demo import DemoSettings, SessionDone

__all__ = [
    "ChannelRow",
    "DemoSummary",
    "ParamRow",
    "build_summary",
    "sample_truth",
    "summary_text",
]

# The demo's protocols, in the order each participant runs them.
PROTOCOLS = ("baseline", "experiment1", "experiment2")


def sample_truth(
    truth: GroundTruth,
    participants: Sequence[str],
    pairs: Sequence[tuple[str, str]],
    levels_db_sl: Sequence[float],
) -> tuple[float, float]:
    """The ramp a (pooled) fit estimates: least squares on the participants' mean true shift.

    Each simulated participant's true shift at a level is its true masked AL minus its true
    unmasked AL (individual offsets included, clipped at 0 like the observer's); averaging over
    the participants and ``pairs`` and fitting a ramp gives the number the analysis estimates.

    Parameters
    ----------
    truth : GroundTruth
        The simulation's ground truth.
    participants : sequence of str
        Participant ids (drawn with the runner's population seed 0).
    pairs : sequence of (target, masker)
        The stimulus pairs pooled into one fit.
    levels_db_sl : sequence of float
        Masker levels the fit used, dB SL.

    Returns
    -------
    (intercept_db, slope)
    """
    from masking_lab.analysis.ramp_fit import fit_ramp
    from masking_lab.simulation.observer import make_participant

    x = np.asarray(levels_db_sl, dtype=float)
    people = [make_participant(truth, pid, 0) for pid in participants]
    shifts = [
        [p.masked_al_db_v(t, m, level) - p.unmasked_al_db_v[t] for level in x]
        for p in people
        for t, m in pairs
    ]
    fit = fit_ramp(x, np.mean(shifts, axis=0))
    if fit.intercept_db is None or fit.slope is None:
        raise AnalysisError(fit.message)
    return float(fit.intercept_db), float(fit.slope)


@dataclass(frozen=True)
class ParamRow:
    """One exported masking function beside the simulation's ground truth.

    Attributes
    ----------
    pair : str
        ``target|masker``.
    pooled_with : str
        The other frequency levels of its pooled group (``-``: none).
    status, message : str
        Fit status and its message (empty when fitted).
    a, b : float or None
        Fitted intercept (dB) and slope (dB per dB SL).
    a_ci, b_ci : (float, float) or None
        Their intervals.
    truth : (float, float) or None
        The ground truth's (intercept dB, slope) for what the fit estimates (None: no truth).
    verdict : str
        Whether the truth lies within the intervals: ``yes``, ``a only``, ``b only``, ``no``.
    """

    pair: str
    pooled_with: str
    status: str
    message: str
    a: float | None = None
    b: float | None = None
    a_ci: tuple[float, float] | None = None
    b_ci: tuple[float, float] | None = None
    truth: tuple[float, float] | None = None
    verdict: str = ""


@dataclass(frozen=True)
class ChannelRow:
    """One channel of the rendered scene: compensated inputs and the uncompensated error.

    Attributes
    ----------
    name, stimulus : str
        ``MV``/``EV`` and the stimulus it plays.
    input_range_db_sl : (float, float) or None
        Range of the compensated inputs, dB SL.
    worst_error_db : float
        Worst perceived error without compensation, dB.
    not_felt, n_points : int
        Points not felt without compensation, of all points.
    above_rating : int
        Points whose compensated input is above the rig's rating (flagged, not clipped).
    max_rated_db_sl : float or None
        The rig's rating, dB SL.
    """

    name: str
    stimulus: str
    input_range_db_sl: tuple[float, float] | None
    worst_error_db: float
    not_felt: int
    n_points: int
    above_rating: int
    max_rated_db_sl: float | None


@dataclass(frozen=True)
class DemoSummary:
    """The numbers of the demo's closing summary (rendered by :func:`summary_text`).

    Attributes
    ----------
    out : Path
        The demo folder.
    participants, n_sessions, n_sets, n_completed, n_trials : int
        What ran.
    device : str
        ``firmware`` (the C firmware's host build), ``emulator`` or ``sim``.
    timings : mapping or None
        Seconds: ``collect``, ``analyse``, ``total``.
    params : tuple of ParamRow
        The exported functions beside the truth.
    scene : (name, mv, ev, b·d) or None
        The rendered scene's masking pair.
    channels : tuple of ChannelRow
        Per channel of the scene.
    n_warnings : int
        Analysis notes in the report.
    mapping : str
        The gamut mapping the scene was rendered with.
    strategies : tuple of (name, rms dB, max dB, geometry r, texture sd dB, share within)
        Each gamut mapping's result as played (the trade between them).
    gamut_outline : tuple of (m_p, e_p) or None
        The perceptual gamut's outline, dB SL (None: folded, b·d ≥ 1, or no ratings).
    points_moved : int
        The scene's targets the mapping moved into the gamut.
    """

    out: Path
    participants: int
    n_sessions: int
    n_sets: int
    n_completed: int
    n_trials: int
    device: str
    timings: Mapping[str, float] | None
    params: tuple[ParamRow, ...]
    scene: tuple[str, str, str, float] | None
    channels: tuple[ChannelRow, ...]
    n_warnings: int
    mapping: str = "none"
    strategies: tuple[tuple[str, float, float, float, float, float], ...] = ()
    gamut_outline: tuple[tuple[float, float], ...] | None = None
    points_moved: int = 0


def build_summary(
    settings: DemoSettings,
    sessions: Sequence[SessionDone],
    params: Mapping[str, Any],
    truth: GroundTruth,
    rendering: Mapping[str, Any],
    *,
    warnings: Sequence[str] = (),
    timings: Mapping[str, float] | None = None,
) -> DemoSummary:
    """Compute the summary's numbers: what ran, fitted vs true parameters, the scene.

    Parameters
    ----------
    settings : DemoSettings
        The demo's settings.
    sessions : sequence of SessionDone
        The sessions that ran.
    params : mapping
        ``masking_params.json`` as read.
    truth : GroundTruth
        The simulation's ground truth.
    rendering : mapping
        :func:`masking_lab.rendering.render.summarize` of the scene.
    warnings : sequence of str
        The analysis' warnings.
    timings : mapping or None
        Seconds per stage.

    Returns
    -------
    DemoSummary

    Examples
    --------
    >>> summary = build_summary(settings, sessions, params, truth, rendering)  # doctest: +SKIP
    """
    people = [f"S{i:02d}" for i in range(1, settings.participants + 1)]
    mm = rendering.get("masking") or {}
    channels = tuple(
        ChannelRow(
            name=name,
            stimulus=ch["stimulus"],
            input_range_db_sl=tuple(ch["input_range_db_sl"]) if ch["input_range_db_sl"] else None,
            worst_error_db=float(ch["uncompensated"]["max_abs_error_db"]),
            not_felt=int(ch["uncompensated"]["points_not_felt"]),
            n_points=int(rendering["n_points"]),
            above_rating=int(ch["points_above_rating"]),
            max_rated_db_sl=ch["max_rated_db_sl"],
        )
        for name, ch in (rendering.get("channels") or {}).items()
    )
    return DemoSummary(
        out=Path(settings.out),
        participants=settings.participants,
        n_sessions=len(sessions),
        n_sets=sum(s.n_sets for s in sessions),
        n_completed=sum(s.n_completed for s in sessions),
        n_trials=sum(s.n_trials for s in sessions),
        device=settings.device.partition(":")[0],  # firmware:PROGRAM -> firmware
        timings=timings,
        params=tuple(_param_row(f, truth, people) for f in params.get("functions", [])),
        scene=(rendering["scene"], mm["mv"], mm["ev"], float(mm["bd"])) if mm else None,
        channels=channels if mm else (),
        n_warnings=len(warnings),
        **_mapping(rendering),
    )


def _mapping(rendering: Mapping[str, Any]) -> dict[str, Any]:
    gm = rendering.get("gamut_mapping") or {}

    def num(t: Mapping[str, Any], key: str) -> float:
        v = t.get(key)
        return math.nan if v is None else float(v)

    rows = tuple(
        (
            name,
            num(t, "rms_error_db"),
            num(t, "max_error_db"),
            num(t, "geometry_correlation"),
            num(t, "texture_sd_db"),
            num(t, "share_within_ratings"),
        )
        for name, t in (gm.get("strategies") or {}).items()
    )
    outline = (rendering.get("gamut") or {}).get("outline")
    return {
        "mapping": gm.get("strategy", "none"),
        "strategies": rows,
        "gamut_outline": None if not outline else tuple((float(m), float(e)) for m, e in outline),
        "points_moved": int(gm.get("points_moved") or 0),
    }


def summary_text(m: DemoSummary) -> str:
    """The demo's closing summary as text: what ran, where the files are, fitted vs truth.

    Parameters
    ----------
    m : DemoSummary
        From :func:`build_summary`.

    Returns
    -------
    str
        Lines joined by newlines (intercepts in dB, levels in dB SL, times in s).

    Examples
    --------
    >>> print(summary_text(build_summary(settings, sessions, params, truth, r)))  # doctest: +SKIP
    """
    out = m.out
    lines = [
        "",
        "masking-lab demo: done",
        f"  ran      {m.n_sessions} sessions ({m.participants} participants x "
        f"{', '.join(PROTOCOLS)}), {m.n_sets} staircases ({m.n_completed} completed), "
        f"{m.n_trials} trials through the {m.device}",
    ]
    if m.timings:
        lines.append(
            f"  time     {m.timings['total']:.0f} s (sessions {m.timings['collect']:.0f} s, "
            f"analysis {m.timings['analyse']:.0f} s)"
        )
    lines += [
        f"  logs     {out / 'data'}/<participant>/*.jsonl",
        f"  analysis {out / 'analysis'}/ (report.html, report.txt, thresholds.csv, anova.csv, "
        "figures/)",
        f"  params   {out / 'analysis' / 'masking_params.json'}",
        f"  scene    {out / 'render'}/ (points.csv, summary.json, figure4.png, gamut.png)",
        "",
        "Masking functions: fitted (95 % interval) beside the simulation's ground truth",
        f"  {'target|masker':<14} {'pooled with':<14} {'intercept dB':>24} {'slope':>20}"
        f"  {'truth a, b':>14}  within interval",
    ]
    lines += [_param_text(r) for r in m.params]
    lines.append(
        "  (truth: the ramp through the simulated participants' mean true AL shift, pooled pairs"
        " averaged)"
    )
    if m.scene is not None:
        name, mv, ev, bd = m.scene
        lines += ["", f"Scene {name}: {mv} with {ev}, b·d = {bd:.2f}"]
        for ch in m.channels:
            lo, hi = ch.input_range_db_sl or (math.nan, math.nan)
            text = (
                f"  {ch.name} ({ch.stimulus}): compensated inputs {lo:.1f}..{hi:.1f} dB SL; "
                f"without compensation worst error {ch.worst_error_db:.1f} dB, "
                f"{ch.not_felt} of {ch.n_points} points not felt"
            )
            if ch.above_rating:
                text += (
                    f"; {ch.above_rating} points need more than the rig's "
                    f"{ch.max_rated_db_sl:g} dB SL (flagged, not clipped)"
                )
            lines.append(text)
        if m.gamut_outline is not None:
            vertices = ", ".join(f"({mp:.1f}, {ep:.1f})" for mp, ep in m.gamut_outline)
            lines.append(
                f"  perceptual gamut (m_p, e_p dB SL) within the rig's ratings: {vertices}; "
                f"{m.points_moved} of {m.channels[0].n_points if m.channels else 0} targets "
                "lay outside it"
            )
        if m.strategies:
            lines += [
                f"  gamut mapping (rendered with {m.mapping}), as the rig plays it:",
                f"    {'strategy':<9} {'RMS dB':>7} {'max dB':>7} {'geometry r':>10} "
                f"{'texture sd dB':>13} {'within ratings':>15}",
            ]
            lines += [
                f"    {n:<9} {rms:>7.2f} {mx:>7.2f} {r:>10.3f} {sd:>13.2f} {100 * w:>14.0f}%"
                for n, rms, mx, r, sd, w in m.strategies
            ]
    if m.n_warnings:
        lines += ["", f"Analysis notes ({m.n_warnings}): see {out / 'analysis' / 'report.txt'}"]
    return "\n".join(lines)


def _param_row(f: Mapping[str, Any], truth: GroundTruth, participants: Sequence[str]) -> ParamRow:
    key = f"{f['target']}|{f['masker']}"
    pooled = [p for p in f.get("pooled_pairs") or [] if p != key]
    pooled_txt = (
        ",".join(p.split("|")[1] if p.startswith(f["target"]) else p.split("|")[0] for p in pooled)
        or "-"
    )
    if f.get("status") != "fitted" or f.get("intercept_db") is None:
        return ParamRow(key, pooled_txt, str(f.get("status")), f.get("message") or "")
    pairs = [tuple(p.split("|")) for p in (f.get("pooled_pairs") or [key])]
    lo, hi = f.get("fitted_range_db_sl") or (5, 25)
    levels = np.arange(lo, hi + 1e-9, 5.0) if hi > lo else np.array([lo])
    a, b = f["intercept_db"], f["slope"]
    a_ci = tuple(f["intercept_ci_db"]) if f.get("intercept_ci_db") else None
    b_ci = tuple(f["slope_ci"]) if f.get("slope_ci") else None
    try:
        ta, tb = sample_truth(truth, participants, pairs, [float(v) for v in levels])
    except (KeyError, AttributeError, MaskingLabError, ValueError):
        return ParamRow(key, pooled_txt, "fitted", "", a, b, a_ci, b_ci)
    inside_a = a_ci is not None and a_ci[0] <= ta <= a_ci[1]
    inside_b = b_ci is not None and b_ci[0] <= tb <= b_ci[1]
    verdict = (
        "yes"
        if inside_a and inside_b
        else ("a only" if inside_a else ("b only" if inside_b else "no"))
    )
    return ParamRow(key, pooled_txt, "fitted", "", a, b, a_ci, b_ci, (ta, tb), verdict)


def _param_text(r: ParamRow) -> str:
    if r.status != "fitted" or r.a is None or r.b is None:
        return f"  {r.pair:<14} {r.pooled_with:<14} {r.status}: {r.message}"
    if r.truth is None:
        return f"  {r.pair:<14} {r.pooled_with:<14} (no ground truth for this pair)"
    a_txt = f"{r.a:6.2f} [{r.a_ci[0]:6.2f},{r.a_ci[1]:6.2f}]" if r.a_ci else f"{r.a:6.2f}"
    b_txt = f"{r.b:5.3f} [{r.b_ci[0]:5.3f},{r.b_ci[1]:5.3f}]" if r.b_ci else f"{r.b:5.3f}"
    ta, tb = r.truth
    return (
        f"  {r.pair:<14} {r.pooled_with:<14} {a_txt:>24} {b_txt:>20}  {ta:6.2f}, {tb:5.3f}  "
        f"{r.verdict}"
    )
