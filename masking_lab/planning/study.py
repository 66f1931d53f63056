"""The speed–accuracy study of docs/speed-accuracy.md: its simulations, tables and figures.

    masking-lab study --out study_out

1. Convergence (Levitt 1971; García-Pérez 1998): long 1-up-3-down tracks against an observer
   whose 0.794 point is 0 dB, for up steps from ¼ to 8 psychometric scales, with equal steps and
   with García-Pérez's 2AFC down/up ratio 0.7393, in 3IFC (guess 1/3, this project's task) and
   in 2AFC (guess 1/2, his); where does the reversal mean settle, in p(correct)?
2. Stop rules, step schedules, down/up ratios and estimators on the paper's experiment I
   (:mod:`masking_lab.planning.plan`): trials, minutes, bias and SD; which setting reaches the
   precision of the paper's 11/8 rule in the fewest trials; how many reversals ±1 dB takes.
3. Procedures (:mod:`masking_lab.planning.procedure_plan`): the staircase settings and QUEST+
   (and, with ``psi``, the psi-marginal) on the same observers, each rated against the
   Cramér-Rao bound; the fewest trials for ±1 dB across procedures.

:func:`regenerate` writes CSV tables, PNG figures (stable bytes) and the document's generated
blocks (``blocks/NAME.md``, Markdown) into ``out`` and nothing else; the computations are pure
functions of their arguments and the seed. The command line is :mod:`masking_lab.commands.study`;
``python docs/generate.py study`` (outside the package) runs it into docs/study/ and pastes the
blocks into docs/speed-accuracy.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from masking_lab.formats.protocol import load_protocol
from masking_lab.formats.resources import shipped
from masking_lab.planning.parallel import Task, chunk_plan, run_tasks
from masking_lab.planning.plan import (
    ESTIMATOR_LABELS,
    GARCIA_PEREZ_RATIO,
    PlanResult,
    PlanSettings,
    Schedule,
    StopRule,
    run_plan,
    true_thresholds_db,
)
from masking_lab.planning.procedure_plan import ProcedureComparison, compare_procedures
from masking_lab.planning.procedure_report import format_fewest
from masking_lab.planning.report import rows_to_csv
from masking_lab.procedures.staircase import StaircaseSettings, implied_target_p
from masking_lab.procedures.staircase_batch import Observer, simulate
from masking_lab.simulation.observer import load_ground_truth

#: Tracks in one chunk of the convergence study (a worker holds their trial-by-trial levels).
CONVERGENCE_CHUNK = 500
STEP_OVER_SCALE = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
STUDY_RULES = ((7, 4), (9, 6), (11, 8), (13, 10), (15, 12))
STUDY_SCHEDULES = ((4.0, 4.0, 4.0, 2.0), (4.0, 2.0), (2.0,))
STUDY_RATIOS = (1.0, GARCIA_PEREZ_RATIO)
#: Guess rates of the convergence study: 3IFC (this project's task) and 2AFC (García-Pérez's).
STUDY_GUESSES = (1.0 / 3.0, 0.5)
#: Generated blocks of the study document (``blocks/NAME.md`` in the output folder).
BLOCKS = ("meta", "convergence", "settings", "answer", "procedures")


# --------------------------------------------------------------------------------------------
# 1. Convergence


def convergence_study(
    step_over_scale: Sequence[float] = STEP_OVER_SCALE,
    ratios: Sequence[float] = STUDY_RATIOS,
    *,
    scale_db: float = 1.5,
    lapse: float = 0.0,
    guess: float = 1.0 / 3.0,
    n_reversals: int = 60,
    n_averaged: int = 48,
    replicates: int = 2000,
    seed: int = 0,
    scheduler: str | None = "synchronous",
) -> list[dict]:
    """Where 1-up-3-down tracks settle, by step size and down/up ratio.

    The tracks run in chunks of :data:`CONVERGENCE_CHUNK` (each with its own seed, the same
    seeds for every step and ratio) wherever ``scheduler`` says
    (:func:`masking_lab.planning.parallel.run_chunks`); the rows do not depend on where.

    The observer guesses with probability ``guess`` (1/3: 3IFC; 1/2: 2AFC, the task of
    García-Pérez's simulations). Each track starts at the observer's 0.794 point (0 dB), runs
    without bounds or cap for
    ``n_reversals`` reversals and averages the last ``n_averaged``; the mean of those ALs over
    replicates is mapped through the observer's psychometric function to p(correct).

    Returns
    -------
    list of dict
        Per (ratio, step): ``step_over_scale``, ``up_step_db``, ``down_up_ratio``,
        ``target_p`` (:func:`~masking_lab.procedures.staircase.implied_target_p`), ``al_mean_db``
        and
        ``al_se_db`` (mean AL and its standard error, dB re the 0.794 point), ``p_converged``
        with ``p_low``/``p_high`` (95 % interval), ``p_trials`` (mean p(correct) over the trials
        from the first averaged reversal on), ``step_over_width`` (up step over the 10–90 % width
        2·ln 9·scale), ``trials_median``, ``completed``, ``guess``.
    """
    observer = Observer(scale_db=scale_db, lapse=lapse, guess=guess)
    psy = observer.psychometric
    chunks = chunk_plan(seed, replicates, CONVERGENCE_CHUNK)
    grid = [(ratio, k) for ratio in ratios for k in step_over_scale]
    tasks: list[Task] = []
    for ratio, k in grid:
        sc = StaircaseSettings(
            start_level_db=0.0,
            step_sizes_db=(k * scale_db,),
            down_up_ratio=ratio,
            n_reversals=n_reversals,
            n_reversals_averaged=n_averaged,
            max_trials=None,
        )
        tasks += [(convergence_chunk, (sc, observer, n, seq)) for n, seq in chunks]
    results = run_tasks(tasks, scheduler=scheduler)
    rows = []
    for g, (ratio, k) in enumerate(grid):
        parts = results[g * len(chunks) : (g + 1) * len(chunks)]
        al, n_trials, done = (np.concatenate([p[i] for p in parts]) for i in range(3))
        p_trials = float(sum(p[3] for p in parts) / sum(p[4] for p in parts))
        mean = float(al.mean())
        se = float(al.std(ddof=1) / math.sqrt(al.size))
        p = psy.p_correct([mean, mean - 1.96 * se, mean + 1.96 * se])
        sc = tasks[g * len(chunks)][1][0]
        rows.append(
            {
                "step_over_scale": float(k),
                "up_step_db": float(k * scale_db),
                "step_over_width": float(k / (2.0 * math.log(9.0))),
                "down_up_ratio": float(ratio),
                "target_p": implied_target_p(sc),
                "al_mean_db": mean,
                "al_se_db": se,
                "p_converged": float(p[0]),
                "p_low": float(p[1]),
                "p_high": float(p[2]),
                "p_trials": p_trials,
                "trials_median": float(np.median(n_trials)),
                "completed": float(np.mean(done)),
                "guess": float(guess),
            }
        )
    return rows


def convergence_chunk(
    settings: StaircaseSettings,
    observer: Observer,
    replicates: int,
    seed: np.random.SeedSequence,
) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.bool_], float, int]:
    """One chunk of :func:`convergence_study`'s tracks (their observer's 0.794 point at 0 dB).

    Returns
    -------
    tuple
        The completed tracks' ALs (dB), every track's trials and whether it completed, and
        the sum and count of p(correct) over the trials from each completed track's first
        averaged reversal on.

    Examples
    --------
    >>> sc = StaircaseSettings(0.0, step_sizes_db=(1.5,), n_reversals=12, n_reversals_averaged=8)
    >>> al, n, done, p_sum, count = convergence_chunk(sc, Observer(1.5, 0.0), 20,
    ...                                               np.random.SeedSequence(0))
    >>> al.shape, bool(done.all()), 0.6 < p_sum / count < 0.95
    ((20,), True, True)
    """
    tracks = simulate(
        settings,
        np.zeros(replicates),
        observer,
        np.random.default_rng(seed),
        trial_limit=100 * settings.n_reversals,
    )
    done = tracks.completed
    # The track itself, not just its reversals: p(correct) over the trials from the first
    # averaged reversal on (the percent correct the track settles at).
    first = tracks.reversal_trials[done, settings.n_reversals - settings.n_reversals_averaged]
    levels = tracks.levels_db[done]
    cols = np.arange(levels.shape[1])[None, :]
    keep = (cols >= first[:, None]) & ~np.isnan(levels)
    p = observer.psychometric.p_correct(levels[keep])
    return tracks.al_db[done], tracks.n_trials, done, float(p.sum()), int(p.size)


# --------------------------------------------------------------------------------------------
# 2. Settings on experiment I


def settings_study(
    protocol_path: str | Path | None = None,
    *,
    replicates: int = 2000,
    ml_replicates: int = 500,
    seed: int = 0,
    max_reversals: int = 41,
    progress=None,
    scheduler: str | None = "synchronous",
) -> PlanResult:
    """:func:`masking_lab.planning.plan.run_plan` on experiment I with the study's grid,
    its chunks run wherever ``scheduler`` says."""
    path = protocol_path or shipped("protocols", "experiment1.yaml")
    protocol = load_protocol(str(path))
    truth = load_ground_truth()
    settings = PlanSettings(
        stop_rules=tuple(StopRule(a, b) for a, b in STUDY_RULES),
        schedules=tuple(Schedule(s, r) for s in STUDY_SCHEDULES for r in STUDY_RATIOS),
        observer=Observer(truth.scale_db, truth.lapse, truth.guess),
        replicates=replicates,
        ml_replicates=ml_replicates,
        max_reversals=max_reversals,
        seed=seed,
    )
    thresholds = true_thresholds_db(
        protocol, truth, replicates, np.random.default_rng(np.random.SeedSequence([seed, 0x7412]))
    )
    return run_plan(protocol, settings, thresholds, progress=progress, scheduler=scheduler)


@dataclass(frozen=True)
class Cheapest:
    """The settings that match the reference's RMSE in the fewest median trials.

    Attributes
    ----------
    reference : dict
        The protocol's own setting with the reversal mean.
    best : dict
        Fewest trials over every estimator.
    best_reversal_mean : dict
        Fewest trials with the reversal mean.
    candidates : int
        Settings that qualify.
    """

    reference: dict
    best: dict
    best_reversal_mean: dict
    candidates: int


def cheapest_matching(result: PlanResult) -> Cheapest:
    """Among table rows (both estimators) and ladder rungs (reversal mean) whose sessions
    complete (≥ 99 %), the fewest median trials with a pooled RMSE (bias and spread together)
    no worse than the protocol's own setting with the reversal mean; ties go to the smaller
    RMSE."""
    ref = next(r for r in result.table if r.get("own") and r["estimator"] == "reversal_mean")
    pool = [r for r in (*result.table, *result.ladder) if r.get("completed", 0) >= 0.99]
    ok = [r for r in pool if r["rmse_db"] <= ref["rmse_db"]]

    def key(r: dict) -> tuple[float, float]:
        return (r["trials_median"], r["rmse_db"])

    best = min(ok, key=key)
    best_rm = min((r for r in ok if r["estimator"] == "reversal_mean"), key=key)
    return Cheapest(ref, best, best_rm, len(ok))


# --------------------------------------------------------------------------------------------
# Text blocks for the document


def _sched(row: dict) -> str:
    return row["schedule"] + (
        "" if row["down_up_ratio"] == 1.0 else f", d/u {row['down_up_ratio']:g}"
    )


def _task(guess: float) -> str:
    return {round(1 / 3, 6): "3IFC", 0.5: "2AFC"}.get(round(guess, 6), f"guess {guess:.3g}")


def convergence_block(rows: Sequence[dict]) -> str:
    lines = [
        "| task | up step / scale | up step (dB) | down/up | target p | reversal-mean AL − 0.794 "
        "point (dB) | p(correct) at that AL (95 % CI) | mean p(correct) over the trials | "
        "trials (median) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {_task(r.get('guess', 1 / 3))} | {r['step_over_scale']:g} | {r['up_step_db']:g} "
            f"| {r['down_up_ratio']:g} | "
            f"{r['target_p']:.4f} | {r['al_mean_db']:+.3f} ± {1.96 * r['al_se_db']:.3f} | "
            f"{r['p_converged']:.3f} ({r['p_low']:.3f}–{r['p_high']:.3f}) | "
            f"{r['p_trials']:.3f} | {r['trials_median']:.0f} |"
        )
    return "\n".join(lines)


def settings_block(result: PlanResult) -> str:
    z = result.settings.z
    lines = [
        "| schedule (dB) | rule | estimator | trials median (p90) | minutes median (p90) | "
        f"bias (dB) | SD (dB) | RMSE (dB) | ±{z:g}·SD, worst set (dB) |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in result.table:
        own = " **(paper)**" if r.get("own") else ""
        lines.append(
            f"| {_sched(r)} | {r['rule']}{own} | {ESTIMATOR_LABELS[r['estimator']]} | "
            f"{r['trials_median']:.0f} ({r['trials_p90']:.0f}) | "
            f"{r['minutes_median']:.1f} ({r['minutes_p90']:.1f}) | {r['bias_db']:+.2f} | "
            f"{r['sd_db']:.2f} | {r['rmse_db']:.2f} | {z * r['worst_sd_db']:.2f} |"
        )
    return "\n".join(lines)


def answer_block(result: PlanResult, cheapest: Cheapest) -> str:
    ref, best = cheapest.reference, cheapest.best
    s = result.settings
    lines = [
        f"- The paper's setting (steps {ref['schedule']} dB, 11/8, reversal mean) gives a pooled "
        f"RMSE of {ref['rmse_db']:.2f} dB (bias {ref['bias_db']:+.2f} dB, SD {ref['sd_db']:.2f} "
        f"dB) in {ref['trials_median']:.0f} trials ({ref['minutes_median']:.1f} min) per set.",
        (
            f"- No setting reaches that precision (RMSE ≤ {ref['rmse_db']:.2f} dB) in fewer trials."
            if best is ref
            else f"- Fewest trials for that precision (RMSE ≤ {ref['rmse_db']:.2f} dB; "
            f"{cheapest.candidates} settings qualify): steps {_sched(best)} dB, stop rule "
            f"{best['rule']}, {ESTIMATOR_LABELS[best['estimator']]}: RMSE {best['rmse_db']:.2f} "
            f"dB in {best['trials_median']:.0f} trials ({best['minutes_median']:.1f} min), "
            f"{ref['trials_median'] - best['trials_median']:.0f} trials fewer."
        ),
        (
            "- With the reversal mean, no setting in the grid or on the reversal ladders reaches "
            "that RMSE in fewer trials than the paper's own."
            if cheapest.best_reversal_mean is ref
            else f"- With the reversal mean only: steps {_sched(cheapest.best_reversal_mean)} dB, "
            f"stop rule {cheapest.best_reversal_mean['rule']}: RMSE "
            f"{cheapest.best_reversal_mean['rmse_db']:.2f} dB in "
            f"{cheapest.best_reversal_mean['trials_median']:.0f} trials "
            f"({cheapest.best_reversal_mean['minutes_median']:.1f} min)."
        ),
    ]
    for a in result.answers:
        sched = a.schedule
        name = ",".join(f"{v:g}" for v in sched.step_sizes_db) + (
            "" if sched.down_up_ratio == 1.0 else f", d/u {sched.down_up_ratio:g}"
        )
        if a.rule is None or a.row is None:
            lines.append(
                f"- ±{s.precision_db:g} dB ({s.z:g}·SD in the worst set), steps {name} dB: not "
                f"reached by {s.max_reversals} reversals (±{a.best['half_width_db']:.2f} dB there)."
            )
        else:
            lines.append(
                f"- ±{s.precision_db:g} dB ({s.z:g}·SD in the worst set), steps {name} dB: "
                f"{a.rule.label}, {a.row['trials_median']:.0f} trials "
                f"({a.row['minutes_median']:.1f} min) per set"
                + (
                    f"; the protocol's {result.max_trials}-trial cap would stop "
                    f"{100 * a.capped_by_protocol:.0f} % of those sessions first."
                    if result.max_trials is not None
                    else "."
                )
            )
    return "\n".join(lines)


def meta_block(
    replicates: int, ml_replicates: int, seed: int, quest_replicates: int = 0, psi: bool = False
) -> str:
    quest = (
        f", {quest_replicates} QUEST+ tracks per set" + (" and as many psi-marginal" if psi else "")
        if quest_replicates
        else ""
    )
    return (
        f"Generated by `python docs/generate.py study"
        f"{' --psi' if psi else ''}` ({replicates} sessions per set and setting, {ml_replicates} "
        f"of them ML-fitted{quest}, seed {seed})."
    )


def procedures_block(comparison: ProcedureComparison) -> str:
    """The procedures table (Markdown) and the fewest-trials answers."""
    lines = [
        "| procedure | setting | estimator | trials median (p90, mean) | minutes median | "
        "bias (dB) | SD (dB) | RMSE (dB) | CR trials | efficiency |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in comparison.rows:
        if not r.get("capped", True) or not math.isfinite(r.get("sd_db", math.nan)):
            continue
        own = " **(protocol)**" if r.get("own") else ""
        lines.append(
            f"| {r['procedure']} | {r['setting']}{own} | "
            f"{ESTIMATOR_LABELS.get(r['estimator'], r['estimator'].replace('_', ' '))} | "
            f"{r['trials_median']:.0f} ({r['trials_p90']:.0f}, {r['trials_mean']:.1f}) | "
            f"{r['minutes_median']:.1f} | {r['bias_db']:+.2f} | {r['sd_db']:.2f} | "
            f"{r['rmse_db']:.2f} | {r['cr_trials']:.1f} | {r['efficiency']:.0%} |"
        )
    head, *answers = format_fewest(comparison).splitlines()
    return "\n".join([*lines, "", head, "", *(f"- {a.strip()}" for a in answers)])


def regenerate(
    out: Path,
    *,
    replicates: int = 2000,
    ml_replicates: int = 500,
    convergence_replicates: int = 2000,
    max_reversals: int = 41,
    quest_replicates: int = 400,
    psi: bool = False,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
    scheduler: str | None = "synchronous",
) -> dict[str, str]:
    """Run the study; write its tables, figures and generated blocks into ``out``.

    Its simulations run in chunks wherever ``scheduler`` says
    (:func:`masking_lab.planning.parallel.run_chunks`): the same bytes on any.

    Returns
    -------
    dict[str, str]
        The generated blocks (Markdown) by name (:data:`BLOCKS`), as written to
        ``out/blocks/NAME.md``.
    """
    from masking_lab.formats.fileio import write_bytes_atomic, write_text_atomic
    from masking_lab.planning.figures import convergence, png_bytes, speed_accuracy
    from masking_lab.planning.procedure_report import procedures_figure

    say = progress or (lambda _msg: None)
    say("convergence by step size (3IFC and 2AFC)")
    conv = [
        row
        for guess in STUDY_GUESSES
        for row in convergence_study(
            replicates=convergence_replicates, seed=seed, guess=guess, scheduler=scheduler
        )
    ]
    levitt = implied_target_p(StaircaseSettings(0.0))
    gp = implied_target_p(StaircaseSettings(0.0, down_up_ratio=GARCIA_PEREZ_RATIO))
    write_text_atomic(out / "convergence.csv", rows_to_csv(conv))
    write_bytes_atomic(
        out / "convergence.png",
        png_bytes(
            convergence(
                [r for r in conv if r["guess"] < 0.4],
                levitt,
                gp,
                title="1-up 3-down (3IFC): where the reversal mean settles",
            )
        ),
    )
    write_bytes_atomic(
        out / "convergence_2afc.png",
        png_bytes(
            convergence(
                [r for r in conv if r["guess"] >= 0.4],
                levitt,
                gp,
                title="1-up 3-down (2AFC): where the reversal mean settles",
            )
        ),
    )

    say("settings on experiment I")
    result = settings_study(
        replicates=replicates,
        ml_replicates=ml_replicates,
        seed=seed,
        max_reversals=max_reversals,
        progress=say,
        scheduler=scheduler,
    )
    write_text_atomic(out / "settings.csv", rows_to_csv(result.table))
    write_text_atomic(out / "ladder.csv", rows_to_csv(result.ladder))
    write_bytes_atomic(
        out / "speed_accuracy.png",
        png_bytes(speed_accuracy(result, title="Experiment I: speed against accuracy")),
    )
    cheapest = cheapest_matching(result)
    blocks = {
        "meta": meta_block(replicates, ml_replicates, seed, quest_replicates, psi),
        "convergence": convergence_block(conv),
        "settings": settings_block(result),
        "answer": answer_block(result, cheapest),
        "procedures": "(not run: quest replicates 0)",
    }
    if quest_replicates:
        say("procedures against the Cramér-Rao bound")
        comparison = procedures_study(
            result,
            quest_replicates=quest_replicates,
            psi=psi,
            seed=seed,
            progress=say,
            scheduler=scheduler,
        )
        write_text_atomic(out / "procedures.csv", rows_to_csv(comparison.rows))
        write_bytes_atomic(
            out / "procedures.png",
            png_bytes(
                procedures_figure(comparison, title="Experiment I: procedures against the bound")
            ),
        )
        blocks["procedures"] = procedures_block(comparison)
    for name, text in blocks.items():
        write_text_atomic(out / "blocks" / f"{name}.md", text.rstrip() + "\n")
    say(f"wrote {out}/")
    return blocks


def procedures_study(
    staircase: PlanResult,
    *,
    quest_replicates: int = 400,
    psi: bool = False,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
    scheduler: str | None = "synchronous",
) -> ProcedureComparison:
    """QUEST+ (shipped experiment1_questplus.yaml) beside the staircase settings of
    :func:`settings_study`, observers drawn from the same population and seed."""
    protocol = load_protocol(str(shipped("protocols", "experiment1_questplus.yaml")))
    truth = load_ground_truth()
    reps = max(quest_replicates, 2)
    thresholds = true_thresholds_db(
        protocol, truth, reps, np.random.default_rng(np.random.SeedSequence([seed, 0x7412]))
    )
    return compare_procedures(
        protocol,
        staircase,
        staircase.settings,
        thresholds,
        quest_replicates=reps,
        psi=psi,
        progress=progress,
        scheduler=scheduler,
    )
