"""The user test of paper §3.3: the protocol, its object scenes, and the trials of a session.

Identify geometry and texture, with and without compensation. The pure parts a runner drives (no
clock, no global RNG; no I/O except :func:`load_usertest`):

- :func:`parse_usertest` checks an already parsed ``protocols/usertest.yaml`` (schema
  ``data_schema/usertest.schema.json``) against its object scenes (one per geometry × texture);
  :func:`load_usertest` is the thin file reader on top.
- :func:`trial_list`: every object × condition × repeat in a seeded random order (paper: 4 × 3 ×
  2 × 5 = 120 trials).
- :func:`trial_record`: what a runner logs per trial.

Elsewhere: :mod:`~masking_lab.usertest.playback` (what each trial plays, in dB SL and dB re 1 V),
:mod:`~masking_lab.usertest.observer` (a simulated participant) and
:mod:`~masking_lab.usertest.stats` (correct rates, paired tests, confusion matrices).

A trial lasts ``lead_in + n·stimulus + (n − 1)·gap`` = 1.2 + 3·1.8 + 2·0.6 = 7.8 s; the object
plays during each 1.8 s presentation while the finger (or cue) crosses the 91.8 mm path, and is
silent during the lead-in and gaps.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from masking_lab.core.errors import ProtocolError
from masking_lab.formats.protocol import MAX_TRIAL_S
from masking_lab.formats.reader import decode_utf8, parse_yaml, read_limited
from masking_lab.formats.schemas import (
    first_problem,
)
from masking_lab.rendering.scene import Scene, load_scene

__all__ = [
    "CONDITIONS",
    "MEASURES",
    "SILENT",
    "Condition",
    "Tracking",
    "UserTestDesign",
    "UserTestTiming",
    "UserTrial",
    "load_usertest",
    "parse_usertest",
    "trial_list",
    "trial_record",
]

Condition = Literal["compensated", "uncompensated"]
CONDITIONS: tuple[Condition, ...] = ("compensated", "uncompensated")
Tracking = Literal["cue", "finger"]
MEASURES = ("both", "geometry", "texture")

_ORDER_STREAM = 0x05E7  # seed-sequence tag of the trial-order stream
SILENT = (-math.inf, -math.inf)


@dataclass(frozen=True)
class UserTestTiming:
    """Timing of one user-test trial, s from the trial's start.

    Attributes
    ----------
    lead_in_s : float
        Silence before the first presentation, s.
    stimulus_s : float
        Each presentation, s (the cue crosses the path in this time).
    gap_s : float
        Silence between presentations, s.
    n_presentations : int
        Presentations per trial.
    inter_trial_s : float
        Pause after the answers, s.
    response_timeout_s : float or None
        Give up waiting for the answers after this long (None: wait).
    """

    lead_in_s: float = 1.2
    stimulus_s: float = 1.8
    gap_s: float = 0.6
    n_presentations: int = 3
    inter_trial_s: float = 0.5
    response_timeout_s: float | None = None

    @property
    def trial_s(self) -> float:
        """Lead-in, presentations and gaps, s (7.8 s in the paper)."""
        n = self.n_presentations
        return self.lead_in_s + n * self.stimulus_s + (n - 1) * self.gap_s

    def onset_s(self, presentation: int) -> float:
        """Onset of ``presentation`` (1-based), s after the trial start."""
        return self.lead_in_s + (presentation - 1) * (self.stimulus_s + self.gap_s)

    def presentation_at(self, t_s: float) -> tuple[int, float] | None:
        """``(presentation, s into it)`` at trial time ``t_s`` s, or None when silent."""
        # 1 ns slack: 1.2 + 2·2.4 + 1.8 is not exactly 7.8 in floats, yet 7.8 s is the end.
        slack = 1e-9
        if not t_s >= self.lead_in_s - slack:  # also NaN
            return None
        period = self.stimulus_s + self.gap_s
        k = int((t_s - self.lead_in_s + slack) // period)
        into = t_s - self.onset_s(k + 1)
        if k >= self.n_presentations or into >= self.stimulus_s - slack:
            return None
        return k + 1, max(0.0, into)


@dataclass(frozen=True)
class UserTrial:
    """One trial: an object (geometry × texture) under one condition.

    Attributes
    ----------
    index : int
        Position in the session, 0-based.
    geometry, texture : str
        What is presented.
    condition : {"compensated", "uncompensated"}
        Inputs from the solver, or the targets played as they are.
    repeat : int
        1-based repeat of this object × condition.
    geometry_key, texture_key : int
        The correct answer keys (1-based, the design's order).
    """

    index: int
    geometry: str
    texture: str
    condition: Condition
    repeat: int
    geometry_key: int
    texture_key: int

    @property
    def compensated(self) -> bool:
        """True when the compensated inputs are played."""
        return self.condition == "compensated"

    @property
    def object(self) -> tuple[str, str]:
        """``(geometry, texture)``."""
        return self.geometry, self.texture


@dataclass(frozen=True)
class UserTestDesign:
    """A validated user-test protocol with its object scenes.

    Attributes
    ----------
    experiment : str
        Experiment id.
    geometries, textures : tuple[str, ...]
        Answer keys 1..n in this order.
    conditions : tuple[str, ...]
        Rendering conditions.
    repeats : int
        Repeats of every object × condition.
    timing : UserTestTiming
        Trial timing.
    tracking : {"cue", "finger"}
        What positions the amplitudes along the path.
    cue_speed_mm_s : float
        Cue speed, mm/s.
    scenes : Mapping[(geometry, texture), Scene]
        One scene per object.
    randomize : bool
        Shuffle the trial order per participant.
    path, sha256, description : str
        Source file, hash of its bytes, free text.
    """

    experiment: str
    geometries: tuple[str, ...]
    textures: tuple[str, ...]
    conditions: tuple[Condition, ...]
    repeats: int
    timing: UserTestTiming
    tracking: Tracking
    cue_speed_mm_s: float
    scenes: Mapping[tuple[str, str], Scene]
    randomize: bool = True
    path: str = "<memory>"
    sha256: str = ""
    description: str = ""
    content: Mapping[str, Any] = field(default_factory=dict, compare=False, repr=False)

    @property
    def n_trials(self) -> int:
        """Trials per participant."""
        return len(self.geometries) * len(self.textures) * len(self.conditions) * self.repeats

    @property
    def sweep_mm(self) -> float:
        """Distance the cue travels in one presentation, mm (51 mm/s × 1.8 s = 91.8 mm)."""
        return self.cue_speed_mm_s * self.timing.stimulus_s

    def stimulus_pairs(self) -> list[tuple[str, str]]:
        """Every (MV, EV) stimulus pair the objects need, sorted."""
        return sorted({p for s in self.scenes.values() for p in s.stimulus_pairs()})


# --------------------------------------------------------------------------------------------
# Loading


def load_usertest(path: str | Path) -> UserTestDesign:
    """Read a user-test protocol and its object scenes (``scenes_dir``), and check them.

    A thin reader over :func:`parse_usertest`: the scene of object (g, t) is the file
    ``<scenes_dir>/<g>_<t>.yaml`` beside the protocol.

    Raises
    ------
    ProtocolError
        Naming the file and key (malformed YAML, schema violations, a missing object scene, or a
        scene whose geometry shape or texture name is not the one its file name promises).
    """
    p = Path(path)
    raw = read_limited(p, what="user-test protocol")
    data, lines = parse_yaml(decode_utf8(raw, str(p)), str(p))

    def scene_file(g: str, t: str) -> Scene:
        # Called only once parse_usertest has validated ``data`` against the schema.
        file = p.parent / data.get("scenes_dir", "scenes") / f"{g}_{t}.yaml"
        try:
            found = file.is_file()
        except OSError:  # e.g. a name too long for the file system
            found = False
        if not found:
            raise ProtocolError(
                str(p),
                "scenes_dir",
                f"no scene for geometry {g!r} with texture {t!r}: expected {file}; write it "
                "(see docs/scenes.md) or fix geometries/textures",
            )
        return load_scene(file)

    return parse_usertest(
        data, scene_file, source=str(p), sha256=hashlib.sha256(raw).hexdigest(), lines=lines
    )


def parse_usertest(
    data: Any,
    scenes: Mapping[str, Scene] | Callable[[str, str], Scene],
    *,
    source: str = "<memory>",
    sha256: str = "",
    lines: Mapping[str, int] | None = None,
) -> UserTestDesign:
    """Validate an already parsed user-test protocol and pair it with its object scenes.

    Pure: no file is read or written. This is how a resumed session rebuilds its design from the
    copies in its log header (scenes from :func:`masking_lab.rendering.scene.parse_scene_text`).

    Parameters
    ----------
    data : mapping
        The protocol's content (what :func:`load_usertest` parses from YAML).
    scenes : mapping or callable
        The object scenes: a mapping ``"<geometry>_<texture>"`` → :class:`Scene`, or a callable
        ``(geometry, texture) -> Scene`` (which raises :class:`ProtocolError` when it has none).
    source : str
        Names the protocol in messages and becomes :attr:`UserTestDesign.path`.
    sha256 : str
        Hash of the protocol file's bytes ("" when built in memory).
    lines : mapping of key path → line, optional
        Where each key stands in the protocol file, for messages.

    Raises
    ------
    ProtocolError
        Schema violations, a missing object scene, or a scene whose geometry shape or texture
        name is not the one its object promises.
    """
    if not isinstance(data, Mapping):
        raise ProtocolError(source, "(top level)", "a user-test protocol is a YAML mapping")
    problem = first_problem(data, "usertest", lines)
    if problem:
        raise ProtocolError(source, *problem)
    timing = UserTestTiming(**data.get("timing", {}))
    if timing.trial_s > MAX_TRIAL_S:
        # The board refuses a longer trial (firmware/core/trial.h): refuse it here instead.
        raise ProtocolError(
            source,
            "timing",
            f"lead_in_s + n_presentations x stimulus_s + (n_presentations - 1) x gap_s = "
            f"{timing.trial_s:g} s, over the {MAX_TRIAL_S:g} s a device plays in one trial; "
            "shorten the presentations or gaps",
        )
    found: dict[tuple[str, str], Scene] = {}
    for g in data["geometries"]:
        for t in data["textures"]:
            scene = _scene_for(scenes, g, t, source)
            if scene.geometry is None or scene.geometry.shape != g:
                raise ProtocolError(
                    scene.source, "geometry.shape", f"the user test expects a {g!r} here"
                )
            if scene.texture is None or scene.texture.name != t:
                raise ProtocolError(
                    scene.source, "texture.name", f"the user test expects {t!r} here"
                )
            found[(g, t)] = scene
    return UserTestDesign(
        experiment=data["experiment"],
        geometries=tuple(data["geometries"]),
        textures=tuple(data["textures"]),
        conditions=tuple(data.get("conditions", CONDITIONS)),
        repeats=int(data.get("repeats", 5)),
        timing=timing,
        tracking=data.get("tracking", "cue"),
        cue_speed_mm_s=float(data.get("cue_speed_mm_s", 51.0)),
        scenes=found,
        randomize=bool(data.get("order", {}).get("randomize", True)),
        path=source,
        sha256=sha256,
        description=str(data.get("description", "")).strip(),
        content=data,
    )


def _scene_for(
    scenes: Mapping[str, Scene] | Callable[[str, str], Scene], g: str, t: str, source: str
) -> Scene:
    if callable(scenes):
        return scenes(g, t)
    scene = scenes.get(f"{g}_{t}")
    if scene is None:
        raise ProtocolError(
            source,
            "scenes",
            f"no scene for geometry {g!r} with texture {t!r}; give one per geometry × texture",
        )
    return scene


# --------------------------------------------------------------------------------------------
# Trials


def trial_list(design: UserTestDesign, seed: int) -> list[UserTrial]:
    """Every object × condition × repeat, shuffled by ``seed`` (same seed → same order).

    Parameters
    ----------
    design : UserTestDesign
        The protocol.
    seed : int
        Session seed (logged), ≥ 0.
    """
    combos = [
        (g, t, c, r)
        for r in range(1, design.repeats + 1)
        for c in design.conditions
        for g in design.geometries
        for t in design.textures
    ]
    if design.randomize:
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), _ORDER_STREAM]))
        combos = [combos[i] for i in rng.permutation(len(combos))]
    return [
        UserTrial(
            index=i,
            geometry=g,
            texture=t,
            condition=c,
            repeat=r,
            geometry_key=design.geometries.index(g) + 1,
            texture_key=design.textures.index(t) + 1,
        )
        for i, (g, t, c, r) in enumerate(combos)
    ]


def trial_record(
    trial: UserTrial,
    participant: str,
    geometry_answer: int | None,
    texture_answer: int | None,
    **extra: Any,
) -> dict[str, Any]:
    """The record a runner logs for one answered trial (JSON-ready).

    Parameters
    ----------
    trial : UserTrial
        The trial.
    participant : str
        Participant id.
    geometry_answer, texture_answer : int or None
        Keys pressed (1-based), None if no answer came.
    **extra
        Anything else to keep (onsets, response times, finger samples).
    """
    return {
        "record": "usertest_trial",
        "participant": participant,
        "trial": trial.index,
        "geometry": trial.geometry,
        "texture": trial.texture,
        "condition": trial.condition,
        "repeat": trial.repeat,
        "geometry_answer": geometry_answer,
        "texture_answer": texture_answer,
        **extra,
    }
