"""What a channel's converter can play: LSB, quantisation, attenuator step choice. Pure.

A channel's output is a converter of ``bits`` bits whose full scale is ``full_scale_v`` peak at
the amplifier input with no attenuation, followed by an optional switchable attenuator
(``steps_db``, e.g. 0/20/40 dB). To play a peak amplitude ``a`` (V at the amplifier input) at
step ``s`` dB the converter plays ``a·10^(s/20)``, rounded to whole LSBs of
``2·full_scale_v / 2^bits``; what reaches the amplifier is that, divided by ``10^(s/20)``.

The host picks, per stimulus, the smallest attenuation at which the amplitude spans at least
``min_lsb`` LSBs (and still fits the full scale); with no such step, the one that spans most.
A level that no step renders within :data:`MAX_ERROR_DB` is refused before the first trial.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

MAX_ERROR_DB = 1.0  # largest |played − requested| a level may have, dB
DEFAULT_MIN_LSB = 10.0


@dataclass(frozen=True)
class Converter:
    """One channel's converter and attenuator.

    Attributes
    ----------
    bits : int
        Converter resolution, bits.
    full_scale_v : float
        Largest |sample| at the amplifier input with no attenuation, peak V.
    steps_db : tuple of float
        Attenuation steps the board can switch, dB, ascending from 0.
    min_lsb : float
        Smallest span, in LSBs, the step choice aims for.
    linear_codes : int or None
        Largest |code| around mid-scale the output stage plays without clipping (HELLO
        ``lin``; the reference board's DAC buffer: 1798 of 2048); None = the converter's whole
        range, 2^(bits−1) − 1. A level needing more codes at a step does not fit that step.

    Examples
    --------
    >>> conv = Converter(12, 10.0, (0.0, 20.0, 40.0))
    >>> round(conv.lsb_v(0.0) * 1000, 3)  # mV at the amplifier input
    4.883
    >>> Converter(12, 10.0, linear_codes=1798).max_code, conv.max_code
    (1798, 2047)
    """

    bits: int
    full_scale_v: float
    steps_db: tuple[float, ...] = (0.0,)
    min_lsb: float = DEFAULT_MIN_LSB
    linear_codes: int | None = None

    @property
    def max_code(self) -> int:
        """Largest |code| played: ``linear_codes``, else 2^(bits−1) − 1 (the converter's)."""
        top = (1 << (self.bits - 1)) - 1
        return top if self.linear_codes is None else min(self.linear_codes, top)

    def code(self, amplitude_v: float, step_db: float) -> int:
        """Code amplitude (whole LSBs, rounded half up) of ``amplitude_v`` V at ``step_db``.

        Examples
        --------
        >>> Converter(12, 10.0).code(0.0878, 40.0), Converter(12, 10.0).code(0.08783, 40.0)
        (1798, 1799)
        """
        lsb0 = 2.0 * self.full_scale_v / 2.0**self.bits
        return math.floor(amplitude_v * 10.0 ** (step_db / 20.0) / lsb0 + 0.5)

    def linear_max_v(self, step_db: float) -> float:
        """The largest amplitude (V at the amplifier input) played linearly at ``step_db``.

        Examples
        --------
        >>> round(Converter(12, 10.0, linear_codes=1798).linear_max_v(40.0), 6)
        0.087793
        """
        return self.max_code * self.lsb_v(step_db)

    def lsb_v(self, step_db: float) -> float:
        """One LSB at the amplifier input at attenuation ``step_db``, V."""
        return 2.0 * self.full_scale_v / 2.0**self.bits / 10.0 ** (step_db / 20.0)

    def played_v(self, amplitude_v: float, step_db: float) -> float:
        """The peak amplitude that reaches the amplifier for a request of ``amplitude_v`` V.

        Examples
        --------
        >>> Converter(12, 10.0).played_v(0.002, 0.0)  # under half an LSB: silence
        0.0
        >>> round(Converter(12, 10.0).played_v(0.002, 40.0), 6)
        0.002002
        """
        return self.code(amplitude_v, step_db) * self.lsb_v(step_db)

    def fits(self, amplitude_v: float | Iterable[float], step_db: float) -> bool:
        """True if ``amplitude_v`` V at step ``step_db`` stays within the codes played linearly.

        Several amplitudes (one channel's target and masker) are rounded one by one and their
        codes added, as the firmware does.

        Examples
        --------
        >>> conv = Converter(12, 10.0, (0.0, 40.0), linear_codes=1798)
        >>> conv.fits(0.0878, 40.0), conv.fits(0.08783, 40.0), conv.fits([0.05, 0.04], 40.0)
        (True, False, False)
        """
        amps = [amplitude_v] if isinstance(amplitude_v, int | float) else list(amplitude_v)
        return sum(self.code(a, step_db) for a in amps if a > 0) <= self.max_code

    def pick_step(self, amplitudes_v: Iterable[float]) -> float:
        """The attenuation step (dB) for amplitudes sharing this channel in one trial.

        The smallest step at which the smallest non-zero amplitude spans ``min_lsb`` LSBs and
        their codes together fit the linear range; else the largest step at which they fit
        (the most LSBs); else 0 dB (above the linear range at every step: refused, see
        :meth:`fits`).

        Examples
        --------
        >>> conv = Converter(12, 10.0, (0.0, 20.0, 40.0))
        >>> conv.pick_step([1.0]), conv.pick_step([0.01]), conv.pick_step([0.001])
        (0.0, 20.0, 40.0)
        """
        return _pick_step(self, tuple(a for a in amplitudes_v if a > 0))

    def error_db(self, amplitude_v: float, step_db: float) -> float:
        """|played − requested| in dB for ``amplitude_v`` > 0 (inf when it plays as silence)."""
        played = self.played_v(amplitude_v, step_db)
        if played <= 0:
            return math.inf
        return abs(20.0 * math.log10(played / amplitude_v))


# Pure in (converter, amplitudes); a staircase revisits the same levels, and every trial asks
# for each channel's step twice (~45 µs of a demo trial's ~1 ms of CPU without this cache).
@functools.lru_cache(maxsize=4096)
def _pick_step(conv: Converter, amps: tuple[float, ...]) -> float:
    if not amps:
        return conv.steps_db[0]
    low = min(amps)
    fitting = [s for s in conv.steps_db if conv.fits(amps, s)]
    if not fitting:
        return conv.steps_db[0]
    for step in fitting:
        if low >= conv.min_lsb * conv.lsb_v(step):
            return step
    return fitting[-1]


def unplayable(
    converter: Converter, amplitudes_v: Sequence[float], max_error_db: float = MAX_ERROR_DB
) -> list[tuple[float, float]]:
    """The amplitudes (V) that no step plays within ``max_error_db``, with their best error, dB.

    Each amplitude is judged alone, at the step :meth:`Converter.pick_step` would choose for it
    (the least error any step gives, since the chosen step spans the most LSBs that fit).

    Examples
    --------
    >>> conv = Converter(12, 10.0, (0.0,))
    >>> [(a, round(e, 2)) for a, e in unplayable(conv, [1.0, 0.01, 0.004])]
    [(0.004, 1.73)]
    """
    bad = []
    for amp in amplitudes_v:
        if amp <= 0:
            continue
        errors = (converter.error_db(amp, s) for s in converter.steps_db if converter.fits(amp, s))
        best = min(errors, default=math.inf)  # beyond the linear range at every step
        if best > max_error_db:
            bad.append((float(amp), best))
    return bad


def quietest_playable_v(converter: Converter, max_error_db: float = MAX_ERROR_DB) -> float:
    """The smallest peak amplitude (V) every amplitude above which plays within the bound.

    Rounding to whole LSBs errs by at most half an LSB, so an amplitude of ``k`` LSBs may play
    as ``k − 1/2``: at most ``−20·log10(1 − 1/(2k))`` dB low. The bound holds from
    ``k = 1/(2·(1 − 10^(−e/20)))`` LSBs of the deepest step.

    Examples
    --------
    >>> round(quietest_playable_v(Converter(12, 10.0, (0.0, 20.0, 40.0))) * 1e3, 3)  # mV
    0.224
    """
    k = 1.0 / (2.0 * (1.0 - 10.0 ** (-max_error_db / 20.0)))
    return k * converter.lsb_v(converter.steps_db[-1])
