"""Ctrl-C with worker processes running: the run says "interrupted" once and ends at once.

A terminal's Ctrl-C signals every process of the foreground group, the workers included. An
idle worker used to print a ``KeyboardInterrupt`` traceback under the run's own message, and a
worker whose task was interrupted went on with the tasks still queued for it, which the
pool's shutdown waited for (~2 s of ``plan`` chunks); under load, a run interrupted while its
logs were read often printed Python 3.11's exit-time ``OSError`` traceback (a pool left
running at the exit) and now and then hung. The unit cases signal a real pool's
real worker process; the end-to-end cases type Ctrl-C into a real pseudo-terminal that
``masking-lab analyze`` and ``plan`` have as their controlling terminal, so that the line
discipline signals the whole process group, as at a lab's terminal.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from masking_lab.core.worker_processes import (
    alive,
    cancel_pool,
    interruptible,
    interrupts_held,
    worker_pool,
)

_HERE = os.getpid()
CLI = Path(sys.executable).with_name("masking-lab")  # the installed command, as users run it


def _wait_for(predicate, what: str, limit_s: float = 120.0) -> None:
    """Poll until ``predicate()``; the limit only ends a test that would otherwise hang."""
    end = time.monotonic() + limit_s
    while not predicate():
        if time.monotonic() > end:
            pytest.fail(f"gave up waiting for {what}")
        time.sleep(0.02)


def _mark_and_sleep(marker: str) -> int:
    """In a worker: leave ``marker`` (its pid), then sleep until interrupted."""
    Path(marker).write_text(str(os.getpid()))
    time.sleep(600)
    return 0


def _touch(path: str) -> int:
    Path(path).write_text("ran")
    return 1


def test_an_idle_worker_notes_ctrl_c_quietly_and_refuses_later_tasks(capfd, tmp_path):
    with worker_pool(1) as pool:
        pid = pool.submit(os.getpid).result()
        assert pid != _HERE
        os.kill(pid, signal.SIGINT)
        late = pool.submit(_touch, str(tmp_path / "late"))
        with pytest.raises(KeyboardInterrupt):
            late.result()
        assert not (tmp_path / "late").exists()
    err = capfd.readouterr().err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err


def test_a_busy_workers_task_is_interrupted_and_its_queued_tasks_are_refused(capfd, tmp_path):
    marker = tmp_path / "running"
    with worker_pool(1) as pool:
        busy = pool.submit(_mark_and_sleep, str(marker))
        queued = [pool.submit(_touch, str(tmp_path / f"queued{i}")) for i in range(3)]
        _wait_for(marker.exists, "the task to start")
        os.kill(int(marker.read_text()), signal.SIGINT)
        with pytest.raises(KeyboardInterrupt):
            busy.result()  # at once: not after the task's 600 s sleep
        for fut in queued:
            with pytest.raises(KeyboardInterrupt):
                fut.result()
    assert not list(tmp_path.glob("queued*"))
    assert "Traceback" not in capfd.readouterr().err


def test_a_new_pools_workers_run_tasks_after_an_earlier_pools_ctrl_c(tmp_path):
    with worker_pool(1) as pool:
        os.kill(pool.submit(os.getpid).result(), signal.SIGINT)
        with pytest.raises(KeyboardInterrupt):
            pool.submit(abs, -1).result()
    with worker_pool(2) as pool:
        assert list(pool.map(abs, [-1, -2, -3])) == [1, 2, 3]


def test_cancel_pool_interrupts_the_running_task_and_leaves_nothing_running(tmp_path):
    # A failed run's figure pool: not waited for, yet joined before the interpreter exits
    # (Python 3.11's exit handler raced a pool thread still closing its pipes).
    marker = tmp_path / "running"
    pool = worker_pool(1)
    busy = pool.submit(_mark_and_sleep, str(marker))
    queued = pool.submit(_touch, str(tmp_path / "queued"))
    _wait_for(marker.exists, "the task to start")
    manager = pool._executor_manager_thread  # the pool's thread (a private attribute)
    cancel_pool(pool)
    assert manager is not None and not manager.is_alive()
    assert isinstance(busy.exception(), KeyboardInterrupt)
    assert queued.cancelled() or isinstance(queued.exception(), KeyboardInterrupt)
    assert not (tmp_path / "queued").exists()
    assert not alive(int(marker.read_text()))


def test_ctrl_c_while_a_worker_is_forked_comes_after_the_fork():
    # Another thread takes the process's SIGINT while this one holds it back: Python runs the
    # handler in the main thread at once, which inside fork's callbacks printed "Exception
    # ignored"; held, the KeyboardInterrupt comes when the block ends, and only then.
    import threading

    other = threading.Event()
    waiter = threading.Thread(target=other.wait, daemon=True)
    waiter.start()
    went_on = []
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt), interrupts_held() as noted:
        os.kill(os.getpid(), signal.SIGINT)  # to the process: the waiting thread takes it
        # Python code runs until the handler has run (where it would raise); on a busy
        # machine the waiting thread may take a while to be scheduled and pass the signal on
        _wait_for(lambda: bool(noted), "the held SIGINT to be noted")
        went_on.append(True)
    other.set()
    assert went_on == [True]
    assert signal.getsignal(signal.SIGINT) is before


def test_a_with_block_that_fails_does_not_wait_for_the_rest_of_its_tasks(tmp_path):
    # The executor's own exit ran every queued task first (plan's chunks: seconds each).
    marker = tmp_path / "running"
    with pytest.raises(ValueError, match="the caller failed"), worker_pool(1) as pool:
        busy = pool.submit(_mark_and_sleep, str(marker))
        queued = [pool.submit(_touch, str(tmp_path / f"queued{i}")) for i in range(3)]
        _wait_for(marker.exists, "the task to start")
        raise ValueError("the caller failed")
    assert isinstance(busy.exception(), KeyboardInterrupt)  # not after its 600 s sleep
    assert all(f.cancelled() or isinstance(f.exception(), KeyboardInterrupt) for f in queued)
    assert not list(tmp_path.glob("queued*"))


_CHUNK_FILES: dict[str, Path] = {}


def _slow_or_failing_chunk(chunk, then=None, compiled=False):
    """pf_table._fit_chunk's stand-in: a worker's chunk marks itself and sleeps (leaving
    ``finished`` if it ever ends); this process's chunk fails once the worker's has begun."""
    if os.getpid() != _HERE:
        _CHUNK_FILES["running"].write_text(str(os.getpid()))
        time.sleep(120)
        _CHUNK_FILES["finished"].write_text("ran to the end")
        return []
    _wait_for(_CHUNK_FILES["running"].exists, "the worker's chunk to start")
    raise ValueError("this process's chunk failed")


def test_failing_psychometric_fits_do_not_wait_for_the_workers_chunks(tmp_path, monkeypatch):
    # fit_all_with had a shutdown of its own that waited for the running chunks (seconds
    # each at 1,000 sessions) before the pool's block interrupted them.
    from masking_lab.analysis import pf_table
    from masking_lab.analysis.pf_table import SetTrials, fit_all_with, pf_job

    _CHUNK_FILES.update(running=tmp_path / "running", finished=tmp_path / "finished")
    monkeypatch.setattr(pf_table, "_fit_chunk", _slow_or_failing_chunk)
    trials = SetTrials({"level_unit": "db_sl"}, [0.0, 2.0, 4.0] * 10, [False, True, True] * 10)
    jobs = [pf_job(trials, seed, 0) for seed in range(4)]  # two chunks: the worker's and ours
    with pytest.raises(ValueError, match="chunk failed"):
        fit_all_with(jobs, None, workers=2)
    pid = int(_CHUNK_FILES["running"].read_text())
    assert not alive(pid)  # interrupted and joined, not left sleeping
    assert not _CHUNK_FILES["finished"].exists()


def test_interruptible_in_this_process_restores_its_handler():
    before = signal.getsignal(signal.SIGINT)
    assert interruptible(divmod, 7, 2) == (3, 1)
    assert signal.getsignal(signal.SIGINT) is before


# --- end to end: Ctrl-C typed into a pseudo-terminal -------------------------------------


def _children(pid: int) -> list[int]:
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as fh:
            return [int(c) for c in fh.read().split()]
    except OSError:
        return []


def _ctrl_c_in_a_terminal(args: list[str], ready, cwd: Path) -> tuple[int, str]:
    """Run ``masking-lab ARGS`` with a pseudo-terminal as its controlling terminal (stdin),
    type Ctrl-C once ``ready(pid)`` holds; its exit code and stderr."""
    import fcntl
    import termios

    master, slave = os.openpty()

    def controlling_terminal() -> None:  # in the child, after setsid (start_new_session)
        fcntl.ioctl(0, termios.TIOCSCTTY, 0)

    proc = subprocess.Popen(
        [str(CLI), *args],
        stdin=slave,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        cwd=cwd,
        start_new_session=True,
        preexec_fn=controlling_terminal,
    )
    os.close(slave)
    try:
        _wait_for(lambda: ready(proc.pid) or proc.poll() is not None, "the workers", 300.0)
        assert proc.poll() is None, "the run ended before it reached the moment to interrupt"
        os.write(master, b"\x03")  # the line discipline sends SIGINT to the whole group
        _, err = proc.communicate(timeout=120)  # a run that hangs fails here
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        os.close(master)
    return proc.returncode, err.decode()


@pytest.fixture(scope="module")
def many_logs(tmp_path_factory) -> Path:
    """70 session logs (more than analyze's PARALLEL_FROM: the reading runs on workers)."""
    from masking_lab.analysis.log_reading import PARALLEL_FROM
    from masking_lab.simulation.synthetic_logs import simulate_study

    root = tmp_path_factory.mktemp("interrupt")
    pool = root / "pool"
    simulate_study(pool, n_participants=2, seed=3)
    logs = sorted(pool.rglob("*.jsonl"))
    data = root / "data"
    for k in range(max(70, PARALLEL_FROM + 6)):
        src = logs[k % len(logs)]
        dest = data / f"P{k:03d}" / src.name
        dest.parent.mkdir(parents=True)
        dest.write_bytes(src.read_bytes().replace(src.parent.name.encode(), f"P{k:03d}".encode()))
    return data


# The processes analyze forks for 70 logs on two cores, in order: the figure worker, two log
# readers, two readers of the second read (per-trial outputs), the psychometric fits' worker.
# Ctrl-C once the k-th has appeared; the version before this test hung now and then at the
# fourth (a reader blocked sending its result to a run that had stopped reading) and printed
# idle workers' tracebacks at most of the others.
@pytest.mark.parametrize("forked", [1, 3, 4, 5, 6])
def test_ctrl_c_during_analyze_prints_one_line_and_leaves_no_worker(many_logs, tmp_path, forked):
    out = tmp_path / "analysis"
    seen: set[int] = set()

    def ready(pid: int) -> bool:
        seen.update(_children(pid))
        return len(seen) >= forked

    code, err = _ctrl_c_in_a_terminal(
        ["analyze", str(many_logs), "--out", str(out)], ready, tmp_path
    )
    assert code == 130, err
    assert err == "masking-lab analyze: interrupted\n"
    assert not out.exists()  # a failed run leaves no results folder
    _wait_for(lambda: not any(alive(p) for p in seen), "the workers to end")


def test_ctrl_c_during_plan_prints_one_line(tmp_path):
    root = Path(__file__).resolve().parents[1]
    protocol = root / "protocols" / "experiment1.yaml"
    code, err = _ctrl_c_in_a_terminal(
        ["plan", str(protocol), "--out", str(tmp_path / "plan")],
        lambda pid: len(_children(pid)) >= 2,
        tmp_path,
    )
    assert code == 130, err
    assert err.splitlines()[-1] == "masking-lab plan: interrupted", err
    assert "Traceback" not in err and "Exception ignored" not in err, err
