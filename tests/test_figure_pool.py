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
import os, signal
from masking_lab.analysis.figure_pool import FigurePool
pool = FigurePool()
print(pool.submit(os.getpid)(), flush=True)
os.kill(os.getpid(), signal.SIGKILL)  # no shutdown runs
"""


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"  # a zombie has ended
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads /proc")
def test_a_killed_run_takes_its_figure_worker_with_it() -> None:
    # An orphaned worker would hold the run's stdout open: run() would wait for it forever
    # (the timeout only guards against that hang).
    done = subprocess.run(
        [sys.executable, "-c", _KILLED_RUN], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == -signal.SIGKILL, done.stderr
    worker = int(done.stdout.split()[0])
    for _ in range(600):  # the kernel delivers the parent-death signal at once; a hang guard
        if not _alive(worker):
            break
        time.sleep(0.05)
    assert not _alive(worker)
