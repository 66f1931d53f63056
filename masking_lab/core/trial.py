"""What one 3IFC trial is: the plan a device plays and the result it reports (pure values).

Levels are peak drive amplitudes in volts (the host converts dB re 1 V with
:mod:`masking_lab.core.levels`); times are seconds on the session clock.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from masking_lab.core.stimulus import Stimulus

__all__ = ["PlayResult", "TrialPlan"]


@dataclass(frozen=True)
class TrialPlan:
    """One 3IFC trial to play.

    Attributes
    ----------
    target : Stimulus
        The stimulus whose AL is measured.
    target_amplitude_v : float
        Peak drive of the target in its interval, V.
    target_interval : int
        1, 2 or 3: the interval that carries the target.
    masker : Stimulus or None
        Masker stimulus, played in all three intervals (None for an unmasked trial).
    masker_amplitude_v : float
        Peak drive of the masker, V (0 when ``masker`` is None).
    stimulus_s : float
        Duration of each interval, s (1.8 s in the paper).
    gap_s : float
        Silence between intervals, s.
    lead_in_s : float
        Silence before the first interval, s.
    n_intervals : int
        Intervals per trial (3 for 3IFC).

    Examples
    --------
    EV270 at 50 mV peak in interval 2, masked by MV120 at 0.2 V in all three:

    >>> from masking_lab.core.stimulus import parse_stimulus
    >>> plan = TrialPlan(parse_stimulus("EV270"), 0.05, 2, parse_stimulus("MV120"), 0.2)
    >>> plan.duration_s
    7.2
    """

    target: Stimulus
    target_amplitude_v: float
    target_interval: int
    masker: Stimulus | None = None
    masker_amplitude_v: float = 0.0
    stimulus_s: float = 1.8
    gap_s: float = 0.6
    lead_in_s: float = 0.6
    n_intervals: int = 3

    def planned_onsets_s(self, start_s: float) -> list[float]:
        """Planned interval onsets in s for a trial starting at ``start_s``.

        Parameters
        ----------
        start_s : float
            Trial start on the session clock, s.

        Returns
        -------
        list of float
            One onset per interval, s.

        Examples
        --------
        >>> from masking_lab.core.stimulus import parse_stimulus
        >>> plan = TrialPlan(parse_stimulus("EV270"), 0.05, 1)
        >>> [round(t, 3) for t in plan.planned_onsets_s(10.0)]
        [10.6, 13.0, 15.4]
        """
        return [
            start_s + self.lead_in_s + k * (self.stimulus_s + self.gap_s)
            for k in range(self.n_intervals)
        ]

    @property
    def duration_s(self) -> float:
        """Total trial duration in s (lead-in, intervals and the gaps between them).

        Examples
        --------
        >>> from masking_lab.core.stimulus import parse_stimulus
        >>> TrialPlan(parse_stimulus("EV270"), 0.05, 1, stimulus_s=1.0, gap_s=0.5).duration_s
        4.6
        """
        n = self.n_intervals
        return self.lead_in_s + n * self.stimulus_s + (n - 1) * self.gap_s


@dataclass(frozen=True)
class PlayResult:
    """What the device reports after playing a trial.

    Attributes
    ----------
    planned_onsets_s : list[float]
        Host-clock planned onset of each interval, s.
    actual_onsets_s : list[float]
        Onsets as reported by the device, converted to host-clock s.
    played_target_v : float
        Target peak amplitude the device actually played, V.
    played_masker_v : float
        Masker peak amplitude the device actually played, V.
    extra : dict
        Back-end specific diagnostics (kept in the log).

    Examples
    --------
    How late each interval started, ms:

    >>> result = PlayResult([0.6, 3.0, 5.4], [0.6002, 3.0001, 5.4003], 0.05, 0.2)
    >>> [round(1000 * (a - p), 1) for p, a in zip(result.planned_onsets_s, result.actual_onsets_s)]
    [0.2, 0.1, 0.3]
    """

    planned_onsets_s: list[float]
    actual_onsets_s: list[float]
    played_target_v: float
    played_masker_v: float
    extra: dict = field(default_factory=dict)
