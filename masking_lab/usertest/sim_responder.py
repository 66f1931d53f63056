"""A simulated participant for the user test, answering from what the device was told to play.

The participant is drawn from a ground-truth file exactly like the 3IFC simulated observer
(:func:`masking_lab.simulation.observer.make_participant`: same id and population seed → the same
true
unmasked ALs as in that participant's baseline), and identifies objects with
:class:`masking_lab.usertest.design.IdentificationObserver`: perceived intensity = input − masked AL
under the participant's *true* masking, plus noise, then template matching.

"Input" is what was streamed: the peak drive each channel held at every tick (after any clipping),
converted to dB SL with the participant's *true* unmasked AL — so calibration errors, the update
rate's dead-band and clipping all reach the answers as they would at the rig. The ticks'
positions are mapped onto the object's interaction points (linear between ticks; a point more
than :data:`REACH_MM` from every touched position is not felt).

Every draw comes from a generator seeded by (session seed, trial index, purpose), so a resumed
session answers exactly as the uninterrupted one would have. With ``tracking: finger`` the
simulated finger follows the cue with a per-presentation lag and speed error.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping

import numpy as np
from numpy.typing import NDArray

from masking_lab.core.errors import ProtocolError
from masking_lab.core.seeding import trial_rng
from masking_lab.rendering.render import Rendering
from masking_lab.rendering.solver import MutualMasking
from masking_lab.simulation.observer import GroundTruth, SimulatedParticipant, make_participant
from masking_lab.usertest.design import UserTestDesign
from masking_lab.usertest.observer import IdentificationObserver
from masking_lab.usertest.responder_base import (
    FingerReader,
    StreamResult,
    UserTestAnswer,
    UserTestInfo,
    UserTrialPresentation,
)

REACH_MM = 2.0
"""A point of the path farther than this from every touched position is not felt, mm."""

# Answer latencies after the last presentation (our choice, not from the paper): the geometry
# key 0.6 s + gamma(4, 0.2 s); the texture key 0.3 s + gamma(3, 0.15 s) after it.
_GEOMETRY_RT = (0.6, 4.0, 0.2)
_TEXTURE_RT = (0.3, 3.0, 0.15)

# The simulated finger: starts 0–0.15 s after the cue, at 1 ± 0.08 times its speed.
_FINGER_LAG_S = 0.15
_FINGER_SPEED_SD = 0.08

_SET_KEY = "usertest"  # trial_rng's set id for every user-test draw


class UserTestSimResponder:
    """Identifies user-test objects as a simulated participant.

    Parameters
    ----------
    design : UserTestDesign
        The protocol (answer keys, timing, tracking).
    objects : mapping (geometry, texture) → Rendering
        The rendered objects (targets and scenes serve as the learned templates).
    observer : IdentificationObserver
        Perception and decision model, with the participant's true masking.
    true_al_db_v : mapping stimulus → dB re 1 V
        The participant's true unmasked ALs.
    seed : int
        The session seed; with the trial index it seeds every draw.
    """

    name = "sim"

    def __init__(
        self,
        design: UserTestDesign,
        objects: Mapping[tuple[str, str], Rendering],
        observer: IdentificationObserver,
        true_al_db_v: Mapping[str, float],
        seed: int,
    ) -> None:
        self.design = design
        self.objects = dict(objects)
        self.observer = observer
        self.true_al_db_v = dict(true_al_db_v)
        self.seed = int(seed)

    @classmethod
    def from_ground_truth(
        cls,
        design: UserTestDesign,
        objects: Mapping[tuple[str, str], Rendering],
        truth: GroundTruth,
        participant: str,
        seed: int,
        *,
        population_seed: int = 0,
        source: str = "the ground truth",
    ) -> UserTestSimResponder:
        """Draw ``participant`` from ``truth`` (the same draw as their 3IFC sessions).

        Raises
        ------
        ProtocolError
            The ground truth lacks an unmasked AL or a masking direction the objects need.
        """
        person = make_participant(truth, participant, population_seed)
        needed = {s for r in objects.values() for s in _stimuli(r)}
        missing = sorted(needed - set(person.unmasked_al_db_v))
        if missing:
            raise ProtocolError(
                source,
                "unmasked_al_db_v",
                f"no unmasked AL for {', '.join(missing)}, which the user test plays; add it or "
                "pass another file with --ground-truth",
            )
        pairs = true_masking(truth, design, person, source)
        return cls(design, objects, IdentificationObserver(pairs), person.unmasked_al_db_v, seed)

    # -- responder protocol -------------------------------------------------------------------

    def start_session(self, info: UserTestInfo) -> None:
        """Nothing to show."""

    def trial(
        self,
        presentation: UserTrialPresentation,
        play: Callable[[FingerReader | None], StreamResult],
    ) -> tuple[StreamResult, UserTestAnswer]:
        """Play the object (following it with a simulated finger if tracked), then answer."""
        finger = self.finger(presentation) if presentation.tracking == "finger" else None
        result = play(finger)
        return result, self.answer(presentation, result)

    def close(self) -> None:
        """Nothing to release."""

    # -- the model ----------------------------------------------------------------------------

    def answer(self, presentation: UserTrialPresentation, result: StreamResult) -> UserTestAnswer:
        """The answers to one trial given what was played (pure given the seed)."""
        trial = presentation.trial
        r = self.objects[trial.object]
        ev_db_sl, mv_db_sl = self.felt_inputs_db_sl(r, result)
        played = r.with_inputs(mv_db_sl, ev_db_sl)
        # The observer feels a rendering's compensated inputs: put what was played there.
        as_played = dataclasses.replace(trial, condition="compensated")
        objects = {**self.objects, trial.object: played}
        rng = trial_rng(self.seed, _SET_KEY, trial.index, "usertest-answer")
        geometry, texture = self.observer.respond(self.design, objects, as_played, rng)
        rt = trial_rng(self.seed, _SET_KEY, trial.index, "usertest-rt")
        g_s = _GEOMETRY_RT[0] + float(rt.gamma(_GEOMETRY_RT[1], _GEOMETRY_RT[2]))
        t_s = g_s + _TEXTURE_RT[0] + float(rt.gamma(_TEXTURE_RT[1], _TEXTURE_RT[2]))
        return UserTestAnswer(geometry, texture, g_s, t_s)

    def felt_inputs_db_sl(
        self, r: Rendering, result: StreamResult
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(ev, mv)`` played at each interaction point of ``r``, true dB SL (-inf: nothing)."""
        out = []
        for ch in ("EV", "MV"):
            name = result.stimuli.get(ch)
            if name is None:
                out.append(np.full(r.x_mm.shape, -np.inf))
                continue
            volts = played_volts_on_path(r.x_mm, result.x_mm, result.held_v[ch])
            with np.errstate(divide="ignore"):
                out.append(20.0 * np.log10(volts) - self.true_al_db_v[name])
        return out[0], out[1]

    def finger(self, presentation: UserTrialPresentation) -> FingerReader:
        """A finger that follows the cue late and at the wrong speed (seeded per trial)."""
        timing = presentation.timing
        rng = trial_rng(self.seed, _SET_KEY, presentation.trial.index, "usertest-finger")
        n = timing.n_presentations
        lags = rng.uniform(0.0, _FINGER_LAG_S, n)
        speeds = np.clip(rng.normal(1.0, _FINGER_SPEED_SD, n), 0.7, 1.3)
        speed = presentation.cue_speed_mm_s

        def reader(t_s: float) -> float | None:
            at = timing.presentation_at(t_s - presentation.start_s)
            if at is None:
                return None
            k, into = at
            moving = into - lags[k - 1]
            if moving < 0:
                return None  # not touching yet
            return float(speeds[k - 1] * speed * moving)

        return reader


def played_volts_on_path(
    path_x_mm: NDArray[np.float64], tick_x_mm: NDArray[np.float64], held_v: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Drive felt at each path point, V, from the drive held at each touched tick position.

    Ticks at the same position (the presentations of a cue-tracked trial) are averaged; between
    ticks the drive is linear; farther than :data:`REACH_MM` from every tick it is 0 V.
    """
    x = np.asarray(tick_x_mm, dtype=float)
    v = np.asarray(held_v, dtype=float)
    ok = np.isfinite(x)
    if not ok.any():
        return np.zeros(np.shape(path_x_mm))
    xs, inverse = np.unique(x[ok], return_inverse=True)
    vs = np.bincount(inverse, weights=v[ok]) / np.bincount(inverse)
    p = np.asarray(path_x_mm, dtype=float)
    felt = np.interp(p, xs, vs)
    idx = np.searchsorted(xs, p)
    left = xs[np.clip(idx - 1, 0, xs.size - 1)]
    right = xs[np.clip(idx, 0, xs.size - 1)]
    felt[np.minimum(np.abs(p - left), np.abs(right - p)) > REACH_MM] = 0.0
    return felt


def true_masking(
    truth: GroundTruth,
    design: UserTestDesign,
    person: SimulatedParticipant,
    source: str = "the ground truth",
) -> dict[tuple[str, str], MutualMasking]:
    """The participant's true masking per stimulus pair of the design.

    The population ramps with the participant's shift offset added to both intercepts (the 3IFC
    observer adds it to every shift above the knee; moving the intercept is the same there).

    Raises
    ------
    ProtocolError
        A direction the objects need has no ramp in the ground truth.
    """
    pairs = {}
    offset = float(person.shift_offset_db)
    for mv, ev in design.stimulus_pairs():
        f = truth.masking_function(mv, ev)
        g = truth.masking_function(ev, mv)
        if f is None or g is None:
            lacking = f"{mv} masked by {ev}" if f is None else f"{ev} masked by {mv}"
            raise ProtocolError(
                source,
                "masking",
                f"no true masking of {lacking}, which the user test's objects play together; "
                "add both directions of the pair",
            )
        pairs[(mv, ev)] = MutualMasking(
            f.intercept_db + offset, f.slope, g.intercept_db + offset, g.slope, mv=mv, ev=ev
        )
    return pairs


def _stimuli(r: Rendering) -> list[str]:
    scene = r.scene
    names = []
    if scene.geometry is not None:
        names.append(scene.geometry.stimulus)
    if scene.texture is not None:
        names.append(scene.texture.stimulus)
    return names


__all__ = [
    "REACH_MM",
    "UserTestSimResponder",
    "played_volts_on_path",
    "true_masking",
]
