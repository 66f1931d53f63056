"""The plan's second core: a call run in a forked worker gives what it gives in this process
(errors included), and the procedures comparison is the same from QUEST+ tracks simulated
elsewhere as from tracks simulated in turn."""

from __future__ import annotations

import numpy as np
import pytest

from masking_lab.planning.parallel import in_background, run_chunks


def _boom(text: str) -> None:
    raise ValueError(text)


def test_a_background_call_returns_its_result_and_raises_its_error():
    assert in_background(divmod, 17, 5).result() == (3, 2)
    with pytest.raises(ValueError, match="from the worker"):
        in_background(_boom, "from the worker").result()


def test_local_worker_processes_keep_the_order_of_the_chunks():
    assert run_chunks(pow, [(2, k) for k in range(6)], scheduler=None, max_workers=2) == [
        1,
        2,
        4,
        8,
        16,
        32,
    ]


def test_the_comparison_from_tracks_simulated_in_another_process_is_the_same():
    from masking_lab.formats.protocol import load_protocol
    from masking_lab.formats.resources import shipped
    from masking_lab.planning.procedure_plan import compare_procedures, quest_simulations
    from masking_lab.planning.settings import PlanSettings, Schedule, StopRule

    p = load_protocol(shipped("protocols", "experiment1_questplus.yaml"))
    s = PlanSettings((StopRule(11, 8),), (Schedule((4.0, 2.0)),), replicates=12, seed=4)
    thr = np.random.default_rng(1).normal(5.0, 2.0, (15, 12))
    here = compare_procedures(p, None, s, thr, quest_replicates=12)
    sims = in_background(quest_simulations, p, s, thr, quest_replicates=12).result()
    there = compare_procedures(p, None, s, thr, quest_replicates=12, simulations=sims)
    assert there.rows == here.rows and there.per_set == here.per_set
    assert [r["trials_mean"] for r in here.rows] and all(
        np.isfinite(r["trials_mean"]) for r in here.rows
    )


def test_a_plan_with_a_schedule_from_another_process_is_the_same():
    from masking_lab.formats.protocol import load_protocol
    from masking_lab.formats.resources import shipped
    from masking_lab.planning.plan import plan_schedule, run_plan
    from masking_lab.planning.settings import PlanSettings, Schedule, StopRule

    p = load_protocol(shipped("protocols", "baseline.yaml"))
    s = PlanSettings(
        (StopRule(7, 4), StopRule(11, 8)),
        (Schedule((4.0, 2.0)), Schedule((2.0,))),
        replicates=30,
        ml_replicates=10,
        max_reversals=12,
        seed=3,
    )
    thr = np.random.default_rng(2).normal(-30.0, 2.0, (4, 30))
    here = run_plan(p, s, thr)
    pending = in_background(plan_schedule, p, s, thr, 2)
    there = run_plan(p, s, thr, done={2: pending.result})
    assert there == here
    assert {r["schedule"] for r in here.table} == {"4,2", "2"}
