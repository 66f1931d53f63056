"""Files of a rendered scene, and the protocol that measures what a scene lacks.

- :func:`points_csv` / :func:`write_rendering`: ``points.csv`` (one row per interaction point,
  columns :data:`POINT_COLUMNS`, levels in dB SL), ``summary.json``
  (:func:`masking_lab.rendering.render.summarize`) and ``figure4.png``
  (:mod:`masking_lab.rendering.figures`).
- :func:`measurement_protocols` / :func:`write_measurement_protocol`: when a scene's masking
  functions are not fitted, the masked-threshold protocols that measure just that pair, one per
  masking direction like experiments I and II (staircase and timing of the shipped experiment I
  protocol, masker levels in dB SL).

This is the I/O side of rendering; :mod:`masking_lab.rendering.render` stays pure.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from masking_lab.core.errors import SolverError
from masking_lab.core.worker_processes import result_or_here
from masking_lab.formats.fileio import write_bytes_atomic, write_text_atomic
from masking_lab.formats.protocol import parse_protocol
from masking_lab.formats.resources import shipped
from masking_lab.rendering.figures import figure4_png
from masking_lab.rendering.render import Rendering, intended, summarize
from masking_lab.rendering.solver import PairProblem
from masking_lab.rendering.uncertainty import RenderingUncertainty

__all__ = [
    "MEASURE_LEVELS_DB_SL",
    "POINT_COLUMNS",
    "check_outputs_finite",
    "measurement_protocol",
    "measurement_protocols",
    "points_csv",
    "write_measurement_protocol",
    "write_rendering",
]

# Masker levels of the paper's experiments I and II (Table 1), dB SL.
MEASURE_LEVELS_DB_SL: tuple[float, ...] = (5.0, 10.0, 15.0, 20.0, 25.0)

POINT_COLUMNS = (
    "x_mm",
    "t_s",
    "mv_target_db_sl",
    "ev_target_db_sl",
    "mv_input_db_sl",
    "ev_input_db_sl",
    "case",
    "status",
    "mv_exceeds_rating",
    "ev_exceeds_rating",
    "mv_masked_al_db_sl",
    "ev_masked_al_db_sl",
    "mv_perceived_db_sl",
    "ev_perceived_db_sl",
    "mv_masked_al_uncomp_db_sl",
    "ev_masked_al_uncomp_db_sl",
    "mv_perceived_uncomp_db_sl",
    "ev_perceived_uncomp_db_sl",
    "mv_intended_db_sl",
    "ev_intended_db_sl",
)


def check_outputs_finite(r: Rendering) -> None:
    """The output guard: every number render writes is finite where it should be.

    Empty fields are allowed in exactly two places: a channel the scene does not play (its
    target is −inf) and the compensated columns of a point without a unique answer (its status
    says why). Anything else non-finite is a defect of the inputs or of the model, refused here
    before a file is written.

    Raises
    ------
    SolverError
        Naming the scene file, the column, the point (position, mm) and its targets.

    Examples
    --------
    >>> check_outputs_finite(render_scene(scene, pair))  # doctest: +SKIP
    """
    sol = r.solution
    unique = np.asarray(sol.status == 1)
    for name in POINT_COLUMNS:
        if name in ("case", "status") or name.endswith(("exceeds_rating", "intended_db_sl")):
            continue
        values = np.asarray(getattr(r, name), dtype=float)
        ch = "mv" if name.startswith("mv") else ("ev" if name.startswith("ev") else "")
        absent = getattr(r, f"{ch}_target_db_sl") == -np.inf if ch else np.zeros_like(unique)
        allowed = np.isfinite(values)
        if ch:
            # A silent channel is −inf (its masked AL is 0); NaN for no unique answer.
            allowed |= absent & (values == -np.inf)
            compensated = "target" not in name and not name.endswith("_uncomp_db_sl")
            if compensated:
                allowed |= ~unique & np.isnan(values)
        bad = np.flatnonzero(~allowed)
        if bad.size:
            i = int(bad[0])
            where = f"x = {float(r.x_mm[i]):g} mm"
            targets = f"MV {float(r.mv_target_db_sl[i])!r}, EV {float(r.ev_target_db_sl[i])!r}"
            raise SolverError(
                f"{r.scene.source}: {name} is {float(values[i])!r} at {bad.size} point(s), "
                f"first at {where} (targets {targets} dB SL); nothing was written. Check the "
                "scene's levels and the masking parameters"
            )


def points_csv(r: Rendering, uncertainty: RenderingUncertainty | None = None) -> str:
    """The per-point table as CSV text (floats round-trip exactly).

    No non-finite number reaches the file: a silent channel (−inf dB SL) and a point without a
    unique answer (NaN) are empty fields; ``status`` tells them apart. With ``uncertainty``,
    its interval columns and flags (0/1) follow :data:`POINT_COLUMNS`.
    """
    sol = r.solution
    cols: list[Sequence[Any]] = []
    for name in POINT_COLUMNS:
        if name == "case":
            cols.append([str(int(c)) for c in sol.case])
        elif name == "status":
            cols.append(sol.status_names())
        elif name.endswith("exceeds_rating"):
            cols.append(["1" if v else "0" for v in getattr(sol, name)])
        elif name.endswith("intended_db_sl"):
            cols.append([_number(v) for v in intended(r)[0 if name[:2] == "mv" else 1]])
        else:
            cols.append([_number(v) for v in getattr(r, name)])
    names = list(POINT_COLUMNS)
    if uncertainty is not None:
        for name, values in uncertainty.columns().items():
            names.append(name)
            if values.dtype == bool:
                cols.append(["1" if v else "0" for v in values])
            else:
                cols.append([_number(v) for v in values])
    lines = [",".join(names)]
    lines += [",".join(row) for row in zip(*cols, strict=True)]
    return "\n".join(lines) + "\n"


def _number(v: float) -> str:
    x = float(v)
    return repr(x) if math.isfinite(x) else ""


def write_rendering(
    r: Rendering,
    out_dir: str | Path,
    *,
    figure: bool = True,
    uncertainty: RenderingUncertainty | None = None,
    strategies: Mapping[str, Any] | None = None,
    figure_worker: bool = False,
) -> list[Path]:
    """Write ``points.csv``, ``summary.json`` and (optionally) ``figure4.png`` and ``gamut.png``
    into ``out_dir``; with ``uncertainty``, its intervals as columns, bands and a summary entry;
    with ``strategies`` (:func:`~masking_lab.rendering.render.compare_strategies`), every gamut
    mapping's metrics under ``gamut_mapping.strategies`` in the summary; with
    ``figure_worker``, ``figure4.png`` (the longest part) is drawn in a worker process while
    this one writes the rest (the same bytes).

    Each file is written atomically and fsynced. Returns the paths written.
    """
    check_outputs_finite(r)
    out = Path(out_dir)
    pool = pending = None
    if figure and figure_worker:
        from masking_lab.core.worker_processes import worker_pool

        pool = worker_pool(1)
        pending = pool.submit(figure4_png, r, bands=uncertainty)
    try:
        return _write_rendering(r, out, figure, uncertainty, strategies, pending)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)


def _write_rendering(
    r: Rendering,
    out: Path,
    figure: bool,
    uncertainty: RenderingUncertainty | None,
    strategies: Mapping[str, Any] | None,
    pending: Future[bytes] | None,
) -> list[Path]:
    summary = summarize(r)
    summary["uncertainty"] = None if uncertainty is None else uncertainty.summary()
    if strategies is not None:
        summary["gamut_mapping"]["strategies"] = dict(strategies)
    written = [
        write_text_atomic(out / "points.csv", points_csv(r, uncertainty)),
        write_text_atomic(
            out / "summary.json", json.dumps(summary, indent=2, allow_nan=False) + "\n"
        ),
    ]
    if figure:
        # in-process, figure 4 is drawn first, as before the worker existed
        fig4 = pending if pending is not None else figure4_png(r, bands=uncertainty)
        gamut = None
        if r.gamut is not None and r.pair is not None:
            from masking_lab.rendering.gamut_figure import gamut_png

            want_m, want_e = intended(r)
            mapped = None if r.gamut_map == "none" else (r.mv_target_db_sl, r.ev_target_db_sl)
            gamut = gamut_png(
                r.gamut, mv_target_db_sl=want_m, ev_target_db_sl=want_e, mapped=mapped
            )
        # a worker that died (killed for memory, say) leaves the figure to this process
        if isinstance(fig4, Future):
            fig4 = result_or_here(fig4, lambda: figure4_png(r, bands=uncertainty))
        written.append(write_bytes_atomic(out / "figure4.png", fig4))
        if gamut is not None:
            written.append(write_bytes_atomic(out / "gamut.png", gamut))
    return written


def measurement_protocol(
    problems: Sequence[PairProblem],
    *,
    levels_db_sl: Sequence[float] = MEASURE_LEVELS_DB_SL,
    writer: str = "render",
) -> dict[str, Any]:
    """A masked-threshold protocol measuring the masking functions in ``problems``, one direction.

    One set per (target, masker, level); the staircase and timing are those of the shipped
    experiment I protocol, so the new data pool with the paper's. Every problem must have the
    same direction (all targets EV, or all MV), as in experiments I and II: ``analyze`` treats
    an experiment's MV stimuli as the levels of one frequency factor, so both directions under
    one experiment id would make one level belong to two pairs. Use
    :func:`measurement_protocols` to split a mixed list.

    Parameters
    ----------
    problems : sequence of PairProblem
        The pairs to measure (target stimulus, masker stimulus), one direction.
    levels_db_sl : sequence of float
        Masker levels, dB SL (default the paper's 5–25 dB SL).
    writer : str
        The command that writes it (``render`` or ``run``), named in the description.

    Returns
    -------
    dict
        The protocol document (``experiment`` = ``measure_<targets>_by_<maskers>``).

    Raises
    ------
    SolverError
        Nothing to measure, or both directions in ``problems``.

    Examples
    --------
    >>> from masking_lab.rendering.solver import PairProblem
    >>> doc = measurement_protocol([PairProblem("EV270", "MV180", "missing")], levels_db_sl=[5])
    >>> doc["experiment"], [s["id"] for s in doc["sets"]]
    ('measure_EV270_by_MV180', ['EV270_by_MV180_05'])
    """
    if not problems:
        raise SolverError("nothing to measure: every masking function the scene needs is fitted")
    if len({p.target.startswith("EV") for p in problems}) > 1:
        raise SolverError(
            "one measurement protocol measures one masking direction (EV masked by MV, or MV "
            "masked by EV); split the pairs with measurement_protocols()"
        )
    template = yaml.safe_load(shipped("protocols", "experiment1.yaml").read_text(encoding="utf-8"))
    targets = sorted({p.target for p in problems})
    maskers = sorted({p.masker for p in problems})
    sets = []
    for p in problems:
        for level in levels_db_sl:
            sets.append(
                {
                    "id": f"{p.target}_by_{p.masker}_{level:02g}",
                    "target": p.target,
                    "masker": p.masker,
                    "masker_level_db_sl": float(level),
                }
            )
    listed = ", ".join(f"{p.target} masked by {p.masker}" for p in problems)
    return {
        "schema_version": 1,
        "experiment": f"measure_{'_'.join(targets)}_by_{'_'.join(maskers)}",
        "description": f"Measures only what a scene needs and the parameters lack: {listed}, "
        f"at {', '.join(f'{lv:g}' for lv in levels_db_sl)} dB SL. Written by masking-lab "
        f"{writer}; run after the baseline of every stimulus involved.",
        "kind": "masked",
        "staircase": template["staircase"],
        "timing": template["timing"],
        "order": {"randomize": True},
        "sets": sets,
    }


def measurement_protocols(
    problems: Sequence[PairProblem],
    *,
    levels_db_sl: Sequence[float] = MEASURE_LEVELS_DB_SL,
    writer: str = "render",
) -> list[dict[str, Any]]:
    """The protocols measuring ``problems``: one per masking direction (EV targets first).

    Parameters
    ----------
    problems : sequence of PairProblem
        The pairs to measure, in either direction.
    levels_db_sl : sequence of float
        Masker levels, dB SL.
    writer : str
        The command that writes them (``render`` or ``run``).

    Returns
    -------
    list of dict
        One or two protocol documents (see :func:`measurement_protocol`).

    Examples
    --------
    >>> from masking_lab.rendering.solver import PairProblem
    >>> docs = measurement_protocols(
    ...     [PairProblem("MV180", "EV270", "missing"), PairProblem("EV270", "MV180", "missing")]
    ... )
    >>> [d["experiment"] for d in docs]
    ['measure_EV270_by_MV180', 'measure_MV180_by_EV270']
    """
    if not problems:
        raise SolverError("nothing to measure: every masking function the scene needs is fitted")
    ev_targets = [p for p in problems if p.target.startswith("EV")]
    mv_targets = [p for p in problems if not p.target.startswith("EV")]
    return [
        measurement_protocol(group, levels_db_sl=levels_db_sl, writer=writer)
        for group in (ev_targets, mv_targets)
        if group
    ]


def write_measurement_protocol(
    protocol: Mapping[str, Any], out_dir: str | Path, *, writer: str = "render"
) -> Path:
    """Validate ``protocol`` with the protocol loader and write it as ``<experiment>.yaml``.

    Parameters
    ----------
    protocol : mapping
        From :func:`measurement_protocol`.
    out_dir : str or Path
        Folder to write into.
    writer : str
        The command that writes it (``render`` or ``run``), named in the header comment.

    Returns
    -------
    Path
        The file written (atomically).

    Examples
    --------
    >>> write_measurement_protocol(doc, "out", writer="run")  # doctest: +SKIP
    PosixPath('out/measure_EV270_by_MV180.yaml')
    """
    text = (
        f"# Written by masking-lab {writer}: measures the masking a scene needs.\n"
        + yaml.safe_dump(dict(protocol), sort_keys=False, allow_unicode=True)
    )
    path = Path(out_dir) / f"{protocol['experiment']}.yaml"
    parse_protocol(text.encode("utf-8"), str(path))
    return write_text_atomic(path, text)
