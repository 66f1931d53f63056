"""``masking-lab demo``: the whole system on its embedded defaults, in one command.

Ten simulated participants (ground truth: ``protocols/simulation/ground_truth.yaml``) run the
baseline and both masking experiments through the firmware emulator over a real
pseudo-terminal on a virtual clock; the logs are analysed (ALs, statistics, pooling, ramp fits),
the masking parameters exported, and the paper's bump-with-rough-texture scene rendered with and
without compensation. The summary puts the fitted parameters beside the ground truth.

Participants run in parallel worker processes (one emulator each); a participant's three
sessions run in order because the masked experiments need the baseline's calibration.
"""

from __future__ import annotations

import io
import math
import os
import sys
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from masking_lab.core.errors import MaskingLabError
from masking_lab.formats.resources import shipped
from masking_lab.simulation.observer import GroundTruth

PROTOCOLS = ("baseline", "experiment1", "experiment2")
SCENE = "bump_rough"


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
        ``emulator`` (real pty, virtual clock) or ``sim`` (in-process).
    jobs : int
        Worker processes running participants in parallel.
    n_boot : int
        Bootstrap replicates of the ramp fits.
    """

    out: Path
    participants: int = 10
    seed: int = 2020
    device: str = "emulator"
    jobs: int = 2
    n_boot: int = 1000


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


def _run_participant(out: str, device: str, master_seed: int, index: int) -> list[SessionDone]:
    """Worker: one participant's three sessions, in order. Runs in a child process."""
    from masking_lab.session.runner import RunOptions, run_session

    participant = f"S{index:02d}"
    done: list[SessionDone] = []
    for k, name in enumerate(PROTOCOLS):
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
        done.append(
            SessionDone(
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
        )
        if result.exit_code != 0:
            break
    return done


def run_demo(settings: DemoSettings, stream: TextIO | None = None) -> int:
    """Run the demo; print progress and the summary to ``stream`` (stderr for progress).

    Returns the process exit code (0 when every stage succeeded).
    """
    out_stream = stream or sys.stdout
    err = sys.stderr if stream is None else stream
    out = Path(settings.out)
    if (out / "data").exists() and any((out / "data").rglob("*.jsonl")):
        raise MaskingLabError(
            f"{out}/data already holds session logs; give an empty or new --out folder so the "
            "demo's analysis sees only its own sessions"
        )
    t_start = time.perf_counter()
    sessions = _collect(settings, err)
    failed = [s for s in sessions if s.exit_code != 0]
    if failed:
        for s in failed:
            print(f"session failed: {s.participant} {s.protocol}: {s.message}", file=err)
        return 3
    t_collect = time.perf_counter() - t_start

    print("analysing the logs ...", file=err, flush=True)
    from masking_lab.analysis.batch import run_analyze
    from masking_lab.analysis.settings import AnalysisSettings

    summary = run_analyze(
        out / "data",
        out / "analysis",
        AnalysisSettings(seed=settings.seed, n_boot=settings.n_boot),
    )
    t_analyse = time.perf_counter() - t_start - t_collect

    print("rendering the bump-with-rough-texture scene ...", file=err, flush=True)
    rendering_summary = _render(out)
    total = time.perf_counter() - t_start

    from masking_lab.formats.masking_params import read_masking_params
    from masking_lab.simulation.observer import load_ground_truth

    params = read_masking_params(out / "analysis" / "masking_params.json")
    truth = load_ground_truth()
    print(
        summary_text(
            settings,
            sessions,
            params,
            truth,
            rendering_summary,
            warnings=summary.warnings,
            timings={"collect": t_collect, "analyse": t_analyse, "total": total},
        ),
        file=out_stream,
    )
    return 0


def _collect(settings: DemoSettings, err: TextIO) -> list[SessionDone]:
    n = settings.participants
    total = n * len(PROTOCOLS)
    where = (
        "the firmware emulator on a pseudo-terminal"
        if settings.device == "emulator"
        else "the in-process device"
    )
    print(
        f"running {n} simulated participants x {len(PROTOCOLS)} protocols through {where} "
        f"({settings.jobs} worker{'s' if settings.jobs > 1 else ''}, virtual clock)",
        file=err,
        flush=True,
    )
    done: list[SessionDone] = []
    jobs = max(1, min(settings.jobs, n))
    args = [(str(settings.out), settings.device, settings.seed, i) for i in range(1, n + 1)]
    if jobs == 1:
        for a in args:
            for s in _run_participant(*a):
                done.append(s)
                _progress(err, len(done), total, s)
    else:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            futures = [pool.submit(_run_participant, *a) for a in args]
            for fut in as_completed(futures):
                for s in fut.result():
                    done.append(s)
                    _progress(err, len(done), total, s)
    return sorted(done, key=lambda s: (s.participant, PROTOCOLS.index(s.protocol)))


def _progress(err: TextIO, k: int, total: int, s: SessionDone) -> None:
    print(
        f"  [{k:>2}/{total}] {s.participant} {s.protocol:<11} {s.n_completed}/{s.n_sets} sets, "
        f"{s.n_trials} trials, {s.seconds:.1f} s",
        file=err,
        flush=True,
    )


def _render(out: Path) -> dict[str, Any]:
    from masking_lab.device.rig_limits import max_level_db_sl
    from masking_lab.formats.masking_params import read_masking_params
    from masking_lab.rendering.outputs import write_rendering
    from masking_lab.rendering.render import needed_pairs, render_scene, summarize
    from masking_lab.rendering.scene import load_scene
    from masking_lab.rendering.solver import pair_from_params

    scene = load_scene(str(shipped("protocols", f"scenes/{SCENE}.yaml")))
    params_path = out / "analysis" / "masking_params.json"
    params = read_masking_params(params_path)
    ((mv, ev),) = needed_pairs(scene)
    pair = pair_from_params(params, mv=mv, ev=ev, source=str(params_path))
    limits = max_level_db_sl(None)
    rendering = render_scene(
        scene, pair, max_mv_db_sl=limits.get("MV"), max_ev_db_sl=limits.get("EV")
    )
    written = write_rendering(rendering, out / "render")
    summary = summarize(rendering)
    summary["files"] = [str(p) for p in written]
    return summary


# --------------------------------------------------------------------------------------------
# Summary (pure)


def sample_truth(
    truth: GroundTruth,
    participants: Sequence[str],
    pairs: Sequence[tuple[str, str]],
    levels_db_sl: Sequence[float],
) -> tuple[float, float]:
    """The ramp a (pooled) fit estimates: least squares on the participants' mean true shift.

    Each simulated participant's true shift at a level is its true masked AL minus its true
    unmasked AL (individual offsets included, clipped at 0 like the observer's); averaging over
    the participants and ``pairs`` and fitting a ramp gives the number the analysis estimates.

    Parameters
    ----------
    truth : GroundTruth
        The simulation's ground truth.
    participants : sequence of str
        Participant ids (drawn with the runner's population seed 0).
    pairs : sequence of (target, masker)
        The stimulus pairs pooled into one fit.
    levels_db_sl : sequence of float
        Masker levels the fit used, dB SL.

    Returns
    -------
    (intercept_db, slope)
    """
    from masking_lab.analysis.ramp_fit import fit_ramp
    from masking_lab.simulation.observer import make_participant

    x = np.asarray(levels_db_sl, dtype=float)
    people = [make_participant(truth, pid, 0) for pid in participants]
    shifts = [
        [p.masked_al_db_v(t, m, level) - p.unmasked_al_db_v[t] for level in x]
        for p in people
        for t, m in pairs
    ]
    fit = fit_ramp(x, np.mean(shifts, axis=0))
    if fit.intercept_db is None or fit.slope is None:
        raise ValueError(fit.message)
    return float(fit.intercept_db), float(fit.slope)


def summary_text(
    settings: DemoSettings,
    sessions: Sequence[SessionDone],
    params: Mapping[str, Any],
    truth: GroundTruth,
    rendering: Mapping[str, Any],
    *,
    warnings: Sequence[str] = (),
    timings: Mapping[str, float] | None = None,
) -> str:
    """The demo's closing summary: what ran, where the files are, fitted vs true parameters."""
    out = Path(settings.out)
    n_sets = sum(s.n_sets for s in sessions)
    n_done = sum(s.n_completed for s in sessions)
    n_trials = sum(s.n_trials for s in sessions)
    lines = [
        "",
        "masking-lab demo: done",
        f"  ran      {len(sessions)} sessions ({settings.participants} participants x "
        f"{', '.join(PROTOCOLS)}), {n_sets} staircases ({n_done} completed), {n_trials} trials "
        f"through the {settings.device}",
    ]
    if timings:
        lines.append(
            f"  time     {timings['total']:.0f} s (sessions {timings['collect']:.0f} s, "
            f"analysis {timings['analyse']:.0f} s)"
        )
    lines += [
        f"  logs     {out / 'data'}/<participant>/*.jsonl",
        f"  analysis {out / 'analysis'}/ (thresholds.csv, anova.csv, report.txt, figures/)",
        f"  params   {out / 'analysis' / 'masking_params.json'}",
        f"  scene    {out / 'render'}/ (points.csv, summary.json, figure4.png)",
        "",
        "Masking functions: fitted (95 % interval) beside the simulation's ground truth",
        f"  {'target|masker':<14} {'pooled with':<14} {'intercept dB':>24} {'slope':>20}"
        f"  {'truth a, b':>14}  within interval",
    ]
    people = [f"S{i:02d}" for i in range(1, settings.participants + 1)]
    for f in params.get("functions", []):
        lines.append(_param_line(f, truth, people))
    lines.append(
        "  (truth: the ramp through the simulated participants' mean true AL shift, pooled pairs"
        " averaged)"
    )
    mm = rendering.get("masking") or {}
    if mm:
        lines += [
            "",
            f"Scene {rendering['scene']}: {mm['mv']} with {mm['ev']}, b·d = {mm['bd']:.2f}",
        ]
        for name, ch in rendering["channels"].items():
            lo, hi = ch["input_range_db_sl"] or (math.nan, math.nan)
            unc = ch["uncompensated"]
            text = (
                f"  {name} ({ch['stimulus']}): compensated inputs {lo:.1f}..{hi:.1f} dB SL; "
                f"without compensation worst error {unc['max_abs_error_db']:.1f} dB, "
                f"{unc['points_not_felt']} of {rendering['n_points']} points not felt"
            )
            if ch["points_above_rating"]:
                text += (
                    f"; {ch['points_above_rating']} points need more than the rig's "
                    f"{ch['max_rated_db_sl']:g} dB SL (flagged, not clipped)"
                )
            lines.append(text)
    if warnings:
        lines += ["", f"Analysis notes ({len(warnings)}): see {out / 'analysis' / 'report.txt'}"]
    return "\n".join(lines)


def _param_line(f: Mapping[str, Any], truth: GroundTruth, participants: Sequence[str]) -> str:
    key = f"{f['target']}|{f['masker']}"
    pooled = [p for p in f.get("pooled_pairs") or [] if p != key]
    pooled_txt = (
        ",".join(p.split("|")[1] if p.startswith(f["target"]) else p.split("|")[0] for p in pooled)
        or "-"
    )
    if f.get("status") != "fitted" or f.get("intercept_db") is None:
        return f"  {key:<14} {pooled_txt:<14} {f.get('status')}: {f.get('message') or ''}"
    pairs = [tuple(p.split("|")) for p in (f.get("pooled_pairs") or [key])]
    lo, hi = f.get("fitted_range_db_sl") or (5, 25)
    levels = np.arange(lo, hi + 1e-9, 5.0) if hi > lo else np.array([lo])
    try:
        ta, tb = sample_truth(truth, participants, pairs, levels)  # type: ignore[arg-type]
    except (KeyError, AttributeError, MaskingLabError, ValueError):
        return f"  {key:<14} {pooled_txt:<14} (no ground truth for this pair)"
    a, b = f["intercept_db"], f["slope"]
    a_ci, b_ci = f.get("intercept_ci_db"), f.get("slope_ci")
    inside_a = a_ci is not None and a_ci[0] <= ta <= a_ci[1]
    inside_b = b_ci is not None and b_ci[0] <= tb <= b_ci[1]
    a_txt = f"{a:6.2f} [{a_ci[0]:6.2f},{a_ci[1]:6.2f}]" if a_ci else f"{a:6.2f}"
    b_txt = f"{b:5.3f} [{b_ci[0]:5.3f},{b_ci[1]:5.3f}]" if b_ci else f"{b:5.3f}"
    verdict = (
        "yes"
        if inside_a and inside_b
        else ("a only" if inside_a else ("b only" if inside_b else "no"))
    )
    return f"  {key:<14} {pooled_txt:<14} {a_txt:>24} {b_txt:>20}  {ta:6.2f}, {tb:5.3f}  {verdict}"


def default_jobs() -> int:
    """Worker processes: the machine's cores, at most 4."""
    return max(1, min(4, os.cpu_count() or 1))
