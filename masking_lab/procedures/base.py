"""The Procedure interface every adaptive threshold procedure implements (pure).

A procedure is an immutable snapshot of one threshold track: it says which level to play next,
returns a new snapshot after each answer, knows when it has finished and what it estimates.
Its whole state is rebuilt by :func:`replay` from its settings and the logged responses, which
is how a crashed session resumes, how the analysis re-estimates a track and how the simulator
checks its vectorised twin. The 1-up-3-down :class:`~masking_lab.procedures.staircase.Staircase`
is one implementation; a new procedure is one new module with a settings class (``kind``,
``start()``) and a state class satisfying :class:`Procedure`, plus its protocol schema entry.

Levels are dB in the unit the session runs the track in (dB re 1 V in a baseline protocol,
dB SL in a masked one); the procedure never needs to know which.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any, Protocol, TypeVar, runtime_checkable

from masking_lab.core.errors import ProcedureError

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

__all__ = [
    "Procedure",
    "ProcedureSettings",
    "ThresholdEstimate",
    "TrackState",
    "replay",
    "settings_from_mapping",
]

SettingsT = TypeVar("SettingsT", bound="DataclassInstance")


@dataclass(frozen=True)
class ThresholdEstimate:
    """What a finished (or running) track says about the threshold.

    Attributes
    ----------
    level_db : float or None
        The threshold estimate, dB; None when the track yields none (a ceiling, a floor, a
        trial cap, or a track that has not finished).
    sd_db : float or None
        Its uncertainty as a standard deviation in dB (posterior SD for Bayesian procedures);
        None where the procedure has no model-based spread (the reversal mean).
    method : str
        How the estimate was formed (``"reversal_mean"``, ``"posterior_mean"``, ...).
    status : str
        The track's status (``"running"``, ``"completed"``, ``"ceiling"``, ``"floor"``,
        ``"trial_cap"``).

    Examples
    --------
    >>> ThresholdEstimate(level_db=4.5, sd_db=None, method="reversal_mean", status="completed")
    ThresholdEstimate(level_db=4.5, sd_db=None, method='reversal_mean', status='completed')
    """

    level_db: float | None
    sd_db: float | None
    method: str
    status: str


@runtime_checkable
class Procedure(Protocol):
    """One adaptive track's immutable state.

    Examples
    --------
    >>> from masking_lab.procedures.staircase import StaircaseSettings
    >>> track = StaircaseSettings(start_level_db=10.0).start()
    >>> isinstance(track, Procedure), track.next_level()
    (True, 10.0)
    >>> track.update(True).n_trials
    1
    """

    @property
    def finished(self) -> bool:
        """True once the track takes no more responses."""
        ...

    @property
    def status(self) -> str:
        """``"running"`` until the track stops; then why it stopped."""
        ...

    @property
    def n_trials(self) -> int:
        """Trials answered so far."""
        ...

    def next_level(self) -> float:
        """The level of the next trial, dB."""
        ...

    def update(self, correct: bool) -> Procedure:
        """The track after one trial at :meth:`next_level` answered ``correct``."""
        ...

    def estimate(self) -> ThresholdEstimate:
        """The threshold estimate from the trials so far."""
        ...


class ProcedureSettings(Protocol):
    """The rules of one procedure, as a protocol states them."""

    @property
    def kind(self) -> str:
        """The protocol's name for the procedure (``"staircase"``, ``"quest_plus"``)."""
        ...

    def start(self) -> Procedure:
        """A fresh track before its first trial."""
        ...


class TrackState:
    """What every track class shares: it is ``running`` until a stop rule sets ``status``, and
    counts its trials by its ``responses``."""

    status: str
    responses: tuple[bool, ...]

    @property
    def finished(self) -> bool:
        """True once a stop rule has ended the track."""
        return self.status != "running"

    @property
    def n_trials(self) -> int:
        """Trials answered so far."""
        return len(self.responses)


def settings_from_mapping(
    cls: type[SettingsT],
    mapping: Mapping[str, Any],
    kind: str,
    *,
    tuples: tuple[str, ...] = (),
    required: tuple[str, ...] = (),
) -> SettingsT:
    """Settings of procedure ``kind`` from a protocol's mapping (keys = ``cls``'s fields, an
    optional ``kind``); ``tuples`` keys take a number or a list; ``required`` ones (dB) must be
    given. Raises :class:`ProcedureError` naming the key (an unknown one: the valid ones too).

    Examples
    --------
    >>> from masking_lab.procedures.quest_plus import QuestPlusSettings
    >>> settings_from_mapping(QuestPlusSettings, {"step": 1}, "quest_plus")
    Traceback (most recent call last):
    masking_lab.core.errors.ProcedureError: quest_plus settings: unknown key(s) step; valid ...
    """
    data = dict(mapping)
    named = data.pop("kind", kind)
    if named != kind:
        raise ProcedureError(f"{kind} settings: kind must be {kind!r}, got {named!r}")
    names = [f.name for f in fields(cls)]
    unknown = sorted(map(str, set(data) - set(names)))
    if unknown:
        raise ProcedureError(
            f"{kind} settings: unknown key(s) {', '.join(unknown)}; valid keys are "
            f"{', '.join(names)}"
        )
    for name in required:
        if name not in data:
            raise ProcedureError(f"{kind} settings: {name} is required (dB)")
    for name in tuples:
        if name in data and not isinstance(data[name], int | float):
            data[name] = tuple(data[name])
    return cls(**data)


def replay(settings: ProcedureSettings, responses: Iterable[bool]) -> Procedure:
    """Rebuild a track from its settings and its responses, in order (the resume path).

    Parameters
    ----------
    settings : ProcedureSettings
        The rules the track ran under.
    responses : iterable of bool
        Whether each trial was answered correctly.

    Returns
    -------
    Procedure
        The same state an uninterrupted track would have after these responses.

    Raises
    ------
    ProcedureError
        If a response comes after the track finished: the responses do not belong to these
        settings.

    Examples
    --------
    >>> from masking_lab.procedures.staircase import StaircaseSettings
    >>> replay(StaircaseSettings(start_level_db=10.0), [True, True, True]).next_level()
    6.0
    """
    state = settings.start()
    for i, correct in enumerate(responses):
        if state.finished:
            raise ProcedureError(
                f"response {i} comes after the {settings.kind} finished ({state.status}); "
                "the responses do not belong to these settings"
            )
        state = state.update(correct)
    return state
