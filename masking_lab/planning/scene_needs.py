"""What a scene needs measured: its masking functions, the masker ranges it plays, and what the
parameters file already covers (issue 19.4, ``masking-lab plan --scene``; pure).

A two-channel scene plays one MV stimulus with one EV stimulus, so it needs two masking
functions: the MV stimulus masked by EV (its masker level is EV's *input*, e_i) and EV masked by
the MV stimulus (masker level m_i). The inputs come from rendering the scene the way ``render``
does (the rig's ratings, a gamut mapping): with the fitted ramps where the parameters have them,
else with the prior's (the simulated population's ramps, ``protocols/simulation/
ground_truth.yaml``), so the ranges of a missing function are a prediction. Per function:

``within``
    fitted, and every masker level the scene plays lies within the fitted masker range;
``extrapolated``
    fitted, but the scene plays the masker beyond that range (by how much, dB, each side);
``missing``
    no usable entry (absent, or not fitted).

:func:`measure_ranges` gives, per function, the masker ranges still to be measured: the whole
used range of a missing function, the part beyond the fitted range of an extrapolated one. A
ramp needs two masker levels, so a range narrower than :data:`MIN_RANGE_DB` is widened to it
(into the fitted range where there is one, else downward). Levels in dB SL of each stimulus.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from masking_lab.core.errors import SolverError
from masking_lab.core.masking import MaskingFunction
from masking_lab.rendering.pair import MutualMasking
from masking_lab.rendering.render import Rendering, render_scene
from masking_lab.rendering.scene import Scene

__all__ = [
    "MIN_RANGE_DB",
    "TOLERANCE_DB",
    "FunctionNeed",
    "ScenePlanInputs",
    "function_needs",
    "measure_ranges",
    "provisional_pair",
]

#: Beyond the fitted range by at most this much (dB) still counts as within: rounding.
TOLERANCE_DB = 0.1
#: The narrowest masker range a ramp is measured on, dB (one step of the paper's levels).
MIN_RANGE_DB = 5.0


@dataclass(frozen=True)
class FunctionNeed:
    """One masking function a scene needs, and how well the parameters cover it.

    Attributes
    ----------
    target, masker : str
        Stimulus names (e.g. ``"EV270"`` masked by ``"MV180"``).
    used_range_db_sl : tuple of float or None
        Lowest and highest masker input the scene plays while the target plays, dB SL of the
        masker (None: never together).
    status : str
        ``"within"``, ``"extrapolated"`` or ``"missing"``.
    fitted_range_db_sl : tuple of float or None
        Masker range the present ramp was fitted on, dB SL.
    below_db, above_db : float
        How far the used range reaches below and above the fitted range, dB (0 if not).
    entry_status : str
        The parameters' status of the entry (``"fitted"``, ``"no_masking"``,
        ``"insufficient_data"``, ``"missing"``).
    intercept_db, slope : float
        The ramp used to predict the inputs (fitted, or the prior's for a missing one).
    """

    target: str
    masker: str
    used_range_db_sl: tuple[float, float] | None
    status: str
    fitted_range_db_sl: tuple[float, float] | None
    below_db: float
    above_db: float
    entry_status: str
    intercept_db: float
    slope: float

    @property
    def direction(self) -> str:
        """``"EV masked by MV"`` or ``"MV masked by EV"``."""
        return "EV masked by MV" if self.target.startswith("EV") else "MV masked by EV"

    @property
    def label(self) -> str:
        """``"<target> masked by <masker>"``."""
        return f"{self.target} masked by {self.masker}"


@dataclass(frozen=True)
class ScenePlanInputs:
    """The ramps a plan starts from: fitted where present, the prior's where missing.

    Attributes
    ----------
    pair : MutualMasking
        Both ramps (fitted ranges set where fitted).
    entry_status : dict
        ``(target, masker)`` → the parameters' status (``"missing"`` if absent).
    fitted : dict
        ``(target, masker)`` → the fitted parameter file entry (absent if not usable).
    """

    pair: MutualMasking
    entry_status: dict[tuple[str, str], str]
    fitted: dict[tuple[str, str], Mapping[str, Any]]


def provisional_pair(
    params: Mapping[str, Any] | None,
    prior: Mapping[tuple[str, str], MaskingFunction],
    *,
    mv: str,
    ev: str,
    params_source: str = "masking_params.json",
    prior_source: str = "the ground truth",
) -> ScenePlanInputs:
    """The scene's two ramps: each from ``params`` if fitted there, else from ``prior``.

    Parameters
    ----------
    params : mapping or None
        A parsed, validated ``masking_params.json`` (None: nothing measured yet).
    prior : mapping
        ``(target, masker)`` → ramp of the simulated population (the ground truth).
    mv, ev : str
        The scene's stimuli.
    params_source, prior_source : str
        Names for messages.

    Raises
    ------
    SolverError
        A missing function that the prior does not know either (naming both sources).

    Examples
    --------
    >>> prior = {("MV180", "EV270"): MaskingFunction("MV180", "EV270", 1.3, 1.06),
    ...          ("EV270", "MV180"): MaskingFunction("EV270", "MV180", -5.9, 0.66)}
    >>> p = provisional_pair(None, prior, mv="MV180", ev="EV270")
    >>> p.pair.b, sorted(p.entry_status.values())
    (1.06, ['missing', 'missing'])
    """
    functions = [] if params is None else list(params.get("functions", []))
    ramps: dict[tuple[str, str], tuple[float, float]] = {}
    ranges: dict[tuple[str, str], tuple[float, float] | None] = {}
    status: dict[tuple[str, str], str] = {}
    fitted: dict[tuple[str, str], Mapping[str, Any]] = {}
    for key in ((mv, ev), (ev, mv)):
        entry = next(
            (f for f in functions if (f.get("target"), f.get("masker")) == key),
            None,
        )
        status[key] = "missing" if entry is None else str(entry.get("status", "fitted"))
        usable = (
            entry is not None
            and status[key] in ("fitted", "no_masking")
            and isinstance(entry.get("intercept_db"), int | float)
            and isinstance(entry.get("slope"), int | float)
        )
        if usable:
            assert entry is not None
            ramps[key] = (float(entry["intercept_db"]), float(entry["slope"]))
            rng = entry.get("fitted_range_db_sl")
            ranges[key] = (float(rng[0]), float(rng[1])) if rng else None
            fitted[key] = entry
            continue
        fn = prior.get(key)
        if fn is None:
            raise SolverError(
                f"{params_source}: no fitted ramp for {key[0]} masked by {key[1]}, and "
                f"{prior_source} has none to predict the scene's inputs with; add a prior ramp "
                "for the pair there (a guess will do: the plan measures it) or pass another "
                "--ground-truth"
            )
        ramps[key] = (fn.intercept_db, fn.slope)
        ranges[key] = None
    (a, b), (c, d) = ramps[(mv, ev)], ramps[(ev, mv)]
    try:
        pair = MutualMasking(
            a,
            b,
            c,
            d,
            mv=mv,
            ev=ev,
            f_fitted_range_db_sl=ranges[(mv, ev)],
            g_fitted_range_db_sl=ranges[(ev, mv)],
        )
    except SolverError as exc:
        raise SolverError(f"{params_source}: {exc}") from exc
    return ScenePlanInputs(pair, status, fitted)


def _used_range(masker_input: np.ndarray, plays: np.ndarray) -> tuple[float, float] | None:
    x = masker_input[plays & np.isfinite(masker_input)]
    if not x.size:
        return None
    return float(x.min()), float(x.max())


def function_needs(
    scene: Scene,
    inputs: ScenePlanInputs,
    *,
    max_mv_db_sl: float | None,
    max_ev_db_sl: float | None,
    gamut_map: str = "clip",
) -> tuple[Rendering, list[FunctionNeed]]:
    """Render ``scene`` with the provisional ramps and say what each masking function covers.

    Parameters
    ----------
    scene : Scene
        A two-channel scene.
    inputs : ScenePlanInputs
        From :func:`provisional_pair`.
    max_mv_db_sl, max_ev_db_sl : float or None
        The rig's rated maxima, dB SL (both needed for a gamut mapping).
    gamut_map : str
        As ``render --gamut-map``.

    Returns
    -------
    rendering, needs
        The provisional rendering and one :class:`FunctionNeed` per direction (EV target
        first).

    Examples
    --------
    >>> from masking_lab.rendering.scene import GeometrySpec, PathSpec, TextureSpec
    >>> scene = Scene("bump_rough", PathSpec(), GeometrySpec("bump"),
    ...               TextureSpec("rough", "MV180", 12.0))
    >>> prior = {("MV180", "EV270"): MaskingFunction("MV180", "EV270", 1.304, 1.062),
    ...          ("EV270", "MV180"): MaskingFunction("EV270", "MV180", -5.927, 0.658)}
    >>> _, needs = function_needs(scene, provisional_pair(None, prior, mv="MV180", ev="EV270"),
    ...                           max_mv_db_sl=30.0, max_ev_db_sl=30.0)
    >>> [(n.label, n.status, round(n.used_range_db_sl[1], 1)) for n in needs]
    [('EV270 masked by MV180', 'missing', 30.0), ('MV180 masked by EV270', 'missing', 19.5)]
    """
    pair = inputs.pair
    mapping = gamut_map if (max_mv_db_sl is not None and max_ev_db_sl is not None) else "none"
    r = render_scene(
        scene, pair, max_mv_db_sl=max_mv_db_sl, max_ev_db_sl=max_ev_db_sl, gamut_map=mapping
    )
    mv_plays = np.isfinite(r.mv_target_db_sl)
    ev_plays = np.isfinite(r.ev_target_db_sl)
    both = mv_plays & ev_plays
    needs = []
    for target, masker, masker_input, rating, ab, fitted_range in (
        (pair.ev, pair.mv, r.mv_input_db_sl, max_mv_db_sl, (pair.c_db, pair.d),
         pair.g_fitted_range_db_sl),
        (pair.mv, pair.ev, r.ev_input_db_sl, max_ev_db_sl, (pair.a_db, pair.b),
         pair.f_fitted_range_db_sl),
    ):  # fmt: skip
        if rating is not None:
            # Unmapped (--gamut-map none), an input above the rating plays at the rating.
            masker_input = np.minimum(masker_input, rating)
        used = _used_range(masker_input, both)
        key = (target, masker)
        present = key in inputs.fitted
        below = above = 0.0
        if not present:
            status = "missing"
        else:
            if used is not None and fitted_range is not None:
                below = max(0.0, fitted_range[0] - used[0])
                above = max(0.0, used[1] - fitted_range[1])
            beyond = below > TOLERANCE_DB or above > TOLERANCE_DB
            status = "extrapolated" if beyond else "within"
        needs.append(
            FunctionNeed(
                target=target,
                masker=masker,
                used_range_db_sl=used,
                status=status,
                fitted_range_db_sl=fitted_range if present else None,
                below_db=below,
                above_db=above,
                entry_status=inputs.entry_status[key],
                intercept_db=ab[0],
                slope=ab[1],
            )
        )
    return r, needs


def _widened(lo: float, hi: float, *, downward: bool) -> tuple[float, float]:
    """``[lo, hi]`` rounded outward to whole dB, at least :data:`MIN_RANGE_DB` wide, ≥ 0."""
    lo, hi = math.floor(lo + 1e-9), math.ceil(hi - 1e-9)
    if hi - lo < MIN_RANGE_DB:
        if downward:
            lo = hi - MIN_RANGE_DB
        else:
            hi = lo + MIN_RANGE_DB
    if lo < 0:  # a masker below its own AL is not a level the protocols play
        lo, hi = 0.0, max(hi, MIN_RANGE_DB)
    return float(lo), float(hi)


def measure_ranges(need: FunctionNeed) -> list[tuple[float, float]]:
    """Masker ranges still to be measured for ``need``, dB SL of the masker.

    A missing function: its whole used range. An extrapolated one: the part below and the
    part above its fitted range (each widened to :data:`MIN_RANGE_DB` into the fitted range, so
    the new ramp shares levels with the old). Within: nothing. Ranges are rounded outward to
    whole dB.

    Examples
    --------
    >>> n = FunctionNeed("EV270", "MV180", (23.3, 30.0), "extrapolated", (5.0, 25.0), 0.0, 5.0,
    ...                  "fitted", -5.9, 0.66)
    >>> measure_ranges(n)
    [(25.0, 30.0)]
    >>> measure_ranges(FunctionNeed("EV270", "MV180", (23.3, 30.0), "missing", None, 0.0, 0.0,
    ...                             "missing", -5.9, 0.66))
    [(23.0, 30.0)]
    """
    if need.status == "within" or need.used_range_db_sl is None:
        return []
    lo, hi = need.used_range_db_sl
    if need.status == "missing" or need.fitted_range_db_sl is None:
        return [_widened(lo, hi, downward=True)]
    fit_lo, fit_hi = need.fitted_range_db_sl
    out = []
    if need.below_db > TOLERANCE_DB:
        out.append(_widened(lo, fit_lo, downward=False))
    if need.above_db > TOLERANCE_DB:
        out.append(_widened(fit_hi, hi, downward=True))
    return out
