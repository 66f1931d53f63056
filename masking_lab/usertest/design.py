"""The user test of paper §3.3: identify geometry and texture, with and without compensation.

The pure parts a runner drives (no I/O except :func:`load_usertest`, no clock, no global RNG):

- :func:`load_usertest` reads ``protocols/usertest.yaml`` (schema ``data_schema/usertest.schema
  .json``) and the object scenes it names (one scene per geometry × texture).
- :func:`trial_list`: every object × condition × repeat in a seeded random order (paper: 4 × 3 ×
  2 × 5 = 120 trials).
- :func:`render_objects`: each object's per-point inputs, compensated and not.
- :func:`trial_levels_db_v`: for a trial and a time (cue tracking, time-locked at 51 mm/s) or a
  finger position (finger tracking, streamed updates), the drive levels to play.
- :class:`IdentificationObserver`: a simulated participant who feels ``input − masked AL`` with
  noise and answers by template matching; :func:`simulate_usertest` runs a simulated study.
- :func:`trial_record` (what a runner logs per trial) and :func:`analyze_usertest` (correct rates
  per participant and condition, a paired test per measure, confusion matrices).

A trial lasts ``lead_in + n·stimulus + (n − 1)·gap`` = 1.2 + 3·1.8 + 2·0.6 = 7.8 s; the object
plays during each 1.8 s presentation while the finger (or cue) crosses the 91.8 mm path, and is
silent during the lead-in and gaps.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from numpy.typing import NDArray

from masking_lab.core.errors import AnalysisError, ProtocolError, SolverError
from masking_lab.formats.schemas import key_path, schema_errors
from masking_lab.rendering.render import Rendering, render_scene
from masking_lab.rendering.scene import Scene, load_scene
from masking_lab.rendering.solver import (
    MissingMaskingError,
    MutualMasking,
    PairProblem,
    Status,
    forward,
)

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
    """Read a user-test protocol and its object scenes, and check them.

    Raises
    ------
    ProtocolError
        Naming the file and key (malformed YAML, schema violations, a missing object scene, or a
        scene whose geometry shape or texture name is not the one its file name promises).
    """
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise ProtocolError(str(p), "", f"cannot read the file ({exc.strerror or exc})") from exc
    try:
        data = yaml.safe_load(raw.decode("utf-8", errors="replace"))
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark else ""
        raise ProtocolError(str(p), where, f"malformed YAML: {exc}") from exc
    if not isinstance(data, Mapping):
        raise ProtocolError(str(p), "(top level)", "a user-test protocol is a YAML mapping")
    errors = schema_errors(data, "usertest")
    if errors:
        err = errors[0]
        more = f" (and {len(errors) - 1} more problem(s))" if len(errors) > 1 else ""
        raise ProtocolError(str(p), key_path(err), f"{err.message}{more}")
    timing = UserTestTiming(**data.get("timing", {}))
    scenes_dir = p.parent / data.get("scenes_dir", "scenes")
    scenes: dict[tuple[str, str], Scene] = {}
    for g in data["geometries"]:
        for t in data["textures"]:
            file = scenes_dir / f"{g}_{t}.yaml"
            if not file.is_file():
                raise ProtocolError(
                    str(p),
                    "scenes_dir",
                    f"no scene for geometry {g!r} with texture {t!r}: expected {file}; write it "
                    "(see docs/scenes.md) or fix geometries/textures",
                )
            scene = load_scene(file)
            if scene.geometry is None or scene.geometry.shape != g:
                raise ProtocolError(
                    str(file), "geometry.shape", f"the user test expects a {g!r} here"
                )
            if scene.texture is None or scene.texture.name != t:
                raise ProtocolError(str(file), "texture.name", f"the user test expects {t!r} here")
            scenes[(g, t)] = scene
    return UserTestDesign(
        experiment=data["experiment"],
        geometries=tuple(data["geometries"]),
        textures=tuple(data["textures"]),
        conditions=tuple(data.get("conditions", CONDITIONS)),
        repeats=int(data.get("repeats", 5)),
        timing=timing,
        tracking=data.get("tracking", "cue"),
        cue_speed_mm_s=float(data.get("cue_speed_mm_s", 51.0)),
        scenes=scenes,
        randomize=bool(data.get("order", {}).get("randomize", True)),
        path=str(p),
        sha256=hashlib.sha256(raw).hexdigest(),
        description=str(data.get("description", "")).strip(),
        content=data,
    )


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


def render_objects(
    design: UserTestDesign,
    pairs: Mapping[tuple[str, str], MutualMasking],
    *,
    max_mv_db_sl: float | None = None,
    max_ev_db_sl: float | None = None,
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

    Raises
    ------
    MissingMaskingError
        Listing every pair without masking functions.
    SolverError
        If an object has points without a unique compensated input.
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
        )
        bad = r.solution.status != Status.UNIQUE
        if np.any(bad):
            at = r.x_mm[np.flatnonzero(bad)[0]]
            raise SolverError(
                f"{scene.source}: {int(bad.sum())} points have no unique compensated input "
                f"(first at {at:.1f} mm); b·d ≥ 1 for this pair, so it cannot be compensated"
            )
        out[key] = r
    return out


def path_position_mm(design: UserTestDesign, t_s: float) -> float | None:
    """Where the cue is along the path at trial time ``t_s`` s, mm; None when silent."""
    at = design.timing.presentation_at(t_s)
    if at is None:
        return None
    return design.cue_speed_mm_s * at[1]


def path_x_from_screen_mm(design: UserTestDesign, x_screen_mm: float) -> float:
    """Finger x on the screen (centre-origin mm, as :mod:`masking_lab.responders.cue` logs it) →
    path mm.

    The cue's lane is centred on the screen, so the path starts at ``−sweep/2``.
    """
    return x_screen_mm + design.sweep_mm / 2


def levels_at(r: Rendering, x_mm: float, *, compensated: bool) -> tuple[float, float]:
    """``(ev_db_sl, mv_db_sl)`` inputs at path position ``x_mm`` mm (linear between points).

    Off the path (or NaN) both channels are silent (``-inf``).
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
        x = path_position_mm(design, t_s)  # type: ignore[assignment]
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


# --------------------------------------------------------------------------------------------
# Simulated participant


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
    """

    truth: Mapping[tuple[str, str], MutualMasking]
    noise_db: float = 3.0
    n_samples: int = 16
    cross_talk: float = 0.5
    level_sd_db: float = 4.0
    quality_weight: float = 0.5
    quality_noise_db: float = 3.0

    def felt(self, r: Rendering, compensated: bool) -> tuple[NDArray[np.float64], ...]:
        """``(mv_felt_db_sl, ev_felt_db_sl)`` at every point: true perceived intensity, ≥ 0."""
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
        """``(geometry_key, texture_key)`` answered for ``trial`` (1-based keys)."""
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


# --------------------------------------------------------------------------------------------
# Logging and analysis


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


@dataclass(frozen=True)
class PairedComparison:
    """Compensated vs uncompensated correct rate for one measure, paired by participant.

    Attributes
    ----------
    measure : {"both", "geometry", "texture"}
        Which answers had to be right.
    n : int
        Participants with both conditions.
    mean_compensated, mean_uncompensated : float
        Mean correct rate (0–1).
    mean_difference : float
        Compensated minus uncompensated, mean over participants.
    t : float or None
        Paired t statistic (df = n − 1); None when it cannot be computed.
    p : float or None
        Two-sided p-value; None when it cannot be computed.
    dz : float or None
        Cohen's d_z (mean difference / SD of differences).
    note : str
        Why t/p are missing, if they are.
    """

    measure: str
    n: int
    mean_compensated: float
    mean_uncompensated: float
    mean_difference: float
    t: float | None
    p: float | None
    dz: float | None
    note: str = ""


@dataclass(frozen=True)
class UserTestAnalysis:
    """Results of :func:`analyze_usertest`.

    Attributes
    ----------
    rates : pandas.DataFrame
        Per participant × condition: ``n_trials``, ``n_no_answer`` and the correct rates
        ``both``, ``geometry``, ``texture`` (0–1; no answer counts as wrong).
    summary : pandas.DataFrame
        Per condition × measure: ``mean``, ``sd`` (between participants, ddof 1), ``n``.
    tests : list[PairedComparison]
        One per measure (needs both conditions).
    confusion : dict
        ``confusion[condition]["geometry" | "texture"]``: counts, rows presented, columns
        answered (plus a ``no answer`` column).
    """

    rates: Any
    summary: Any
    tests: list[PairedComparison]
    confusion: dict[str, dict[str, Any]]


def analyze_usertest(
    records: Iterable[Mapping[str, Any]],
    geometries: Sequence[str],
    textures: Sequence[str],
) -> UserTestAnalysis:
    """Correct rates per participant and condition, paired tests and confusion matrices.

    Parameters
    ----------
    records : iterable of mapping
        Logged trials (:func:`trial_record`); answers are 1-based keys or None.
    geometries, textures : sequence of str
        The design's answer keys, in order.

    Raises
    ------
    AnalysisError
        No records, a record without a required field, an unknown geometry/texture/condition,
        or an answer key out of range — naming the record.
    """
    import pandas as pd
    from scipy import stats

    rows = []
    for i, rec in enumerate(records):
        rows.append(_check_record(i, rec, geometries, textures))
    if not rows:
        raise AnalysisError("no user-test trial records to analyse; point at the session logs")
    df = pd.DataFrame(rows)
    df["geometry_ok"] = df["geometry_answer"] == df["geometry_key"]
    df["texture_ok"] = df["texture_answer"] == df["texture_key"]
    df["both_ok"] = df["geometry_ok"] & df["texture_ok"]
    grouped = df.groupby(["participant", "condition"], sort=True)
    rates = grouped.agg(
        n_trials=("both_ok", "size"),
        n_no_answer=("no_answer", "sum"),
        both=("both_ok", "mean"),
        geometry=("geometry_ok", "mean"),
        texture=("texture_ok", "mean"),
    ).reset_index()
    summary = (
        rates.melt(
            id_vars=["participant", "condition"], value_vars=list(MEASURES), var_name="measure"
        )
        .groupby(["condition", "measure"], sort=True)["value"]
        .agg(mean="mean", sd=_sd, n="size")
        .reset_index()
    )
    tests = []
    wide = rates.pivot(index="participant", columns="condition", values=list(MEASURES))
    for m in MEASURES:
        tests.append(_paired(wide, m, stats))
    confusion: dict[str, dict[str, Any]] = {}
    for cond, part in df.groupby("condition", sort=True):
        confusion[str(cond)] = {
            "geometry": _confusion(part, "geometry", "geometry_answer", geometries),
            "texture": _confusion(part, "texture", "texture_answer", textures),
        }
    return UserTestAnalysis(rates=rates, summary=summary, tests=tests, confusion=confusion)


_REQUIRED = ("participant", "geometry", "texture", "condition", "geometry_answer", "texture_answer")


def _check_record(
    i: int, rec: Mapping[str, Any], geometries: Sequence[str], textures: Sequence[str]
) -> dict[str, Any]:
    for key in _REQUIRED:
        if key not in rec:
            raise AnalysisError(
                f"user-test record {i}: no {key!r}; records need {', '.join(_REQUIRED)}"
            )
    if rec["geometry"] not in geometries:
        raise AnalysisError(
            f"user-test record {i}: geometry {rec['geometry']!r} is not one of {list(geometries)}"
        )
    if rec["texture"] not in textures:
        raise AnalysisError(
            f"user-test record {i}: texture {rec['texture']!r} is not one of {list(textures)}"
        )
    if rec["condition"] not in CONDITIONS:
        raise AnalysisError(
            f"user-test record {i}: condition {rec['condition']!r} is not one of {CONDITIONS}"
        )
    answers = {}
    for key, n in (("geometry_answer", len(geometries)), ("texture_answer", len(textures))):
        a = rec[key]
        if a is not None and (isinstance(a, bool) or not isinstance(a, int) or not 1 <= a <= n):
            raise AnalysisError(
                f"user-test record {i}: {key} is {a!r}; it must be a key 1..{n} or null (no answer)"
            )
        answers[key] = a
    return {
        "participant": str(rec["participant"]),
        "condition": rec["condition"],
        "geometry": rec["geometry"],
        "texture": rec["texture"],
        "geometry_key": geometries.index(rec["geometry"]) + 1,
        "texture_key": textures.index(rec["texture"]) + 1,
        "geometry_answer": answers["geometry_answer"],
        "texture_answer": answers["texture_answer"],
        "no_answer": answers["geometry_answer"] is None or answers["texture_answer"] is None,
    }


def _sd(values: Any) -> float:
    # Between-participant SD; undefined for one participant.
    return float(np.std(values, ddof=1)) if len(values) > 1 else math.nan


def _paired(wide: Any, measure: str, stats: Any) -> PairedComparison:
    cols = [(measure, c) for c in CONDITIONS]
    if any(c not in wide.columns for c in cols):
        present = sorted({c for _, c in wide.columns})
        return PairedComparison(
            measure,
            0,
            math.nan,
            math.nan,
            math.nan,
            None,
            None,
            None,
            f"needs both conditions; the records have only {present}",
        )
    both = wide[cols].dropna()
    comp = both[(measure, "compensated")].to_numpy(dtype=float)
    unc = both[(measure, "uncompensated")].to_numpy(dtype=float)
    n = comp.size
    diff = comp - unc
    mean_c = float(comp.mean()) if n else math.nan
    mean_u = float(unc.mean()) if n else math.nan
    mean_d = float(diff.mean()) if n else math.nan
    if n < 2:
        return PairedComparison(
            measure,
            n,
            mean_c,
            mean_u,
            mean_d,
            None,
            None,
            None,
            f"a paired test needs ≥ 2 participants with both conditions, got {n}",
        )
    sd = float(np.std(diff, ddof=1))
    # Rates are multiples of 1/trials: equal differences can differ in the last bits.
    if sd <= 1e-12 * max(1.0, float(np.max(np.abs(diff)))):
        return PairedComparison(
            measure,
            n,
            mean_c,
            mean_u,
            mean_d,
            None,
            None,
            None,
            "every participant's difference is the same; the paired t-test is undefined",
        )
    res = stats.ttest_rel(comp, unc)
    return PairedComparison(
        measure, n, mean_c, mean_u, mean_d, float(res.statistic), float(res.pvalue), mean_d / sd
    )


def _confusion(part: Any, presented: str, answered: str, labels: Sequence[str]) -> Any:
    import pandas as pd

    columns = [*labels, "no answer"]
    table = pd.DataFrame(0, index=list(labels), columns=columns)
    for shown, ans in zip(part[presented], part[answered], strict=True):
        missing = ans is None or (isinstance(ans, float) and math.isnan(ans))
        col = "no answer" if missing else labels[int(ans) - 1]
        table.loc[shown, col] += 1
    table.index.name = f"{presented} presented"
    table.columns.name = "answered"
    return table
