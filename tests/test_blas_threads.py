"""One BLAS thread inside a session and a plan, the process's own limit restored afterwards
(core/blas_threads.py; the session itself is checked in tests/test_quest_plus_session.py)."""

from __future__ import annotations

import argparse

import numpy  # noqa: F401  (loads the BLAS pool that threadpoolctl lists)
import pytest

threadpoolctl = pytest.importorskip("threadpoolctl")


def _os_has_proc() -> bool:
    import os

    return os.path.isdir("/proc/self/task")


def _blas_threads() -> set[int]:
    return {p["num_threads"] for p in threadpoolctl.threadpool_info() if p["user_api"] == "blas"}


@pytest.fixture(autouse=True)
def _needs_blas():
    if not _blas_threads():
        pytest.skip("this numpy has no BLAS thread pool")


def test_one_blas_thread_inside_the_block_and_the_limit_back_after_an_error():
    from masking_lab.core.blas_threads import one_blas_thread

    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        with pytest.raises(RuntimeError, match="inside"), one_blas_thread():
            assert _blas_threads() == {1}
            raise RuntimeError("inside")
        assert _blas_threads() == {2}


def test_plan_runs_on_one_blas_thread(monkeypatch):
    from masking_lab.commands import plan

    seen = []
    monkeypatch.setattr(plan, "_run", lambda args: seen.append(_blas_threads()) or 0)
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        assert plan.run(argparse.Namespace()) == 0
        assert _blas_threads() == {2}
    assert seen == [{1}]


def test_the_environment_asks_for_one_thread_and_keeps_a_users_own():
    from masking_lab.core.blas_threads import BLAS_THREAD_VARIABLES, one_blas_thread_from_start

    env = {"PATH": "/bin"}
    assert one_blas_thread_from_start(env) == dict.fromkeys(BLAS_THREAD_VARIABLES, "1")
    assert env == {"PATH": "/bin", **dict.fromkeys(BLAS_THREAD_VARIABLES, "1")}
    mine = {"OPENBLAS_NUM_THREADS": "4", "MKL_NUM_THREADS": ""}  # empty: as if unset
    assert one_blas_thread_from_start(mine) == {"MKL_NUM_THREADS": "1"}
    assert mine["OPENBLAS_NUM_THREADS"] == "4"


# Run in a fresh process: what matters is what happens before and after numpy loads there.
_REPORT = (
    "import os, numpy; from threadpoolctl import threadpool_info; "
    "print(sorted({p['num_threads'] for p in threadpool_info() if p['user_api'] == 'blas'}), "
    "len(os.listdir('/proc/self/task')), os.environ.get('OPENBLAS_NUM_THREADS'))"
)


def _fresh(code: str, **env: str) -> str:
    import os
    import subprocess
    import sys

    clean = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    done = subprocess.run(
        [sys.executable, "-c", code], env={**clean, **env}, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def _cores() -> int:
    import os

    return os.cpu_count() or 1


def _openblas() -> bool:
    return any(p["internal_api"] == "openblas" for p in threadpoolctl.threadpool_info())


@pytest.mark.skipif(not _os_has_proc(), reason="counts threads in /proc (Linux)")
def test_the_masking_lab_command_runs_numpy_on_one_blas_thread_unless_told_otherwise():
    # console_main asks before main() (where every command loads numpy) runs
    run = (
        "import sys; from masking_lab.commands import cli; "
        f"cli.main = lambda: exec({_REPORT!r}) or 0; sys.argv = ['masking-lab']; "
        "sys.exit(cli.console_main())"
    )
    assert _fresh(run) == "[1] 1 1"  # one BLAS thread: no server thread beside the main one
    if _openblas() and _cores() > 1:
        assert _fresh(run, OPENBLAS_NUM_THREADS="2").startswith("[2] ")  # the user's own
        pools, tasks, _ = _fresh(_REPORT).split(" ")
        assert pools != "[1]" and int(tasks) > 1  # without it: OpenBLAS's server threads


@pytest.mark.skipif(not _os_has_proc(), reason="counts threads in /proc (Linux)")
def test_a_worker_limited_for_good_starts_no_blas_thread_after_a_fork_and_a_block():
    # OpenBLAS stops its threads before a fork (here: subprocess with a preexec_fn, as the
    # demo starts each firmware process) and starts fresh ones, which spin ~0.1 s, as soon as
    # the next one-thread block sets a limit; in a process limited for good the blocks leave
    # OpenBLAS alone.
    steps = (
        "import os, subprocess, numpy\n"
        "from masking_lab.core.blas_threads import one_blas_thread, one_blas_thread_here\n"
        "if {here}: one_blas_thread_here()\n"
        "for _ in range(2):\n"
        "    subprocess.run(['true'], preexec_fn=lambda: None, check=True)\n"
        "    with one_blas_thread():\n"
        "        pass\n"
        "print(len(os.listdir('/proc/self/task')))\n"
    )
    assert _fresh(steps.format(here=True)) == "1"
    if _openblas() and _cores() > 1:
        assert int(_fresh(steps.format(here=False))) > 1  # the restored pool's fresh threads


def test_the_demos_workers_run_on_one_blas_thread(tmp_path):
    from masking_lab.demo import DemoSettings, _run_in_pool

    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        seen = list(_run_in_pool(str(tmp_path), DemoSettings(out=tmp_path), 2, run=_report_done))
    # every participant's baseline, then their two masked sessions
    assert len(seen) == 10 * 3 and {s.message for s in seen} == {"[1]"}


def _report_done(out, device, seed, index, k):
    from masking_lab.demo import PROTOCOLS, SessionDone

    threads = sorted(_blas_threads())
    return SessionDone(f"S{index:02d}", PROTOCOLS[k], "", 0, 1, 1, 1, 0.0, str(threads))
