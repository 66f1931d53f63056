"""Which set plays the next trial of an interleaved session (pure).

With ``order: {interleave: true}`` every set of the session runs at once, as PsychoPy's
MultiStairHandler does: each trial comes from a set drawn at random among those still running.
The draw is keyed by (session seed, the session's trial count so far), so a resumed session,
whose trial count and running sets are rebuilt by replaying the log, draws exactly what an
uninterrupted one would.
"""

from __future__ import annotations

from collections.abc import Sequence

from masking_lab.core.seeding import trial_rng

#: The per-trial random stream of the interleaving draw (independent of the others).
STREAM_INTERLEAVE = "interleave"
_SESSION_KEY = "(interleaved session)"


def next_set(seed: int, session_trial_index: int, running: Sequence[str]) -> str:
    """The set that plays trial ``session_trial_index`` (0-based, counted over all sets).

    Parameters
    ----------
    seed : int
        The session seed (≥ 0).
    session_trial_index : int
        Trials the session has run so far, over all sets.
    running : sequence of str
        Ids of the sets still running, in the session's set order.

    Returns
    -------
    str
        One of ``running``, each equally likely.

    Raises
    ------
    ValueError
        If no set is running.

    Examples
    --------
    >>> next_set(1, 0, ["a", "b", "c"]) == next_set(1, 0, ["a", "b", "c"])
    True
    >>> next_set(1, 5, ["only"])
    'only'
    """
    if not running:
        raise ValueError("no set is running; the interleaved session has finished")
    rng = trial_rng(seed, _SESSION_KEY, session_trial_index, STREAM_INTERLEAVE)
    return running[int(rng.integers(0, len(running)))]
