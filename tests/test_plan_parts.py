"""`plan`'s QUEST+ chunks split by sets into parts that run anywhere are the whole chunk, bit
for bit (the same random numbers, the same placements, the same rows)."""

from __future__ import annotations

import numpy as np
import pytest

from masking_lab.core.errors import ProcedureError
from masking_lab.planning.procedure_plan import (
    QUEST_PART_SETS,
    chunk_outcome,
    quest_chunk,
)
from masking_lab.procedures.quest_plus import QuestPlusSettings
from masking_lab.procedures.quest_plus_batch import simulate_quest_plus
from masking_lab.procedures.staircase_batch import Observer

# Small grids (a coarse level step, few nuisance points) keep this quick; the code paths are
# the shipped ones: the joint entropy (slope known) and the psi-marginal (slope, lapse unknown).
KNOWN = QuestPlusSettings(
    -20.0, 45.0, level_step_db=1.0, scales_db=(1.5,), lapses=(0.02,), target_sd_db=1.6,
    min_trials=10, max_trials=40,
)  # fmt: skip
MARGINAL = QuestPlusSettings(
    -20.0, 45.0, level_step_db=1.0, scales_db=(0.75, 1.5, 3.0), lapses=(0.0, 0.08),
    entropy_over="threshold", target_sd_db=1.6, min_trials=10, max_trials=40,
)  # fmt: skip
OBSERVER = Observer(scale_db=1.5, lapse=0.02)


def thresholds(n_sets: int, n: int) -> np.ndarray:
    return np.random.default_rng(7).normal(10.0, 6.0, (n_sets, n))


@pytest.mark.parametrize("own", [KNOWN, MARGINAL], ids=["joint", "psi-marginal"])
def test_parts_of_a_chunk_are_the_whole_chunk_bit_for_bit(own):
    thr = thresholds(7, 4)
    seed = np.random.SeedSequence([3, 0x9E57, 0])
    targets = (0.8, 1.6)
    whole = quest_chunk(own, targets, OBSERVER, thr, seed, (0, 7))
    parts = [quest_chunk(own, targets, OBSERVER, thr, seed, (a, b)) for a, b in ((0, 3), (3, 7))]
    joined = chunk_outcome(own, targets, parts)
    alone = chunk_outcome(own, targets, [whole])
    # An unsplit chunk reads its outcomes in the worker: the same as its traces read here.
    unsplit = quest_chunk(own, targets, OBSERVER, thr, seed)
    assert unsplit.keys() == alone.keys()
    for key in alone:
        for mine, theirs in zip(unsplit[key], alone[key], strict=True):
            np.testing.assert_array_equal(mine, theirs)
    assert joined.keys() == alone.keys() and len(joined) == 2 * len(targets)
    for key in alone:
        (code, n, est), (code_w, n_w, est_w) = joined[key], alone[key]
        np.testing.assert_array_equal(code, code_w)
        np.testing.assert_array_equal(n, n_w)
        # BLAS sums a row of a matrix-vector product in an order that can depend on how many
        # rows the product has, so a posterior mean may move by an ulp (never a printed digit).
        np.testing.assert_allclose(est, est_w, rtol=1e-13, atol=0)
        np.testing.assert_array_equal(np.isnan(est), np.isnan(est_w))
    # The traces themselves too, padded to the longest track of the chunk.
    width = whole.sd_db.shape[1]
    first = parts[0].sd_db
    assert first.shape[1] <= width
    np.testing.assert_allclose(first, whole.sd_db[: first.shape[0], : first.shape[1]], rtol=1e-13)


def test_a_part_answers_as_in_the_whole_run():
    thr = np.linspace(0.0, 20.0, 6)
    whole = simulate_quest_plus(KNOWN, thr, rng=np.random.default_rng(5))
    part = simulate_quest_plus(KNOWN, thr[2:5], rng=np.random.default_rng(5), part_of=(2, 6))
    n = part.n_trials
    np.testing.assert_array_equal(n, whole.n_trials[2:5])
    np.testing.assert_array_equal(part.correct, whole.correct[2:5, : part.correct.shape[1]])
    np.testing.assert_array_equal(part.levels_db, whole.levels_db[2:5, : part.levels_db.shape[1]])


def test_a_part_that_does_not_fit_its_run_is_refused():
    with pytest.raises(ProcedureError, match="part_of"):
        simulate_quest_plus(KNOWN, [1.0, 2.0], rng=np.random.default_rng(0), part_of=(5, 6))


def test_a_chunk_outcome_counts_an_unfinished_track_to_the_chunks_longest():
    # A track that never reached the target is read at the whole chunk's last column (as an
    # unsplit chunk reads it), whichever part it ran in.
    own = QuestPlusSettings(0.0, 20.0, target_sd_db=1.0, max_trials=3)
    short = np.array([[3.0, 2.0]])
    long = np.array([[3.0, 2.0, 0.5]])
    parts = [(np.full_like(short, 5.0), short), (np.full_like(long, 5.0), long)]
    from masking_lab.planning.procedure_plan import QuestPart

    out = chunk_outcome(own, [1.0], [QuestPart(*p) for p in parts])
    _, n, _ = out[(1.0, False)]
    assert n.tolist() == [3, 3]
    assert QUEST_PART_SETS >= 1


def test_per_set_rows_are_the_summaries_of_each_sets_sessions():
    # assemble_plan reads set j's sessions as a slice of the set-major rows; the same rows as
    # picking them out one by one by their set (and the ML fits' by their replicate).
    from masking_lab.formats.protocol import load_protocol
    from masking_lab.formats.resources import shipped
    from masking_lab.planning.parallel import run_tasks
    from masking_lab.planning.plan import assemble_plan, plan_tasks, summarize, trial_duration_s
    from masking_lab.planning.plan_chunks import ml_chunk, schedule_chunk
    from masking_lab.planning.settings import PlanSettings, Schedule, StopRule

    p = load_protocol(shipped("protocols", "baseline.yaml"))
    s = PlanSettings((StopRule(7, 4), StopRule(9, 6)), (Schedule((4.0, 2.0)),), replicates=12,
                     ml_replicates=5, max_reversals=10)  # fmt: skip
    thr = np.random.default_rng(4).normal(-30.0, 4.0, (4, 12))
    tasks = plan_tasks(p, s, thr)
    plan = assemble_plan(p, s, thr, run_tasks(tasks))
    (ml_fn, ml_args), (long_fn, long_args) = tasks
    assert ml_fn is ml_chunk and long_fn is schedule_chunk
    rules, _ = long_fn(*long_args)
    ml_al = ml_fn(*ml_args)
    n_sets, reps = thr.shape
    set_of_row = np.repeat(np.arange(n_sets), reps)
    replicate = np.tile(np.arange(reps), n_sets)
    trial_s = trial_duration_s(p.timing, s.response_s)
    rows = iter(plan.per_set)
    for i, _rule in enumerate(s.stop_rules):
        out = rules[i]
        for est in ("reversal_mean", "ml"):
            for j in range(n_sets):
                row = next(rows)
                assert row["estimator"] == est and row["set"] == p.sets[j].id
                mine = set_of_row == j
                if est == "ml":
                    mine &= replicate < s.ml_replicates
                    al = ml_al[i][set_of_row[replicate < s.ml_replicates] == j]
                else:
                    al = out.al_db[mine]
                cost = summarize(out.n_trials[set_of_row == j], out.status_code[set_of_row == j],
                                 None, thr.reshape(-1), trial_s)  # fmt: skip
                err = summarize(out.n_trials[mine], out.status_code[mine], al,
                                thr.reshape(-1)[mine], trial_s)  # fmt: skip
                for key, value in {**cost, **{k: err[k] for k in ("n_al", "bias_db", "sd_db",
                                                                  "rmse_db")}}.items():  # fmt: skip
                    assert row[key] == value or (np.isnan(row[key]) and np.isnan(value)), key
