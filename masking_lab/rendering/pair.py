"""The two masking ramps of one MV/EV stimulus pair, and reading them from masking_params.json.

:class:`MutualMasking` holds f (EV masking the MV stimulus) and g (the MV stimulus masking EV),
paper Eq. (1)–(4), with the scalar forward model and the scalar inverse
(:meth:`MutualMasking.solve_point`, whose case analysis is in
:mod:`masking_lab.rendering.ramp_inverse`). :func:`pair_from_params` builds one from a parsed
``masking_params.json`` and says which directions are missing. Pure: no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Any

import numpy as np

from masking_lab.core.errors import SolverError
from masking_lab.core.masking import MaskingFunction
from masking_lab.rendering.ramp_inverse import (
    MAX_INTERCEPT_DB,
    MAX_SLOPE,
    PointSolution,
    point_answer,
)

__all__ = ["MissingMaskingError", "MutualMasking", "PairProblem", "pair_from_params"]


@dataclass(frozen=True)
class MutualMasking:
    """The two masking ramps of one MV stimulus and one EV stimulus (paper Eq. 1–2).

    Attributes
    ----------
    a_db : float
        Intercept of f, the AL shift of the MV stimulus caused by EV, dB.
    b : float
        Slope of f, dB of AL shift per dB SL of EV (≥ 0).
    c_db : float
        Intercept of g, the AL shift of EV caused by the MV stimulus, dB.
    d : float
        Slope of g, dB of AL shift per dB SL of MV (≥ 0).
    mv : str
        Name of the MV stimulus (e.g. ``"MV180"``); labels only.
    ev : str
        Name of the EV stimulus (``"EV270"``); labels only.
    f_fitted_range_db_sl, g_fitted_range_db_sl : tuple[float, float] or None
        EV (for f) and MV (for g) masker levels the ramps were fitted on, dB SL; beyond them a
        ramp is an extrapolation. None if unknown.
    notes : tuple[str, ...]
        Caveats from the parameter file (e.g. a direction with no masking found).
    """

    a_db: float
    b: float
    c_db: float
    d: float
    mv: str = "MV"
    ev: str = "EV270"
    f_fitted_range_db_sl: tuple[float, float] | None = field(default=None, compare=False)
    g_fitted_range_db_sl: tuple[float, float] | None = field(default=None, compare=False)
    notes: tuple[str, ...] = field(default=(), compare=False)
    one_minus_bd: float = field(init=False, repr=False)
    bd_side: int = field(init=False, repr=False)

    def __post_init__(self) -> None:
        for name in ("a_db", "b", "c_db", "d"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float | np.floating):
                raise SolverError(f"masking parameter {name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise SolverError(
                    f"masking parameter {name} must be finite, got {value!r}; check the fitted "
                    "masking functions"
                )
            object.__setattr__(self, name, float(value))
        for name in ("a_db", "c_db"):
            if abs(getattr(self, name)) > MAX_INTERCEPT_DB:
                raise SolverError(
                    f"masking intercept {name} is {getattr(self, name)!r} dB: the solver works on "
                    f"intercepts within ±{MAX_INTERCEPT_DB:g} dB (the paper's are within ±8 dB). "
                    "Check the fit"
                )
        for name, what in (("b", f"{self.mv} by {self.ev}"), ("d", f"{self.ev} by {self.mv}")):
            if getattr(self, name) > MAX_SLOPE:
                raise SolverError(
                    f"masking slope {name} ({what}) is {getattr(self, name)!r}: the solver works "
                    f"on slopes up to {MAX_SLOPE:g} dB/dB (the paper's are 0.6–1.1); beyond it "
                    "float arithmetic cannot give a trustworthy answer. Check the fit"
                )
            if getattr(self, name) < 0:
                raise SolverError(
                    f"masking slope {name} ({what}) is {getattr(self, name)!r}: a masking ramp "
                    "rises with the masker, so slopes must be ≥ 0. A negative fitted slope means "
                    "no masking was found; use slope 0 with intercept ≤ 0 for 'no masking'"
                )
        # 1 − b·d exactly, then rounded once: near b·d = 1 the plain float product loses it.
        exact = 1 - Fraction(self.b) * Fraction(self.d)
        object.__setattr__(self, "one_minus_bd", float(exact))
        object.__setattr__(self, "bd_side", (exact < 0) - (exact > 0))

    # ----------------------------------------------------------------------------- building

    @classmethod
    def from_functions(cls, mv_by_ev: MaskingFunction, ev_by_mv: MaskingFunction) -> MutualMasking:
        """Pair two :class:`~masking_lab.core.masking.MaskingFunction` objects.

        Parameters
        ----------
        mv_by_ev : MaskingFunction
            Target an MV stimulus, masker the EV stimulus (gives a, b).
        ev_by_mv : MaskingFunction
            Target the EV stimulus, masker the same MV stimulus (gives c, d).
        """
        if mv_by_ev.target != ev_by_mv.masker or mv_by_ev.masker != ev_by_mv.target:
            raise SolverError(
                f"the two masking functions do not form a pair: {mv_by_ev.target} by "
                f"{mv_by_ev.masker} and {ev_by_mv.target} by {ev_by_mv.masker}; pass the MV "
                "stimulus masked by EV and EV masked by the same MV stimulus"
            )
        return cls(
            mv_by_ev.intercept_db,
            mv_by_ev.slope,
            ev_by_mv.intercept_db,
            ev_by_mv.slope,
            mv=mv_by_ev.target,
            ev=mv_by_ev.masker,
        )

    @property
    def bd(self) -> float:
        """Product of the two slopes b·d (dimensionless); < 1 means every target is reachable."""
        return self.b * self.d

    @property
    def bd_text(self) -> str:
        """b·d for messages; within 1e-6 of 1 written as ``1 ∓ gap`` so the side of 1 shows.

        Examples
        --------
        >>> MutualMasking(0.0, 1.0, 0.0, 1.0 - 2.0**-53).bd_text
        '1 − 1.11e-16'
        >>> MutualMasking(0.0, 1.09, 0.0, 0.66).bd_text
        '0.7194'
        """
        gap = self.one_minus_bd
        if gap != 0 and abs(gap) < 1e-6:
            return f"1 {'−' if gap > 0 else '+'} {abs(gap):.3g}"
        return f"{self.bd:.6g}"

    # ----------------------------------------------------------------------------- forward

    def forward_point(self, mv_input_db_sl: float, ev_input_db_sl: float) -> tuple[float, float]:
        """Perceived (m_p, e_p) in dB SL for inputs (m_i, e_i) in dB SL (paper Eq. 3–4)."""
        m_i = float(mv_input_db_sl)
        e_i = float(ev_input_db_sl)
        return m_i - _ramp(self.a_db, self.b, e_i), e_i - _ramp(self.c_db, self.d, m_i)

    # ----------------------------------------------------------------------------- inverse

    def solve_point(self, mv_target_db_sl: float, ev_target_db_sl: float) -> PointSolution:
        """Inputs (m_i, e_i) in dB SL that are perceived as (m_p, e_p) in dB SL; scalar path.

        Plain float arithmetic (no numpy) so that it fits a 1 kHz haptic loop.

        Parameters
        ----------
        mv_target_db_sl : float
            Wanted perceived MV intensity m_p, dB SL (``-inf``: MV off).
        ev_target_db_sl : float
            Wanted perceived EV intensity e_p, dB SL (``-inf``: EV off).
        """
        return point_answer(self, float(mv_target_db_sl), float(ev_target_db_sl))


def _ramp(intercept: float, slope: float, x: float) -> float:
    # slope 0 times ±inf would be NaN; a flat ramp ignores its masker.
    y = intercept + slope * x if slope else intercept
    return y if y > 0.0 else (0.0 if y == y else y)


# --------------------------------------------------------------------------------------------
# masking_params.json → a pair


@dataclass(frozen=True)
class PairProblem:
    """Why one direction of a stimulus pair cannot be used.

    Attributes
    ----------
    target, masker : str
        Stimulus names of the missing masking function.
    status : str
        ``"missing"`` (no entry) or the entry's status (e.g. ``"insufficient_data"``).
    """

    target: str
    masker: str
    status: str


class MissingMaskingError(SolverError):
    """The parameters file lacks a fitted masking function the solver needs.

    Attributes
    ----------
    problems : list[PairProblem]
        Each unusable direction, with why.
    """

    def __init__(self, message: str, problems: list[PairProblem]) -> None:
        super().__init__(message)
        self.problems = problems


def pair_from_params(
    params: Mapping[str, Any], *, mv: str, ev: str = "EV270", source: str = "masking_params.json"
) -> MutualMasking:
    """Look up the two masking functions of one MV/EV stimulus pair in a parsed params file.

    Only that pair's two entries are read. A ``"no_masking"`` entry is used (its ramp is flat)
    and reported in ``notes``; an entry without a ramp (``"insufficient_data"``) is an error.

    Parameters
    ----------
    params : mapping
        Parsed ``masking_params.json`` (``{"functions": [{target, masker, intercept_db, slope,
        status, ...}, ...]}``).
    mv, ev : str
        Stimulus names, e.g. ``"MV180"`` and ``"EV270"``.
    source : str
        Name of the file, for messages.

    Raises
    ------
    MissingMaskingError
        If either direction is absent or has no ramp (e.g. ``"insufficient_data"``); lists both.
    """
    functions = params.get("functions") if isinstance(params, Mapping) else None
    if not isinstance(functions, list):
        raise SolverError(
            f"{source}: no 'functions' list; is this a masking_params.json written by "
            "`masking-lab fit`?"
        )
    found: dict[tuple[str, str], MaskingFunction] = {}
    ranges: dict[tuple[str, str], tuple[float, float] | None] = {}
    notes: list[str] = []
    problems: list[PairProblem] = []
    for target, masker in ((mv, ev), (ev, mv)):
        entry = next(
            (
                f
                for f in functions
                if isinstance(f, Mapping) and (f.get("target"), f.get("masker")) == (target, masker)
            ),
            None,
        )
        if entry is None:
            problems.append(PairProblem(target, masker, "missing"))
            continue
        status = entry.get("status", "fitted")
        if status not in ("fitted", "no_masking"):
            problems.append(PairProblem(target, masker, str(status)))
            continue
        try:
            found[(target, masker)] = MaskingFunction(
                target, masker, float(entry["intercept_db"]), float(entry["slope"])
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise SolverError(
                f"{source}: the entry for {target} masked by {masker} has no numeric "
                f"intercept_db/slope ({exc}); re-export it with `masking-lab fit`"
            ) from exc
        rng = entry.get("fitted_range_db_sl")
        ranges[(target, masker)] = (float(rng[0]), float(rng[1])) if rng else None
        if status == "no_masking":
            fn = found[(target, masker)]
            notes.append(
                f"{target} masked by {masker}: no masking was found (status 'no_masking'); "
                f"using the exported ramp max(0, {fn.intercept_db:g} + {fn.slope:g}·x)"
            )
    if problems:
        listed = "; ".join(
            f"{p.target} masked by {p.masker}: "
            + ("no entry" if p.status == "missing" else f"status {p.status!r}, not fitted")
            for p in problems
        )
        raise MissingMaskingError(
            f"{source}: cannot compensate {mv} with {ev}: {listed}. Measure the pair (masked "
            "sessions of each stimulus by the other), fit, and export again",
            problems,
        )
    f, g = found[(mv, ev)], found[(ev, mv)]
    try:
        return MutualMasking(
            f.intercept_db,
            f.slope,
            g.intercept_db,
            g.slope,
            mv=mv,
            ev=ev,
            f_fitted_range_db_sl=ranges[(mv, ev)],
            g_fitted_range_db_sl=ranges[(ev, mv)],
            notes=tuple(notes),
        )
    except SolverError as exc:
        raise SolverError(f"{source}: {exc}") from exc
