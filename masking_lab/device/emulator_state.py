"""Pieces of the firmware emulator that are not about serving a port.

The output snapshot tests read, the state of a scheduled trial, the PLAY field parsing and
checks (the same order and error codes as ``firmware/core/commands.c``), and the virtual-time
onset lateness generator, which is defined bit for bit in ``docs/device-protocol.md`` so the
emulator and the C firmware report the same onsets for the same seed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType

from masking_lab.core.stimulus import CHANNELS, Stimulus
from masking_lab.device import protocol as proto
from masking_lab.device.base import TrialPlan

PRNG_SEED_MIX = 0x6D2B79F5
_MASK32 = 0xFFFFFFFF
MAX_INTERVALS = 9
MAX_TRIAL_US = 60_000_000
INTERLOCK_TEXT = "interlock open: check HV enable, E-stop and the grounding wristband"


@dataclass(frozen=True)
class OutputSnapshot:
    """What the emulated outputs are doing right now (thread-safe copy).

    Attributes
    ----------
    amplitude_v : Mapping[str, float]
        Peak drive currently output per channel, V (0 = silent).
    playing : bool
        True while a PLAY is scheduled or in progress.
    last_sample_v : Mapping[str, float]
        Final sample of the last rendered trial buffer per channel, V (real-time mode).
    connected : bool
        False after the port was closed (unplugged or emulator closed).
    interlock_open : bool
        True while the interlock input is open (outputs forced to 0 V).

    Examples
    --------
    >>> silent = MappingProxyType({"EV": 0.0, "MV": 0.0})
    >>> OutputSnapshot(silent, False, silent, True).zero
    True
    >>> OutputSnapshot(MappingProxyType({"EV": 0.2, "MV": 0.0}), True, silent, True).zero
    False
    """

    amplitude_v: MappingProxyType[str, float]
    playing: bool
    last_sample_v: MappingProxyType[str, float]
    connected: bool
    interlock_open: bool = False

    @property
    def zero(self) -> bool:
        """True when both outputs are at 0 V and nothing is scheduled."""
        return not self.playing and all(v == 0.0 for v in self.amplitude_v.values())


@dataclass
class PlayState:
    """A scheduled or playing trial.

    Attributes
    ----------
    seq : int
        Sequence number of its PLAY.
    start : float
        Device time of the trial start, s.
    plan : TrialPlan
        What to play.
    planned : list[float]
        Planned onsets, device s.
    steps : list[tuple[float, str, int]]
        Pending ``(device s, "on" | "off", interval)`` steps (real time).
    actual : list[float]
        Onsets as played, device s.
    """

    seq: int
    start: float
    plan: TrialPlan
    planned: list[float]
    steps: list[tuple[float, str, int]] = field(default_factory=list)
    actual: list[float] = field(default_factory=list)


class OnsetLateness:
    """The documented virtual-time lateness generator (xorshift32, integer µs).

    ``state = (seed mod 2**32) ^ 0x6D2B79F5`` (``0x6D2B79F5`` if that is 0); each draw is
    Marsaglia's xorshift32 with shifts 13, 17, 5, and one onset's lateness is
    ``draw % (max_us + 1)`` µs. ``firmware/core/prng.c`` is the same generator in C.

    Parameters
    ----------
    seed : int
        Any integer (reduced mod 2**32).
    max_us : int
        Largest lateness, µs (``emulator.onset_jitter_s`` rounded to µs).

    Examples
    --------
    The same seed gives the same onset lateness as the C firmware, µs:

    >>> gen = OnsetLateness(seed=42, max_us=500)
    >>> [gen.lateness_us() for _ in range(5)]
    [111, 101, 365, 100, 73]
    """

    def __init__(self, seed: int, max_us: int) -> None:
        state = (int(seed) & _MASK32) ^ PRNG_SEED_MIX
        self.state = state or PRNG_SEED_MIX
        self.max_us = max(0, int(max_us))

    def next(self) -> int:
        """The next 32-bit draw.

        Examples
        --------
        >>> OnsetLateness(seed=0, max_us=0).next()
        1085196063
        """
        x = self.state
        x ^= (x << 13) & _MASK32
        x ^= x >> 17
        x ^= (x << 5) & _MASK32
        self.state = x
        return x

    def lateness_us(self) -> int:
        """Lateness of one onset, µs, in ``0..max_us``."""
        return self.next() % (self.max_us + 1)


def interlock_text(is_open: bool) -> str:
    """The wire value of the interlock state (``il=`` in HELLO and DIAG).

    Examples
    --------
    >>> interlock_text(True), interlock_text(False)
    ('open', 'closed')
    """
    return "open" if is_open else "closed"


def to_us(seconds: float) -> int:
    """A wire time (≤ 6 decimals) as exact integer µs.

    Parameters
    ----------
    seconds : float
        Time, s.

    Returns
    -------
    int
        The same time, µs (rounded to the nearest µs).

    Examples
    --------
    >>> to_us(1.8), to_us(0.000002)
    (1800000, 2)
    """
    return round(seconds * 1_000_000)


def channel(frame: proto.Frame, key: str) -> str:
    """Field ``key`` as ``"EV"``/``"MV"``; ValueError otherwise.

    Examples
    --------
    >>> channel(proto.decode(proto.encode_command(1, "AMP", {"ch": "MV"})), "ch")
    'MV'
    """
    ch = frame.fields.get(key)
    if ch not in CHANNELS:
        raise ValueError(f"{key}={ch!r} is not EV or MV")
    return ch


def check_frequency(carrier: float, env: float | None, sample_rate_hz: float) -> None:
    """ValueError unless ``0 < carrier < fs/2`` and ``0 <= env < fs/2`` (Hz).

    Examples
    --------
    >>> check_frequency(270.0, None, 1000.0)
    >>> check_frequency(600.0, None, 1000.0)
    Traceback (most recent call last):
    ...
    ValueError: frequencies must be in (0, 500) Hz
    """
    nyquist = sample_rate_hz / 2
    if not 0 < carrier < nyquist or (env is not None and not 0 <= env < nyquist):
        raise ValueError(f"frequencies must be in (0, {nyquist:g}) Hz")


def plan_from(frame: proto.Frame, sample_rate_hz: float) -> TrialPlan:
    """The TrialPlan of a PLAY frame; FrameError/ValueError (→ ``ERR ARGS``) if a field is bad.

    Parameters
    ----------
    frame : Frame
        A decoded PLAY command (carriers and envelopes in Hz, amplitudes in V, times in s).
    sample_rate_hz : float
        The emulator's sample rate, Hz (frequencies must lie below half of it).

    Returns
    -------
    TrialPlan

    Examples
    --------
    >>> play = proto.decode(proto.encode_command(7, "PLAY", {
    ...     "tch": "EV", "tcar": 270, "tenv": 0, "tamp": 0.05, "ti": 2, "n": 3, "mch": "MV",
    ...     "mcar": 120, "menv": 0, "mamp": 0.2, "stim": 1.8, "gap": 0.6, "lead": 0.6}))
    >>> plan = plan_from(play, 10_000.0)
    >>> plan.target.name, plan.target_amplitude_v, plan.masker.name, plan.duration_s
    ('EV270', 0.05, 'MV120', 7.2)
    """
    target = Stimulus(channel(frame, "tch"), frame.number("tcar"), frame.number("tenv") or None)
    check_frequency(target.carrier_hz, target.envelope_hz, sample_rate_hz)
    masker = None
    if frame.fields.get("mch", "-") != "-":
        masker = Stimulus(channel(frame, "mch"), frame.number("mcar"), frame.number("menv") or None)
        check_frequency(masker.carrier_hz, masker.envelope_hz, sample_rate_hz)
    n = int(frame.number("n"))
    ti = int(frame.number("ti"))
    if not 1 <= ti <= n or n > MAX_INTERVALS:
        raise ValueError(f"ti={ti} n={n}: need 1 <= ti <= n <= {MAX_INTERVALS}")
    plan = TrialPlan(
        target=target,
        target_amplitude_v=frame.number("tamp"),
        target_interval=ti,
        masker=masker,
        masker_amplitude_v=frame.number("mamp") if masker is not None else 0.0,
        stimulus_s=frame.number("stim"),
        gap_s=frame.number("gap"),
        lead_in_s=frame.number("lead"),
        n_intervals=n,
    )
    if plan.stimulus_s <= 0 or plan.gap_s < 0 or plan.lead_in_s < 0 or plan.duration_s > 60:
        raise ValueError("durations must be stim > 0, gap >= 0, lead >= 0, trial <= 60 s")
    return plan


def virtual_play(plan: TrialPlan, start_us: int, lateness: OnsetLateness) -> tuple[list[int], int]:
    """Onsets and end of a virtual-time trial, integer µs, exactly as the C firmware computes.

    Returns
    -------
    onsets_us : list[int]
        ``start + lead + k·(stim + gap)`` plus one lateness draw each, µs.
    end_us : int
        ``start + lead + n·stim + (n − 1)·gap``, µs.

    Examples
    --------
    A default 3IFC trial (0.6 s lead-in, 1.8 s intervals, 0.6 s gaps) starting at 1 s:

    >>> from masking_lab.core.stimulus import parse_stimulus
    >>> plan = TrialPlan(parse_stimulus("EV270"), 0.05, 2)
    >>> virtual_play(plan, 1_000_000, OnsetLateness(seed=42, max_us=0))
    ([1600000, 4000000, 6400000], 8200000)
    >>> virtual_play(plan, 1_000_000, OnsetLateness(seed=42, max_us=500))[0]
    [1600111, 4000101, 6400365]
    """
    lead, stim, gap = to_us(plan.lead_in_s), to_us(plan.stimulus_s), to_us(plan.gap_s)
    n = plan.n_intervals
    onsets = [start_us + lead + k * (stim + gap) + lateness.lateness_us() for k in range(n)]
    return onsets, start_us + lead + n * stim + (n - 1) * gap
