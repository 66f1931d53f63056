"""Pieces of the firmware emulator that are not about serving a port.

The output snapshot tests read, the state of a scheduled trial, the plan of a checked PLAY
(the checks themselves are in :mod:`masking_lab.device.emulator_checks`), the build id, and
the virtual-time
onset lateness generator, which is defined bit for bit in ``docs/device-protocol.md`` so the
emulator and the C firmware report the same onsets for the same seed.
"""

from __future__ import annotations

import functools
import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

from masking_lab.core import waveforms
from masking_lab.core.stimulus import Channel, Stimulus
from masking_lab.device.base import TrialPlan
from masking_lab.device.emulator_checks import ONE, CheckedPlay, Part

PRNG_SEED_MIX = 0x6D2B79F5
_MASK32 = 0xFFFFFFFF
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


def plan_of(play: CheckedPlay) -> TrialPlan:
    """The TrialPlan of a checked PLAY, amplitudes as played (quantised), for rendering.

    Parameters
    ----------
    play : CheckedPlay
        Fields in integer µs / µV / µHz that passed the firmware's checks and levels.

    Returns
    -------
    TrialPlan

    Examples
    --------
    >>> from masking_lab.device.emulator_checks import Part
    >>> play = CheckedPlay(Part("EV", 270_000_000, 0, 50_000, played_uv=48_828),
    ...                    None, 2, 3, 1_800_000, 600_000, 600_000, 0)
    >>> plan = plan_of(play)
    >>> plan.target.name, plan.target_amplitude_v, plan.duration_s
    ('EV270', 0.048828, 7.2)
    """
    return _plan(play.target, play.masker, play.ti, play.n, play.stim_us, play.gap_us, play.lead_us)


# Pure in the checked fields but the start time; a staircase revisits levels, so most PLAYs of a
# session build a plan an earlier one built (TrialPlan and its stimuli are frozen: shared).
@functools.lru_cache(maxsize=1024)
def _plan(
    target: Part, m: Part | None, ti: int, n: int, stim_us: int, gap_us: int, lead_us: int
) -> TrialPlan:
    def stim(part: Part) -> Stimulus:
        env = part.envelope_uhz / ONE or None
        return Stimulus(part.channel, part.carrier_uhz / ONE, env)

    return TrialPlan(
        target=stim(target),
        target_amplitude_v=target.played_uv / ONE,
        target_interval=ti,
        masker=stim(m) if m is not None else None,
        masker_amplitude_v=m.played_uv / ONE if m is not None else 0.0,
        stimulus_s=stim_us / ONE,
        gap_s=gap_us / ONE,
        lead_in_s=lead_us / ONE,
        n_intervals=n,
    )


def render_trial(
    plan: TrialPlan, sample_rate_hz: float, ramp_s: float, overdrive: float = 1.0
) -> dict[Channel, tuple[float, float]]:
    """Render a trial like the output stage: per channel (largest |sample|, last sample), V.

    Each tone peaks at its played (quantised) amplitude; ``overdrive`` scales every sample
    afterwards (fault injection for the per-sample limit check). A stimulus under 3 samples
    is silent, as in the firmware. (The firmware scales each tone by its closed-form peak
    bound rather than the sampled peak, so its samples are never larger than these.)

    Examples
    --------
    >>> from masking_lab.core.stimulus import parse_stimulus
    >>> plan = TrialPlan(parse_stimulus("EV270"), 0.5, 1, stimulus_s=0.05, n_intervals=1)
    >>> render_trial(plan, 10_000.0, 0.002)["EV"]
    (0.5, 0.0)
    """
    out: dict[Channel, tuple[float, float]] = {"EV": (0.0, 0.0), "MV": (0.0, 0.0)}
    if round(plan.stimulus_s * sample_rate_hz) + 1 < 3:
        return out
    bufs = waveforms.trial_buffers(plan, sample_rate_hz, ramp_s=ramp_s)
    for ch in out:
        samples = bufs.channel(ch) * overdrive
        if len(samples):
            out[ch] = (float(abs(samples).max()), float(samples[-1]))
    return out


def build_hash(root: Path | None = None) -> str:
    """The firmware build id HELLO reports: 12 hex digits of SHA-256 over the host build's sources.

    The emulator is the twin of the host build, so it reports the host build's ``FW_BUILD``, by
    the Makefile's recipe: the bytes of ``firmware/core/*.c *.h`` and ``firmware/host/*.c *.h
    *.ld``, in byte-wise sorted path order (relative to ``firmware/``), concatenated.
    ``root`` holds ``firmware/``; by default the checkout's, else the copy a plain install
    ships as ``masking_lab/firmware`` (core and host board). ``000000000000`` when the sources
    are not found.

    Examples
    --------
    >>> len(build_hash()), build_hash(Path("/nonexistent"))
    (12, '000000000000')
    """
    if root is None:
        here = Path(__file__).resolve()
        root = next(
            (r for r in (here.parents[2], here.parents[1]) if (r / "firmware" / "core").is_dir()),
            here.parents[2],
        )
    firmware = root / "firmware"
    wanted = {"core": (".c", ".h"), "host": (".c", ".h", ".ld")}
    files = [
        p
        for folder, suffixes in wanted.items()
        if (firmware / folder).is_dir()
        for p in (firmware / folder).iterdir()
        if p.suffix in suffixes and p.is_file()
    ]
    if not files:
        return "000000000000"
    digest = hashlib.sha256()
    for path in sorted(files, key=lambda p: p.relative_to(firmware).as_posix().encode()):
        digest.update(path.read_bytes())
    return digest.hexdigest()[:12]


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
