"""Render a scene: per-point targets → compensated inputs, and what each input pair feels like.

:func:`render_scene` takes, for every interaction point, the scene's perceived targets
(m_p, e_p), asks the solver for the inputs (m_i, e_i), and runs the forward model twice — on the
compensated inputs and on the targets played as they are (no compensation, paper Figure 4b) — to
give the masked ALs and the perceived intensities of both. :func:`summarize` condenses a
:class:`Rendering` into a JSON-ready summary.

With rated maxima, ``render_scene`` also computes the perceptual gamut
(:mod:`masking_lab.rendering.gamut`) and, with ``gamut_map``, first brings the targets into it
(:mod:`masking_lab.rendering.mapping`); :func:`compare_strategies` scores every mapping.

Model only what a scene needs (:func:`needed_pairs`): a single-channel scene has nothing to mask
it and passes straight through without parameters; a two-channel scene needs exactly the two
masking functions of its (MV, EV) stimulus pair.

Pure: no file is read or written here. :mod:`masking_lab.rendering.outputs` writes the per-point
table, the summary and the figure, and the protocol that measures missing masking functions.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray

from masking_lab import __version__
from masking_lab.core.errors import SolverError
from masking_lab.formats.records import json_number
from masking_lab.rendering.gamut import gamut_for_targets
from masking_lab.rendering.mapping import (
    STRATEGIES,
    map_targets,
    mapping_metrics,
    playable_inputs,
)
from masking_lab.rendering.ramp_inverse import REPRODUCE_TOL_DB
from masking_lab.rendering.scene import Scene
from masking_lab.rendering.solver import (
    REASON_TEXT,
    MutualMasking,
    Reason,
    Solution,
    Status,
    ev_masked_al_db_sl,
    forward,
    mv_masked_al_db_sl,
    solve,
)

__all__ = [
    "NO_MASKING",
    "Rendering",
    "compare_strategies",
    "intended",
    "needed_pairs",
    "played_metrics",
    "render_scene",
    "runs_mm",
    "summarize",
]

# Nothing masks a channel that plays alone: the ramps are identically 0.
NO_MASKING = MutualMasking(0.0, 0.0, 0.0, 0.0, mv="none", ev="none")


def _solution_array(name: str) -> property:
    """A read-only attribute that is the solution's array ``name``."""
    return property(lambda self: getattr(self.solution, name), doc=f"``solution.{name}``.")


def _felt(input_name: str, masked_al_name: str) -> cached_property[NDArray[np.float64]]:
    """An attribute computed once: perceived intensity = input − masked AL, dB SL."""

    def felt(self: Rendering) -> NDArray[np.float64]:
        return getattr(self, input_name) - getattr(self, masked_al_name)

    felt.__doc__ = f"``{input_name} − {masked_al_name}``, dB SL (< 0: not felt)."
    return cached_property(felt)


@dataclass(frozen=True)
class Rendering:
    """A rendered scene; every array has one value per interaction point.

    Attributes
    ----------
    scene : Scene
        What was rendered.
    pair : MutualMasking or None
        Masking functions used (None: single-channel scene, passed through).
    x_mm, t_s : ndarray
        Position along the path, mm, and when the cue reaches it, s.
    mv_target_db_sl, ev_target_db_sl : ndarray
        Perceived targets m_p, e_p, dB SL (−inf: channel absent).
    solution : Solution
        The solver's answer per point (status, case, rating flags).
    mv_input_db_sl, ev_input_db_sl : ndarray
        Compensated inputs m_i, e_i, dB SL (NaN where there is no unique answer).
    mv_masked_al_db_sl, ev_masked_al_db_sl : ndarray
        Masked ALs under the compensated inputs, dB SL: f(e_i) and g(m_i).
    mv_perceived_db_sl, ev_perceived_db_sl : ndarray
        Perceived intensities under the compensated inputs, dB SL (< 0: not felt).
    mv_masked_al_uncomp_db_sl, ev_masked_al_uncomp_db_sl : ndarray
        Masked ALs when the targets are played as inputs, dB SL.
    mv_perceived_uncomp_db_sl, ev_perceived_uncomp_db_sl : ndarray
        Perceived intensities when the targets are played as inputs, dB SL.
    gamut_map : str
        Gamut mapping applied to the scene's targets (``"none"``: targets as designed).
    gamut : Gamut or None
        What the rig can render (:mod:`masking_lab.rendering.gamut`), when ratings were given.
    mv_intended_db_sl, ev_intended_db_sl : ndarray or None
        The scene's own targets, dB SL, when a mapping changed them (the ``*_target_*`` arrays
        then hold the mapped targets).
    gain : float
        The common gain of the ``scale`` mapping (1.0 otherwise).
    from_gamut_edge : ndarray of bool or None
        Points whose inputs were found on the gamut's edge rather than by the solver.
    """

    scene: Scene
    pair: MutualMasking | None
    x_mm: NDArray[np.float64]
    t_s: NDArray[np.float64]
    solution: Solution
    mv_masked_al_db_sl: NDArray[np.float64]
    ev_masked_al_db_sl: NDArray[np.float64]
    mv_masked_al_uncomp_db_sl: NDArray[np.float64]
    ev_masked_al_uncomp_db_sl: NDArray[np.float64]
    gamut_map: str = "none"
    gamut: Any = None
    mv_intended_db_sl: NDArray[np.float64] | None = None
    ev_intended_db_sl: NDArray[np.float64] | None = None
    gain: float = 1.0
    from_gamut_edge: NDArray[np.bool_] | None = None

    # Targets and inputs live in the solution only, and what is felt is derived from them, so
    # a rendering cannot disagree with itself (see :meth:`with_inputs`).
    mv_target_db_sl = _solution_array("mv_target_db_sl")
    ev_target_db_sl = _solution_array("ev_target_db_sl")
    mv_input_db_sl = _solution_array("mv_input_db_sl")
    ev_input_db_sl = _solution_array("ev_input_db_sl")
    mv_perceived_db_sl = _felt("mv_input_db_sl", "mv_masked_al_db_sl")
    ev_perceived_db_sl = _felt("ev_input_db_sl", "ev_masked_al_db_sl")
    mv_perceived_uncomp_db_sl = _felt("mv_target_db_sl", "mv_masked_al_uncomp_db_sl")
    ev_perceived_uncomp_db_sl = _felt("ev_target_db_sl", "ev_masked_al_uncomp_db_sl")

    def with_inputs(
        self, mv_input_db_sl: NDArray[np.float64], ev_input_db_sl: NDArray[np.float64]
    ) -> Rendering:
        """The same rendering with other inputs (dB SL), e.g. what a device actually played.

        The masked ALs stay those of the solver's inputs; perceived intensities follow the new
        inputs.

        Examples
        --------
        >>> from masking_lab.rendering.scene import GeometrySpec, PathSpec, Scene
        >>> r = render_scene(Scene("bump", PathSpec(), GeometrySpec("bump"), None), None)
        >>> quiet = r.with_inputs(r.mv_input_db_sl, r.ev_input_db_sl - 3.0)
        >>> float(np.nanmax(r.ev_perceived_db_sl - quiet.ev_perceived_db_sl))
        3.0
        """
        played = replace(
            self.solution, mv_input_db_sl=mv_input_db_sl, ev_input_db_sl=ev_input_db_sl
        )
        return replace(self, solution=played)

    def inputs(self, compensated: bool) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(mv_input_db_sl, ev_input_db_sl)`` to play: compensated, or the targets as they are.

        Parameters
        ----------
        compensated : bool
            True for the solver's inputs, False for the targets played unchanged.

        Returns
        -------
        mv_db_sl, ev_db_sl : ndarray
            Inputs per point, dB SL.
        """
        if compensated:
            return self.mv_input_db_sl, self.ev_input_db_sl
        return self.mv_target_db_sl, self.ev_target_db_sl

    def perceived(self, compensated: bool) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(mv_perceived_db_sl, ev_perceived_db_sl)`` with or without compensation.

        Parameters
        ----------
        compensated : bool
            True for the compensated inputs, False for the targets played unchanged.

        Returns
        -------
        mv_db_sl, ev_db_sl : ndarray
            Perceived intensity per point, dB SL (< 0: not felt).
        """
        if compensated:
            return self.mv_perceived_db_sl, self.ev_perceived_db_sl
        return self.mv_perceived_uncomp_db_sl, self.ev_perceived_uncomp_db_sl


def needed_pairs(scene: Scene) -> list[tuple[str, str]]:
    """(MV stimulus, EV stimulus) pairs whose masking functions ``scene`` needs (0 or 1).

    Examples
    --------
    >>> from masking_lab.rendering.scene import GeometrySpec, PathSpec, Scene, TextureSpec
    >>> bump = GeometrySpec("bump")
    >>> needed_pairs(Scene("bump_rough", PathSpec(), bump, TextureSpec("rough", "MV180", 12.0)))
    [('MV180', 'EV270')]
    >>> needed_pairs(Scene("bump", PathSpec(), bump, None))  # EV alone: nothing masks it
    []
    """
    return scene.stimulus_pairs()


def render_scene(
    scene: Scene,
    pair: MutualMasking | None,
    *,
    max_mv_db_sl: float | None = None,
    max_ev_db_sl: float | None = None,
    gamut_map: str = "none",
) -> Rendering:
    """Targets, compensated inputs and perceived intensities at every point of ``scene``.

    Parameters
    ----------
    scene : Scene
        The scene.
    pair : MutualMasking or None
        Masking functions of the scene's (MV, EV) pair; None for a single-channel scene.
    max_mv_db_sl, max_ev_db_sl : float, optional
        Rated maximum input per channel, dB SL. With ``gamut_map="none"`` points needing more
        are flagged, not clipped.
    gamut_map : {"none", "clip", "scale", "compress"}
        How targets outside the gamut are brought in (:mod:`masking_lab.rendering.mapping`);
        any strategy but ``"none"`` needs both maxima and keeps every input within them.

    Returns
    -------
    Rendering
        Targets, inputs, masked ALs and perceived intensities per point, dB SL.

    Raises
    ------
    SolverError
        A two-channel scene without ``pair``, or a pair for other stimuli than the scene's.

    Examples
    --------
    The bump (EV270, 0–10 dB SL) with the rough texture (MV180 at 12 dB SL), under ramps
    f(e) = max(0, −2 + 0.5·e) and g(m) = max(0, −1 + 0.4·m). At the bump's steepest ascent
    the compensated inputs are felt at their targets; played as they are, EV is felt 3.8 dB low:

    >>> from masking_lab.rendering.pair import MutualMasking
    >>> from masking_lab.rendering.scene import GeometrySpec, PathSpec, Scene, TextureSpec
    >>> scene = Scene("bump_rough", PathSpec(), GeometrySpec("bump"),
    ...               TextureSpec("rough", "MV180", 12.0))
    >>> pair = MutualMasking(a_db=-2.0, b=0.5, c_db=-1.0, d=0.4, mv="MV180", ev="EV270")
    >>> r = render_scene(scene, pair)
    >>> i = int(np.argmax(r.ev_target_db_sl))
    >>> print(f"x = {r.x_mm[i]:.1f} mm, t = {r.t_s[i]:.2f} s: EV target "
    ...       f"{r.ev_target_db_sl[i]:.1f}, input {r.ev_input_db_sl[i]:.2f}, felt "
    ...       f"{r.ev_perceived_db_sl[i]:.1f} (uncompensated {r.ev_perceived_uncomp_db_sl[i]:.1f})")
    x = 41.0 mm, t = 0.80 s: EV target 10.0, input 16.25, felt 10.0 (uncompensated 6.2)
    """
    needs = needed_pairs(scene)
    if needs:
        if pair is None:
            mv, ev = needs[0]
            raise SolverError(
                f"{scene.source}: scene {scene.name!r} plays {mv} and {ev} together and needs "
                "their masking functions; load them from masking_params.json"
            )
        if (pair.mv, pair.ev) != needs[0]:
            raise SolverError(
                f"{scene.source}: scene {scene.name!r} uses {needs[0][0]} with {needs[0][1]} "
                f"but the masking functions given are for {pair.mv} with {pair.ev}"
            )
        model = pair
    else:
        pair = None
        model = NO_MASKING
    x, mv_t, ev_t = scene.targets()
    if not np.all(np.isfinite(mv_t) | (mv_t == -np.inf)) or not np.all(
        np.isfinite(ev_t) | (ev_t == -np.inf)
    ):
        raise SolverError(
            f"{scene.source}: scene {scene.name!r} gives non-finite perceived targets (its levels "
            "or shape overflow float arithmetic); use levels within the scene schema's bounds"
        )
    gamut = None
    if max_mv_db_sl is not None and max_ev_db_sl is not None:
        gamut = gamut_for_targets(model, max_mv_db_sl, max_ev_db_sl, mv_t, ev_t)
    extra: dict[str, Any] = {"gamut": gamut}
    if gamut_map != "none":
        if gamut is None or max_mv_db_sl is None or max_ev_db_sl is None:  # (None together)
            raise SolverError(
                f"gamut mapping {gamut_map!r} needs both channels' rated maxima (--max-mv-db-sl, "
                "--max-ev-db-sl or a rig config with channels.<MV|EV>.max_level_db_sl)"
            )
        mapped_m, mapped_e, gain = map_targets(gamut, mv_t, ev_t, gamut_map)
        sol = solve(model, mapped_m, mapped_e)
        mi, ei, edge = playable_inputs(
            gamut,
            mapped_m,
            mapped_e,
            sol.mv_input_db_sl,
            sol.ev_input_db_sl,
            several=sol.status == Status.MULTIPLE,
        )
        sol = replace(
            sol,
            mv_input_db_sl=mi,
            ev_input_db_sl=ei,
            mv_exceeds_rating=mi > max_mv_db_sl,
            ev_exceeds_rating=ei > max_ev_db_sl,
            max_mv_db_sl=max_mv_db_sl,
            max_ev_db_sl=max_ev_db_sl,
        )
        extra.update(
            gamut_map=gamut_map,
            mv_intended_db_sl=mv_t,
            ev_intended_db_sl=ev_t,
            gain=gain,
            from_gamut_edge=edge,
        )
        mv_t, ev_t = mapped_m, mapped_e
    else:
        sol = solve(model, mv_t, ev_t, max_mv_db_sl=max_mv_db_sl, max_ev_db_sl=max_ev_db_sl)
    return Rendering(
        scene=scene,
        pair=pair,
        x_mm=x,
        t_s=x / scene.path.speed_mm_s,
        solution=sol,
        mv_masked_al_db_sl=mv_masked_al_db_sl(model, sol.ev_input_db_sl),
        ev_masked_al_db_sl=ev_masked_al_db_sl(model, sol.mv_input_db_sl),
        mv_masked_al_uncomp_db_sl=mv_masked_al_db_sl(model, ev_t),
        ev_masked_al_uncomp_db_sl=ev_masked_al_db_sl(model, mv_t),
        **extra,
    )


def intended(r: Rendering) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The scene's own targets (before any gamut mapping), dB SL."""
    if r.mv_intended_db_sl is None or r.ev_intended_db_sl is None:
        return r.mv_target_db_sl, r.ev_target_db_sl
    return r.mv_intended_db_sl, r.ev_intended_db_sl


def played_metrics(r: Rendering) -> dict[str, Any]:
    """:func:`~masking_lab.rendering.mapping.mapping_metrics` of what the rig would play.

    Inputs above a rating are played at the rating (the rig cannot do more); a point without
    an input is counted without a level.
    """
    sol = r.solution
    mi, ei = r.mv_input_db_sl, r.ev_input_db_sl
    within = ~(np.asarray(sol.mv_exceeds_rating) | np.asarray(sol.ev_exceeds_rating))
    within &= ~(np.isnan(mi) | np.isnan(ei))
    if sol.max_mv_db_sl is not None:
        mi = np.minimum(mi, sol.max_mv_db_sl)
    if sol.max_ev_db_sl is not None:
        ei = np.minimum(ei, sol.max_ev_db_sl)
    model = r.pair if r.pair is not None else NO_MASKING
    with np.errstate(invalid="ignore"):
        mp, ep = forward(model, mi, ei)
    want_m, want_e = intended(r)
    return mapping_metrics(r.x_mm, want_m, want_e, mp, ep, within)


def compare_strategies(
    scene: Scene, pair: MutualMasking | None, max_mv_db_sl: float, max_ev_db_sl: float
) -> dict[str, dict[str, Any]]:
    """Each gamut mapping's :func:`played_metrics` on one scene (the trade between them).

    Examples
    --------
    >>> from masking_lab.rendering.scene import GeometrySpec, PathSpec, Scene, TextureSpec
    >>> scene = Scene("bump_rough", PathSpec(), GeometrySpec("bump"),
    ...               TextureSpec("rough", "MV180", 12.0))
    >>> pair = MutualMasking(1.304, 1.062, -5.927, 0.658, mv="MV180", ev="EV270")
    >>> trade = compare_strategies(scene, pair, 30.0, 30.0)
    >>> [round(trade[s]["share_within_ratings"], 2) for s in STRATEGIES]
    [1.0, 1.0, 1.0, 0.07]
    """
    return {
        s: played_metrics(
            render_scene(
                scene, pair, max_mv_db_sl=max_mv_db_sl, max_ev_db_sl=max_ev_db_sl, gamut_map=s
            )
        )
        for s in STRATEGIES
    }


# --------------------------------------------------------------------------------------------
# Summaries


def runs_mm(mask: NDArray[np.bool_], x_mm: NDArray[np.float64]) -> list[tuple[float, float]]:
    """Contiguous stretches where ``mask`` holds, as (first, last) positions in mm.

    Parameters
    ----------
    mask : ndarray of bool
        One flag per point.
    x_mm : ndarray
        Position of each point along the path, mm.

    Returns
    -------
    list of (float, float)
        First and last position of each run, mm.

    Examples
    --------
    >>> runs_mm(np.array([False, True, True, False, True]), np.array([0.0, 0.1, 0.2, 0.3, 0.4]))
    [(0.1, 0.2), (0.4, 0.4)]
    """
    idx = np.flatnonzero(np.diff(np.concatenate(([0], mask.astype(np.int8), [0]))))
    pairs = zip(idx[::2], idx[1::2], strict=True)
    return [(round(float(x_mm[a]), 6), round(float(x_mm[b - 1]), 6)) for a, b in pairs]


def summarize(r: Rendering) -> dict[str, Any]:
    """JSON-ready summary: statuses, cases, rating problems, worst perceived errors.

    Levels are in dB SL, positions in mm; non-finite numbers become ``"inf"``/``"-inf"`` or None.

    Parameters
    ----------
    r : Rendering
        A rendered scene.

    Returns
    -------
    dict
        Scene identity, masking parameters, status and case counts, and per channel the target
        and input ranges, points above the rating, and the worst perceived error and points not
        felt with and without compensation.

    Examples
    --------
    Without compensation, the masked EV bump goes unfelt at 107 of its 919 points:

    >>> from masking_lab.rendering.pair import MutualMasking
    >>> from masking_lab.rendering.scene import GeometrySpec, PathSpec, Scene, TextureSpec
    >>> scene = Scene("bump_rough", PathSpec(), GeometrySpec("bump"),
    ...               TextureSpec("rough", "MV180", 12.0))
    >>> pair = MutualMasking(a_db=-2.0, b=0.5, c_db=-1.0, d=0.4, mv="MV180", ev="EV270")
    >>> ev = summarize(render_scene(scene, pair))["channels"]["EV"]
    >>> ev["uncompensated"]["points_not_felt"], ev["compensated"]["points_not_felt"]
    (107, 0)
    """
    sol = r.solution
    out: dict[str, Any] = {
        "scene": r.scene.name,
        "scene_file": r.scene.source,
        "scene_sha256": r.scene.sha256,
        "software_version": __version__,
        "n_points": int(r.x_mm.size),
        "single_channel": r.pair is None,
        "masking": None
        if r.pair is None
        else {
            "mv": r.pair.mv,
            "ev": r.pair.ev,
            "a_db": r.pair.a_db,
            "b": r.pair.b,
            "c_db": r.pair.c_db,
            "d": r.pair.d,
            "bd": r.pair.bd,
            "one_minus_bd": r.pair.one_minus_bd,
        },
        "reproduce_tol_db": REPRODUCE_TOL_DB,
        "status_counts": sol.counts(),
        "case_counts": {str(k): int(np.count_nonzero(sol.case == k)) for k in range(1, 5)},
        "notes": [] if r.pair is None else list(r.pair.notes),
        "no_answer_reasons": {
            REASON_TEXT[Reason(k)]: int(np.count_nonzero(sol.reason == k))
            for k in range(1, len(Reason))
            if np.any(sol.reason == k)
        },
    }
    out["gamut"] = None if r.gamut is None else r.gamut.as_dict()
    out["gamut_mapping"] = {
        "strategy": r.gamut_map,
        "gain": r.gain,
        "points_moved": 0
        if r.mv_intended_db_sl is None
        else int(
            np.count_nonzero(
                (r.mv_intended_db_sl != r.mv_target_db_sl)
                | (r.ev_intended_db_sl != r.ev_target_db_sl)
            )
        ),
        "points_from_gamut_edge": 0
        if r.from_gamut_edge is None
        else int(np.count_nonzero(r.from_gamut_edge)),
        "as_played": played_metrics(r),
    }
    channels: dict[str, Any] = {}
    for ch, name in (("mv", "MV"), ("ev", "EV")):
        target = getattr(r, f"{ch}_target_db_sl")
        if np.all(target == -np.inf):
            continue
        inp = getattr(r, f"{ch}_input_db_sl")
        limit = getattr(sol, f"max_{ch}_db_sl")
        over = getattr(sol, f"{ch}_exceeds_rating")
        entry: dict[str, Any] = {
            "stimulus": _stimulus(r.scene, ch),
            "target_range_db_sl": _range(target),
            "input_range_db_sl": _range(inp),
            "max_rated_db_sl": limit,
            "points_above_rating": int(np.count_nonzero(over)),
            "above_rating_mm": [list(run) for run in runs_mm(over, r.x_mm)],
        }
        # This channel's input is the masker of the other channel's ramp; beyond the masker
        # levels that ramp was fitted on, the compensation extrapolates.
        fitted = None
        if r.pair is not None:
            fitted = r.pair.g_fitted_range_db_sl if ch == "mv" else r.pair.f_fitted_range_db_sl
        entry["masks_other_fitted_range_db_sl"] = list(fitted) if fitted else None
        entry["points_beyond_fitted_range"] = (
            int(np.count_nonzero(inp > fitted[1])) if fitted else None
        )
        for label, compensated in (("compensated", True), ("uncompensated", False)):
            perceived = r.perceived(compensated)[0 if ch == "mv" else 1]
            err = np.abs(perceived - target)
            lost = (target >= 0) & (perceived < 0)
            entry[label] = {
                "max_abs_error_db": json_number(np.nanmax(err))
                if np.any(np.isfinite(err))
                else None,
                "points_not_felt": int(np.count_nonzero(lost)),
            }
        channels[name] = entry
    out["channels"] = channels
    return out


def _stimulus(scene: Scene, ch: str) -> str:
    if ch == "mv":
        return scene.texture.stimulus if scene.texture is not None else ""
    return scene.geometry.stimulus if scene.geometry is not None else ""


def _range(a: NDArray[np.float64]) -> list[Any] | None:
    ok = a[np.isfinite(a)]
    return [json_number(ok.min()), json_number(ok.max())] if ok.size else None
