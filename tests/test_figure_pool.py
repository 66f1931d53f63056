"""The figure worker of `analyze` (masking_lab.analysis.figure_pool): the same bytes as drawing
in-process, and a worker that dies leaves its figures to the main process."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from masking_lab.analysis.figure_pool import FigurePool
from masking_lab.analysis.figures import masking_function_png
from masking_lab.analysis.lab_figures import shift_figure_png
from masking_lab.core.worker_processes import alive

PARENT = os.getpid()
CELLS = [
    {"mv_stimulus": "MV120", "pair": "EV270|MV120", "masker_level_db_sl": x,
     "mean_shift_db": 0.6 * x - 2.0, "se_db": 0.4}
    for x in (5.0, 15.0, 25.0)
]  # fmt: skip
FITS = [
    {"label": "MV120", "levels": ("MV120",), "intercept_db": -2.0, "slope": 0.6,
     "fitted_range_db_sl": (5.0, 25.0), "status": "fitted"}
]  # fmt: skip
SHIFTS = [
    {"participant": p, "mv_stimulus": "MV120", "pair": "EV270|MV120",
     "masker_level_db_sl": x, "shift_db": 0.5 * x + d}
    for p, d in (("P1", 0.0), ("P2", 1.5)) for x in (5.0, 15.0, 25.0)
]  # fmt: skip


def _twice_but_die_in_a_worker(x: int) -> int:
    if os.getpid() != PARENT:
        os._exit(3)  # the worker dies mid-task (as when killed for memory)
    return 2 * x


def test_figures_from_the_worker_are_the_bytes_drawn_in_process() -> None:
    here = masking_function_png(title="experiment1: EV270", cells=CELLS, fits=FITS)
    here_shifts = shift_figure_png("Individual AL shifts", SHIFTS, {("P2", "MV120", 25.0)})
    pool = FigurePool()
    try:
        there = pool.submit(
            masking_function_png, title="experiment1: EV270", cells=CELLS, fits=FITS
        )
        shifts = pool.submit(
            shift_figure_png, "Individual AL shifts", SHIFTS, {("P2", "MV120", 25.0)}
        )
        assert there() == here
        assert shifts() == here_shifts
    finally:
        pool.close()
    assert here[1:4] == b"PNG"


def test_a_dead_worker_leaves_the_work_to_this_process() -> None:
    pool = FigurePool()
    try:
        result = pool.submit(_twice_but_die_in_a_worker, 21)
        assert result() == 42
        # the pool is broken now: later work is done here too
        assert pool.submit(_twice_but_die_in_a_worker, 5)() == 10
    finally:
        pool.close()


def test_without_a_worker_the_work_runs_here_when_asked() -> None:
    calls: list[int] = []

    def record(x: int) -> int:  # not picklable: proves nothing left this process
        calls.append(x)
        return x

    pool = FigurePool(enabled=False)
    result = pool.submit(record, 7)
    assert calls == []  # drawn only when its result is asked for
    assert result() == 7 and calls == [7]
    pool.close()


def test_a_cancelled_pool_does_not_draw_what_is_queued() -> None:
    pool = FigurePool()
    pool.submit(masking_function_png, title="t", cells=CELLS, fits=FITS)
    pool.close(cancel=True)
    pool.close()  # closing twice is harmless


def _pid_once_file_exists(path: str) -> int:
    while not os.path.exists(path):  # held until the test lets it go (no timing involved)
        time.sleep(0.01)
    return os.getpid()


def test_a_widened_pool_spreads_figures_over_its_workers_with_the_same_bytes(tmp_path) -> None:
    here = masking_function_png(title="t", cells=CELLS, fits=FITS)
    gate = tmp_path / "go"
    pool = FigurePool()
    pool.widen(2)
    try:
        first = pool.submit(_pid_once_file_exists, str(gate))  # busy until the gate opens
        second = pool.submit(_pid_once_file_exists, str(gate))  # so this goes to the other
        figure = pool.submit(masking_function_png, title="t", cells=CELLS, fits=FITS)
        gate.touch()
        assert first() != second() and PARENT not in (first(), second())
        assert figure() == here
    finally:
        pool.close()


_KILLED_RUN = """
import os, signal, time
from masking_lab.analysis.figure_pool import FigurePool
gate = {gate!r}
def held(path=gate):  # both workers busy at once: one task each
    while not os.path.exists(path):
        time.sleep(0.01)
    return os.getpid()
pool = FigurePool()  # its workers are forked from here on: they know held()
first, second = pool.submit(held), pool.submit(held)
open(gate, "w").close()
print(first(), second(), flush=True)
os.kill(os.getpid(), signal.SIGKILL)  # no shutdown runs
"""


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads /proc")
def test_a_killed_run_takes_both_figure_workers_with_it(tmp_path) -> None:
    # Output to files, not pipes: an orphaned worker holding a pipe would hang the test.
    out, err = tmp_path / "pids.txt", tmp_path / "stderr.txt"
    with out.open("w") as stdout, err.open("w") as stderr:
        done = subprocess.run(
            [sys.executable, "-c", _KILLED_RUN.format(gate=str(tmp_path / "go"))],
            stdout=stdout,
            stderr=stderr,
        )
    assert done.returncode == -signal.SIGKILL, err.read_text()
    workers = [int(p) for p in out.read_text().split()]
    assert len(set(workers)) == 2  # the first worker and the one it forked
    for _ in range(600):  # the kernel delivers the parent-death signal at once; a hang guard
        if not any(alive(w) for w in workers):
            break
        time.sleep(0.05)
    assert not any(alive(w) for w in workers)


def _parent_pid(_: object = None) -> tuple[int, int]:
    return os.getpid(), os.getppid()


def _fail(message: str) -> None:
    raise ValueError(message)


def _first_worker(pool: FigurePool) -> int:
    (pid,) = pool._lanes[0][0]._processes  # type: ignore[attr-defined]
    return int(pid)


def test_the_second_worker_is_forked_from_the_first_once_warm(tmp_path) -> None:
    gate = tmp_path / "go"
    pool = FigurePool()
    try:
        first = pool.submit(_pid_once_file_exists, str(gate))  # holds the first worker
        second = pool.submit(_parent_pid)  # so this goes to the second
        w2, its_parent = second()
        gate.touch()
        w1 = first()
        assert its_parent == w1 != w2 and PARENT not in (w1, w2)
    finally:
        pool.close()


def _burn_cpu(seconds: float) -> tuple[int, float]:
    """Spend ``seconds`` of this process's CPU time; its pid and its CPU time so far."""
    end = time.process_time() + seconds
    while time.process_time() < end:
        pass
    return os.getpid(), time.process_time()


def test_the_second_workers_cpu_time_is_counted_with_this_process_children(tmp_path) -> None:
    # The first worker waits for the second at its end: its CPU reaches this process's
    # RUSAGE_CHILDREN (and a run's wait4, /usr/bin/time) instead of being re-parented.
    import resource

    def children_cpu() -> float:
        ru = resource.getrusage(resource.RUSAGE_CHILDREN)
        return ru.ru_utime + ru.ru_stime

    gate = tmp_path / "go"
    before = children_cpu()
    pool = FigurePool()
    try:
        held = pool.submit(_pid_once_file_exists, str(gate))  # holds the first worker
        burnt = pool.submit(_burn_cpu, 1.5)  # so this goes to the second
        w2, w2_cpu = burnt()
        gate.touch()
        w1 = held()
        assert w2 != w1 and w2_cpu >= 1.5
    finally:
        pool.close()
    # Without the wait, only the first worker (its matplotlib import, ~0.5 s) would be counted.
    assert children_cpu() - before >= w2_cpu


def test_an_error_in_the_second_worker_is_raised_here(tmp_path) -> None:
    gate = tmp_path / "go"
    pool = FigurePool()
    try:
        held = pool.submit(_pid_once_file_exists, str(gate))
        failing = pool.submit(_fail, "no such level")
        with pytest.raises(ValueError, match="no such level"):
            failing()
        gate.touch()
        assert held() != PARENT
    finally:
        pool.close()


def test_a_dead_second_worker_leaves_its_work_to_this_process(tmp_path) -> None:
    here = masking_function_png(title="t", cells=CELLS, fits=FITS)
    gate = tmp_path / "go"
    pool = FigurePool()
    try:
        held = pool.submit(_pid_once_file_exists, str(gate))
        dying = pool.submit(_twice_but_die_in_a_worker, 21)  # the second worker dies
        assert dying() == 42  # computed here once the worker is found gone
        gate.touch()
        assert held() != PARENT
        figure = pool.submit(masking_function_png, title="t", cells=CELLS, fits=FITS)
        assert figure() == here  # the first worker goes on drawing
    finally:
        pool.close()


def test_a_first_worker_dead_before_forking_leaves_all_work_here() -> None:
    pool = FigurePool()
    try:
        os.kill(_first_worker(pool), signal.SIGKILL)  # while it loads matplotlib
        results = [pool.submit(_parent_pid) for _ in range(3)]
        assert [r()[0] for r in results] == [PARENT] * 3
    finally:
        pool.close()


def test_closed_pools_leave_no_thread_behind() -> None:
    # A long-lived process (a notebook, this suite) makes many pools: each queue's feeder
    # thread must end with its pool.
    import threading

    before = {t.ident for t in threading.enumerate()}
    for _ in range(3):
        pool = FigurePool()
        answers = [pool.submit(_parent_pid) for _ in range(3)]  # both workers get some
        assert all(a()[0] != PARENT for a in answers)
        pool.close()
    for _ in range(600):  # a hang guard: the threads end as soon as their queues are written
        left = [t for t in threading.enumerate() if t.ident not in before and t.is_alive()]
        if not left:
            break
        time.sleep(0.05)
    assert left == []
