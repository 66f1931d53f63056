"""``masking-lab demo``: the whole system on its embedded defaults, in one command.

Ten simulated participants (ground truth: ``protocols/simulation/ground_truth.yaml``) run the
baseline and both masking experiments over real pseudo-terminals on a virtual clock: through
the C firmware's host build where it can be built here (compiled with this machine's C
compiler once, then cached: :mod:`masking_lab.device.host_build`), else through the firmware
emulator, which answers alike (the same trials). The logs are analysed (ALs, statistics,
pooling, ramp fits), the masking parameters exported, and the paper's bump-with-rough-texture
scene rendered with and without compensation. The summary puts the fitted parameters beside
the ground truth.

Sessions run in parallel worker processes, each session on a firmware process or an emulator
of its own. A participant's two masked experiments need the baseline's calibration, so they
start when that baseline has finished, and then run side by side. Every session has its own
seed, so the logs do not depend on the order or the number of workers. While the workers run,
this process imports what the analysis and the scene need. The analysis hands over the text of
``masking_params.json`` as soon as the ramp fits are done, and the scene is rendered from it in
a worker while the analysis writes its per-trial outputs and psychometric fits.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, wait
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from masking_lab.core.blas_threads import one_blas_thread_here
from masking_lab.core.errors import MaskingLabError
from masking_lab.core.worker_processes import Beside, worker_pool
from masking_lab.demo_summary import PROTOCOLS, build_summary, sample_truth, summary_text
from masking_lab.formats.resources import shipped

__all__ = [
    "PROTOCOLS",
    "DemoSettings",
    "SessionDone",
    "default_jobs",
    "new_demo_folder",
    "resolved_device",
    "run_demo",
    "sample_truth",
]

SCENE = "bump_rough"
# What the demo writes inside its folder; --force removes exactly these, nothing else.
DEMO_PARTS = ("data", "analysis", "render")


@dataclass(frozen=True)
class DemoSettings:
    """What the demo runs.

    Attributes
    ----------
    out : Path
        Output folder (``data/``, ``analysis/``, ``render/`` are created inside).
    participants : int
        Simulated participants (the paper had 10).
    seed : int
        Master seed: session seeds and the analysis bootstrap derive from it.
    device : str
        ``auto`` (the C firmware's host build if one can be made here, else the emulator; the
        default), ``firmware`` (the host build, or an error saying why there is none),
        ``emulator`` (real pty, virtual clock) or ``sim`` (in-process). The workers get
        ``firmware:PROGRAM`` for the host build (:func:`resolved_device`).
    jobs : int
        Worker processes running participants in parallel.
    n_boot : int
        Bootstrap replicates of the ramp fits.
    force : bool
        Overwrite an earlier demo in ``out`` (its ``data/``, ``analysis/``, ``render/``).
    """

    out: Path
    participants: int = 10
    seed: int = 2020
    device: str = "auto"
    jobs: int = 2
    n_boot: int = 1000
    force: bool = False


def _holds_logs(folder: Path) -> bool:
    return (folder / "data").exists() and any((folder / "data").rglob("*.jsonl"))


def new_demo_folder(base: Path) -> Path:
    """``base`` if it holds no demo yet, else the first free ``base-2``, ``base-3``, ...

    Parameters
    ----------
    base : Path
        The default folder (``demo_out``).

    Returns
    -------
    Path
        A folder without session logs, so a rerun never mixes two demos.

    Examples
    --------
    >>> new_demo_folder(Path("/nonexistent/demo_out"))
    PosixPath('/nonexistent/demo_out')
    """
    k = 1
    folder = base
    while _holds_logs(folder):
        k += 1
        folder = base.with_name(f"{base.name}-{k}")
    return folder


@dataclass(frozen=True)
class SessionDone:
    """One finished session, as reported by a worker."""

    participant: str
    protocol: str
    log_path: str
    exit_code: int
    n_sets: int
    n_completed: int
    n_trials: int
    seconds: float
    message: str


def session_seed(master: int, participant_index: int, protocol_index: int) -> int:
    """Seed of one session, derived from the master seed (pure, documented in the header)."""
    return int(
        np.random.SeedSequence([master, participant_index, protocol_index]).generate_state(1)[0]
    )


def _run_one(out: str, device: str, master_seed: int, index: int, k: int) -> SessionDone:
    """Worker: one session (participant ``index``, ``PROTOCOLS[k]``). Runs in a child process.

    ``device`` ``firmware:PROGRAM`` runs the session on that host build, started for it on a
    fresh pseudo-terminal in virtual time and stopped after it (the emulator's defaults: the
    same onset lateness, so the same trials)."""
    if device.startswith("firmware:"):
        from masking_lab.device.host_build import running_host_firmware

        with running_host_firmware(Path(device.partition(":")[2]), "--virtual-time") as port:
            return _run_session(out, f"serial:{port}", master_seed, index, k)
    return _run_session(out, device, master_seed, index, k)


def _run_session(out: str, device: str, master_seed: int, index: int, k: int) -> SessionDone:
    from masking_lab.session.runner import RunOptions, run_session

    participant = f"S{index:02d}"
    name = PROTOCOLS[k]
    t0 = time.perf_counter()
    result = run_session(
        RunOptions(
            protocol=Path(str(shipped("protocols", f"{name}.yaml"))),
            participant=participant,
            device=device,
            responder="sim",
            data_dir=Path(out) / "data",
            seed=session_seed(master_seed, index, k),
            progress=False,
        ),
        stream=io.StringIO(),
    )
    return SessionDone(
        participant=participant,
        protocol=name,
        log_path=str(result.log_path),
        exit_code=result.exit_code,
        n_sets=len(result.outcomes),
        n_completed=sum(o.status == "completed" for o in result.outcomes),
        n_trials=sum(o.n_trials for o in result.outcomes),
        seconds=time.perf_counter() - t0,
        message=result.message,
    )


def _run_participant(out: str, device: str, master_seed: int, index: int) -> list[SessionDone]:
    """One participant's three sessions in order, stopping at the first that fails."""
    done: list[SessionDone] = []
    for k in range(len(PROTOCOLS)):
        done.append(_run_one(out, device, master_seed, index, k))
        if done[-1].exit_code != 0:
            break
    return done


def run_demo(
    settings: DemoSettings,
    stream: TextIO | None = None,
    progress: Callable[[str], None] | None = None,
) -> int:
    """Run the demo; print progress and the summary to ``stream`` (stderr for progress).

    Parameters
    ----------
    settings : DemoSettings
        What to run and where (an existing demo there is refused unless ``force``).
    stream : TextIO or None
        Where to print (None: the summary to stdout, progress to stderr).
    progress : callable or None
        Hears one line per finished session, the analysis and rendering steps, then "done"
        (``participants × 3 + 3`` calls; the command's progress bar); None prints the lines to
        stderr.

    Returns
    -------
    int
        The process exit code (0 when every stage succeeded, 3 when a session failed).

    Raises
    ------
    MaskingLabError
        ``settings.out`` already holds a demo's logs and ``force`` is off, or the analysis
        settings are refused (an ``AnalysisError``, e.g. ``n_boot`` below 100), before any
        session runs.

    Examples
    --------
    >>> run_demo(DemoSettings(out=Path("demo_out"), participants=2))  # doctest: +SKIP
    0
    """
    from masking_lab.analysis.settings import AnalysisSettings

    out_stream = stream or sys.stdout
    err = sys.stderr if stream is None else stream
    # Checked before any session runs or an earlier demo is cleared (e.g. too few replicates).
    analysis_settings = AnalysisSettings(seed=settings.seed, n_boot=settings.n_boot)
    out = Path(settings.out)
    if out.exists() and not out.is_dir():
        raise MaskingLabError(f"--out {out}: a file, not a folder; name a folder for the demo")
    old_demo = _holds_logs(out)
    if old_demo and not settings.force:
        raise MaskingLabError(
            f"{out}/data already holds session logs; pass --force to overwrite that demo, "
            "or leave out --out to write a new folder, so the demo's analysis sees only its "
            "own sessions"
        )
    # before an earlier demo is removed: --device firmware may be refused
    device, where = resolved_device(settings.device)  # may compile the firmware (~1 s, once)
    settings = replace(settings, device=device)
    if old_demo:
        import shutil

        for part in DEMO_PARTS:
            shutil.rmtree(out / part, ignore_errors=True)
    say = progress or (lambda line: print(line, file=err, flush=True))
    t_start = time.perf_counter()
    sessions = _collect(settings, err, say, where)
    failed = [s for s in sessions if s.exit_code != 0]
    if failed:
        for s in failed:
            print(f"session failed: {s.participant} {s.protocol}: {s.message}", file=err)
        return 3
    t_collect = time.perf_counter() - t_start

    say("analysing the logs ...")
    from masking_lab.analysis.batch import run_analyze

    scene = _SceneRender(out)
    try:
        # The scene is rendered in a worker from the exported parameters while the analysis
        # writes its per-trial outputs and psychometric fits.
        summary = run_analyze(
            out / "data", out / "analysis", analysis_settings, on_params=scene.start
        )
        t_analyse = time.perf_counter() - t_start - t_collect
        say("rendering the bump-with-rough-texture scene ...")
        rendering_summary = scene.result()
    except BaseException:
        scene.close(discard=True)  # no scene beside a failed analysis, as before
        raise
    scene.close()
    total = time.perf_counter() - t_start

    from masking_lab.formats.masking_params import read_masking_params
    from masking_lab.simulation.observer import load_ground_truth

    params = read_masking_params(out / "analysis" / "masking_params.json")
    truth = load_ground_truth()
    model = build_summary(
        settings,
        sessions,
        params,
        truth,
        rendering_summary,
        warnings=summary.warnings,
        timings={"collect": t_collect, "analyse": t_analyse, "total": total},
    )
    if progress is not None:
        progress("done")  # the bar's last step ends its line before the summary
    print(summary_text(model), file=out_stream)
    return 0


def resolved_device(device: str) -> tuple[str, str]:
    """The device the demo's workers open, and the words that name it.

    Parameters
    ----------
    device : str
        ``auto``, ``firmware``, ``emulator`` or ``sim`` (:class:`DemoSettings`).

    Returns
    -------
    spec : str
        ``firmware:PROGRAM`` (the host build, compiled first if the cache lacks it),
        ``emulator`` or ``sim``.
    where : str
        What the sessions run through, for the demo's first line (with ``auto``, why it is the
        emulator when it is).

    Raises
    ------
    MaskingLabError
        ``firmware`` asked for and no host build can be made (the reason is in the message).

    Examples
    --------
    >>> resolved_device("sim")
    ('sim', 'the in-process device')
    """
    if device in ("sim", "emulator"):
        where = "the in-process device" if device == "sim" else "the firmware emulator"
        return device, where + ("" if device == "sim" else " on a pseudo-terminal")
    from masking_lab.device.host_build import host_firmware

    built = host_firmware()
    if built.program is not None:
        return f"firmware:{built.program}", (
            f"the C firmware (host build {built.build}) on pseudo-terminals"
        )
    if device == "firmware":
        # the advice that fits the reason: a compiler only where none was found
        fix = "install a C compiler (or set CC), or" if "no C compiler" in built.reason else "or"
        raise MaskingLabError(
            f"--device firmware: the C firmware's host build cannot be made here: {built.reason}; "
            f"{fix} use --device emulator"
        )
    return "emulator", (
        f"the firmware emulator on a pseudo-terminal (no host build of the C firmware: "
        f"{built.reason})"
    )


def _collect(
    settings: DemoSettings, err: TextIO, say: Callable[[str], None], where: str | None = None
) -> list[SessionDone]:
    """Every session; ``where`` names ``settings.device`` once resolved (else resolved here)."""
    if where is None:
        device, where = resolved_device(settings.device)
        settings = replace(settings, device=device)
    n = settings.participants
    total = n * len(PROTOCOLS)
    print(
        f"running {n} simulated participants x {len(PROTOCOLS)} protocols through {where} "
        f"({settings.jobs} worker{'s' if settings.jobs > 1 else ''}, virtual clock)",
        file=err,
        flush=True,
    )
    done: list[SessionDone] = []
    jobs = max(1, min(settings.jobs, n * len(PROTOCOLS)))
    out = str(settings.out)
    if jobs == 1:
        for i in range(1, n + 1):
            for s in _run_participant(out, settings.device, settings.seed, i):
                done.append(s)
                say(_progress(len(done), total, s))
    else:
        for s in _run_in_pool(out, settings, jobs):
            done.append(s)
            say(_progress(len(done), total, s))
    return sorted(done, key=lambda s: (s.participant, PROTOCOLS.index(s.protocol)))


def _run_in_pool(
    out: str,
    settings: DemoSettings,
    jobs: int,
    run: Callable[[str, str, int, int, int], SessionDone] | None = None,
) -> Iterator[SessionDone]:
    """Every session in ``jobs`` worker processes, yielded as each finishes.

    A session is one task, so the two masked experiments of a participant run side by side
    once that participant's baseline (their calibration) is done. The queue is kept here, not
    in the pool, so the next free worker takes the most useful ready session: baselines first
    (each unlocks two), then the longer experiment I before experiment II. The logs do not
    depend on the order: every session has its own seed (:func:`session_seed`). A participant
    whose baseline fails runs no experiment. ``run`` replaces :func:`_run_one` (tests).
    """
    run = run or _run_one
    _session_imports()
    n = settings.participants
    ready = [(0, i) for i in range(1, n + 1)]  # (protocol index, participant index)
    running: dict[Future[SessionDone], tuple[int, int]] = {}
    warm: threading.Thread | None = None
    # One BLAS thread per worker for good: a session's own one-thread block then leaves
    # OpenBLAS alone, so the fork that starts each session's firmware process does not make it
    # start a fresh, spinning thread after every session (core/blas_threads).
    with worker_pool(jobs, initializer=one_blas_thread_here) as pool:
        while ready or running:
            ready.sort()
            while ready and len(running) < jobs:
                k, i = ready.pop(0)
                fut = pool.submit(run, out, settings.device, settings.seed, i, k)
                running[fut] = (k, i)
            if warm is None:
                # The workers exist now (forked at the first submit): load what the analysis
                # and the scene need while they run, on the CPU time their pty round trips
                # leave idle.
                warm = threading.Thread(target=_warm_imports, name="demo-warm", daemon=True)
                warm.start()
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for fut in finished:
                k, i = running.pop(fut)
                s = _session_done(fut, [(k, i), *running.values()], settings)
                if s.exit_code == 0 and k == 0:
                    ready += [(j, i) for j in range(1, len(PROTOCOLS))]
                yield s
    if warm is not None:
        warm.join()


def _session_done(
    fut: Future[SessionDone], running: list[tuple[int, int]], settings: DemoSettings
) -> SessionDone:
    """A session's result, or a clear error if a worker process died: it breaks the pool, so
    every session ``running`` (protocol index, participant index) was cut off mid-log; none
    is run again here, nor analysed."""
    from concurrent.futures.process import BrokenProcessPool

    try:
        return fut.result()
    except BrokenProcessPool:
        cut = ", ".join(
            f"S{i:02d} {PROTOCOLS[k]}" for k, i in sorted(running, key=lambda x: x[::-1])
        )
        raise MaskingLabError(
            "a demo worker process died (killed from outside, perhaps by the system for "
            f"memory) while these sessions ran: {cut}; their logs in {settings.out}/data end "
            "mid-session, so nothing was analysed. Run the demo again with --force (or with "
            f"fewer --jobs than {settings.jobs} on a small machine)"
        ) from None


# What a session loads (the device, responder and procedure modules, numpy's generators),
# imported before the workers fork so that each starts with them: ~0.5 s of CPU per worker
# otherwise (with the fork start method; spawned workers import them themselves).
_SESSION_MODULES = (
    "masking_lab.session.runner",
    "masking_lab.session.participant_info",
    "masking_lab.device.emulator",
    "masking_lab.device.serial_device",
    "masking_lab.responders.sim",
    "numpy.random",
    "threadpoolctl",
)
# What the analysis and the scene load, imported while the sessions run. The analysis imports
# jinja2 (report.html) and pyarrow.parquet (trials.parquet) only when it first needs them: CPU
# on its critical path otherwise.
_LATER_MODULES = (
    "masking_lab.analysis.batch",
    # batch loads these only once its log reading has started (analyze's own start-up)
    "masking_lab.analysis.experiment",
    "masking_lab.analysis.export",
    "masking_lab.rendering.render",
    "jinja2",
    "pyarrow.parquet",
    # the tests' p values and the ramps' intervals (analysis/distributions.py): loaded here,
    # the statistics' worker inherits them and the summary's ramp fits find them loaded
    "scipy.special",
)


def _session_imports() -> None:
    for name in _SESSION_MODULES:
        importlib.import_module(name)
    from masking_lab.procedures.registry import kinds

    kinds()


def _warm_imports() -> None:
    """Import the analysis, figure and rendering modules and compile the report's template
    (errors surface where they are used)."""
    for name in _LATER_MODULES:
        with contextlib.suppress(Exception):  # e.g. pyarrow, an optional dependency
            importlib.import_module(name)
    with contextlib.suppress(Exception):
        from masking_lab.formats.png_figure import pyplot

        pyplot()
    with contextlib.suppress(Exception):  # report.html's template, compiled (~0.1 s of CPU)
        from masking_lab.analysis.report_html import prepare_html

        prepare_html()


def _progress(k: int, total: int, s: SessionDone) -> str:
    return (
        f"  [{k:>2}/{total}] {s.participant} {s.protocol:<11} {s.n_completed}/{s.n_sets} sets, "
        f"{s.n_trials} trials, {s.seconds:.1f} s"
    )


class _SceneRender:
    """The scene rendered in a worker process from ``masking_params.json``'s text, handed over
    by the analysis (``run_analyze(on_params=...)``) before that file is written.

    :meth:`result` waits for the worker, or renders here from the written file when the
    analysis never handed the text over. Either way the same bytes are written.
    """

    def __init__(self, out: Path) -> None:
        self.out = out
        self.pending: Beside[dict[str, Any]] | None = None

    def start(self, params_text: str) -> None:
        """Start rendering from the text of ``masking_params.json`` (JSON)."""
        if self.pending is None:
            self.pending = Beside(_render, self.out, params_text)

    def result(self) -> dict[str, Any]:
        """The rendering's summary (``summarize`` plus the strategies and files written)."""
        if self.pending is None:
            return _render(self.out)
        # a worker that died (killed for memory, say) leaves the scene to this process
        return self.pending.result()

    def close(self, discard: bool = False) -> None:
        """Wait for the worker to end; with ``discard`` (the analysis failed), remove the
        ``render/`` folder it wrote."""
        if self.pending is None:
            return
        self.pending.close()
        if discard:
            import shutil

            shutil.rmtree(self.out / "render", ignore_errors=True)


def _render(out: Path, params_text: str | None = None) -> dict[str, Any]:
    """Render the scene into ``out/render`` from ``out/analysis/masking_params.json``, or from
    ``params_text``, that file's text before it is written."""
    from masking_lab.device.rig_limits import max_level_db_sl
    from masking_lab.formats.masking_params import parse_masking_params, read_masking_params
    from masking_lab.rendering.outputs import write_rendering
    from masking_lab.rendering.render import (
        compare_strategies,
        needed_pairs,
        render_scene,
        summarize,
    )
    from masking_lab.rendering.scene import load_scene
    from masking_lab.rendering.solver import pair_from_params

    scene = load_scene(str(shipped("protocols", f"scenes/{SCENE}.yaml")))
    params_path = out / "analysis" / "masking_params.json"
    if params_text is None:
        params = read_masking_params(params_path)
    else:
        params = parse_masking_params(params_text, str(params_path))
    ((mv, ev),) = needed_pairs(scene)
    pair = pair_from_params(params, mv=mv, ev=ev, source=str(params_path))
    limits = max_level_db_sl(None)
    max_mv, max_ev = limits["MV"], limits["EV"]
    # Mapped into the rig's gamut (clip), so every input is within the ratings.
    rendering = render_scene(
        scene, pair, max_mv_db_sl=max_mv, max_ev_db_sl=max_ev, gamut_map="clip"
    )
    trade = compare_strategies(scene, pair, max_mv, max_ev)
    # figure4.png (most of this step) is drawn in a worker while gamut.png is drawn here.
    written = write_rendering(rendering, out / "render", strategies=trade, figure_worker=True)
    summary = summarize(rendering)
    summary["gamut_mapping"]["strategies"] = trade
    summary["files"] = [str(p) for p in written]
    return summary


def default_jobs() -> int:
    """Worker processes: the machine's cores, at most 4."""
    return max(1, min(4, os.cpu_count() or 1))
