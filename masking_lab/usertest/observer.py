"""A simulated participant of the user test, and a simulated study.

:class:`IdentificationObserver` feels each channel's ``input − masked AL`` (dB SL) under its true
masking, with noise, and answers by template matching; :func:`simulate_usertest` runs every
participant's seeded session and returns the trial records a runner would log. Pure: the
randomness comes from the seed given.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from masking_lab.core.errors import SolverError
from masking_lab.rendering.render import Rendering
from masking_lab.rendering.solver import MutualMasking, forward
from masking_lab.usertest.design import UserTestDesign, UserTrial, trial_list, trial_record

__all__ = ["IdentificationObserver", "simulate_usertest"]


@dataclass(frozen=True)
class IdentificationObserver:
    """A simulated participant of the user test.

    On each presentation it feels, at ``n_samples`` points along the path, each channel's
    ``input − masked AL`` under its *true* masking (nothing below 0 dB SL), plus Gaussian noise.
    Averaging the presentations, it picks the geometry whose intended EV profile is nearest (sum
    of squares) and the texture whose intended MV level is nearest, helped by how much the MV
    feels like that texture's stimulus (carrier and envelope). Channels are not perfectly
    separated: ``cross_talk`` of the MV's spatial variation leaks into the geometry percept —
    the confusion the paper describes for uncompensated objects (its Figure 8b).

    Attributes
    ----------
    truth : mapping (mv, ev) → MutualMasking
        The participant's true masking per stimulus pair.
    noise_db : float
        SD of the perceived intensity per sample and presentation, dB.
    n_samples : int
        Points along the path the participant integrates.
    cross_talk : float
        Weight of the MV profile's variation in the geometry percept (0: none).
    level_sd_db : float
        How precisely the participant judges a texture's level, dB (SD).
    quality_weight : float
        Weight of the stimulus-identity evidence in the texture choice, per dB.
    quality_noise_db : float
        SD of the stimulus-identity evidence, dB.

    Examples
    --------
    An observer whose true masking is the one compensated for
    (f(e) = max(0, −2 + 0.5·e), g(m) = max(0, −1 + 0.4·m)):

    >>> from masking_lab.formats.resources import shipped
    >>> from masking_lab.usertest.design import load_usertest
    >>> from masking_lab.usertest.playback import render_objects
    >>> design = load_usertest(str(shipped("protocols", "usertest.yaml")))
    >>> pairs = {pair: MutualMasking(-2.0, 0.5, -1.0, 0.4, mv=pair[0], ev=pair[1])
    ...          for pair in design.stimulus_pairs()}
    >>> objects = render_objects(design, pairs)
    >>> observer = IdentificationObserver(pairs)
    >>> trial = trial_list(design, seed=7)[0]
    >>> trial.geometry, trial.texture, trial.condition
    ('hole', 'smooth', 'uncompensated')
    >>> observer.respond(design, objects, trial, np.random.default_rng(0))  # (geometry, texture)
    (2, 1)

    The bump's EV peak of 10 dB SL is felt at 6.2 dB SL under the rough texture unless
    compensated (:meth:`felt`, dB SL):

    >>> for compensated in (False, True):
    ...     mv, ev = observer.felt(objects[("bump", "rough")], compensated)
    ...     print(compensated, round(float(ev.max()), 2), round(float(mv.max()), 2))
    False 6.2 12.0
    True 10.0 12.0
    """

    truth: Mapping[tuple[str, str], MutualMasking]
    noise_db: float = 3.0
    n_samples: int = 16
    cross_talk: float = 0.5
    level_sd_db: float = 4.0
    quality_weight: float = 0.5
    quality_noise_db: float = 3.0

    def felt(self, r: Rendering, compensated: bool) -> tuple[NDArray[np.float64], ...]:
        """``(mv_felt_db_sl, ev_felt_db_sl)`` at every point: true perceived intensity, ≥ 0.

        Raises
        ------
        SolverError
            If the observer has no true masking for the object's stimulus pair.

        The class's example shows it on the bump under the rough texture.
        """
        mv_in, ev_in = r.inputs(compensated)
        needs = r.scene.stimulus_pairs()
        if needs:
            if needs[0] not in self.truth:
                raise SolverError(f"the simulated observer has no true masking for {needs[0]}")
            mv_p, ev_p = forward(self.truth[needs[0]], mv_in, ev_in)
        else:
            mv_p, ev_p = mv_in, ev_in
        return np.maximum(mv_p, 0.0), np.maximum(ev_p, 0.0)

    def respond(
        self,
        design: UserTestDesign,
        objects: Mapping[tuple[str, str], Rendering],
        trial: UserTrial,
        rng: np.random.Generator,
    ) -> tuple[int, int]:
        """``(geometry_key, texture_key)`` answered for ``trial`` (1-based keys).

        Parameters
        ----------
        design : UserTestDesign
            The protocol (answer keys, presentations per trial).
        objects : mapping (geometry, texture) → Rendering
            Rendered objects (their inputs are in dB SL).
        trial : UserTrial
            The trial to answer.
        rng : numpy.random.Generator
            Source of the perceptual noise.

        Returns
        -------
        geometry_key, texture_key : int
        """
        r = objects[trial.object]
        idx = np.linspace(0, r.x_mm.size - 1, self.n_samples).round().astype(int)
        mv_felt, ev_felt = (a[idx] for a in self.felt(r, trial.compensated))
        n_pres = design.timing.n_presentations
        shape = (n_pres, idx.size)
        mv_obs = (mv_felt + rng.normal(0.0, self.noise_db, shape)).mean(axis=0)
        ev_obs = (ev_felt + rng.normal(0.0, self.noise_db, shape)).mean(axis=0)
        # Shape is judged from how intensity varies along the path, not from its mean level.
        geometry_percept = ev_obs + self.cross_talk * (mv_obs - mv_obs.mean())
        geometry_percept = geometry_percept - geometry_percept.mean()
        g_cost = []
        for g in design.geometries:
            template = _geometry_template(objects, design, g)[idx]
            g_cost.append(float(np.sum((geometry_percept - (template - template.mean())) ** 2)))
        played = r.scene.texture.stimulus if r.scene.texture is not None else ""
        felt_level = float(mv_obs.mean())
        t_cost = []
        for t in design.textures:
            level, stimulus = _texture_template(objects, design, t)
            # Identity evidence (carrier, envelope) grows with how strongly the MV is felt.
            evidence = max(0.0, felt_level) * (stimulus == played)
            evidence += rng.normal(0.0, self.quality_noise_db)
            level_cost = 0.5 * ((felt_level - level) / self.level_sd_db) ** 2
            t_cost.append(level_cost - self.quality_weight * evidence)
        return int(np.argmin(g_cost)) + 1, int(np.argmin(t_cost)) + 1


def _geometry_template(
    objects: Mapping[tuple[str, str], Rendering], design: UserTestDesign, geometry: str
) -> NDArray[np.float64]:
    # What the participant learned in training: the intended (target) EV profile.
    return objects[(geometry, design.textures[0])].ev_target_db_sl


def _texture_template(
    objects: Mapping[tuple[str, str], Rendering], design: UserTestDesign, texture: str
) -> tuple[float, str]:
    scene = objects[(design.geometries[0], texture)].scene
    assert scene.texture is not None
    return float(scene.texture.perceived_db_sl), scene.texture.stimulus


def simulate_usertest(
    design: UserTestDesign,
    objects: Mapping[tuple[str, str], Rendering],
    observers: Mapping[str, IdentificationObserver],
    seed: int,
) -> list[dict[str, Any]]:
    """A simulated study: every participant answers every trial of its own seeded order.

    Parameters
    ----------
    design, objects
        The protocol and its rendered objects.
    observers : mapping participant id → IdentificationObserver
        The simulated participants.
    seed : int
        Study seed; each participant's session seed and answers derive from it and their id.

    Returns
    -------
    list of dict
        One :func:`trial_record` per trial, participants in the given order.

    Examples
    --------
    Two simulated participants identify the geometry more often with compensation:

    >>> from masking_lab.formats.resources import shipped
    >>> from masking_lab.usertest.design import load_usertest
    >>> from masking_lab.usertest.playback import render_objects
    >>> design = load_usertest(str(shipped("protocols", "usertest.yaml")))
    >>> pairs = {pair: MutualMasking(-2.0, 0.5, -1.0, 0.4, mv=pair[0], ev=pair[1])
    ...          for pair in design.stimulus_pairs()}
    >>> objects = render_objects(design, pairs)
    >>> observers = {"S1": IdentificationObserver(pairs),
    ...              "S2": IdentificationObserver(pairs, noise_db=1.0)}
    >>> records = simulate_usertest(design, objects, observers, seed=3)
    >>> def geometry_rate(condition):
    ...     rs = [r for r in records if r["condition"] == condition]
    ...     right = [r["geometry_answer"] == design.geometries.index(r["geometry"]) + 1 for r in rs]
    ...     return round(sum(right) / len(rs), 2)
    >>> len(records), geometry_rate("compensated"), geometry_rate("uncompensated")
    (240, 0.97, 0.84)
    """
    records: list[dict[str, Any]] = []
    for participant, observer in observers.items():
        digest = hashlib.sha256(f"{participant}|{seed}".encode()).digest()
        session_seed = int.from_bytes(digest[:4], "little")
        rng = np.random.default_rng(np.random.SeedSequence([session_seed, 1]))
        for trial in trial_list(design, session_seed):
            g, t = observer.respond(design, objects, trial, rng)
            records.append(trial_record(trial, participant, g, t))
    return records
