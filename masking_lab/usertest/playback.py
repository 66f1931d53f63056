"""What each user-test trial plays: rendered objects, and drive levels by time or finger position.

- :func:`render_objects`: each object's per-point inputs, compensated and not (dB SL).
- :func:`path_position_mm` / :func:`path_x_from_screen_mm`: where along the path (mm) the cue is
  at a trial time, or the finger is on the screen.
- :func:`levels_at` and :func:`trial_levels_db_v`: for a trial and a time (cue tracking,
  time-locked at 51 mm/s) or a finger position (finger tracking, streamed updates), the levels to
  play, in dB SL and in dB re 1 V.

Pure: no I/O, no clock.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from masking_lab.core.errors import SolverError
from masking_lab.rendering.render import Rendering, render_scene
from masking_lab.rendering.solver import MissingMaskingError, MutualMasking, PairProblem, Status
from masking_lab.usertest.design import SILENT, UserTestDesign, UserTrial

__all__ = [
    "levels_at",
    "path_position_mm",
    "path_x_from_screen_mm",
    "render_objects",
    "trial_levels_db_v",
]


def render_objects(
    design: UserTestDesign,
    pairs: Mapping[tuple[str, str], MutualMasking],
    *,
    max_mv_db_sl: float | None = None,
    max_ev_db_sl: float | None = None,
    gamut_map: str = "none",
) -> dict[tuple[str, str], Rendering]:
    """Render every object: targets, compensated inputs, perceived intensities.

    Parameters
    ----------
    design : UserTestDesign
        The protocol and its scenes.
    pairs : mapping (mv, ev) → MutualMasking
        Fitted masking of each stimulus pair the objects use (:meth:`UserTestDesign
        .stimulus_pairs`); extra pairs are ignored.
    max_mv_db_sl, max_ev_db_sl : float, optional
        Rated maximum inputs, dB SL; flagged per point in each rendering.
    gamut_map : str
        Gamut mapping of each scene's targets (:mod:`masking_lab.rendering.mapping`); any
        but ``"none"`` needs both maxima.

    Raises
    ------
    MissingMaskingError
        Listing every pair without masking functions.
    SolverError
        If an object has points without a unique compensated input.

    Returns
    -------
    dict of (geometry, texture) → Rendering

    Examples
    --------
    The shipped user test: 4 geometries × 3 textures, every MV texture paired with EV270
    (ramps f(e) = max(0, −2 + 0.5·e), g(m) = max(0, −1 + 0.4·m) for the example):

    >>> from masking_lab.formats.resources import shipped
    >>> from masking_lab.usertest.design import load_usertest
    >>> design = load_usertest(str(shipped("protocols", "usertest.yaml")))
    >>> pairs = {pair: MutualMasking(-2.0, 0.5, -1.0, 0.4, mv=pair[0], ev=pair[1])
    ...          for pair in design.stimulus_pairs()}
    >>> objects = render_objects(design, pairs)
    >>> len(objects), design.stimulus_pairs()[1]
    (12, ('MV180', 'EV270'))
    >>> render_objects(design, {})
    Traceback (most recent call last):
    ...
    masking_lab.rendering.pair.MissingMaskingError: ...: no masking functions for MV120am40 ...
    """
    missing = [pr for pr in design.stimulus_pairs() if pr not in pairs]
    if missing:
        problems = [
            PairProblem(a, b, "missing") for mv, ev in missing for a, b in ((mv, ev), (ev, mv))
        ]
        listed = ", ".join(f"{mv} with {ev}" for mv, ev in missing)
        raise MissingMaskingError(
            f"{design.path}: no masking functions for {listed}; measure them (`masking-lab "
            "render` on one of the scenes writes the protocol) and fit",
            problems,
        )
    out: dict[tuple[str, str], Rendering] = {}
    for key, scene in design.scenes.items():
        needs = scene.stimulus_pairs()
        r = render_scene(
            scene,
            pairs[needs[0]] if needs else None,
            max_mv_db_sl=max_mv_db_sl,
            max_ev_db_sl=max_ev_db_sl,
            gamut_map=gamut_map,
        )
        bad = r.solution.status != Status.UNIQUE
        if r.from_gamut_edge is not None:
            bad &= ~r.from_gamut_edge  # inputs found on the gamut's edge are playable
        if np.any(bad):
            at = r.x_mm[np.flatnonzero(bad)[0]]
            raise SolverError(
                f"{scene.source}: {int(bad.sum())} points have no unique compensated input "
                f"(first at {at:.1f} mm); b·d ≥ 1 for this pair, so it cannot be compensated"
            )
        out[key] = r
    return out


def path_position_mm(design: UserTestDesign, t_s: float) -> float | None:
    """Where the cue is along the path at trial time ``t_s`` s, mm; None when silent.

    Examples
    --------
    After the 1.2 s lead-in the cue moves at 51 mm/s; 0.9 s later it is halfway along:

    >>> from masking_lab.formats.resources import shipped
    >>> from masking_lab.usertest.design import load_usertest
    >>> design = load_usertest(str(shipped("protocols", "usertest.yaml")))
    >>> round(path_position_mm(design, 1.2 + 0.9), 6), path_position_mm(design, 0.5)
    (45.9, None)
    """
    at = design.timing.presentation_at(t_s)
    if at is None:
        return None
    return design.cue_speed_mm_s * at[1]


def path_x_from_screen_mm(design: UserTestDesign, x_screen_mm: float) -> float:
    """Finger x on the screen (centre-origin mm, as :mod:`masking_lab.responders.cue` logs it) →
    path mm.

    The cue's lane is centred on the screen, so the path starts at ``−sweep/2``.

    Examples
    --------
    >>> from masking_lab.formats.resources import shipped
    >>> from masking_lab.usertest.design import load_usertest
    >>> design = load_usertest(str(shipped("protocols", "usertest.yaml")))
    >>> path_x_from_screen_mm(design, -45.9), path_x_from_screen_mm(design, 0.0)
    (0.0, 45.9)
    """
    return x_screen_mm + design.sweep_mm / 2


def levels_at(r: Rendering, x_mm: float, *, compensated: bool) -> tuple[float, float]:
    """``(ev_db_sl, mv_db_sl)`` inputs at path position ``x_mm`` mm (linear between points).

    Off the path (or NaN) both channels are silent (``-inf``).

    Examples
    --------
    >>> from masking_lab.formats.resources import shipped
    >>> from masking_lab.usertest.design import load_usertest
    >>> design = load_usertest(str(shipped("protocols", "usertest.yaml")))
    >>> pairs = {pair: MutualMasking(-2.0, 0.5, -1.0, 0.4, mv=pair[0], ev=pair[1])
    ...          for pair in design.stimulus_pairs()}
    >>> objects = render_objects(design, pairs)
    >>> bump_rough = objects[("bump", "rough")]
    >>> [round(v, 2) for v in levels_at(bump_rough, 41.0, compensated=True)]
    [16.25, 18.12]
    >>> [round(v, 2) for v in levels_at(bump_rough, 41.0, compensated=False)]
    [10.0, 12.0]
    >>> levels_at(bump_rough, -1.0, compensated=True)
    (-inf, -inf)
    """
    x = float(x_mm)
    if not (r.x_mm[0] <= x <= r.x_mm[-1]):
        return SILENT
    mv, ev = r.inputs(compensated)
    return float(np.interp(x, r.x_mm, ev)), float(np.interp(x, r.x_mm, mv))


def trial_levels_db_v(
    design: UserTestDesign,
    objects: Mapping[tuple[str, str], Rendering],
    trial: UserTrial,
    unmasked_al_db_v: Mapping[str, float],
    *,
    t_s: float,
    finger_x_mm: float | None = None,
) -> tuple[float, float]:
    """Drive levels ``(ev_level_db_v, mv_level_db_v)`` in dB re 1 V to play now.

    Parameters
    ----------
    design : UserTestDesign
        The protocol (timing, tracking, cue speed).
    objects : mapping
        From :func:`render_objects`.
    trial : UserTrial
        The trial being played.
    unmasked_al_db_v : mapping stimulus name → dB re 1 V
        The participant's calibration; dB SL + unmasked AL = dB re 1 V.
    t_s : float
        Trial time, s from the trial start; outside the presentations both channels are silent.
    finger_x_mm : float, optional
        Finger position along the path, mm (:func:`path_x_from_screen_mm`); required with
        finger tracking, ignored with cue tracking.

    Returns
    -------
    tuple of float
        ``-inf`` means silence (0 V) on that channel.

    Raises
    ------
    SolverError
        Finger tracking without a finger position, or a stimulus missing from the calibration.

    Examples
    --------
    A compensated bump_rough trial 0.8 s into its first presentation (41 mm along the path),
    for a participant with ALs of −20 (EV270) and −30 (MV180) dB re 1 V:

    >>> from masking_lab.formats.resources import shipped
    >>> from masking_lab.usertest.design import load_usertest
    >>> design = load_usertest(str(shipped("protocols", "usertest.yaml")))
    >>> pairs = {pair: MutualMasking(-2.0, 0.5, -1.0, 0.4, mv=pair[0], ev=pair[1])
    ...          for pair in design.stimulus_pairs()}
    >>> objects = render_objects(design, pairs)
    >>> from masking_lab.usertest.design import trial_list
    >>> trial = next(t for t in trial_list(design, seed=7)
    ...              if t.object == ("bump", "rough") and t.compensated)
    >>> als = {"EV270": -20.0, "MV180": -30.0}
    >>> ev, mv = trial_levels_db_v(design, objects, trial, als, t_s=1.2 + 41.0 / 51.0)
    >>> round(ev, 2), round(mv, 2)
    (-3.75, -11.88)
    >>> trial_levels_db_v(design, objects, trial, als, t_s=0.5)  # lead-in: silent
    (-inf, -inf)
    """
    if design.timing.presentation_at(t_s) is None:
        return SILENT
    if design.tracking == "finger":
        if finger_x_mm is None:
            raise SolverError(
                "finger tracking needs the finger's path position (finger_x_mm); pass the "
                "latest touch sample, or set tracking: cue"
            )
        x = finger_x_mm
    else:
        x = path_position_mm(design, t_s)  # type: ignore[assignment]  # not None: presenting
    r = objects[trial.object]
    ev_sl, mv_sl = levels_at(r, x, compensated=trial.compensated)
    scene = r.scene
    ev_name = scene.geometry.stimulus if scene.geometry is not None else None
    mv_name = scene.texture.stimulus if scene.texture is not None else None
    return _db_v(ev_sl, ev_name, unmasked_al_db_v), _db_v(mv_sl, mv_name, unmasked_al_db_v)


def _db_v(level_db_sl: float, name: str | None, als: Mapping[str, float]) -> float:
    if name is None or level_db_sl == -math.inf:
        return -math.inf
    if name not in als:
        raise SolverError(
            f"the calibration has no unmasked AL for {name}; run the baseline for {name} first"
        )
    return level_db_sl + float(als[name])
