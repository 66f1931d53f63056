"""The QUEST+ placement: the level of least expected entropy, the psi-marginal one screened in
float32 and settled in float64.

The psi-marginal's expected entropy (:func:`~masking_lab.procedures.quest_plus_model.
expected_entropy`) needs, per track and level, the joint probability of each answer and each
threshold: two (T × N) · (N × S) products and 2·T·S logarithms per trial, 131 × 28 × 131 on the
shipped grid. Only the level with the least entropy matters, and usually no other level comes
close. So :func:`best_levels`

1. computes every level's entropy in float32 (single-precision products and logarithms, half
   the memory traffic of float64) together with a bound on its error (:func:`screen`),
2. keeps the levels whose lower bound is below the least upper bound, one or a few per track:
   the level of least float64 entropy is always among them,
3. computes those levels' entropies in float64, term by term as the full computation does, and
   returns the least (the lowest level of equal ones, as :func:`numpy.argmin` does).

The result is the argmin of the float64 entropies, not an approximation of it: two levels
whose float64 entropies differ by less than their rounding (~1e-15 nats) may come out either
way, as they already do between a batch of tracks and one track alone (BLAS sums a product's
row in an order that depends on the number of rows).

The error bound (nats): a float32 product of N positive terms, each rounded once on input, is
within (N + 4)·u of the exact sum (u = 2⁻²⁴, any summation order); ln in float32 is within 4
ulp (8·u) of ln; so each m·ln m is within (N + 14)·u·m·(|ln m| + 1) of its exact value and each
p·ln p within (N + 14)·u·p·(|ln p| + 1). Summed over thresholds and answers, with m ≤ 1, that is
(N + 14)·u · Σ_answers (H_answer + p + p·(|ln p| + 1)), H = −Σ m·ln m, computed from the
float32 values themselves; :data:`SAFETY` doubles it. Posterior and table cells below
:data:`FLUSH` are set to 0 before the products, so every product is 0 or at least FLUSH² (far
above float32's subnormal range, slow on x86) and so is every m: an m of 0 adds nothing to
either sum, and no m needs clamping before its logarithm. The change those cells make,
≤ N·FLUSH per m, is added as an absolute term. Each
track's tails (at most :data:`TAIL`/4 of its mass on either side) are left out, which spares a
fifth of the thresholds late in a track; leaving out mass D changes the entropy by at most
D·(ln 2T − ln D) + D·(max |ln p| + 1), also added.
"""

from __future__ import annotations

import functools
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from masking_lab.procedures.fused import COMPILED_FROM, compiled_loops
from masking_lab.procedures.quest_plus_model import EntropyOver, expected_entropy, xlogx

if TYPE_CHECKING:
    from masking_lab.procedures.quest_plus import Tables

__all__ = ["FLUSH", "SAFETY", "TAIL", "best_levels", "screen"]

#: Posterior and likelihood cells below this are 0 in the float32 screen: a product of two
#: cells is then 0 or above 1e-36, never subnormal (float32's normal range ends at 1.2e-38).
FLUSH = 1e-18
#: Posterior mass of a track's two tails that the screen may leave out (its thresholds' share
#: of the bound, ~3e-7 nats, is a hundredth of the rounding's).
TAIL = 1e-8
#: Factor on the screen's error bound (the bound holds at 1; measured errors are ~30× below it).
SAFETY = 2.0
#: Tracks per float32 screen pass (sorted by posterior mean, so that they share dead tails).
#: ``plan`` places 40 tracks at a time (a psi-marginal set's part): in one pass they took
#: ~10 % less CPU than as passes of 32 and 8 (the same levels; bench_commands.py --only plan).
_TRACKS_PER_PASS = 48
#: Thresholds per block of a pass: its two (block, tracks, 2S) float32 buffers take ≤ 0.8 MB.
_THRESHOLDS_PER_BLOCK = 8
_U32 = 2.0**-24
#: Below ln(FLUSH²) ≈ -82.9, the logarithm of every m that is not 0: m·max(ln m, this) is
#: m·ln m, and 0 (not NaN) where m is 0.
_LOG_FLOOR = np.float32(-1e30)
_TINY64 = 1e-300


def best_levels(
    t: Tables, posterior: NDArray[np.float64], entropy_over: EntropyOver = "threshold"
) -> NDArray[np.intp]:
    """Index of the level of least expected posterior entropy, per track.

    Parameters
    ----------
    t : Tables
        From :func:`masking_lab.procedures.quest_plus.tables`.
    posterior : ndarray, shape (R, T, N)
        Current posteriors of R tracks (each summing to 1).
    entropy_over : {"threshold", "all"}
        The threshold's marginal entropy (psi-marginal; screened in float32, settled in
        float64) or the joint one (two matrix products: computed in float64 directly).

    Returns
    -------
    ndarray of intp, shape (R,)
        Indices into ``t.levels_db``: ``argmin(expected_entropy(t, posterior, entropy_over),
        axis=1)`` (to the rounding of the float64 entropies).

    Examples
    --------
    >>> from masking_lab.procedures.quest_plus import QuestPlusSettings, tables
    >>> t = tables(QuestPlusSettings(0.0, 20.0, max_trials=5))
    >>> post = t.prior * t.p_correct[30]          # one correct answer at 15 dB
    >>> post = (post / post.sum())[None]
    >>> bool(best_levels(t, post)[0] == np.argmin(expected_entropy(t, post)[0]))
    True
    """
    r, n_t, n_n = posterior.shape
    if n_n == 1 or entropy_over == "all":
        return np.argmin(expected_entropy(t, posterior, entropy_over), axis=1)
    if r <= _TRACKS_PER_PASS:
        return _place(t, posterior, use_compiled=r >= COMPILED_FROM)
    out = np.empty(r, dtype=np.intp)
    # Tracks with nearby posteriors share a pass, so that the thresholds they all rule out
    # (which a pass skips) are many.
    order = np.argsort(posterior.sum(axis=2) @ np.arange(n_t), kind="stable")
    for a in range(0, r, _TRACKS_PER_PASS):
        rows = order[a : a + _TRACKS_PER_PASS]
        out[rows] = _place(t, posterior[rows])
    return out


def _place(
    t: Tables, posterior: NDArray[np.float64], *, use_compiled: bool = True
) -> NDArray[np.intp]:
    """:func:`best_levels` of one pass: screen every level, settle the ones left."""
    low, high = screen(t, posterior, use_compiled=use_compiled)
    keep = low <= high.min(axis=1)[:, None]
    return _settle(t, posterior, keep, use_compiled=use_compiled)


def screen(
    t: Tables, posterior: NDArray[np.float64], *, use_compiled: bool = True
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Lower and upper bounds of each level's psi-marginal expected entropy, from float32.

    Parameters
    ----------
    t : Tables
        From :func:`masking_lab.procedures.quest_plus.tables`.
    posterior : ndarray, shape (R, T, N)
        Current posteriors (float64, each summing to 1).
    use_compiled : bool
        False forces the numpy route for the column sums (the tests compare the two).

    Returns
    -------
    low, high : ndarray, shape (R, S)
        Bounds (nats) that hold the float64 :func:`expected_entropy` of every level.

    Examples
    --------
    >>> from masking_lab.procedures.quest_plus import QuestPlusSettings, tables
    >>> t = tables(QuestPlusSettings(0.0, 20.0, max_trials=5))
    >>> low, high = screen(t, t.prior[None])
    >>> exact = expected_entropy(t, t.prior[None])
    >>> bool(np.all((low <= exact) & (exact <= high)))
    True
    """
    r, n_t, n_n = posterior.shape
    n_s = t.levels_db.size
    both = _float32_tables(t)  # (T, N, 2S): p(correct) then p(wrong)
    loops = compiled_loops("psi_loops") if use_compiled else None
    p32, lo, hi = _float32_posterior(posterior, loops)
    pk = np.zeros((r, 2 * n_s))
    h = np.zeros((r, 2 * n_s))
    # A block of thresholds at a time: its joint probabilities and their logarithms stay in
    # cache from the product to the sums (the whole (T, R, 2S) array would not).
    block = np.empty((min(_THRESHOLDS_PER_BLOCK, hi - lo), r, 2 * n_s), dtype=np.float32)
    log_m = np.empty_like(block)
    # Each m is 0 or normal (see FLUSH): ln 0 = -inf, taken as 0·ln 0 = 0 in the sums.
    with np.errstate(divide="ignore"):  # once: entering it per block cost 6 % of the screen
        for a in range(lo, hi, _THRESHOLDS_PER_BLOCK):
            b = min(a + _THRESHOLDS_PER_BLOCK, hi)
            m, lm = block[: b - a], log_m[: b - a]
            np.matmul(p32[a:b], both[a:b], out=m)
            np.log(m, out=lm)
            if loops is not None:
                loops.add_column_sums(m, lm, pk, h)
            else:
                np.maximum(lm, _LOG_FLOOR, out=lm)
                pk += m.sum(axis=0, dtype=np.float64)
                h += np.multiply(m, lm, dtype=np.float64).sum(axis=0)
    rel = (n_n + 14) * _U32
    flushed = n_n * FLUSH
    floor = 8 * n_t * flushed * (1.0 - np.log(flushed)) + 1e-12
    # The tails left out (mass D ≤ TAIL/2 + rounding < TAIL): their cells' −Σ m·ln m is at most
    # D·(ln 2T − ln D), and each answer's p·ln p moves by at most δ·(|ln p| + 1), Σ δ = D.
    tail = TAIL * (np.log(2 * n_t) - np.log(TAIL) + 1.01)
    if loops is not None:
        low, high = np.empty((r, n_s)), np.empty((r, n_s))
        loops.entropy_bounds(pk, h, rel, floor, tail, TAIL, SAFETY, low, high)
        return low, high
    # An answer that no m reaches (p = 0) adds 0·ln 0 = 0.
    log_pk = np.log(np.maximum(pk, _TINY64))
    terms = pk * log_pk
    entropy = terms[:, :n_s] + terms[:, n_s:] - h[:, :n_s] - h[:, n_s:]
    spread = -h + pk * (2.0 - log_pk)
    spread = spread[:, :n_s] + spread[:, n_s:]
    worst_log = np.maximum(np.abs(log_pk[:, :n_s]), np.abs(log_pk[:, n_s:]))
    spread = SAFETY * (rel * spread + floor + tail + TAIL * worst_log)
    return entropy - spread, entropy + spread


def _float32_posterior(
    posterior: NDArray[np.float64], loops: ModuleType | None
) -> tuple[NDArray[np.float32], int, int]:
    """The posteriors the screen multiplies, shape (T, R, N), float32, and the span (first,
    stop) of the thresholds it needs (where some track's value is not 0).

    Each track leaves out its tails' thresholds (at most :data:`TAIL`/4 of its mass each side,
    about a fifth of the span late in a track) and its cells below :data:`FLUSH`; both changes
    are in :func:`screen`'s bound.
    """
    r, n_t, n_n = posterior.shape
    if loops is not None:
        p32 = np.empty((n_t, r, n_n), dtype=np.float32)
        lo, hi = loops.trimmed_float32(np.ascontiguousarray(posterior), FLUSH, TAIL / 4, p32)
    else:
        p32 = np.ascontiguousarray(posterior.transpose(1, 0, 2), dtype=np.float32)
        p32[p32 < FLUSH] = 0.0
        mass = posterior.sum(axis=2)  # (R, T)
        tails = np.cumsum(mass, axis=1) <= TAIL / 4
        tails |= np.cumsum(mass[:, ::-1], axis=1)[:, ::-1] <= TAIL / 4
        p32[tails.T] = 0.0
        live = np.flatnonzero(p32.reshape(n_t, -1).any(axis=1))
        lo, hi = (int(live[0]), int(live[-1]) + 1) if live.size else (0, 0)
    return (p32, lo, hi) if hi > lo else (p32, 0, 1)


@functools.lru_cache(maxsize=8)
def _float32_tables(t: Tables) -> NDArray[np.float32]:
    """p(correct) and p(wrong) side by side, shape (T, N, 2S), float32, cells below
    :data:`FLUSH` set to 0."""
    a = np.concatenate([t.p_correct.transpose(1, 2, 0), t.p_wrong.transpose(1, 2, 0)], axis=2)
    a = np.ascontiguousarray(a, dtype=np.float32)
    a[a < FLUSH] = 0.0
    a.flags.writeable = False
    return a


def _settle(
    t: Tables,
    posterior: NDArray[np.float64],
    keep: NDArray[np.bool_],
    *,
    use_compiled: bool = True,
) -> NDArray[np.intp]:
    """Per track, the kept level of least float64 entropy (``keep``: (R, S), ≥ 1 per row)."""
    best = np.argmax(keep, axis=1)  # the only kept level, where there is one
    count = keep.sum(axis=1)
    several = np.flatnonzero(count > 1)
    if several.size:
        local, levels = np.nonzero(keep[several])
        entropy = pair_entropies(t, posterior, several[local], levels, use_compiled=use_compiled)
        full = np.full((several.size, keep.shape[1]), np.inf)
        full[local, levels] = entropy
        best[several] = np.argmin(full, axis=1)
    lost = np.flatnonzero(count == 0)  # only if a bound were NaN; never seen, still handled
    if lost.size:
        best[lost] = np.argmin(expected_entropy(t, posterior[lost]), axis=1)
    return best


def pair_entropies(
    t: Tables,
    posterior: NDArray[np.float64],
    rows: NDArray[np.intp],
    levels: NDArray[np.intp],
    *,
    use_compiled: bool = True,
) -> NDArray[np.float64]:
    """Psi-marginal expected entropy (nats, float64) of track ``rows[k]`` at level ``levels[k]``.

    The terms of :func:`expected_entropy` for the given (track, level) pairs only.

    Examples
    --------
    >>> from masking_lab.procedures.quest_plus import QuestPlusSettings, tables
    >>> t = tables(QuestPlusSettings(0.0, 20.0, max_trials=5))
    >>> e = pair_entropies(t, t.prior[None], np.array([0, 0]), np.array([3, 20]))
    >>> np.allclose(e, expected_entropy(t, t.prior[None])[0, [3, 20]], rtol=1e-13, atol=0)
    True
    """
    loops = compiled_loops("psi_loops") if use_compiled else None
    post = np.ascontiguousarray(posterior)
    out = np.zeros(rows.size)
    if loops is not None:
        loops.pair_entropies(post, t.p_correct, t.p_wrong, rows, levels, out)
        return out
    for like in (t.p_correct, t.p_wrong):
        m = np.einsum("ktn,ktn->kt", post[rows], like[levels])
        out += xlogx(m.sum(axis=1)) - xlogx(m).sum(axis=1)
    return out
