"""What a session plays, worked out before anything is played (pure: no I/O, no clock).

Per set: the unit the staircase runs in, the conversions dB SL ↔ dB re 1 V through the
participant's calibration, the effective level bounds (protocol bounds ∩ what the device can
drive), the masker's drive and the per-trial :class:`~masking_lab.device.base.TrialPlan`.
Per trial: the target interval, drawn from a generator seeded by (session seed, set, trial) so a
resumed session draws exactly what an uninterrupted one would. Per session: the time left.

Units: ``_db_v`` is dB re 1 V (drive), ``_db_sl`` dB above the participant's unmasked AL of
that stimulus, ``_v`` volts peak, ``_s`` seconds. A staircase level without a suffix
(``level_db``) is in the set's ``level_unit``: dB re 1 V in a baseline protocol, dB SL in a
masked one.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from masking_lab.core.errors import CalibrationError, LevelError
from masking_lab.core.levels import check_within_rating, db_v_to_volts, volts_to_db_v
from masking_lab.core.stimulus import Stimulus
from masking_lab.core.trial import TrialPlan
from masking_lab.formats.protocol import SetSpec, Timing
from masking_lab.procedures.log_fields import SetProcedure
from masking_lab.procedures.registry import kind_of

LevelUnit = Literal["db_sl", "db_v"]
UNIT_LABEL: dict[str, str] = {"db_sl": "dB SL", "db_v": "dB re 1 V"}


# Rounding slack when a level sits exactly on the device limit: dB → V → dB is not exact.
_LIMIT_SLACK_DB = 1e-9


@dataclass(frozen=True)
class SetPlan:
    """Everything needed to run one set, in both level units.

    Attributes
    ----------
    set_id : str
        Set identifier from the protocol.
    target, masker : Stimulus, Stimulus or None
        Stimuli of the set.
    masker_level_db_sl : float or None
        Masker level, dB SL of the masker.
    level_unit : {"db_sl", "db_v"}
        Unit the staircase runs in.
    unmasked_al_db_v : float or None
        The target's unmasked AL, dB re 1 V (None in a baseline set: levels are drive levels).
    masker_level_db_v : float or None
        The masker's drive, dB re 1 V = its unmasked AL + ``masker_level_db_sl``.
    masker_amplitude_v : float
        The masker's peak drive, V (0 without a masker).
    target_max_v : float
        Largest target drive the device allows, V peak: the channel's limit, less the masker's
        drive when both share a channel (peak drives on one channel add).
    procedure : settings of a registered procedure kind
        The set's procedure with ``max_level_db`` lowered to what the device can drive.
    masker_unmasked_al_db_v : float or None
        The masker's unmasked AL, dB re 1 V, for procedures that choose the masker level per
        trial (None otherwise).
    masker_limit_v : float
        The masker channel's drive limit, V peak (inf without a masker).
    """

    set_id: str
    target: Stimulus
    masker: Stimulus | None
    masker_level_db_sl: float | None
    level_unit: LevelUnit
    unmasked_al_db_v: float | None
    masker_level_db_v: float | None
    masker_amplitude_v: float
    target_max_v: float
    procedure: SetProcedure
    masker_unmasked_al_db_v: float | None = None
    masker_limit_v: float = math.inf

    @property
    def staircase(self) -> SetProcedure:
        """The set's procedure settings (the name from when every set ran a staircase)."""
        return self.procedure

    def level_db_v(self, level_db: float) -> float:
        """Target drive in dB re 1 V for a staircase level in ``level_unit``."""
        if self.unmasked_al_db_v is None:
            return float(level_db)
        return float(level_db) + self.unmasked_al_db_v

    def level_db_sl(self, level_db: float) -> float | None:
        """Target level in dB SL for a staircase level in ``level_unit`` (None in a baseline)."""
        return float(level_db) if self.unmasked_al_db_v is not None else None

    def to_level_unit_db(self, level_db_v: float) -> float:
        """Inverse of :meth:`level_db_v`: a drive in dB re 1 V expressed in ``level_unit``."""
        if self.unmasked_al_db_v is None:
            return float(level_db_v)
        return float(level_db_v) - self.unmasked_al_db_v


def plan_set(
    spec: SetSpec,
    level_unit: LevelUnit,
    calibration_db_v: Mapping[str, float],
    max_drive_v: Mapping[str, float],
) -> SetPlan:
    """Work out a set before playing it, or refuse it.

    Parameters
    ----------
    spec : SetSpec
        The protocol's set.
    level_unit : {"db_sl", "db_v"}
        ``protocol.level_unit``.
    calibration_db_v : mapping of stimulus name → dB re 1 V
        The participant's unmasked ALs (unused in a baseline set).
    max_drive_v : mapping of channel → V
        The device's limits (``DeviceIdentity.limits.max_drive_v``).

    Raises
    ------
    CalibrationError
        A dB SL set whose target or masker has no unmasked AL in ``calibration_db_v``.
    LevelError
        The start level is above what the device can drive, the device limit lies at or below
        the protocol's lower bound, or the masker's drive exceeds the device's limit (alone, or
        leaves no room for a target on the same channel).
    """
    unmasked: float | None = None
    if level_unit == "db_sl":
        unmasked = _calibrated(calibration_db_v, spec.target, spec.id)
    sc = spec.settings
    kind = kind_of(sc)
    unit = UNIT_LABEL[level_unit]

    masker_db_v: float | None = None
    masker_v = 0.0
    masker_al_db_v: float | None = None
    masker_limit_v = math.inf
    if spec.masker is not None and kind.places_masker:
        # The procedure picks every trial's masker level: its range stops at the rig's rating.
        masker_al_db_v = _calibrated(calibration_db_v, spec.masker, spec.id)
        masker_limit_v = _channel_limit_v(spec.masker, max_drive_v)
        sc = kind.within_masker_limit(sc, volts_to_db_v(masker_limit_v) - masker_al_db_v)
        masker_range = kind.masker_range_db_sl(sc)
        assert masker_range is not None  # a kind that places the masker states its range
        masker_v = min(db_v_to_volts(masker_al_db_v + masker_range[1]), masker_limit_v)
    elif spec.masker is not None and spec.masker_level_db_sl is not None:
        masker_al = _calibrated(calibration_db_v, spec.masker, spec.id)
        masker_db_v = masker_al + spec.masker_level_db_sl
        masker_limit_v = _channel_limit_v(spec.masker, max_drive_v)
        check_within_rating(
            masker_db_v,
            masker_limit_v,
            what=f"set {spec.id}: masker {spec.masker.name} at {spec.masker_level_db_sl:g} dB SL",
        )
        masker_v = min(db_v_to_volts(masker_db_v), masker_limit_v)

    limit_v = _channel_limit_v(spec.target, max_drive_v)
    if spec.masker is not None and spec.masker.channel == spec.target.channel:
        # Peak drives on one channel add: the target gets what the masker leaves.
        limit_v -= masker_v
        if not limit_v > 0:
            raise LevelError(
                f"set {spec.id}: the masker {spec.masker.name} alone uses the whole "
                f"{spec.target.channel} drive limit; nothing is left for the target"
            )
    limit_db_v = volts_to_db_v(limit_v)
    device_max = limit_db_v if unmasked is None else limit_db_v - unmasked
    protocol_max = sc.max_level_db if sc.max_level_db is not None else math.inf
    effective_max = min(protocol_max, device_max)
    start_db = kind.start_level_db(sc)
    if start_db > effective_max + _LIMIT_SLACK_DB:
        raise LevelError(
            f"set {spec.id}: start level {start_db:g} {unit} of {spec.target.name} is "
            f"above what the device can drive ({limit_v:g} V = {effective_max:.2f} {unit}); "
            f"lower {kind.start_key} in the protocol, or check the participant's "
            "calibration and the device config"
        )
    if sc.min_level_db is not None and sc.min_level_db >= effective_max - _LIMIT_SLACK_DB:
        raise LevelError(
            f"set {spec.id}: the device limit for {spec.target.name} ({limit_v:g} V = "
            f"{effective_max:.2f} {unit}) is not above the protocol's min_level_db "
            f"({sc.min_level_db:g} {unit}); the {sc.kind} would have no room to move"
        )
    settings: SetProcedure = kind.within_limit(sc, effective_max)
    return SetPlan(
        set_id=spec.id,
        target=spec.target,
        masker=spec.masker,
        masker_level_db_sl=spec.masker_level_db_sl,
        level_unit=level_unit,
        unmasked_al_db_v=unmasked,
        masker_level_db_v=masker_db_v,
        masker_amplitude_v=masker_v,
        target_max_v=limit_v,
        procedure=settings,
        masker_unmasked_al_db_v=masker_al_db_v,
        masker_limit_v=masker_limit_v,
    )


def plan_trial(
    set_plan: SetPlan,
    level_db: float,
    target_interval: int,
    timing: Timing,
    masker_level_db_sl: float | None = None,
) -> TrialPlan:
    """The device's view of one trial at staircase level ``level_db`` (in ``level_unit``).

    ``masker_level_db_sl`` is the trial's masker level (dB SL of the masker) for procedures
    that choose it per trial; None plays the set's masker level.

    Raises
    ------
    LevelError
        If the target's or the masker's drive exceeds the device limit (the bounds of
        :func:`plan_set` prevent this; the check guards against a track rebuilt with other
        bounds).
    """
    if target_interval not in (1, 2, 3):
        raise LevelError(f"target_interval must be 1, 2 or 3, got {target_interval!r}")
    level_db_v = set_plan.level_db_v(level_db)
    check_within_rating(
        level_db_v,
        set_plan.target_max_v,
        what=f"set {set_plan.set_id}: target {set_plan.target.name}",
    )
    # A level on the limit may come back a hair above it from dB → V; the limit is what we meant.
    amplitude_v = min(db_v_to_volts(level_db_v), set_plan.target_max_v)
    masker_v = set_plan.masker_amplitude_v
    if masker_level_db_sl is not None:
        if set_plan.masker is None or set_plan.masker_unmasked_al_db_v is None:
            raise LevelError(
                f"set {set_plan.set_id}: a masker level was asked for but the set has no "
                "masker with a calibrated unmasked AL"
            )
        masker_db_v = set_plan.masker_unmasked_al_db_v + float(masker_level_db_sl)
        check_within_rating(
            masker_db_v,
            set_plan.masker_limit_v,
            what=f"set {set_plan.set_id}: masker {set_plan.masker.name} at "
            f"{masker_level_db_sl:g} dB SL",
        )
        masker_v = min(db_v_to_volts(masker_db_v), set_plan.masker_limit_v)
    return TrialPlan(
        target=set_plan.target,
        target_amplitude_v=amplitude_v,
        target_interval=target_interval,
        masker=set_plan.masker,
        masker_amplitude_v=masker_v,
        stimulus_s=timing.stimulus_s,
        gap_s=timing.gap_s,
        lead_in_s=timing.lead_in_s,
    )


def estimate_time_left_s(
    *,
    seconds_per_trial: float,
    trials_done_in_set: int,
    reversals_in_set: int,
    n_reversals: int,
    max_trials: int | None,
    sets_after_current: int,
    finished_set_trials: Sequence[int] = (),
    rest_between_sets_s: float = 0.0,
    prior_trials_per_reversal: float = 6.0,
) -> float:
    """Expected session time left in s, from the pace so far and the protocol.

    The current set needs ``n_reversals − reversals_in_set`` more reversals at this set's pace
    (trials per reversal so far, once it has 2 reversals), else at the pace of the session's
    finished sets, else at ``prior_trials_per_reversal``. Each later set takes the mean trial
    count of the finished sets (or ``n_reversals × prior``), capped at ``max_trials``; a rest of
    ``rest_between_sets_s`` precedes each.

    Parameters
    ----------
    seconds_per_trial : float
        Time per trial including answer and pause, s.
    trials_done_in_set, reversals_in_set : int
        Progress of the current set.
    n_reversals : int
        Reversals that end a set.
    max_trials : int or None
        Trial cap of a set.
    sets_after_current : int
        Sets still to run after the current one.
    finished_set_trials : sequence of int
        Trial counts of the sets this session has finished.
    rest_between_sets_s : float
        Rest before each later set, s.
    prior_trials_per_reversal : float
        Pace assumed before any is observed (1-up 3-down tracks take about 6 trials/reversal).

    Returns
    -------
    float
        Seconds, ≥ 0.
    """
    if finished_set_trials:
        per_reversal = float(np.mean(finished_set_trials)) / n_reversals
    else:
        per_reversal = prior_trials_per_reversal
    if reversals_in_set >= 2:
        per_reversal = trials_done_in_set / reversals_in_set
    reversals_left = max(0, n_reversals - reversals_in_set)
    current_left = reversals_left * per_reversal
    if max_trials is not None:
        current_left = min(current_left, max(0, max_trials - trials_done_in_set))
    if finished_set_trials:
        per_set = float(np.mean(finished_set_trials))
    else:
        per_set = n_reversals * prior_trials_per_reversal
    if max_trials is not None:
        per_set = min(per_set, float(max_trials))
    trials_left = current_left + sets_after_current * per_set
    return max(0.0, trials_left * seconds_per_trial + sets_after_current * rest_between_sets_s)


def nominal_seconds_per_trial(timing: Timing, response_time_s: float = 1.0) -> float:
    """Time per trial in s before any is observed: the presentations, an answer and the pause."""
    return timing.trial_s + response_time_s + timing.inter_trial_s


def _calibrated(calibration_db_v: Mapping[str, float], stimulus: Stimulus, set_id: str) -> float:
    try:
        value = float(calibration_db_v[stimulus.name])
    except KeyError:
        raise CalibrationError(
            f"set {set_id}: no unmasked AL for {stimulus.name} in the participant's calibration; "
            "run the baseline protocol for this participant first"
        ) from None
    if not math.isfinite(value):
        raise CalibrationError(
            f"set {set_id}: the calibration's unmasked AL for {stimulus.name} is {value!r}, "
            "not a finite dB re 1 V value; re-run the baseline for this stimulus"
        )
    return value


def _channel_limit_v(stimulus: Stimulus, max_drive_v: Mapping[str, float]) -> float:
    limit = max_drive_v.get(stimulus.channel)
    if limit is None or not (math.isfinite(float(limit)) and float(limit) > 0):
        raise LevelError(
            f"the device reports no usable drive limit for channel {stimulus.channel} "
            f"(got {limit!r}) so {stimulus.name} cannot be played; set "
            f"channels.{stimulus.channel}.max_drive_v in the device config"
        )
    return float(limit)
