"""A simulated observer that answers 3IFC trials, for dry runs and tests.

The observer is a :class:`~masking_lab.simulation.observer.SimulatedParticipant` drawn from a
ground-truth
file: p(correct) = ψ(target level − its masked AL) with the 3IFC guess rate and a lapse rate.
It answers from what the device was asked to play, as a participant would: the target's drive in
dB re 1 V and the masker's drive converted to dB SL with the participant's *true* unmasked AL of
the masker (not the calibration's estimate), so a calibration error propagates as it would at
the rig.

Each answer draws from its own generator seeded by (session seed, set, trial), so a resumed
session answers exactly as the uninterrupted one would have.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import yaml

from masking_lab.core.errors import ProtocolError
from masking_lab.core.levels import volts_to_db_v
from masking_lab.core.seeding import STREAM_RESPONDER, trial_rng
from masking_lab.core.trial import PlayResult
from masking_lab.responders.base import Response, SetInfo, TrialPresentation
from masking_lab.simulation.observer import (
    SimulatedParticipant,
    load_ground_truth,
    make_participant,
)

# Simulated answer latency after the last interval: 0.4 s plus a gamma with mean 0.6 s.
_RT_FLOOR_S = 0.4
_RT_SHAPE = 4.0
_RT_SCALE_S = 0.15


class SimResponder:
    """Answers trials as a simulated participant.

    Parameters
    ----------
    participant : SimulatedParticipant
        The observer (true ALs, masking, psychometric function).
    seed : int
        The session seed; with the set id and trial index it seeds each answer.
    source : str
        Where the ground truth came from (for messages).

    Examples
    --------
    Far below its AL the simulated participant guesses (1/3 correct in 3IFC); far above it,
    it is right except for lapses:

    >>> from masking_lab.core.levels import db_v_to_volts
    >>> from masking_lab.core.stimulus import parse_stimulus
    >>> from masking_lab.core.trial import TrialPlan
    >>> sim = SimResponder.from_ground_truth(None, "P01", seed=7)
    >>> al_db_v = sim.participant.unmasked_al_db_v["EV270"]
    >>> def fraction_correct(level_db_sl, n=300):
    ...     level_db_v = al_db_v + level_db_sl
    ...     plan = TrialPlan(parse_stimulus("EV270"), db_v_to_volts(level_db_v), 2)
    ...     shown = [TrialPresentation("A", i, plan, 0.0, level_db_v, level_db_sl, None)
    ...              for i in range(n)]
    ...     return round(sum(sim.answer(p).interval == 2 for p in shown) / n, 2)
    >>> fraction_correct(-20.0), fraction_correct(20.0)
    (0.35, 0.97)
    """

    name = "sim"

    def __init__(self, participant: SimulatedParticipant, seed: int, source: str = "") -> None:
        self.participant = participant
        self.seed = int(seed)
        self.source = source or "the ground truth"

    @classmethod
    def from_ground_truth(
        cls,
        path: str | Path | None,
        participant_id: str,
        seed: int,
        population_seed: int = 0,
    ) -> SimResponder:
        """Draw ``participant_id`` from a ground-truth file (None: the packaged default).

        ``population_seed`` (not the session seed) fixes the participant's true ALs, so the same
        simulated participant sits the baseline and every masked session.

        Parameters
        ----------
        path : str, Path or None
            Ground-truth YAML or JSON file; None for the packaged one.
        participant_id : str
            Participant to draw (e.g. ``"P01"``).
        seed : int
            Session seed for the answers.
        population_seed : int
            Seed of the participant's true ALs (dB re 1 V).

        Returns
        -------
        SimResponder

        Raises
        ------
        ProtocolError
            If the file cannot be read or is malformed.

        Examples
        --------
        >>> sim = SimResponder.from_ground_truth(None, "P01", seed=7)
        >>> sim.name, "EV270" in sim.participant.unmasked_al_db_v
        ('sim', True)
        """
        try:
            truth = load_ground_truth(path)
        except OSError as exc:
            raise ProtocolError(
                str(path), "", f"cannot read the ground truth ({exc.strerror or exc})"
            ) from exc
        except (yaml.YAMLError, ValueError) as exc:
            raise ProtocolError(str(path), "", f"malformed YAML or JSON: {exc}") from exc
        participant = make_participant(truth, participant_id, population_seed)
        return cls(participant, seed, str(path) if path is not None else "")

    def start_set(self, info: SetInfo) -> None:
        """Check that the ground truth knows the set's stimuli (before any trial is played).

        Raises
        ------
        ProtocolError
            If the ground truth has no unmasked AL (dB re 1 V) for the target or the masker.
        """
        for stim in (info.target, info.masker):
            if stim is not None and stim.name not in self.participant.unmasked_al_db_v:
                raise ProtocolError(
                    self.source,
                    "unmasked_al_db_v",
                    f"no unmasked AL for {stim.name} (set {info.set_id}); add it to the ground "
                    "truth file or pass another one with --ground-truth",
                )

    def answer(self, presentation: TrialPresentation) -> Response:
        """The simulated answer to ``presentation`` (pure given the seed).

        Parameters
        ----------
        presentation : TrialPresentation
            The trial; its target level in dB re 1 V and the masker's drive in V are used.

        Returns
        -------
        Response
            The chosen interval and a response time in s (≥ 0.4 s).

        Examples
        --------
        >>> from masking_lab.core.stimulus import parse_stimulus
        >>> from masking_lab.core.trial import TrialPlan
        >>> sim = SimResponder.from_ground_truth(None, "P01", seed=7)
        >>> shown = TrialPresentation(
        ...     "A", 0, TrialPlan(parse_stimulus("EV270"), 0.05, 2), 0.0, -26.0, None, None)
        >>> sim.answer(shown) == sim.answer(shown)  # the same seed, set and trial: same answer
        True
        """
        plan = presentation.plan
        rng = trial_rng(self.seed, presentation.set_id, presentation.trial_index, STREAM_RESPONDER)
        masker_sl = -math.inf
        masker_name = plan.masker.name if plan.masker is not None else None
        if masker_name is not None and plan.masker_amplitude_v > 0:
            true_al = self.participant.unmasked_al_db_v[masker_name]
            masker_sl = volts_to_db_v(plan.masker_amplitude_v) - true_al
        p = self.participant.p_correct(
            plan.target.name, presentation.level_db_v, masker_name, masker_sl
        )
        # Always draw the same numbers in the same order, whatever the outcome.
        u, pick, rt = rng.random(), int(rng.integers(0, 2)), rng.gamma(_RT_SHAPE, _RT_SCALE_S)
        if u < p:
            interval = plan.target_interval
        else:
            others = [i for i in range(1, plan.n_intervals + 1) if i != plan.target_interval]
            interval = others[pick % len(others)]
        return Response(interval=interval, response_time_s=_RT_FLOOR_S + float(rt))

    def trial(
        self, presentation: TrialPresentation, play: Callable[[], PlayResult]
    ) -> tuple[PlayResult, Response]:
        """Play the trial, then answer it."""
        result = play()
        return result, self.answer(presentation)

    def close(self) -> None:
        """Nothing to release."""
