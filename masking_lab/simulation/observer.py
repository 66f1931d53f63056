"""Simulated observers: the ground truth that dry runs, the simulator and the demo respond from.

A population is described by a :class:`GroundTruth` (population unmasked ALs, masking ramps,
psychometric scale and lapse, between-participant spread). :func:`make_participant` draws one
reproducible :class:`SimulatedParticipant` from it; the participant answers a 3IFC trial with
p(correct) = ψ(target level − masked AL), ψ from :mod:`masking_lab.core.psychometric`.
"""

from __future__ import annotations

import copy
import functools
import hashlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from masking_lab.core.errors import ProtocolError
from masking_lab.core.masking import MaskingFunction
from masking_lab.core.psychometric import GUESS_3IFC, Psychometric
from masking_lab.formats.reader import parse_document, read_limited, syntax_of
from masking_lab.formats.resources import shipped
from masking_lab.formats.schemas import (
    first_problem,
)


@dataclass(frozen=True)
class GroundTruth:
    """A simulated population.

    Attributes
    ----------
    unmasked_al_db_v : Mapping[str, float]
        Population mean unmasked AL per stimulus name, dB re 1 V.
    masking : tuple[MaskingFunction, ...]
        True masking ramps (masker level in dB SL → AL shift in dB).
    participant_sd_db : float
        Between-participant SD of unmasked ALs, dB.
    shift_sd_db : float
        Between-participant SD of an additive offset on every AL shift, dB (applied above the knee).
    scale_db : float
        Psychometric logistic scale, dB.
    lapse : float
        Lapse rate.
    guess : float
        Guess rate (1/3 for 3IFC).
    """

    unmasked_al_db_v: Mapping[str, float]
    masking: tuple[MaskingFunction, ...]
    participant_sd_db: float = 2.0
    shift_sd_db: float = 1.0
    scale_db: float = 1.5
    lapse: float = 0.02
    guess: float = GUESS_3IFC

    def masking_function(self, target: str, masker: str) -> MaskingFunction | None:
        """The true ramp for ``target`` masked by ``masker``, or None if they do not interact."""
        for fn in self.masking:
            if fn.target == target and fn.masker == masker:
                return fn
        return None


@dataclass(frozen=True)
class SimulatedParticipant:
    """One simulated participant drawn from a :class:`GroundTruth`."""

    participant: str
    truth: GroundTruth
    unmasked_al_db_v: Mapping[str, float]
    shift_offset_db: float = 0.0
    rng_seed: int = 0
    _psy: Psychometric = field(init=False, repr=False, compare=False)
    _location_db: float = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        psy = Psychometric(0.0, self.truth.scale_db, self.truth.guess, self.truth.lapse)
        object.__setattr__(self, "_psy", psy)
        object.__setattr__(self, "_location_db", psy.location_db)  # constant: once, not per trial

    def masked_al_db_v(self, target: str, masker: str | None, masker_level_db_sl: float) -> float:
        """True AL of ``target`` in dB re 1 V with ``masker`` at ``masker_level_db_sl`` dB SL."""
        al = self.unmasked_al_db_v[target]
        if masker is None or masker_level_db_sl == -np.inf:
            return al
        fn = self.truth.masking_function(target, masker)
        if fn is None:
            return al
        shift = float(fn.shift_db(masker_level_db_sl))
        if shift > 0:
            shift = max(0.0, shift + self.shift_offset_db)
        return al + shift

    def p_correct(
        self, target: str, level_db_v: float, masker: str | None, masker_level_db_sl: float
    ) -> float:
        """p(correct) in a 3IFC trial with the target at ``level_db_v`` dB re 1 V."""
        al = self.masked_al_db_v(target, masker, masker_level_db_sl)
        return scalar_p_correct(self._psy, self._location_db, level_db_v - al)


def scalar_p_correct(psy: Psychometric, location_db: float, level_db: float) -> float:
    """``float(psy.p_correct(level_db))`` for one level, without the array machinery.

    The same operations in the same order on float64 (numpy's ``exp``, so the same last bit):
    the same value, in a twentieth of the time (it runs once per simulated trial).

    Parameters
    ----------
    psy : Psychometric
        The psychometric function.
    location_db : float
        ``psy.location_db`` (dB), computed once by the caller.
    level_db : float
        Stimulus level, dB (same reference as ``psy.threshold_db``); −inf gives γ.

    Returns
    -------
    float
        p(correct), in [γ, 1 − λ].

    Examples
    --------
    >>> psy = Psychometric(threshold_db=-30.0)
    >>> scalar_p_correct(psy, psy.location_db, -20.0) == float(psy.p_correct(-20.0))
    True
    """
    z = (float(level_db) - location_db) / psy.scale_db
    e = float(np.exp(-abs(z)))
    f = 1.0 / (1.0 + e) if z >= 0 else e / (1.0 + e)
    return psy.guess + (1.0 - psy.guess - psy.lapse) * f


def make_participant(truth: GroundTruth, participant: str, seed: int = 0) -> SimulatedParticipant:
    """Draw a reproducible participant: same ``truth``, ``participant`` and ``seed`` → same ALs."""
    digest = hashlib.sha256(f"{participant}|{seed}".encode()).digest()
    rng_seed = int.from_bytes(digest[:8], "little")
    rng = np.random.default_rng(rng_seed)
    als = {
        name: float(mean + rng.normal(0.0, truth.participant_sd_db))
        for name, mean in sorted(truth.unmasked_al_db_v.items())
    }
    offset = float(rng.normal(0.0, truth.shift_sd_db))
    return SimulatedParticipant(participant, truth, als, offset, rng_seed)


def ground_truth_from_dict(
    data: Any, source: str = "<ground truth>", lines: Mapping[str, int] | None = None
) -> GroundTruth:
    """Validate a parsed ground-truth mapping (``data_schema/ground_truth.schema.json``: every
    number finite and in range) and build a :class:`GroundTruth`.

    Parameters
    ----------
    data : mapping
        As in ``protocols/simulation/ground_truth.yaml`` (ALs in dB re 1 V, masker levels dB SL).
    source : str
        Names the data in messages.
    lines : mapping of key path → line, optional
        Where each key stands in the source file.

    Raises
    ------
    ProtocolError
        Naming ``source``, the key path (and line) and what is wrong.

    Examples
    --------
    >>> ground_truth_from_dict({"unmasked_al_db_v": {"EV270": -18.0}, "masking": []}).lapse
    0.02
    """
    if not isinstance(data, Mapping):
        raise ProtocolError(source, "(top level)", "a ground truth is a mapping of keys to values")
    problem = first_problem(data, "ground_truth", lines)
    if problem:
        at, what = problem
        raise ProtocolError(source, at, f"not a valid ground-truth file: {what}")
    masking = tuple(
        MaskingFunction(m["target"], m["masker"], float(m["intercept_db"]), float(m["slope"]))
        for m in data["masking"]
    )
    psy = data.get("psychometric", {})
    return GroundTruth(
        unmasked_al_db_v={k: float(v) for k, v in data["unmasked_al_db_v"].items()},
        masking=masking,
        participant_sd_db=float(data.get("participant_sd_db", 2.0)),
        shift_sd_db=float(data.get("shift_sd_db", 1.0)),
        scale_db=float(psy.get("scale_db", 1.5)),
        lapse=float(psy.get("lapse", 0.02)),
        guess=float(psy.get("guess", GUESS_3IFC)),
    )


def read_ground_truth(path: str | Path | None = None) -> tuple[Any, str]:
    """Read and validate a ground-truth YAML/JSON file (the shipped one if None) through the
    shared reader; return its parsed content (plain data, logged in session headers) and name.

    Raises
    ------
    ProtocolError
        Unreadable, not UTF-8, malformed, or not a valid ground truth (file, key, line).

    Examples
    --------
    >>> sorted(read_ground_truth()[0])[:2]
    ['masking', 'participant_sd_db']
    """
    if path is None:
        source = "protocols/simulation/ground_truth.yaml"
        file, what = Path(str(shipped("protocols", "simulation/ground_truth.yaml"))), "x"
    else:
        source, file, what = str(path), Path(path), "ground truth"
    # Read every time, parsed and validated once per content (a demo worker opens 15 sessions
    # on the same file); each caller gets its own copy of the plain data.
    raw = read_limited(file, what=what)
    return copy.deepcopy(_checked_truth(raw, str(file), syntax_of(file), source)), source


@functools.lru_cache(maxsize=8)
def _checked_truth(raw: bytes, file: str, fmt: str, source: str) -> Any:
    doc = parse_document(raw, file, fmt=fmt)
    ground_truth_from_dict(doc.data, source, doc.lines)
    return doc.data


def load_ground_truth(path: str | Path | None = None) -> GroundTruth:
    """Load a ground-truth YAML/JSON file, or the embedded default (paper Table 2 ramps).

    Raises
    ------
    ProtocolError
        As :func:`read_ground_truth`.

    Examples
    --------
    >>> load_ground_truth().masking_function("EV270", "MV120").slope
    0.711
    """
    data, source = read_ground_truth(path)
    return ground_truth_from_dict(data, source)
