"""A board's numbers are data to check: a DONE report against the trial it answers. Pure.

A ``DONE`` is accepted only if its onsets are finite, strictly increasing and each lies within
``[planned − EARLY_S, planned + late_s]`` of its own planned onset (device time, so the host's
clock-offset estimate plays no part), its end lies after the last onset's planned stimulus end
(within ``late_s`` of it), and each played amplitude is within one LSB of what the converter
plays for the request. Anything else is a firmware fault: the trial is not logged as played.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

EARLY_S = 0.001  # an onset may precede its plan by this much (µs rounding, clock steps), s
AMP_SLACK_V = 2e-6  # amplitudes travel with 6 decimals (µV)


class ReplyError(ValueError):
    """A device report that contradicts the trial it answers (what is wrong, in words)."""


@dataclass(frozen=True)
class Expected:
    """What a DONE must say about one trial (device time).

    Attributes
    ----------
    onsets_s : tuple of float
        Planned onset of each interval, device s.
    stimulus_s : float
        Duration of each interval, s.
    late_s : float
        How late an onset or the end may be, s (the stated tolerance).
    target_v, masker_v : float
        Peak amplitudes the converter plays for the requests, V.
    target_lsb_v, masker_lsb_v : float
        One LSB at the attenuator step in use, V (0: no quantisation known).
    """

    onsets_s: tuple[float, ...]
    stimulus_s: float
    late_s: float
    target_v: float
    masker_v: float
    target_lsb_v: float = 0.0
    masker_lsb_v: float = 0.0


def check_done(
    onsets_s: Sequence[float], end_s: float | None, target_v: float, masker_v: float, want: Expected
) -> None:
    """Raise :class:`ReplyError` unless a DONE's numbers fit the trial in ``want``.

    Parameters
    ----------
    onsets_s : sequence of float
        Reported onsets, device s.
    end_s : float or None
        Reported end of the trial, device s (None: not reported).
    target_v, masker_v : float
        Reported played amplitudes, V.
    want : Expected
        The trial as planned.

    Examples
    --------
    >>> want = Expected((1.0, 1.5, 2.0), 0.2, 0.5, 0.1, 0.0)
    >>> check_done([1.0, 1.5, 2.0001], 2.2, 0.1, 0.0, want)
    >>> try:
    ...     check_done([1.0, 2.0, 1.5], 2.2, 0.1, 0.0, want)
    ... except ReplyError as exc:
    ...     print(exc)
    onsets [1, 2, 1.5] s are not strictly increasing
    """
    shown = ", ".join(f"{t:.9g}" for t in onsets_s)
    if len(onsets_s) != len(want.onsets_s):
        raise ReplyError(f"{len(onsets_s)} onsets reported, {len(want.onsets_s)} planned")
    if not all(math.isfinite(t) for t in onsets_s):
        raise ReplyError(f"onsets [{shown}] s are not all finite")
    if any(b <= a for a, b in itertools.pairwise(onsets_s)):
        raise ReplyError(f"onsets [{shown}] s are not strictly increasing")
    for k, (got, planned) in enumerate(zip(onsets_s, want.onsets_s, strict=True)):
        if not planned - EARLY_S <= got <= planned + want.late_s:
            raise ReplyError(
                f"onset {k + 1} at {got:.9g} s is outside its window {planned - EARLY_S:.6f}.."
                f"{planned + want.late_s:.6f} s (planned {planned:.6f} s, tolerance "
                f"-{EARLY_S * 1e3:g} ms/+{want.late_s:g} s)"
            )
    if end_s is not None:
        last_end = want.onsets_s[-1] + want.stimulus_s
        if not (math.isfinite(end_s) and onsets_s[-1] < end_s <= last_end + want.late_s):
            raise ReplyError(
                f"end at {end_s:.9g} s is not after the last onset ({onsets_s[-1]:.6f} s) and "
                f"within {want.late_s:g} s of the planned end ({last_end:.6f} s)"
            )
    for what, got, expect, lsb in (
        ("target", target_v, want.target_v, want.target_lsb_v),
        ("masker", masker_v, want.masker_v, want.masker_lsb_v),
    ):
        if not (math.isfinite(got) and abs(got - expect) <= lsb + AMP_SLACK_V):
            raise ReplyError(
                f"played {what} amplitude {got:.9g} V differs from the {expect:.6f} V the "
                f"converter plays for the request by more than one LSB ({lsb:.3g} V)"
            )
