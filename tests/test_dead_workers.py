"""A worker process of `analyze` killed from outside (the kernel's out-of-memory killer, say):
what it had not returned is done in the analysing process, with the same results, instead of
a ``BrokenProcessPool`` traceback (issue 22; the fits' and figures' pools already did this).

Each case kills a real forked worker with SIGKILL from inside its task, once, and leaves a
marker file so that the test knows the kill happened. Each runs twice, the second time in a
process that watches a device (device.safety's SIGTERM handler installed, as after a session):
the workers must still end when the pool ends them, and a forked child must never stop its
parent's devices."""

from __future__ import annotations

import contextlib
import os
import signal
from pathlib import Path

import pytest

from masking_lab.analysis import log_reading, study_reading, track_figures
from masking_lab.analysis.thresholds import EstimatorSettings
from masking_lab.core.worker_processes import Beside, rest_here, worker_pool
from masking_lab.simulation.synthetic_logs import simulate_study

_HERE = os.getpid()  # a forked worker inherits this value

# and nothing fails in the pool's own thread
pytestmark = pytest.mark.filterwarnings("error::pytest.PytestUnhandledThreadExceptionWarning")


def _kill_worker_once(marker: Path) -> None:
    """In a worker (not this test's process), the first time: leave ``marker`` and die."""
    if os.getpid() != _HERE and not marker.exists():
        marker.write_text(str(os.getpid()))
        os.kill(os.getpid(), signal.SIGKILL)


def _square_or_die(item: tuple[int, str]) -> int:
    value, marker = item
    if value == 3:
        _kill_worker_once(Path(marker))
    return value * value


def _cube_or_die(value: int, marker: str) -> int:
    return _square_or_die((value, marker)) * value


class _Device:
    def stop(self) -> None:
        pass


@contextlib.contextmanager
def _watching(device):
    """``device`` watched by device.safety, its SIGTERM handler installed over the default
    action (as a session's process has it); then this process's handlers and safety's state
    as they were, whatever earlier tests of this process left."""
    from masking_lab.device import safety

    signals = (signal.SIGTERM, signal.SIGHUP)
    saved = {sig: signal.getsignal(sig) for sig in signals}
    state = safety._installed, dict(safety._previous)
    for sig in signals:
        signal.signal(sig, signal.SIG_DFL)
    safety._installed = False
    safety._previous.clear()
    safety.zero_on_exit(device)
    assert signal.getsignal(signal.SIGTERM) is safety._on_signal
    try:
        yield
    finally:
        safety.forget(device)
        for sig, handler in saved.items():
            signal.signal(sig, handler)
        safety._installed = state[0]
        safety._previous.clear()
        safety._previous.update(state[1])


@pytest.fixture(autouse=True, params=["plain", "device watched"])
def watched(request):
    """Run each case also in a process that watches a device: the workers must still die
    when the pool ends them (the surviving reader, blocked on its full result pipe, ran the
    inherited handler, whose SystemExit the pool swallowed, and the run hung)."""
    if request.param == "plain":
        yield
        return
    with _watching(_Device()):
        yield


def test_pool_workers_die_of_sigterm_whatever_their_parent_handles(watched):
    with worker_pool(1) as pool:
        assert pool.submit(signal.getsignal, signal.SIGTERM).result() == signal.SIG_DFL
        assert pool.submit(signal.getsignal, signal.SIGHUP).result() == signal.SIG_DFL


class _MarkedDevice:
    """A watched device whose ``stop()`` leaves a file (its owner's pid) behind."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def stop(self) -> None:
        self.marker.write_text(str(os.getpid()))


def test_a_forked_child_never_stops_its_parents_devices(tmp_path, watched):
    from masking_lab.device import safety

    with _watching(_MarkedDevice(tmp_path / "parent's stopped")):
        # terminated, the child dies without touching the parent's device
        status = _in_child(lambda: os.kill(os.getpid(), signal.SIGTERM))
        assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGTERM
        assert not (tmp_path / "parent's stopped").exists()

        def own_device() -> None:  # one the child opens itself is watched, and stopped
            device = _MarkedDevice(tmp_path / "child's stopped")  # held: safety's are weak
            safety.zero_on_exit(device)
            os.kill(os.getpid(), signal.SIGTERM)

        status = _in_child(own_device)
        assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 128 + signal.SIGTERM
        assert (tmp_path / "child's stopped").is_file()
        assert not (tmp_path / "parent's stopped").exists()


def _in_child(act) -> int:
    """Fork, run ``act`` in the child and end it (never returning into pytest there): its
    wait status. A SystemExit ends the child with its code; anything else with 99; falling
    through (the signal did not end it) with 3."""
    pid = os.fork()
    if pid == 0:
        code = 3
        try:
            act()
        except SystemExit as exc:
            code = int(exc.code or 0)
        except BaseException:
            code = 99
        os._exit(code)
    return os.waitpid(pid, 0)[1]


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    root = tmp_path_factory.mktemp("study")
    simulate_study(root, n_participants=3, seed=5)
    return root, sorted(root.rglob("*.jsonl"))


def test_rest_here_does_in_this_process_what_a_dead_worker_left(tmp_path):
    items = [(v, str(tmp_path / "killed")) for v in range(8)]
    with worker_pool(2) as pool:
        got = list(rest_here(pool.map(_square_or_die, items), _square_or_die, items))
    assert got == [v * v for v in range(8)]
    assert (tmp_path / "killed").is_file()  # the worker did die
    with worker_pool(2) as pool:  # and nothing changes when none dies
        assert list(rest_here(pool.map(abs, [-1, 2]), abs, [-1, 2])) == [1, 2]


def test_beside_computes_here_what_its_dead_worker_left(tmp_path):
    with Beside(_cube_or_die, 3, str(tmp_path / "killed")) as cube:
        assert cube.result() == 27
    assert (tmp_path / "killed").is_file()


_REAL_STATISTICS: list = []  # the statistics function _statistics_or_die stands in front of


def _statistics_or_die(shifts, settings):
    _kill_worker_once(Path(os.environ["DEAD_WORKER_MARKER"]))
    return _REAL_STATISTICS[0](shifts, settings)


def test_the_statistics_of_a_dead_worker_are_computed_here(study, tmp_path, monkeypatch):
    from masking_lab.analysis import batch
    from masking_lab.analysis.settings import AnalysisSettings

    root, _ = study
    settings = AnalysisSettings(figures="none")
    batch.run_analyze(root, tmp_path / "alive", settings)
    monkeypatch.setenv("DEAD_WORKER_MARKER", str(tmp_path / "killed"))
    _REAL_STATISTICS[:] = [batch._statistics]
    monkeypatch.setattr(batch, "_statistics", _statistics_or_die)
    batch.run_analyze(root, tmp_path / "dead", settings)
    assert (tmp_path / "killed").is_file()
    names = sorted(p.relative_to(tmp_path / "alive") for p in (tmp_path / "alive").rglob("*"))
    assert names == sorted(p.relative_to(tmp_path / "dead") for p in (tmp_path / "dead").rglob("*"))
    for name in names:
        if (tmp_path / "alive" / name).is_file():
            assert (tmp_path / "alive" / name).read_bytes() == (
                tmp_path / "dead" / name
            ).read_bytes(), name


def test_logs_of_a_dead_reader_are_read_here(study, tmp_path, monkeypatch):
    root, paths = study
    marker = tmp_path / "killed"
    real = log_reading.read_one

    def read_or_die(path, rel, settings):
        if path == paths[5]:  # in the third chunk of two logs: the first two came back
            _kill_worker_once(marker)
        return real(path, rel, settings)

    settings = EstimatorSettings()
    alone = list(log_reading.read_logs(paths, root, settings, workers=1))
    monkeypatch.setattr(log_reading, "_CHUNK", 2)
    monkeypatch.setattr(log_reading, "read_one", read_or_die)  # the forked workers see it
    seen: list[tuple[int, int]] = []
    both = list(log_reading.read_logs(paths, root, settings, workers=2, progress=_to(seen)))
    assert marker.is_file()
    assert [(r.rel, r.sha256, r.rows, r.error) for r in both] == [
        (r.rel, r.sha256, r.rows, r.error) for r in alone
    ]
    assert seen[-1] == (len(paths), len(paths)) and seen == sorted(seen)


def test_parts_of_a_dead_reader_are_read_here(study, tmp_path, monkeypatch):
    root, paths = study
    rels = [p.relative_to(root).as_posix() for p in paths]
    marker = tmp_path / "killed"
    real = study_reading.read_part

    def part_or_die(path, rel, *args, **kwargs):
        if rel == rels[2]:
            _kill_worker_once(marker)
        return real(path, rel, *args, **kwargs)

    alone = list(study_reading.read_parts(root, rels, csv=True, workers=1))
    monkeypatch.setattr(study_reading, "_CHUNK", 2)
    monkeypatch.setattr(study_reading, "read_part", part_or_die)
    both = list(study_reading.read_parts(root, rels, csv=True, workers=2))
    assert marker.is_file()
    assert both == alone


def test_track_figures_of_a_dead_worker_are_drawn_here(study, tmp_path, monkeypatch):
    from masking_lab.formats.session_log import read_log

    _, paths = study
    marker = tmp_path / "killed"
    jobs = [
        track_figures.track_job(tmp_path / f"{k}.png", read_log(p), {})
        for k, p in enumerate(paths[:4])
    ]
    real = track_figures._track_png

    def png_or_die(job):
        if job.path == str(tmp_path / "2.png"):
            _kill_worker_once(marker)
        return real(job)

    alone = [real(job) for job in jobs]
    monkeypatch.setattr(track_figures, "_CHUNK", 1)
    monkeypatch.setattr(track_figures, "_track_png", png_or_die)
    drawn = track_figures.draw_tracks(jobs, workers=2)
    assert marker.is_file()
    assert [p.name for p in drawn] == ["0.png", "1.png", "2.png", "3.png"]
    assert [p.read_bytes() for p in drawn] == alone


def test_plan_tasks_of_a_dead_worker_are_run_here(tmp_path):
    from masking_lab.planning.parallel import run_chunks, started_tasks

    args = [(v, str(tmp_path / "killed")) for v in range(6)]
    assert run_chunks(_cube_or_die, args, scheduler="local", max_workers=2) == [
        v**3 for v in range(6)
    ]
    assert (tmp_path / "killed").is_file()
    args = [(v, str(tmp_path / "killed again")) for v in range(6)]
    with started_tasks([(_cube_or_die, a) for a in args], scheduler="local") as results:
        assert results.wait(4, 6) + results.wait(0, 4) == [64, 125, 0, 1, 8, 27]
        assert results.wait(3, 4) == [27]  # kept, not run again
    assert (tmp_path / "killed again").is_file()


def _session_or_die(out: str, device: str, seed: int, index: int, k: int):
    from masking_lab.demo import PROTOCOLS, SessionDone

    if (index, k) == (2, 0):
        _kill_worker_once(Path(out) / "killed")
    return SessionDone(
        f"S{index:02d}", PROTOCOLS[k], f"{out}/{index}-{k}.jsonl", 0, 1, 1, 9, 0.0, ""
    )


def test_a_dead_demo_session_worker_is_a_clear_error_naming_the_session(tmp_path):
    from masking_lab import demo
    from masking_lab.core.errors import MaskingLabError

    settings = demo.DemoSettings(out=tmp_path, participants=3, device="sim", jobs=2)
    with pytest.raises(MaskingLabError) as err:
        list(demo._run_in_pool(str(tmp_path), settings, 2, run=_session_or_die))
    assert (tmp_path / "killed").is_file()
    # the pool broke under every session running then: each is named, the killed one too
    ran = str(err.value).split("while these sessions ran: ")[1].split(";")[0].split(", ")
    assert "S02 baseline" in ran and 1 <= len(ran) <= 2
    assert "--force" in str(err.value) and str(tmp_path) in str(err.value)


def _scene_or_die(out: Path, params_text: str | None = None) -> dict:
    _kill_worker_once(out / "killed")
    return {"out": str(out), "text": params_text}  # stands in for the rendered scene


def test_the_demo_scene_of_a_dead_worker_is_rendered_here(tmp_path, monkeypatch):
    from masking_lab import demo

    monkeypatch.setattr(demo, "_render", _scene_or_die)
    scene = demo._SceneRender(tmp_path)
    try:
        scene.start('{"handed": "text"}')
        assert scene.pending is not None  # started in the worker
        assert scene.result() == {"out": str(tmp_path), "text": '{"handed": "text"}'}
    finally:
        scene.close()
    assert (tmp_path / "killed").is_file()


def _figure4_or_die(r, *, bands=None):
    from masking_lab.rendering.figures import figure4_png

    _kill_worker_once(Path(os.environ["DEAD_WORKER_MARKER"]))
    return figure4_png(r, bands=bands)


def test_figure4_of_a_dead_worker_is_drawn_here(tmp_path, monkeypatch):
    from masking_lab.rendering import outputs
    from masking_lab.rendering.render import render_scene
    from masking_lab.rendering.scene import GeometrySpec, PathSpec, Scene, TextureSpec
    from masking_lab.rendering.solver import MutualMasking

    scene = Scene(
        "tiny",
        PathSpec(length_mm=10.0, n_points=21),
        GeometrySpec("bump", position_mm=5.0, height_mm=1.0, max_inclination=0.5),
        TextureSpec("rough", "MV180", 12.0),
    )
    pair = MutualMasking(a_db=-2.0, b=0.5, c_db=-1.0, d=0.4, mv="MV180", ev="EV270")
    r = render_scene(scene, pair, max_mv_db_sl=30.0, max_ev_db_sl=30.0, gamut_map="clip")
    here = outputs.write_rendering(r, tmp_path / "here")
    monkeypatch.setenv("DEAD_WORKER_MARKER", str(tmp_path / "killed"))
    monkeypatch.setattr(outputs, "figure4_png", _figure4_or_die)
    worker = outputs.write_rendering(r, tmp_path / "worker", figure_worker=True)
    assert (tmp_path / "killed").is_file()
    assert [p.name for p in here] == [p.name for p in worker]
    for a, b in zip(here, worker, strict=True):
        assert a.read_bytes() == b.read_bytes(), a.name


def _to(seen: list[tuple[int, int]]):
    return lambda done, n: seen.append((done, n))
