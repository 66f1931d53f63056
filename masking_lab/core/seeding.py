"""Per-trial random streams: the same (session seed, set, trial, stream), the same draws.

A resumed session must draw exactly what an uninterrupted one would, so every random choice of
a trial comes from its own generator keyed by stable hashes, never from a shared or global one.
"""

from __future__ import annotations

import functools
import hashlib

import numpy as np

__all__ = ["STREAM_RESPONDER", "STREAM_TARGET_INTERVAL", "draw_target_interval", "trial_rng"]

# Streams of per-trial randomness; each has its own generator so that adding one never shifts
# another (a resumed session must draw the same target intervals and simulated answers).
STREAM_TARGET_INTERVAL = "target_interval"
STREAM_RESPONDER = "responder"


def trial_rng(seed: int, set_id: str, trial_index: int, stream: str) -> np.random.Generator:
    """A generator for one (session seed, set, trial, stream): the same inputs, the same draws.

    Parameters
    ----------
    seed : int
        The session seed (≥ 0, logged in the header).
    set_id : str
        Set identifier.
    trial_index : int
        0-based trial index within the set.
    stream : str
        What the draws are for (``STREAM_TARGET_INTERVAL``, ``STREAM_RESPONDER``).

    Returns
    -------
    numpy.random.Generator
        A fresh generator; equal inputs give equal draws in any process.

    Raises
    ------
    ValueError
        If ``seed`` or ``trial_index`` is negative.

    Examples
    --------
    >>> a = trial_rng(7, "A", 0, STREAM_RESPONDER).integers(0, 100, 3)
    >>> b = trial_rng(7, "A", 0, STREAM_RESPONDER).integers(0, 100, 3)
    >>> bool((a == b).all())
    True
    """
    if seed < 0 or trial_index < 0:
        raise ValueError(f"seed and trial_index must be ≥ 0, got {seed}, {trial_index}")
    # The key [seed, key(set_id), trial_index, key(stream)] given as the uint32 words numpy's
    # SeedSequence would split it into: the same entropy pool and draws, and a third less time
    # (numpy coerces a list of Python ints word by word; this runs twice per simulated trial).
    words = [*_words(int(seed)), *_key_words(set_id), *_words(int(trial_index))]
    words += _key_words(stream)
    entropy = np.array(words, dtype=np.uint32)
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(entropy)))


def draw_target_interval(seed: int, set_id: str, trial_index: int, n_intervals: int = 3) -> int:
    """The interval (1 … ``n_intervals``) that carries the target in this trial.

    Parameters
    ----------
    seed : int
        The session seed (≥ 0).
    set_id : str
        Set identifier.
    trial_index : int
        0-based trial index within the set.
    n_intervals : int
        Intervals per trial (3 for 3IFC).

    Returns
    -------
    int
        The target interval, 1-based.

    Examples
    --------
    >>> draws = [draw_target_interval(7, "A", i) for i in range(200)]
    >>> sorted(set(draws))
    [1, 2, 3]
    >>> draws[:5] == [draw_target_interval(7, "A", i) for i in range(5)]
    True
    """
    rng = trial_rng(seed, set_id, trial_index, STREAM_TARGET_INTERVAL)
    return int(rng.integers(1, n_intervals + 1))


def _words(n: int) -> list[int]:
    """``n`` ≥ 0 as little-endian uint32 words, as numpy's SeedSequence splits an integer."""
    if n < 1 << 32:
        return [n]
    out = []
    while n > 0:
        out.append(n & 0xFFFFFFFF)
        n >>= 32
    return out


@functools.lru_cache(maxsize=1024)
def _key_words(text: str) -> tuple[int, ...]:
    return tuple(_words(_stable_key(text)))


def _stable_key(text: str) -> int:
    # Python's hash() is salted per process; a resumed session needs the same number.
    return int.from_bytes(hashlib.sha256(text.encode("utf-8")).digest()[:8], "little")
