"""Gamut mapping: bring a scene's perceived targets inside what the rig can render (issue 19.2).

Strategies (all levels dB SL):

- ``clip``: each point out of the gamut moves to the nearest renderable pair (Euclidean, dB).
- ``scale``: one gain s ≤ 1 on every target (both channels, toward 0 dB SL), the largest that
  fits the whole scene; keeps both profiles' shape exactly and loses level.
- ``compress``: a soft knee along the ray from 0 dB SL to each target, as tone mapping does:
  a point at fraction ρ of the way to the gamut's edge along its ray stays where it is while
  ρ ≤ :data:`KNEE`, and beyond it ρ is squeezed smoothly (tanh) below 1, so the order of levels
  along the path, the geometry's contrast profile, survives.
- ``none``: targets unchanged (the solver flags what the rig cannot play).

:func:`playable_inputs` turns mapped targets into inputs within the ratings in every case: the
solver's answer where it is unique and within the box, else inputs found on the gamut's edge
from the box's corners (:meth:`~masking_lab.rendering.gamut.Gamut.boundary_inputs`), never a
non-finite number. :func:`mapping_metrics` scores a rendering against what the scene intended.
Pure: no I/O.
"""

from __future__ import annotations

import math
from typing import Any, SupportsFloat

import numpy as np
from numpy.typing import NDArray

from masking_lab.core.errors import SolverError
from masking_lab.rendering.gamut import Gamut

__all__ = ["KNEE", "STRATEGIES", "map_targets", "mapping_metrics", "playable_inputs"]

STRATEGIES = ("clip", "scale", "compress", "none")
#: Fraction of the way to the gamut's edge below which ``compress`` leaves a point alone.
KNEE = 0.7
#: A rendered point counts as "at its target" within this many dB on both channels.
AT_TARGET_DB = 0.5

Arr = NDArray[np.float64]


def map_targets(g: Gamut, mv_db_sl: Arr, ev_db_sl: Arr, strategy: str) -> tuple[Arr, Arr, float]:
    """Mapped targets (dB SL) and the gain used (1.0 except for ``scale``).

    A channel the scene does not play (−inf everywhere) stays −inf; the other is mapped against
    the gamut's edge at that channel's floor.

    Parameters
    ----------
    g : Gamut
        What the rig can render.
    mv_db_sl, ev_db_sl : ndarray
        Intended perceived targets per point, dB SL.
    strategy : {"clip", "scale", "compress", "none"}
        See the module docstring.

    Returns
    -------
    mv_db_sl, ev_db_sl : ndarray
        Mapped targets, dB SL.
    gain : float
        The common gain of ``scale`` (1.0 otherwise).

    Examples
    --------
    >>> from masking_lab.rendering.gamut import perceptual_gamut
    >>> from masking_lab.rendering.pair import MutualMasking
    >>> g = perceptual_gamut(MutualMasking(0.0, 0.0, 0.0, 0.0), 30.0, 20.0)  # no masking
    >>> m, e, s = map_targets(g, np.array([10.0, 15.0]), np.array([10.0, 40.0]), "scale")
    >>> np.round(m, 9).tolist(), np.round(e, 9).tolist(), round(s, 9)
    ([5.0, 7.5], [5.0, 20.0], 0.5)
    """
    if strategy not in STRATEGIES:
        raise SolverError(f"unknown gamut mapping {strategy!r}; use one of {', '.join(STRATEGIES)}")
    m = np.array(mv_db_sl, dtype=float)
    e = np.array(ev_db_sl, dtype=float)
    if strategy == "none":
        return m, e, 1.0
    m_off, e_off = bool(np.all(m == -np.inf)), bool(np.all(e == -np.inf))
    # A silent channel sits at its floor for the geometry (it masks nothing there).
    mw = np.full_like(m, g.mv_box_db_sl[0]) if m_off else m.copy()
    ew = np.full_like(e, g.ev_box_db_sl[0]) if e_off else e.copy()
    ok = np.isfinite(mw) & np.isfinite(ew)
    gain = 1.0
    if strategy == "clip":
        qm, qe = g.nearest(mw[ok], ew[ok])
        mw[ok], ew[ok] = qm, qe
    elif strategy == "scale":
        gain = _largest_gain(g, mw[ok], ew[ok], m_off, e_off)
        if not m_off:
            mw[ok] *= gain
        if not e_off:
            ew[ok] *= gain
    else:
        mw[ok], ew[ok] = _compress(g, mw[ok], ew[ok])
    # Whatever is still outside by more than rounding (a gamut that is not star-shaped, or one
    # that does not hold 0 dB SL) goes to its nearest renderable pair.
    out = ok & ~g.contains(mw, ew, tol_db=1e-9)
    if out.any():
        qm, qe = g.nearest(mw[out], ew[out])
        mw[out], ew[out] = qm, qe
    return (m if m_off else mw), (e if e_off else ew), gain


def _largest_gain(g: Gamut, m: Arr, e: Arr, m_off: bool, e_off: bool) -> float:
    if m.size == 0 or np.all(g.contains(m, e)):
        return 1.0

    def fits(s: float) -> bool:
        # Exactly inside (no tolerance), so the gain never overshoots a rating.
        mm_, ee_ = (m if m_off else s * m), (e if e_off else s * e)
        return bool(np.all(g.contains(mm_, ee_, tol_db=0.0)))

    lo, hi = 0.0, 1.0
    if not fits(lo):
        return 0.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if fits(mid):
            lo = mid
        else:
            hi = mid
    return lo


def _compress(g: Gamut, m: Arr, e: Arr) -> tuple[Arr, Arr]:
    """Radial soft knee toward (0, 0) dB SL (or the gamut's pair nearest to it)."""
    am, ae = g.nearest(np.array([0.0]), np.array([0.0]))
    anchor = np.array([float(am[0]), float(ae[0])])
    d = np.stack([m - anchor[0], e - anchor[1]], axis=-1)
    norm = np.hypot(d[:, 0], d[:, 1])
    moving = norm > 0
    if not moving.any():
        return m, e
    lo = _ray_exit(g, anchor, d)
    rho = np.where(moving, 1.0 / np.maximum(lo, 1e-300), 0.0)  # target's fraction of the way
    squeezed = np.where(rho > KNEE, KNEE + (1 - KNEE) * np.tanh((rho - KNEE) / (1 - KNEE)), rho)
    # Stay a hair inside the edge so the solver's answer is within the ratings.
    squeezed = np.minimum(squeezed, 1.0 - 1e-9)
    factor = np.where(rho > KNEE, squeezed / np.where(rho > 0, rho, 1.0), 1.0)
    return anchor[0] + factor * d[:, 0], anchor[1] + factor * d[:, 1]


def _ray_exit(g: Gamut, anchor: NDArray[np.float64], d: NDArray[np.float64]) -> Arr:
    """Where each ray ``anchor + s·d`` (s ≥ 0) first leaves the gamut, as s (exact clipping).

    Each piece is convex, so a ray crosses it in one interval of s (Cyrus–Beck: one half-plane
    per edge); the first exit is the end of the chain of intervals that starts at s = 0.
    """
    n = len(d)
    s_in = np.full((len(g.pieces), n), np.inf)
    s_out = np.full((len(g.pieces), n), -np.inf)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for k, piece in enumerate(g.pieces):
            v = piece.vertices
            area2 = float(np.sum(v[:, 0] * np.roll(v[:, 1], -1) - np.roll(v[:, 0], -1) * v[:, 1]))
            if not area2 > 0.0:
                continue  # a collapsed piece (b·d = 1) adds no interior
            lo = np.zeros(n)
            hi = np.full(n, np.inf)
            for i in range(len(v)):
                edge = v[(i + 1) % len(v)] - v[i]
                normal = np.array([edge[1], -edge[0]])  # outward for counter-clockwise vertices
                den = d @ normal
                num = (v[i] - anchor) @ normal
                # s·den ≤ num: an upper bound where den > 0, a lower bound where den < 0.
                bound = num / den
                hi = np.where(den > 0, np.minimum(hi, bound), hi)
                lo = np.where(den < 0, np.maximum(lo, bound), lo)
                empty = (den == 0) & (num < 0)
                hi = np.where(empty, -np.inf, hi)
            s_in[k], s_out[k] = lo, hi
    exit_s = np.zeros(n)
    for _ in range(len(g.pieces) + 1):
        reach = (s_in <= exit_s + 1e-12) & (s_out > exit_s)
        longer = np.where(reach, s_out, exit_s).max(axis=0)
        if np.array_equal(longer, exit_s):
            break
        exit_s = longer
    return exit_s


def playable_inputs(
    g: Gamut,
    mv_target_db_sl: Arr,
    ev_target_db_sl: Arr,
    mv_input_db_sl: Arr,
    ev_input_db_sl: Arr,
    several: NDArray[np.bool_] | None = None,
) -> tuple[Arr, Arr, NDArray[np.bool_]]:
    """Inputs within the ratings for mapped targets: the solver's where usable, else the edge's.

    Parameters
    ----------
    g : Gamut
        The gamut the targets were mapped into.
    mv_target_db_sl, ev_target_db_sl : ndarray
        Mapped targets, dB SL (−inf: channel off).
    mv_input_db_sl, ev_input_db_sl : ndarray
        The solver's answers for them, dB SL (NaN where not unique).
    several : ndarray of bool, optional
        Targets with several answers (b·d ≥ 1): left without inputs, since choosing one is the
        designer's call, never made silently.

    Returns
    -------
    mv_input_db_sl, ev_input_db_sl : ndarray
        Inputs within the box (−inf for a channel that is off), dB SL.
    from_edge : ndarray of bool
        Points whose inputs come from the gamut's edge instead of the solver.

    Examples
    --------
    >>> from masking_lab.rendering.gamut import perceptual_gamut
    >>> from masking_lab.rendering.pair import MutualMasking
    >>> g = perceptual_gamut(MutualMasking(0.0, 0.0, 0.0, 0.0), 30.0, 30.0)
    >>> mi, ei, edge = playable_inputs(g, np.array([30.0]), np.array([5.0]),
    ...                                np.array([30.000000000001]), np.array([np.nan]))
    >>> float(mi[0]), float(ei[0]), bool(edge[0])
    (30.0, 5.0, True)
    """
    mi = np.array(mv_input_db_sl, dtype=float)
    ei = np.array(ev_input_db_sl, dtype=float)
    (m_lo, m_hi), (e_lo, e_hi) = g.mv_box_db_sl, g.ev_box_db_sl
    m_off = mv_target_db_sl == -np.inf
    e_off = ev_target_db_sl == -np.inf
    slack_m = 1e-9 * (1 + abs(m_hi))
    slack_e = 1e-9 * (1 + abs(e_hi))
    usable = (m_off | ((mi >= m_lo - slack_m) & (mi <= m_hi + slack_m))) & (
        e_off | ((ei >= e_lo - slack_e) & (ei <= e_hi + slack_e))
    )
    # Rounding past the rating by a few ulps is clamped; anything else comes from the edge.
    mi = np.where(m_off, mi, np.clip(mi, m_lo, m_hi))
    ei = np.where(e_off, ei, np.clip(ei, e_lo, e_hi))
    edge = ~usable
    if several is not None:
        edge &= ~several
    if edge.any():
        tm = np.where(m_off, m_lo, mv_target_db_sl)[edge]
        te = np.where(e_off, e_lo, ev_target_db_sl)[edge]
        good = np.isfinite(tm) & np.isfinite(te)
        _, _, bm, be = g.boundary_inputs(np.where(good, tm, m_lo), np.where(good, te, e_lo))
        mi[edge] = np.where(m_off[edge], -np.inf, bm)
        ei[edge] = np.where(e_off[edge], -np.inf, be)
    return mi, ei, edge


def mapping_metrics(
    x_mm: Arr,
    mv_intended_db_sl: Arr,
    ev_intended_db_sl: Arr,
    mv_perceived_db_sl: Arr,
    ev_perceived_db_sl: Arr,
    within_ratings: NDArray[np.bool_],
) -> dict[str, Any]:
    """How a rendering compares with what the scene intended (JSON-ready; dB, shares 0–1).

    Parameters
    ----------
    x_mm : ndarray
        Positions, mm.
    mv_intended_db_sl, ev_intended_db_sl : ndarray
        The scene's targets, dB SL (−inf: channel off).
    mv_perceived_db_sl, ev_perceived_db_sl : ndarray
        What the played inputs are perceived as, dB SL.
    within_ratings : ndarray of bool
        Points whose played inputs are within the ratings.

    Returns
    -------
    dict
        ``rms_error_db`` and ``max_error_db`` (over points and played channels),
        ``geometry_correlation`` (perceived vs intended EV profile, Pearson),
        ``geometry_contrast_ratio`` (perceived EV range / intended range), ``texture_sd_db``
        (spread of the perceived MV level; 0 is uniform) and its intended value,
        ``texture_mean_shift_db``, ``share_within_ratings``, ``share_at_target`` (within
        :data:`AT_TARGET_DB` dB on both channels).

    Examples
    --------
    >>> x = np.linspace(0.0, 1.0, 3)
    >>> out = mapping_metrics(x, np.full(3, 6.0), np.array([0.0, 10.0, 0.0]),
    ...                       np.full(3, 5.0), np.array([0.0, 5.0, 0.0]), np.ones(3, bool))
    >>> out["geometry_correlation"], out["geometry_contrast_ratio"], out["max_error_db"]
    (1.0, 0.5, 5.0)
    """
    errs = []
    at = np.ones(x_mm.shape, dtype=bool)
    for want, got in (
        (mv_intended_db_sl, mv_perceived_db_sl),
        (ev_intended_db_sl, ev_perceived_db_sl),
    ):
        if np.all(want == -np.inf):
            continue
        err = np.abs(np.asarray(got, float) - want)
        err = np.where(np.isfinite(err), err, np.inf)
        errs.append(err)
        at &= err <= AT_TARGET_DB
    allerr = np.concatenate(errs) if errs else np.zeros(0)
    finite = allerr[np.isfinite(allerr)]
    out: dict[str, Any] = {
        "rms_error_db": _rms(finite) if finite.size else None,
        "max_error_db": _num(finite.max()) if finite.size else None,
        "points_without_a_level": int(np.count_nonzero(~np.isfinite(allerr))),
        "share_within_ratings": _num(np.mean(within_ratings)) if within_ratings.size else None,
        "share_at_target": _num(np.mean(at)) if at.size else None,
    }
    ev_ok = np.isfinite(ev_intended_db_sl) & np.isfinite(ev_perceived_db_sl)
    if ev_ok.sum() > 2 and np.ptp(ev_intended_db_sl[ev_ok]) > 0:
        want, got = ev_intended_db_sl[ev_ok], ev_perceived_db_sl[ev_ok]
        out["geometry_correlation"] = _correlation(want, got)
        with np.errstate(over="ignore"):
            out["geometry_contrast_ratio"] = _num(np.ptp(got) / np.ptp(want))
    mv_ok = np.isfinite(mv_intended_db_sl) & np.isfinite(mv_perceived_db_sl)
    if mv_ok.any():
        out["texture_sd_db"] = _num(np.std(mv_perceived_db_sl[mv_ok]))
        out["texture_intended_sd_db"] = _num(np.std(mv_intended_db_sl[mv_ok]))
        out["texture_mean_shift_db"] = _num(
            np.mean(mv_perceived_db_sl[mv_ok]) - np.mean(mv_intended_db_sl[mv_ok])
        )
    return out


def _rms(x: Arr) -> float | None:
    """Root mean square, scaled by the largest value so that squaring cannot overflow."""
    top = float(np.max(np.abs(x)))
    return _num(top * np.sqrt(np.mean(np.square(x / top)))) if top > 0 else 0.0


def _correlation(a: Arr, b: Arr) -> float:
    """Pearson r of two profiles; 0 when either is flat (or its spread is not finite)."""
    with np.errstate(all="ignore"):
        da, db = a - a.mean(), b - b.mean()
        den = float(np.sqrt(np.sum(da * da) * np.sum(db * db)))
        r = float(np.sum(da * db)) / den if den > 0 and np.isfinite(den) else 0.0
    return round(max(-1.0, min(1.0, r)), 9) if np.isfinite(r) else 0.0


def _num(v: SupportsFloat) -> float | None:
    # JSON-ready: a metric that overflowed is unknown (None), never inf or NaN in a summary.
    x = float(v)
    return round(x, 9) if math.isfinite(x) else None
