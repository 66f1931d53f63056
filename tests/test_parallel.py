"""Simulations that scale out: `plan` and `study` give the same bytes whether their chunks run
in this process (`--scheduler synchronous`), on forked worker processes (`local`, the default)
or on a real two-process Dask cluster (`distributed.LocalCluster`), and a scheduler address
that answers nothing, or is no address, is refused with a message naming the option."""

from __future__ import annotations

import socket
from pathlib import Path

import numpy as np
import pytest

from masking_lab.commands.cli import main as cli_main
from masking_lab.formats.resources import shipped
from masking_lab.planning import parallel
from masking_lab.planning.parallel import chunk_plan, run_chunks, run_tasks, started_tasks

# Few replicates, cut into several chunks each (the shipped chunk sizes would make one).
PLAN_ARGS = [
    "--replicates", "24", "--ml-replicates", "8", "--quest-replicates", "6",
    "--max-reversals", "13", "--stop-rules", "7/4,11/8", "--seed", "5", "--no-progress",
]  # fmt: skip
STUDY_ARGS = [
    "--replicates", "6", "--ml-replicates", "4", "--convergence-replicates", "12",
    "--max-reversals", "15", "--quest-replicates", "4", "--seed", "2", "--no-progress",
]  # fmt: skip


@pytest.fixture
def small_chunks(monkeypatch):
    """Chunk sizes that cut the tests' few replicates into several chunks."""
    from masking_lab.planning import plan_chunks, procedure_plan, study

    monkeypatch.setattr(plan_chunks, "CHUNK_REPLICATES", 10)
    monkeypatch.setattr(plan_chunks, "ML_CHUNK_REPLICATES", 3)
    monkeypatch.setattr(procedure_plan, "QUEST_CHUNK_REPLICATES", 4)
    monkeypatch.setattr(study, "CONVERGENCE_CHUNK", 5)


@pytest.fixture(scope="module")
def cluster():
    """A real Dask cluster of two worker processes, one thread each."""
    import distributed  # a runtime dependency (dask[distributed]): never skipped

    with distributed.LocalCluster(
        n_workers=2, processes=True, threads_per_worker=1, dashboard_address=None
    ) as c:
        yield c


def _files(folder: Path) -> dict[str, bytes]:
    return {
        p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()
    }


def _plan(tmp_path: Path, name: str, scheduler: str) -> dict[str, bytes]:
    out = tmp_path / name
    protocol = str(shipped("protocols", "baseline.yaml"))
    argv = ["plan", protocol, *PLAN_ARGS, "--out", str(out), "--scheduler", scheduler]
    assert cli_main(argv) == 0
    return _files(out)


def _study(tmp_path: Path, name: str, scheduler: str) -> dict[str, bytes]:
    out = tmp_path / name
    assert cli_main(["study", *STUDY_ARGS, "--out", str(out), "--scheduler", scheduler]) == 0
    return _files(out)


def test_chunks_cover_the_replicates_and_their_seeds_depend_on_the_seed_only():
    plan = chunk_plan(7, 23, 10)
    assert [n for n, _ in plan] == [10, 10, 3]
    again = chunk_plan(7, 23, 10)
    states = [s.generate_state(2).tolist() for _, s in plan]
    assert states == [s.generate_state(2).tolist() for _, s in again]
    assert len({tuple(s) for s in states}) == 3  # every chunk a stream of its own
    assert states != [s.generate_state(2).tolist() for _, s in chunk_plan(8, 23, 10)]
    with pytest.raises(ValueError, match="≥ 1"):
        chunk_plan(0, 0, 10)


def test_local_worker_processes_keep_the_order_of_the_chunks():
    assert run_chunks(pow, [(2, k) for k in range(6)], scheduler="local", max_workers=2) == [
        1,
        2,
        4,
        8,
        16,
        32,
    ]
    assert run_tasks([(divmod, (17, 5)), (pow, (3, 2))], scheduler="local") == [(3, 2), 9]


@pytest.mark.parametrize("scheduler", ["synchronous", "local"])
def test_started_tasks_hand_back_each_result_when_waited_for_in_any_order(scheduler):
    tasks = [(pow, (2, k)) for k in range(5)]
    with started_tasks(tasks, scheduler=scheduler) as results:
        late = results.wait(3, 5)  # the last ones first: plan reads the staircase's early
        early = results.wait(0, 3)
        again = results.wait(1, 2)
        with pytest.raises(IndexError, match="not among the 5"):
            results.wait(4, 6)
    assert early + late == run_tasks(tasks) == [1, 2, 4, 8, 16]
    assert again == [2]


def test_a_failing_task_raises_where_its_result_is_waited_for():
    tasks = [(pow, (2, 1)), (divmod, (1, 0))]
    with pytest.raises(ZeroDivisionError), started_tasks(tasks, scheduler="local") as results:
        assert results.wait(0, 1) == [2]
        results.wait(1, 2)


def test_synchronous_tasks_run_in_this_process_only_when_wanted():
    calls = []
    with started_tasks([(calls.append, (k,)) for k in range(3)]) as results:
        results.wait(1, 2)
        assert calls == [1]
        results.wait(1, 3)
    assert calls == [1, 2]


def test_plan_tables_are_the_same_in_process_on_local_workers_and_on_a_dask_cluster(
    tmp_path, small_chunks, cluster
):
    here = _plan(tmp_path, "sync", "synchronous")
    assert {"plan_table.csv", "plan_procedures.csv", "plan_ladder.csv"} <= set(here)
    assert _plan(tmp_path, "local", "local") == here
    assert _plan(tmp_path, "dask", cluster.scheduler_address) == here
    # The chunks matter: a different seed gives different tables.
    other = tmp_path / "seed6"
    protocol = str(shipped("protocols", "baseline.yaml"))
    argv = ["plan", protocol, *PLAN_ARGS, "--seed", "6", "--out", str(other)]
    assert cli_main(argv) == 0
    assert _files(other)["plan_table.csv"] != here["plan_table.csv"]


def test_study_files_are_the_same_in_process_on_local_workers_and_on_a_dask_cluster(
    tmp_path, small_chunks, cluster
):
    here = _study(tmp_path, "sync", "synchronous")
    assert {"settings.csv", "convergence.csv", "procedures.csv"} <= set(here)
    assert _study(tmp_path, "local", "local") == here
    assert _study(tmp_path, "dask", cluster.scheduler_address) == here


def test_a_scene_plan_is_the_same_in_process_on_local_workers_and_on_a_dask_cluster(
    tmp_path, monkeypatch, cluster
):
    """`plan --scene` simulates each function's participants in seeded chunks too."""
    from masking_lab.planning import scene_budget

    monkeypatch.setattr(scene_budget, "PARTICIPANTS_PER_CHUNK", 2)
    scene = str(shipped("protocols", "scenes/bump_rough.yaml"))
    quick = ["--tracks", "5", "--studies", "10", "--participants", "2,4", "--trials", "12"]

    def scene_plan(name: str, scheduler: str, seed: str = "3") -> dict[str, bytes]:
        out = tmp_path / name
        argv = ["plan", "--scene", scene, *quick, "--seed", seed, "--out", str(out)]
        assert cli_main([*argv, "--scheduler", scheduler]) == 0
        return _files(out)

    here = scene_plan("sync", "synchronous")
    assert any(name.endswith(".csv") for name in here)
    assert scene_plan("local", "local") == here
    assert scene_plan("dask", cluster.scheduler_address) == here
    assert scene_plan("seed4", "synchronous", seed="4") != here


def test_the_plan_is_the_same_whatever_the_number_of_workers(small_chunks):
    from masking_lab.formats.protocol import load_protocol
    from masking_lab.planning.plan import run_plan
    from masking_lab.planning.settings import PlanSettings, Schedule, StopRule

    p = load_protocol(shipped("protocols", "baseline.yaml"))
    s = PlanSettings(
        (StopRule(7, 4), StopRule(11, 8)),
        (Schedule((4.0, 2.0)), Schedule((2.0,))),
        replicates=30,
        ml_replicates=9,
        max_reversals=12,
        seed=3,
    )
    thr = np.random.default_rng(2).normal(-30.0, 2.0, (4, 30))
    here = run_plan(p, s, thr)
    assert run_plan(p, s, thr, scheduler="local") == here
    assert {r["schedule"] for r in here.table} == {"4,2", "2"}
    assert all(np.isfinite(r["sd_db"]) for r in here.table)


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("command", ["plan", "study"])
def test_a_scheduler_that_does_not_answer_is_named_in_a_clear_error(
    tmp_path, monkeypatch, capsys, command
):
    monkeypatch.setattr(parallel, "CONNECT_TIMEOUT_S", 1.0)
    address = f"tcp://127.0.0.1:{_closed_port()}"
    if command == "plan":
        argv = ["plan", str(shipped("protocols", "baseline.yaml")), *PLAN_ARGS]
    else:
        argv = ["study", *STUDY_ARGS]
    assert cli_main([*argv, "--out", str(tmp_path / "o"), "--scheduler", address]) == 2
    err = capsys.readouterr().err
    assert f"--scheduler {address}: no Dask scheduler answered" in err
    assert "--scheduler local" in err and "Traceback" not in err


@pytest.mark.parametrize("command", ["plan", "study"])
def test_a_scheduler_that_is_no_address_is_a_usage_error(tmp_path, capsys, command):
    argv = [command, *([str(shipped("protocols", "baseline.yaml"))] if command == "plan" else [])]
    with pytest.raises(SystemExit) as exc:
        cli_main([*argv, "--out", str(tmp_path / "o"), "--scheduler", "10.0.0.5:8786"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--scheduler" in err and "tcp://host:8786" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_chunk_results_that_do_not_match_the_chunks_are_refused():
    from masking_lab.core.errors import AnalysisError
    from masking_lab.formats.protocol import load_protocol
    from masking_lab.planning.plan import assemble_plan, plan_tasks
    from masking_lab.planning.procedure_plan import compare_procedures
    from masking_lab.planning.settings import PlanSettings, Schedule, StopRule

    p = load_protocol(shipped("protocols", "baseline.yaml"))
    s = PlanSettings((StopRule(7, 4),), (Schedule((2.0,)),), replicates=4, ml_replicates=0,
                     max_reversals=8)  # fmt: skip
    thr = np.full((4, 4), -30.0)
    results = run_tasks(plan_tasks(p, s, thr))
    assert assemble_plan(p, s, thr, results).table
    with pytest.raises(AnalysisError, match="chunk results"):
        assemble_plan(p, s, thr, [*results, *results])
    with pytest.raises(ValueError, match="QUEST\\+ chunk results"):
        compare_procedures(p, None, s, thr, quest_replicates=4, outcomes=[])
