"""What a procedure's settings may ask for so that a session that validates also runs (pure).

Bayesian procedures keep likelihood tables over grids; a grid fine enough to need gigabytes is
refused when the protocol is read, not when the first set starts. Every track also has a finite
trial cap: a protocol that gives none gets :data:`DEFAULT_BAYES_TRIAL_CAP` (Bayesian kinds) or
25 trials per reversal (the staircase), shown in ``validate``'s summary. A whole session is
bounded too: at most :data:`MAX_SESSION_TRIALS` trials over its sets' caps, and at most
:data:`MAX_SESSION_WORK` table cells visited over all its trials (the placement of each trial
of a Bayesian track scans its whole table), so that what ``validate`` accepts also runs in the
simulator in seconds.

Units: grid steps and ranges in dB, memory in bytes.
"""

from __future__ import annotations

import math

__all__ = [
    "DEFAULT_BAYES_TRIAL_CAP",
    "MAX_GRID_BYTES",
    "MAX_SESSION_TRIALS",
    "MAX_SESSION_WORK",
    "MAX_TABLE_ELEMENTS",
    "grid_memory_problem",
    "grid_points",
    "grid_top",
    "normal_prior_problem",
    "session_work_problem",
    "trial_work",
]

#: Trial cap of a Bayesian track whose protocol gives none (QUEST+ at the paper's precision
#: takes ~30 trials, psi-marginal ~55; a track at 500 has not converged and ends as trial_cap).
DEFAULT_BAYES_TRIAL_CAP = 500

#: Largest likelihood table (stimuli × parameter points) a procedure may build. Two float64
#: tables (p(correct), p(wrong)) of this size take 256 MiB; the placement's work arrays are
#: chunked separately and stay below ~50 MB.
MAX_TABLE_ELEMENTS = 16_000_000

#: Bytes of the tables at :data:`MAX_TABLE_ELEMENTS` (stated in messages).
MAX_GRID_BYTES = 2 * 8 * MAX_TABLE_ELEMENTS

#: Most trials a session's sets may take together (sum of their trial caps): at 3 s per trial
#: over 8 hours of a participant's time, more than any lab session; the shipped protocols
#: need at most 2,250.
MAX_SESSION_TRIALS = 10_000

#: Most table cells a session's trial placements may visit (sum over sets of trial cap ×
#: :func:`trial_work`): about 12 s of one core for QUEST+ (measured ~12 ns per cell and trial);
#: the shipped QUEST+ and functional protocols need 2e7 and 1.2e8.
MAX_SESSION_WORK = 1_000_000_000

# Cells visited per table cell and trial, by procedure kind: the functional procedure's
# placement costs about an eighth of QUEST+'s per cell (measured, 3.7e6 cells: 1.6 ns against
# ~12 ns), the staircase has no table.
_WORK_PER_CELL = {"quest_plus": 1.0, "functional_ramp": 0.125}


def grid_points(lo: float, hi: float, step: float) -> int:
    """Points of the grid lo, lo + step, … ≤ hi, without building it (0 if empty or invalid).

    Examples
    --------
    >>> grid_points(-20.0, 45.0, 0.5)
    131
    >>> grid_points(0.0, 1.0, 1e-300) > 10**200
    True
    """
    if not (math.isfinite(lo) and math.isfinite(hi) and step > 0 and hi >= lo):
        return 0
    n = (hi - lo) / step
    return int(n + 1e-9) + 1 if math.isfinite(n) else 10**308


def grid_top(lo: float, step: float, limit: float) -> float:
    """The highest point of the grid lo, lo + step, … at or below ``limit`` (dB, rounded to
    1e-9 dB so that it stays the decimal number a protocol writes).

    Examples
    --------
    >>> grid_top(-10.0, 1.0, 22.7)
    22.0
    """
    return round(lo + step * math.floor((limit - lo) / step + 1e-9), 9)


def grid_memory_problem(elements: int, what: str) -> str | None:
    """Why a table of ``elements`` float64 cells is refused (beyond :data:`MAX_TABLE_ELEMENTS`),
    or None.

    Examples
    --------
    >>> grid_memory_problem(131 * 131, "QUEST+ grid") is None
    True
    >>> grid_memory_problem(10**9, "QUEST+ grid")[:40]
    'the QUEST+ grid needs 1e+09 table cells '
    """
    if elements <= MAX_TABLE_ELEMENTS:
        return None
    gib = 2 * 8 * elements / 2**30
    size = f"{gib:.3g} GiB" if gib < 1e6 else "far more memory than any machine has"
    return (
        f"the {what} needs {elements:.3g} table cells ({size}); the limit is "
        f"{MAX_TABLE_ELEMENTS:.3g} cells ({MAX_GRID_BYTES / 2**20:.0f} MiB): use coarser "
        "steps, narrower ranges or fewer nuisance values"
    )


def normal_prior_problem(
    mean_db: float, sd_db: float, lo_db: float, hi_db: float, step_db: float
) -> tuple[str, str] | None:
    """(key, why) for a normal prior the grid cannot hold, or None: its mean outside the grid,
    or an SD below half a grid step (a point mass the grid cannot represent).

    Examples
    --------
    >>> normal_prior_problem(5.0, 3.0, -20.0, 45.0, 0.5) is None
    True
    >>> normal_prior_problem(500.0, 3.0, -20.0, 45.0, 0.5)[0]
    'prior_mean_db'
    >>> normal_prior_problem(5.0, 1e-300, -20.0, 45.0, 0.5)[0]
    'prior_sd_db'
    """
    if not lo_db <= mean_db <= hi_db:
        return (
            "prior_mean_db",
            f"{mean_db:g} dB lies outside the threshold grid ({lo_db:g}..{hi_db:g} dB); a "
            "prior must put its mass where the grid can hold it: move the mean or widen the grid",
        )
    if not sd_db >= step_db / 2:
        return (
            "prior_sd_db",
            f"{sd_db:g} dB is below half the threshold grid step ({step_db:g} dB): the grid "
            "cannot represent so narrow a prior; widen it or use a finer threshold_step_db",
        )
    return None


def trial_work(settings: object) -> int:
    """Table cells one trial's placement visits for a procedure's ``settings`` (0: no table).

    Examples
    --------
    >>> from masking_lab.procedures.quest_plus import QuestPlusSettings
    >>> trial_work(QuestPlusSettings(-20.0, 45.0, scales_db=1.5, lapses=0.02))
    17161
    >>> trial_work(QuestPlusSettings(-20.0, 45.0))  # 7 scales × 4 lapses marginalised
    480508
    """
    cells = getattr(settings, "table_cells", 0)
    weight = _WORK_PER_CELL.get(str(getattr(settings, "kind", "")), 1.0)
    return int(cells * weight) if isinstance(cells, int) else 0


def session_work_problem(caps: list[tuple[int, int]]) -> str | None:
    """Why a session of sets with these (trial cap, :func:`trial_work`) pairs is refused, or
    None: more than :data:`MAX_SESSION_TRIALS` trials, or more than :data:`MAX_SESSION_WORK`
    table cells visited.

    Examples
    --------
    >>> session_work_problem([(150, 0)] * 15) is None
    True
    >>> session_work_problem([(5000, 0)] * 3)[:44]
    'its 3 sets may take up to 15000 trials; the '
    >>> session_work_problem([(5000, 10**7)])[:38]
    'its sets may visit up to 5e+10 table c'
    """
    trials = sum(cap for cap, _ in caps)
    if trials > MAX_SESSION_TRIALS:
        return (
            f"its {len(caps)} sets may take up to {trials} trials; the limit is "
            f"{MAX_SESSION_TRIALS} per session: give lower max_trials (or n_reversals), or "
            "split the sets over several protocols"
        )
    work = sum(cap * cells for cap, cells in caps)
    if work > MAX_SESSION_WORK:
        return (
            f"its sets may visit up to {work:.3g} table cells in placing their trials (trial "
            f"cap × grid cells, summed over sets); the limit is {MAX_SESSION_WORK:.3g} per "
            "session: use coarser steps, narrower ranges, fewer nuisance values or lower "
            "max_trials"
        )
    return None
