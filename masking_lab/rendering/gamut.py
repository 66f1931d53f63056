"""The perceptual gamut: every perceived pair (m_p, e_p) the rig can render (issue 19, §4.3).

The forward model (paper Eq. 3–4) maps an input pair (m_i, e_i), dB SL, to the perceived pair

    m_p = m_i − max(0, a + b·e_i),     e_p = e_i − max(0, c + d·m_i).

The rig plays inputs in a box: each channel from a floor up to its rated maximum (the rig
config's ``channels.<EV|MV>.max_level_db_sl``, a device or comfort limit). The gamut is the image
of that box. The two knees ``m_i = −c/d`` and ``e_i = −a/b`` cut the box into at most four
rectangles, and on each the model is linear (the solver's cases 1–4), so each rectangle maps to
a parallelogram whose vertices are the images of its corners. The gamut is the union of those
pieces, with exact vertices (each one forward evaluation of a corner, rounded once per term):

- b·d < 1: every piece keeps its orientation and the map is one-to-one, so the pieces tile a
  single simple polygon, :attr:`Gamut.outline`, the image of the box's boundary (its four
  corners and up to four knee crossings).
- b·d > 1: the both-ramps piece flips orientation and folds over the others (targets with two
  answers); b·d = 1: it collapses to a segment. The gamut is the union of the pieces.

Nothing here divides by 1 − b·d, so b·d within ulps of 1 and slopes or intercepts at their
schema bounds are as exact as anywhere (a knee beyond float range is simply off the box).

The floor: inputs below 0 dB SL are below threshold, and a felt target (m_p, e_p ≥ 0) never
needs one (m_i ≥ m_p because masking only adds), so with the default floor of 0 dB SL the gamut
is exact on the felt quadrant. :func:`gamut_for_targets` lowers the floor to the lowest target,
so that "inside the gamut" is exactly "solvable with inputs within the ratings". Pure: no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from masking_lab.core.errors import SolverError
from masking_lab.rendering.pair import MutualMasking
from masking_lab.rendering.ramp_inverse import MAX_TARGET_DB_SL

__all__ = ["Gamut", "GamutPiece", "fitted_caps", "gamut_for_targets", "perceptual_gamut"]

#: Default lowest input considered, dB SL (threshold: below it a channel is not felt).
DEFAULT_FLOOR_DB_SL = 0.0


@dataclass(frozen=True)
class GamutPiece:
    """The image of one rectangle of the input box on which the model is linear.

    Attributes
    ----------
    case : int
        Which ramps are rising there, numbered as the solver's cases (1 neither, 2 g, 3 f,
        4 both).
    mv_input_db_sl, ev_input_db_sl : tuple[float, float]
        The rectangle of inputs, dB SL.
    vertices : ndarray, shape (4, 2)
        Its image, (m_p, e_p) in dB SL, counter-clockwise (collapsed onto a line when the piece
        is degenerate, b·d = 1).
    corners : ndarray, shape (4, 2)
        The input pairs (m_i, e_i), dB SL, whose images are ``vertices``, in the same order.
    """

    case: int
    mv_input_db_sl: tuple[float, float]
    ev_input_db_sl: tuple[float, float]
    vertices: NDArray[np.float64]
    corners: NDArray[np.float64]


@dataclass(frozen=True)
class Gamut:
    """The perceived pairs a pair of ramps can produce from inputs in a box (dB SL).

    Attributes
    ----------
    pair : MutualMasking
        The masking ramps.
    mv_box_db_sl, ev_box_db_sl : tuple[float, float]
        Floor and rated maximum of each channel's input, dB SL.
    pieces : tuple[GamutPiece, ...]
        The images of the linear rectangles; the gamut is their union.
    outline : ndarray of shape (n, 2) or None
        For b·d < 1, the gamut as one simple counter-clockwise polygon (m_p, e_p), dB SL; None
        when the pieces fold (b·d ≥ 1).
    """

    pair: MutualMasking
    mv_box_db_sl: tuple[float, float]
    ev_box_db_sl: tuple[float, float]
    pieces: tuple[GamutPiece, ...]
    outline: NDArray[np.float64] | None

    @property
    def folded(self) -> bool:
        """True when b·d ≥ 1 (pieces overlap or collapse)."""
        return self.pair.bd_side >= 0

    def distance_db(self, mv_db_sl: ArrayLike, ev_db_sl: ArrayLike) -> NDArray[np.float64]:
        """Euclidean distance in dB from each perceived pair to the gamut (0 inside).

        Parameters
        ----------
        mv_db_sl, ev_db_sl : array_like
            Perceived pairs (m_p, e_p), dB SL, broadcast together. Non-finite → inf.

        Returns
        -------
        ndarray
            Distance, dB.

        Examples
        --------
        Without masking the gamut is the box itself:

        >>> g = perceptual_gamut(MutualMasking(0.0, 0.0, 0.0, 0.0), 30.0, 30.0)
        >>> g.distance_db([10.0, 40.0], [5.0, 0.0]).tolist()
        [0.0, 10.0]
        """
        m, e = np.broadcast_arrays(np.asarray(mv_db_sl, float), np.asarray(ev_db_sl, float))
        p = np.stack([m.ravel(), e.ravel()], axis=-1)
        best = np.full(p.shape[0], np.inf)
        ok = np.isfinite(p).all(axis=-1)
        for piece in self.pieces:
            best[ok] = np.minimum(best[ok], _distance_to_convex(piece.vertices, p[ok]))
        return best.reshape(m.shape)

    def contains(
        self, mv_db_sl: ArrayLike, ev_db_sl: ArrayLike, *, tol_db: float = 1e-9
    ) -> NDArray[np.bool_]:
        """Whether each perceived pair is renderable (within ``tol_db`` dB of the gamut).

        Examples
        --------
        >>> g = perceptual_gamut(MutualMasking(0.0, 0.5, 0.0, 0.5), 30.0, 30.0)
        >>> g.contains([10.0, 40.0], [5.0, 0.0]).tolist()
        [True, False]
        """
        m, e = np.broadcast_arrays(np.asarray(mv_db_sl, float), np.asarray(ev_db_sl, float))
        p = np.stack([m.ravel(), e.ravel()], axis=-1)
        # Cheap half-plane tests first: only points inside no piece need the distance (the
        # projections dominate a 100,000-point scene's scale search otherwise).
        inside = np.zeros(p.shape[0], dtype=bool)
        ok = np.isfinite(p).all(axis=-1)
        for piece in self.pieces:
            inside[ok] |= _inside_convex(piece.vertices, p[ok])
        rest = ok & ~inside
        if rest.any():
            inside[rest] = self.distance_db(p[rest, 0], p[rest, 1]) <= tol_db
        return inside.reshape(m.shape)

    def cases_at(self, mv_db_sl: float, ev_db_sl: float, *, tol_db: float = 1e-9) -> list[int]:
        """The pieces (solver cases) whose image holds (m_p, e_p), dB SL: one answer each.

        Examples
        --------
        >>> g = perceptual_gamut(MutualMasking(-2.0, 2.0, -2.0, 1.0), 20.0, 20.0)  # b·d = 2
        >>> g.cases_at(1.0, 0.5)  # two answers in the box: (1, 0.5) and (4, 2.5) dB SL
        [1, 4]
        """
        p = np.array([[float(mv_db_sl), float(ev_db_sl)]])
        return [
            piece.case
            for piece in self.pieces
            if _distance_to_convex(piece.vertices, p)[0] <= tol_db
        ]

    def nearest(
        self, mv_db_sl: ArrayLike, ev_db_sl: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The renderable pair nearest to each perceived pair (itself when inside), dB SL.

        Examples
        --------
        >>> g = perceptual_gamut(MutualMasking(0.0, 0.0, 0.0, 0.0), 30.0, 20.0)
        >>> [v.tolist() for v in g.nearest([40.0], [25.0])]
        [[30.0], [20.0]]
        """
        m, e = np.broadcast_arrays(np.asarray(mv_db_sl, float), np.asarray(ev_db_sl, float))
        p = np.stack([m.ravel(), e.ravel()], axis=-1)
        best_d = np.full(p.shape[0], np.inf)
        best = p.copy()
        for piece in self.pieces:
            q, d = _project_to_convex(piece.vertices, p)
            closer = d < best_d
            best[closer] = q[closer]
            best_d[closer] = d[closer]
        return best[:, 0].reshape(m.shape), best[:, 1].reshape(m.shape)

    def boundary_inputs(
        self, mv_db_sl: ArrayLike, ev_db_sl: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """The nearest renderable pair on a piece's edge, and inputs in the box that produce it.

        An affine map keeps where a point sits along a segment, so the point at fraction t of
        the edge between two vertices is the image of the point at t between their corners: an
        input pair inside the box by construction, found without solving anything (and so
        without dividing by 1 − b·d).

        Parameters
        ----------
        mv_db_sl, ev_db_sl : array_like
            Perceived pairs, dB SL (finite), broadcast.

        Returns
        -------
        mv_db_sl, ev_db_sl, mv_input_db_sl, ev_input_db_sl : ndarray
            Nearest edge point (dB SL) and its inputs (dB SL, clamped into the box).

        Examples
        --------
        >>> g = perceptual_gamut(MutualMasking(0.0, 0.0, 0.0, 0.0), 30.0, 30.0)
        >>> [float(v[0]) for v in g.boundary_inputs([40.0], [0.0])]
        [30.0, 0.0, 30.0, 0.0]
        """
        m, e = np.broadcast_arrays(np.asarray(mv_db_sl, float), np.asarray(ev_db_sl, float))
        p = np.stack([m.ravel(), e.ravel()], axis=-1)
        best_d = np.full(p.shape[0], np.inf)
        best = p.copy()
        inputs = np.full_like(p, np.nan)
        for piece in self.pieces:
            v, c = piece.vertices, piece.corners
            for i in range(4):
                j = (i + 1) % 4
                q, d, t = _segment_projection(v[i], v[j], p)
                closer = d < best_d
                best[closer] = q[closer]
                best_d[closer] = d[closer]
                inputs[closer] = c[i] + t[closer, None] * (c[j] - c[i])
        np.clip(inputs[:, 0], *self.mv_box_db_sl, out=inputs[:, 0])
        np.clip(inputs[:, 1], *self.ev_box_db_sl, out=inputs[:, 1])
        shape = m.shape
        return (
            best[:, 0].reshape(shape),
            best[:, 1].reshape(shape),
            inputs[:, 0].reshape(shape),
            inputs[:, 1].reshape(shape),
        )

    def as_dict(self) -> dict[str, object]:
        """JSON-ready description: the box, b·d, the pieces and (b·d < 1) the outline, dB SL."""
        return {
            "mv_input_box_db_sl": list(self.mv_box_db_sl),
            "ev_input_box_db_sl": list(self.ev_box_db_sl),
            "bd": self.pair.bd,
            "folded": self.folded,
            "outline": None if self.outline is None else self.outline.tolist(),
            "pieces": [
                {
                    "case": p.case,
                    "mv_input_db_sl": list(p.mv_input_db_sl),
                    "ev_input_db_sl": list(p.ev_input_db_sl),
                    "vertices": p.vertices.tolist(),
                }
                for p in self.pieces
            ],
        }


def perceptual_gamut(
    pair: MutualMasking,
    max_mv_db_sl: float,
    max_ev_db_sl: float,
    *,
    floor_mv_db_sl: float = DEFAULT_FLOOR_DB_SL,
    floor_ev_db_sl: float = DEFAULT_FLOOR_DB_SL,
) -> Gamut:
    """The image of the input box ``[floor, max]²`` under the masking model, exactly.

    Parameters
    ----------
    pair : MutualMasking
        The two masking ramps.
    max_mv_db_sl, max_ev_db_sl : float
        Rated maximum input per channel, dB SL (finite).
    floor_mv_db_sl, floor_ev_db_sl : float
        Lowest input per channel, dB SL (default 0: exact on the felt quadrant).

    Returns
    -------
    Gamut
        Pieces and, for b·d < 1, the outline polygon.

    Raises
    ------
    SolverError
        A non-finite bound, or a floor above its maximum.

    Examples
    --------
    The paper's MV180/EV270 ramps and the reference rig's 30 dB SL on both channels. EV masks
    MV at every EV level (a > 0), so only the knee of g (MV ≈ 9 dB SL) cuts the box; with EV at
    its maximum, MV needs more than f(30) ≈ 33 dB SL to be felt at all. 12 dB SL of texture
    over 5 dB SL of geometry is out of reach:

    >>> pair = MutualMasking(1.304, 1.062, -5.927, 0.658, mv="MV180", ev="EV270")
    >>> g = perceptual_gamut(pair, 30.0, 30.0)
    >>> g.outline.round(2).tolist()  # doctest: +NORMALIZE_WHITESPACE
    [[-1.3, 0.0], [7.7, 0.0], [28.7, -13.81], [-3.16, 16.19], [-24.16, 30.0], [-33.16, 30.0]]
    >>> [p.case for p in g.pieces]
    [3, 4]
    >>> bool(g.contains(12.0, 5.0)), bool(g.contains(6.0, 2.0))
    (False, True)
    """
    bounds = {
        "max_mv_db_sl": max_mv_db_sl,
        "max_ev_db_sl": max_ev_db_sl,
        "floor_mv_db_sl": floor_mv_db_sl,
        "floor_ev_db_sl": floor_ev_db_sl,
    }
    for name, value in bounds.items():
        if not isinstance(value, int | float) or not math.isfinite(value):
            raise SolverError(f"gamut: {name} must be a finite level in dB SL, got {value!r}")
        if abs(value) > MAX_TARGET_DB_SL:
            raise SolverError(
                f"gamut: {name} is {value:g} dB SL, beyond the solver's range of "
                f"±{MAX_TARGET_DB_SL:g} dB SL; give the rig's real rating"
            )
    if floor_mv_db_sl > max_mv_db_sl or floor_ev_db_sl > max_ev_db_sl:
        raise SolverError(
            f"gamut: the input floor ({floor_mv_db_sl:g}, {floor_ev_db_sl:g} dB SL) is above the "
            f"rated maximum ({max_mv_db_sl:g}, {max_ev_db_sl:g} dB SL); lower the floor"
        )
    m_lo, m_hi = float(floor_mv_db_sl), float(max_mv_db_sl)
    e_lo, e_hi = float(floor_ev_db_sl), float(max_ev_db_sl)
    # g rises for m_i above its knee, f for e_i above its knee (±inf for a flat ramp).
    km = _knee(pair.c_db, pair.d)
    ke = _knee(pair.a_db, pair.b)
    m_cuts = _split(m_lo, m_hi, km)
    e_cuts = _split(e_lo, e_hi, ke)
    pieces = []
    for m0, m1 in m_cuts:
        for e0, e1 in e_cuts:
            g_on = m0 >= km  # the lower edge is at or past the knee: the whole strip rises
            f_on = e0 >= ke
            case = 1 + int(g_on) + 2 * int(f_on)
            corners = np.array([(m0, e0), (m1, e0), (m1, e1), (m0, e1)])
            v = np.array([pair.forward_point(m, e) for m, e in corners])
            if case == 4 and pair.bd_side > 0:
                # The map reverses orientation here: keep vertices counter-clockwise.
                v, corners = v[::-1], corners[::-1]
            pieces.append(GamutPiece(case, (m0, m1), (e0, e1), v, corners))
    outline = None
    if pair.bd_side < 0:
        ring = _boundary_ring(m_lo, m_hi, e_lo, e_hi, km, ke)
        outline = _drop_collinear(np.array([pair.forward_point(m, e) for m, e in ring]))
    return Gamut(pair, (m_lo, m_hi), (e_lo, e_hi), tuple(pieces), outline)


def gamut_for_targets(
    pair: MutualMasking,
    max_mv_db_sl: float,
    max_ev_db_sl: float,
    mv_target_db_sl: ArrayLike,
    ev_target_db_sl: ArrayLike,
) -> Gamut:
    """The gamut with each floor at min(0, the lowest finite target), dB SL.

    An input is never below its target (masking only adds), so with that floor a target is in
    the gamut exactly when the solver answers it with inputs within the ratings.

    Examples
    --------
    >>> g = gamut_for_targets(MutualMasking(0.0, 0.5, 0.0, 0.5), 30.0, 30.0, [-5.0], [2.0])
    >>> g.mv_box_db_sl, g.ev_box_db_sl
    ((-5.0, 30.0), (0.0, 30.0))
    """
    floors = []
    for t, hi in ((mv_target_db_sl, max_mv_db_sl), (ev_target_db_sl, max_ev_db_sl)):
        a = np.asarray(t, float)
        ok = a[np.isfinite(a)]
        floors.append(min(DEFAULT_FLOOR_DB_SL, float(ok.min()) if ok.size else 0.0, hi))
    return perceptual_gamut(
        pair, max_mv_db_sl, max_ev_db_sl, floor_mv_db_sl=floors[0], floor_ev_db_sl=floors[1]
    )


def fitted_caps(
    pair: MutualMasking, max_mv_db_sl: float, max_ev_db_sl: float
) -> tuple[float, float]:
    """Rated maxima capped at the top of the masker range each ramp was fitted on, dB SL.

    MV's input is the masker of g, EV's the masker of f: with these caps the gamut holds only
    what the fitted ramps cover (no extrapolation). An unknown range leaves the rating.

    Examples
    --------
    >>> pair = MutualMasking(1.3, 1.06, -5.9, 0.66, f_fitted_range_db_sl=(5.0, 25.0),
    ...                      g_fitted_range_db_sl=(5.0, 20.0))
    >>> fitted_caps(pair, 30.0, 30.0)
    (20.0, 25.0)
    """
    g_rng, f_rng = pair.g_fitted_range_db_sl, pair.f_fitted_range_db_sl
    mv = min(max_mv_db_sl, g_rng[1]) if g_rng else max_mv_db_sl
    ev = min(max_ev_db_sl, f_rng[1]) if f_rng else max_ev_db_sl
    return mv, ev


# --------------------------------------------------------------------------------------------
# Geometry helpers


def _knee(intercept: float, slope: float) -> float:
    # Where max(0, intercept + slope·x) starts to rise; a flat ramp rises never or everywhere.
    if slope == 0:
        return -math.inf if intercept > 0 else math.inf
    with np.errstate(over="ignore"):
        k = -intercept / slope
    return k if math.isfinite(k) else (math.inf if k > 0 else -math.inf)


def _split(lo: float, hi: float, knee: float) -> list[tuple[float, float]]:
    if lo < knee < hi:
        return [(lo, knee), (knee, hi)]
    return [(lo, hi)]


def _boundary_ring(
    m_lo: float, m_hi: float, e_lo: float, e_hi: float, km: float, ke: float
) -> list[tuple[float, float]]:
    """The box's boundary counter-clockwise, with the knee crossings as extra vertices."""
    ring = [(m_lo, e_lo)]
    if m_lo < km < m_hi:
        ring.append((km, e_lo))
    ring.append((m_hi, e_lo))
    if e_lo < ke < e_hi:
        ring.append((m_hi, ke))
    ring.append((m_hi, e_hi))
    if m_lo < km < m_hi:
        ring.append((km, e_hi))
    ring.append((m_lo, e_hi))
    if e_lo < ke < e_hi:
        ring.append((m_lo, ke))
    return ring


def _drop_collinear(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Remove repeated vertices and those exactly on the line of their neighbours."""
    keep = []
    n = len(v)
    for i in range(n):
        p, q, r = v[i - 1], v[i], v[(i + 1) % n]
        if np.array_equal(p, q):
            continue
        cross = (q[0] - p[0]) * (r[1] - q[1]) - (q[1] - p[1]) * (r[0] - q[0])
        if cross != 0.0:
            keep.append(q)
    return np.array(keep) if len(keep) >= 3 else v


def _segment_projection(
    a: NDArray[np.float64], b: NDArray[np.float64], p: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Nearest points on segment a–b to points p (n, 2), their distances and fractions t."""
    ab = b - a
    den = float(ab @ ab)
    t = np.zeros(len(p)) if den == 0.0 else np.clip(((p - a) @ ab) / den, 0.0, 1.0)
    q = a + t[:, None] * ab
    return q, np.hypot(p[:, 0] - q[:, 0], p[:, 1] - q[:, 1]), t


def _segment_distance(
    a: NDArray[np.float64], b: NDArray[np.float64], p: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Nearest points on segment a–b to points p (n, 2), and their distances."""
    q, d, _ = _segment_projection(a, b, p)
    return q, d


def _inside_convex(v: NDArray[np.float64], p: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Points inside (or on) a counter-clockwise convex polygon with positive area."""
    inside = np.ones(len(p), dtype=bool)
    n = len(v)
    area2 = 0.0
    for i in range(n):
        a, b = v[i], v[(i + 1) % n]
        area2 += a[0] * b[1] - b[0] * a[1]
        cross = (b[0] - a[0]) * (p[:, 1] - a[1]) - (b[1] - a[1]) * (p[:, 0] - a[0])
        inside &= cross >= 0.0
    if not area2 > 0.0:
        return np.zeros(len(p), dtype=bool)  # degenerate: only its edges count
    return inside


def _project_to_convex(
    v: NDArray[np.float64], p: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    best_d = np.full(len(p), np.inf)
    best = p.copy()
    for i in range(len(v)):
        q, d = _segment_distance(v[i], v[(i + 1) % len(v)], p)
        closer = d < best_d
        best[closer] = q[closer]
        best_d[closer] = d[closer]
    inside = _inside_convex(v, p)
    best[inside] = p[inside]
    best_d[inside] = 0.0
    return best, best_d


def _distance_to_convex(v: NDArray[np.float64], p: NDArray[np.float64]) -> NDArray[np.float64]:
    return _project_to_convex(v, p)[1]
