"""Worker processes end with the run that started them (masking_lab.core.worker_processes).

Each test runs a real process in a subprocess, lets it start real workers, kills it with
SIGKILL (no shutdown, no finally, no atexit) and checks in /proc that its workers are gone.
Without the helper, a worker waiting on its task queue would sleep forever: it holds the
queue's write end itself.
"""

from __future__ import annotations

import ast
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from masking_lab.analysis import log_reading
from masking_lab.core import worker_processes
from masking_lab.core.worker_processes import alive, worker_pool

pytestmark = pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads /proc")

PACKAGE = Path(__file__).resolve().parents[1] / "masking_lab"


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"  # a zombie has ended
    except FileNotFoundError:
        return False


def _killed_run(script: str, tmp_path: Path) -> list[int]:
    """Run ``script`` (it prints its workers' pids on one line, then SIGKILLs itself); the pids
    of its workers still alive after the kill, waiting up to a hang guard.

    Its output goes to files, not pipes: an orphaned worker holding a pipe open would keep
    ``subprocess.run`` waiting, and the test would hang instead of failing."""
    out, err = tmp_path / "pids.txt", tmp_path / "stderr.txt"
    with out.open("w") as stdout, err.open("w") as stderr:
        done = subprocess.run(
            [sys.executable, "-c", textwrap.dedent(script)], stdout=stdout, stderr=stderr
        )
    assert done.returncode == -signal.SIGKILL, err.read_text()
    workers = [int(p) for p in out.read_text().split()]
    assert workers, err.read_text()
    for _ in range(600):  # the kernel's signal is immediate, the watch thread's ≤ 0.5 s
        if not any(_alive(p) for p in workers):
            break
        time.sleep(0.05)
    return [p for p in workers if _alive(p)]


def _set_flag(value: str) -> None:
    os.environ["MASKING_LAB_TEST_FLAG"] = value


def _flag() -> str | None:
    return os.environ.get("MASKING_LAB_TEST_FLAG")


def test_the_pool_runs_tasks_and_its_initializer_after_arming() -> None:
    with worker_pool(2, initializer=_set_flag, initargs=("set",)) as pool:
        assert list(pool.map(abs, [-1, 2, -3])) == [1, 2, 3]
        assert pool.submit(_flag).result() == "set"
        assert pool.submit(os.getppid).result() == os.getpid()
    assert _flag() is None  # the initializer ran in the workers only


_IDLE_WORKERS = """
    import os, signal
    from masking_lab.core import worker_processes as wp
    {patch}
    import multiprocessing as mp
    pool = wp.worker_pool(2, mp_context=mp.get_context("{method}"))
    pids = {{pool.submit(os.getpid).result() for _ in range(20)}}
    print(*sorted(pids), flush=True)
    os.kill(os.getpid(), signal.SIGKILL)  # the workers now wait on their task queue
"""


@pytest.mark.parametrize(
    ("method", "patch"),
    [
        ("fork", ""),  # Linux: the kernel's parent-death signal
        # where prctl is missing (macOS): the watching thread, on a child of the run
        ("fork", "wp._arm_parent_death_signal = lambda: False"),
        # a fork server's children are not the run's: the thread asks whether the run exists
        ("forkserver", ""),
    ],
    ids=["pdeathsig", "watch-thread", "forkserver"],
)
def test_a_killed_run_takes_its_idle_workers_with_it(
    method: str, patch: str, tmp_path: Path
) -> None:
    assert _killed_run(_IDLE_WORKERS.format(method=method, patch=patch), tmp_path) == []


_READ_BLOCKED = """
    import os, signal, time
    from pathlib import Path
    from masking_lab.analysis.log_reading import read_logs
    from masking_lab.analysis.thresholds import EstimatorSettings
    data = Path({data!r})
    logs = sorted(data.glob("*.jsonl"))  # named pipes nobody writes: open() blocks
    reading = read_logs(logs, data, EstimatorSettings(), workers=2)  # workers start now
    me = str(os.getpid())
    for _ in range(6000):
        kids = [p for p in os.listdir("/proc") if p.isdigit()
                and open(f"/proc/{{p}}/stat").read().rsplit(")", 1)[1].split()[1] == me]
        if len(kids) >= 2:
            break
        time.sleep(0.01)
    print(*kids, flush=True)
    os.kill(os.getpid(), signal.SIGKILL)
"""


def test_a_killed_analyze_takes_its_log_readers_with_it(tmp_path: Path) -> None:
    # The readers are stuck in open() of logs that never arrive (a stalled network share):
    # the parent-death signal ends them there too.
    data = tmp_path / "data"
    data.mkdir()
    for i in range(2 * log_reading._CHUNK):  # two chunks: two readers
        os.mkfifo(data / f"S{i:03d}.jsonl")
    assert _killed_run(_READ_BLOCKED.format(data=str(data)), tmp_path) == []


def test_every_worker_pool_of_the_package_ends_with_its_run() -> None:
    # A ProcessPoolExecutor made directly would have workers that outlive a killed run.
    direct = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.name == "worker_processes.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call):
                f = node.func
                name = f.id if isinstance(f, ast.Name) else getattr(f, "attr", None)
                if name == "ProcessPoolExecutor":
                    direct.append(f"{path.relative_to(PACKAGE)}:{node.lineno}")
    assert direct == []


def test_alive_tells_running_ended_and_unreaped_processes_apart() -> None:
    assert alive(os.getpid())
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    for _ in range(600):  # ended but not reaped: a zombie, which no longer runs
        if not alive(child.pid):
            break
        time.sleep(0.05)
    assert not alive(child.pid)
    child.wait()
    assert not alive(child.pid)  # reaped: gone


def test_alive_never_signals_a_process_on_windows(monkeypatch: pytest.MonkeyPatch) -> None:
    # There os.kill(pid, 0) terminates the process instead of asking whether it exists.
    sent: list[tuple[int, int]] = []
    monkeypatch.setattr(worker_processes.os, "name", "nt")
    monkeypatch.setattr(worker_processes.os, "kill", lambda pid, sig: sent.append((pid, sig)))
    assert alive(os.getpid()) and sent == []


def _pid_and_power(base: int, exponent: int) -> tuple[int, int]:
    return os.getpid(), base**exponent


def _fails(message: str) -> None:
    raise ValueError(message)


def test_beside_computes_in_a_worker_of_its_own_and_ends_it() -> None:
    with worker_processes.Beside(_pid_and_power, 2, 10) as power:
        pid, value = power.result()
        assert value == 1024
        assert pid != os.getpid()  # a worker computed it
    assert not _alive(pid)  # and has ended (joined)


def test_beside_raises_what_its_function_raised() -> None:
    with (
        worker_processes.Beside(_fails, "bad levels") as failing,
        pytest.raises(ValueError, match="bad levels"),
    ):
        failing.result()


def test_beside_computes_here_where_no_worker_can_start(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_processes(*args: object, **kwargs: object) -> None:
        raise OSError("no processes here")

    monkeypatch.setattr(worker_processes, "worker_pool", no_processes)
    with worker_processes.Beside(_pid_and_power, 3, 3) as power:
        assert power.result() == (os.getpid(), 27)


def test_beside_without_a_worker_computes_at_once_here() -> None:
    power = worker_processes.Beside(_pid_and_power, 2, 5, worker=False)
    assert power._pool is None
    assert power.result() == (os.getpid(), 32)
    with pytest.raises(ValueError, match="at once"):
        worker_processes.Beside(_fails, "at once", worker=False)


def test_beside_left_before_its_result_ends_its_worker() -> None:
    with (
        pytest.raises(RuntimeError, match="the caller failed"),
        worker_processes.Beside(_pid_and_power, 5, 2) as power,
    ):
        pool = power._pool
        assert pool is not None
        workers = list(pool._processes.values())  # started with the task
        assert workers
        raise RuntimeError("the caller failed")
    assert power._pool is None
    assert [w.is_alive() for w in workers] == [False] * len(workers)
