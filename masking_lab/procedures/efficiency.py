"""How close each procedure comes to the Cramér-Rao bound, by simulation.

:func:`compare` runs the paper's 1-up-3-down staircase (steps 4,4,4,2 dB, 11 reversals, mean of
the last 8, start 20 dB) and QUEST+ (slope known) and psi-marginal (slope unknown) tracks
against the same simulated observers, and reports for each the trials used, the SD and bias of
its threshold estimates, and its efficiency: the Cramér-Rao trials for the SD it achieved
(:mod:`masking_lab.procedures.fisher`) divided by the trials it used.

:func:`report` formats the table of docs/procedures.md (``python docs/generate.py efficiency``
prints it; command-line options live in ``masking-lab plan`` and ``masking-lab study``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from masking_lab.core.masking import ramp
from masking_lab.procedures.fisher import cramer_rao_trials, efficiency, max_information
from masking_lab.procedures.quest_plus import QuestPlusSettings
from masking_lab.procedures.quest_plus_batch import simulate_quest_plus
from masking_lab.procedures.staircase import StaircaseSettings
from masking_lab.procedures.staircase_batch import Observer, simulate

#: Experiment I's 15 masked ALs (dB SL): EV270 under MV120/180/270 at 5–25 dB SL, from the
#: ramps of protocols/simulation/ground_truth.yaml (least-squares fits to the paper's Table 2).
#: Copied here because procedures/ may not read protocol files (imports point toward core/).
EXPERIMENT1_RAMPS = ((-7.442, 0.711), (-5.927, 0.658), (-2.240, 0.602))
EXPERIMENT1_MASKER_DB_SL = (5.0, 10.0, 15.0, 20.0, 25.0)

#: The psi-marginal's slope grid: logistic scales from a third to four times the default 1.5 dB.
PSI_SCALES_DB = tuple(float(v) for v in np.round(np.geomspace(0.5, 6.0, 10), 3))

PAPER_STAIRCASE = StaircaseSettings(
    20.0, step_sizes_db=(4.0, 4.0, 4.0, 2.0), min_level_db=-20.0, max_level_db=45.0, max_trials=150
)


def experiment1_thresholds_db() -> NDArray[np.float64]:
    """The 15 masked ALs of experiment I's sets, dB SL.

    Examples
    --------
    >>> experiment1_thresholds_db().round(1)[:5].tolist()
    [0.0, 0.0, 3.2, 6.8, 10.3]
    """
    x = np.asarray(EXPERIMENT1_MASKER_DB_SL)
    return np.concatenate([ramp(x, a, b) for a, b in EXPERIMENT1_RAMPS])


@dataclass(frozen=True)
class EfficiencyRow:
    """One procedure's speed and precision against the bound.

    Attributes
    ----------
    procedure : str
        What ran (and its stop rule).
    trials_median, trials_mean, trials_p90 : float
        Trials per track.
    sd_db : float
        SD of (estimate − true threshold), root-mean-square over the true thresholds, dB.
    bias_db : float
        Mean of (estimate − true threshold), dB.
    cr_trials : float
        Trials the Cramér-Rao bound needs for ``sd_db``.
    efficiency : float
        ``cr_trials / trials_mean``.
    """

    procedure: str
    trials_median: float
    trials_mean: float
    trials_p90: float
    sd_db: float
    bias_db: float
    cr_trials: float
    efficiency: float


def _row(
    name: str, n: NDArray, err: NDArray, groups: NDArray, model: dict[str, float]
) -> EfficiencyRow:
    ok = np.isfinite(err) & np.isfinite(n)
    sds = [float(np.std(err[ok & (groups == g)])) for g in np.unique(groups)]
    sd = math.sqrt(float(np.mean(np.square(sds))))
    n_ok = n[ok]
    return EfficiencyRow(
        name,
        float(np.median(n_ok)),
        float(np.mean(n_ok)),
        float(np.percentile(n_ok, 90)),
        sd,
        float(np.mean(err[ok])),
        float(cramer_rao_trials(sd, **model)),
        float(efficiency(sd, float(np.mean(n_ok)), **model)),
    )


def compare(
    true_thresholds_db: Sequence[float] | NDArray[np.float64],
    n_per_threshold: int,
    rng: np.random.Generator,
    *,
    scale_db: float = 1.5,
    lapse: float = 0.02,
    targets_sd_db: Sequence[float] = (1.08, 0.5),
    psi_scales_db: Sequence[float] = PSI_SCALES_DB,
    psi: bool = True,
) -> list[EfficiencyRow]:
    """Simulate each procedure on the same observers and rate it against the bound.

    Parameters
    ----------
    true_thresholds_db : sequence of float
        The thresholds simulated (each ``n_per_threshold`` times), dB.
    n_per_threshold : int
        Tracks per threshold.
    rng : numpy.random.Generator
        Source of every answer.
    scale_db, lapse : float
        The observers' logistic scale (dB) and lapse rate (3IFC: guess 1/3).
    targets_sd_db : sequence of float
        Posterior-SD stop rules for the Bayesian procedures, dB.
    psi_scales_db : sequence of float
        Scale grid the psi-marginal marginalises over, dB.
    psi : bool
        Include the psi-marginal (the slowest to simulate).

    Returns
    -------
    list of EfficiencyRow

    Examples
    --------
    >>> rows = compare([5.0], 20, np.random.default_rng(0), targets_sd_db=(1.5,), psi=False)
    >>> [r.procedure.split(",")[0] for r in rows]
    ['staircase 11/8', 'QUEST+ (slope known)']
    """
    thr = np.repeat(np.asarray(true_thresholds_db, dtype=float), n_per_threshold)
    groups = np.repeat(np.arange(len(true_thresholds_db)), n_per_threshold)
    model = {"scale_db": scale_db, "lapse": lapse}
    sc = simulate(PAPER_STAIRCASE, thr, Observer(scale_db, lapse), rng, store_levels=False)
    rows = [
        _row(
            "staircase 11/8, steps 4,4,4,2 dB",
            np.where(sc.completed, sc.n_trials, np.nan),
            sc.al_db - thr,
            groups,
            model,
        )
    ]
    strictest = min(targets_sd_db)
    kinds: list[tuple[str, tuple[float, ...]]] = [("QUEST+ (slope known)", (scale_db,))]
    if psi:
        kinds.append(("psi-marginal (slope unknown)", tuple(psi_scales_db)))
    for name, scales in kinds:
        s = QuestPlusSettings(
            -20.0, 45.0, scales_db=scales, lapses=(lapse,), target_sd_db=strictest, max_trials=400
        )
        sim = simulate_quest_plus(s, thr, scale_db=scale_db, lapse=lapse, rng=rng)
        for target in targets_sd_db:
            n = sim.trials_to_sd(target)
            rows.append(_row(f"{name}, SD ≤ {target:g} dB", n, sim.mean_at(n) - thr, groups, model))
    return rows


def format_table(rows: Sequence[EfficiencyRow], *, scale_db: float, lapse: float) -> str:
    """The rows as a Markdown table, preceded by the bound's numbers."""
    info, p, offset = max_information(scale_db=scale_db, lapse=lapse)
    lines = [
        f"Fisher information peaks at {info:.4f} dB^-2 at p(correct) = {p:.3f} "
        f"({offset:+.2f} dB re the 0.794 point); Cramér-Rao: "
        f"{float(cramer_rao_trials(1.08, scale_db=scale_db, lapse=lapse)):.1f} trials for SD "
        f"1.08 dB, {float(cramer_rao_trials(0.5, scale_db=scale_db, lapse=lapse)):.1f} for 0.5 dB.",
        "",
        "| procedure | trials median (mean, p90) | SD (dB) | bias (dB) | CR trials | efficiency |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r.procedure} | {r.trials_median:.0f} ({r.trials_mean:.1f}, {r.trials_p90:.0f}) "
            f"| {r.sd_db:.2f} | {r.bias_db:+.2f} | {r.cr_trials:.1f} | {r.efficiency:.0%} |"
        )
    return "\n".join(lines)


def report(
    per_set: int = 134,
    seed: int = 0,
    *,
    scale_db: float = 1.5,
    lapse: float = 0.02,
    psi: bool = True,
) -> str:
    """The efficiency table of docs/procedures.md (``psi=False`` skips the slow psi-marginal).

    ``python docs/generate.py efficiency`` prints it with the defaults; ``masking-lab study``
    and ``masking-lab plan`` give the same comparison for any protocol.
    """
    rows = compare(
        experiment1_thresholds_db(),
        per_set,
        np.random.default_rng(seed),
        scale_db=scale_db,
        lapse=lapse,
        psi=psi,
    )
    return format_table(rows, scale_db=scale_db, lapse=lapse)
