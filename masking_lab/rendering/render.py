"""Render a scene: per-point targets → compensated inputs, and what each input pair feels like.

:func:`render_scene` is pure: for every interaction point it takes the scene's perceived targets
(m_p, e_p), asks the solver for the inputs (m_i, e_i), and runs the forward model twice — on the
compensated inputs and on the targets played as they are (no compensation, paper Figure 4b) — to
give the masked ALs and the perceived intensities of both. :func:`write_rendering` writes the
per-point table, a summary and a Figure-4-like figure.

Model only what a scene needs (:func:`needed_pairs`): a single-channel scene has nothing to mask
it and passes straight through without parameters; a two-channel scene loads exactly the two
masking functions of its (MV, EV) stimulus pair. When those are not fitted,
:func:`measurement_protocol` builds the masked-threshold protocol that measures just that pair.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from masking_lab import __version__
from masking_lab.core.errors import SolverError
from masking_lab.formats.fileio import write_bytes_atomic, write_text_atomic
from masking_lab.formats.resources import shipped
from masking_lab.rendering.scene import Scene
from masking_lab.rendering.solver import (
    REASON_TEXT,
    MutualMasking,
    PairProblem,
    Reason,
    Solution,
    ev_masked_al_db_sl,
    mv_masked_al_db_sl,
    solve,
)

# Masker levels of the paper's experiments I and II (Table 1), dB SL.
MEASURE_LEVELS_DB_SL: tuple[float, ...] = (5.0, 10.0, 15.0, 20.0, 25.0)

# Nothing masks a channel that plays alone: the ramps are identically 0.
NO_MASKING = MutualMasking(0.0, 0.0, 0.0, 0.0, mv="none", ev="none")


@dataclass(frozen=True)
class Rendering:
    """A rendered scene; every array has one value per interaction point.

    Attributes
    ----------
    scene : Scene
        What was rendered.
    pair : MutualMasking or None
        Masking functions used (None: single-channel scene, passed through).
    x_mm, t_s : ndarray
        Position along the path, mm, and when the cue reaches it, s.
    mv_target_db_sl, ev_target_db_sl : ndarray
        Perceived targets m_p, e_p, dB SL (−inf: channel absent).
    solution : Solution
        The solver's answer per point (status, case, rating flags).
    mv_input_db_sl, ev_input_db_sl : ndarray
        Compensated inputs m_i, e_i, dB SL (NaN where there is no unique answer).
    mv_masked_al_db_sl, ev_masked_al_db_sl : ndarray
        Masked ALs under the compensated inputs, dB SL: f(e_i) and g(m_i).
    mv_perceived_db_sl, ev_perceived_db_sl : ndarray
        Perceived intensities under the compensated inputs, dB SL (< 0: not felt).
    mv_masked_al_uncomp_db_sl, ev_masked_al_uncomp_db_sl : ndarray
        Masked ALs when the targets are played as inputs, dB SL.
    mv_perceived_uncomp_db_sl, ev_perceived_uncomp_db_sl : ndarray
        Perceived intensities when the targets are played as inputs, dB SL.
    """

    scene: Scene
    pair: MutualMasking | None
    x_mm: NDArray[np.float64]
    t_s: NDArray[np.float64]
    mv_target_db_sl: NDArray[np.float64]
    ev_target_db_sl: NDArray[np.float64]
    solution: Solution
    mv_input_db_sl: NDArray[np.float64]
    ev_input_db_sl: NDArray[np.float64]
    mv_masked_al_db_sl: NDArray[np.float64]
    ev_masked_al_db_sl: NDArray[np.float64]
    mv_perceived_db_sl: NDArray[np.float64]
    ev_perceived_db_sl: NDArray[np.float64]
    mv_masked_al_uncomp_db_sl: NDArray[np.float64]
    ev_masked_al_uncomp_db_sl: NDArray[np.float64]
    mv_perceived_uncomp_db_sl: NDArray[np.float64]
    ev_perceived_uncomp_db_sl: NDArray[np.float64]

    def inputs(self, compensated: bool) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(mv_input_db_sl, ev_input_db_sl)`` to play: compensated, or the targets as they are."""
        if compensated:
            return self.mv_input_db_sl, self.ev_input_db_sl
        return self.mv_target_db_sl, self.ev_target_db_sl

    def perceived(self, compensated: bool) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(mv_perceived_db_sl, ev_perceived_db_sl)`` with or without compensation."""
        if compensated:
            return self.mv_perceived_db_sl, self.ev_perceived_db_sl
        return self.mv_perceived_uncomp_db_sl, self.ev_perceived_uncomp_db_sl


def needed_pairs(scene: Scene) -> list[tuple[str, str]]:
    """(MV stimulus, EV stimulus) pairs whose masking functions ``scene`` needs (0 or 1)."""
    return scene.stimulus_pairs()


def render_scene(
    scene: Scene,
    pair: MutualMasking | None,
    *,
    max_mv_db_sl: float | None = None,
    max_ev_db_sl: float | None = None,
) -> Rendering:
    """Targets, compensated inputs and perceived intensities at every point of ``scene``.

    Parameters
    ----------
    scene : Scene
        The scene.
    pair : MutualMasking or None
        Masking functions of the scene's (MV, EV) pair; None for a single-channel scene.
    max_mv_db_sl, max_ev_db_sl : float, optional
        Rated maximum input per channel, dB SL; points needing more are flagged, not clipped.

    Raises
    ------
    SolverError
        A two-channel scene without ``pair``, or a pair for other stimuli than the scene's.
    """
    needs = needed_pairs(scene)
    if needs:
        if pair is None:
            mv, ev = needs[0]
            raise SolverError(
                f"{scene.source}: scene {scene.name!r} plays {mv} and {ev} together and needs "
                "their masking functions; load them from masking_params.json"
            )
        if (pair.mv, pair.ev) != needs[0]:
            raise SolverError(
                f"{scene.source}: scene {scene.name!r} uses {needs[0][0]} with {needs[0][1]} "
                f"but the masking functions given are for {pair.mv} with {pair.ev}"
            )
        model = pair
    else:
        pair = None
        model = NO_MASKING
    x, mv_t, ev_t = scene.targets()
    sol = solve(model, mv_t, ev_t, max_mv_db_sl=max_mv_db_sl, max_ev_db_sl=max_ev_db_sl)
    m_i, e_i = sol.mv_input_db_sl, sol.ev_input_db_sl
    f_c, g_c = mv_masked_al_db_sl(model, e_i), ev_masked_al_db_sl(model, m_i)
    f_u, g_u = mv_masked_al_db_sl(model, ev_t), ev_masked_al_db_sl(model, mv_t)
    return Rendering(
        scene=scene,
        pair=pair,
        x_mm=x,
        t_s=x / scene.path.speed_mm_s,
        mv_target_db_sl=mv_t,
        ev_target_db_sl=ev_t,
        solution=sol,
        mv_input_db_sl=m_i,
        ev_input_db_sl=e_i,
        mv_masked_al_db_sl=f_c,
        ev_masked_al_db_sl=g_c,
        mv_perceived_db_sl=m_i - f_c,
        ev_perceived_db_sl=e_i - g_c,
        mv_masked_al_uncomp_db_sl=f_u,
        ev_masked_al_uncomp_db_sl=g_u,
        mv_perceived_uncomp_db_sl=mv_t - f_u,
        ev_perceived_uncomp_db_sl=ev_t - g_u,
    )


# --------------------------------------------------------------------------------------------
# Summaries


def runs_mm(mask: NDArray[np.bool_], x_mm: NDArray[np.float64]) -> list[tuple[float, float]]:
    """Contiguous stretches where ``mask`` holds, as (first, last) positions in mm."""
    idx = np.flatnonzero(np.diff(np.concatenate(([0], mask.astype(np.int8), [0]))))
    pairs = zip(idx[::2], idx[1::2], strict=True)
    return [(round(float(x_mm[a]), 6), round(float(x_mm[b - 1]), 6)) for a, b in pairs]


def summarize(r: Rendering) -> dict[str, Any]:
    """JSON-ready summary: statuses, cases, rating problems, worst perceived errors."""
    sol = r.solution
    out: dict[str, Any] = {
        "scene": r.scene.name,
        "scene_file": r.scene.source,
        "scene_sha256": r.scene.sha256,
        "software_version": __version__,
        "n_points": int(r.x_mm.size),
        "single_channel": r.pair is None,
        "masking": None
        if r.pair is None
        else {
            "mv": r.pair.mv,
            "ev": r.pair.ev,
            "a_db": r.pair.a_db,
            "b": r.pair.b,
            "c_db": r.pair.c_db,
            "d": r.pair.d,
            "bd": r.pair.bd,
        },
        "status_counts": sol.counts(),
        "case_counts": {str(k): int(np.count_nonzero(sol.case == k)) for k in range(1, 5)},
        "notes": [] if r.pair is None else list(r.pair.notes),
        "no_answer_reasons": {
            REASON_TEXT[Reason(k)]: int(np.count_nonzero(sol.reason == k))
            for k in range(1, len(Reason))
            if np.any(sol.reason == k)
        },
    }
    channels: dict[str, Any] = {}
    for ch, name in (("mv", "MV"), ("ev", "EV")):
        target = getattr(r, f"{ch}_target_db_sl")
        if np.all(target == -np.inf):
            continue
        inp = getattr(r, f"{ch}_input_db_sl")
        limit = getattr(sol, f"max_{ch}_db_sl")
        over = getattr(sol, f"{ch}_exceeds_rating")
        entry: dict[str, Any] = {
            "stimulus": _stimulus(r.scene, ch),
            "target_range_db_sl": _range(target),
            "input_range_db_sl": _range(inp),
            "max_rated_db_sl": limit,
            "points_above_rating": int(np.count_nonzero(over)),
            "above_rating_mm": [list(run) for run in runs_mm(over, r.x_mm)],
        }
        # This channel's input is the masker of the other channel's ramp; beyond the masker
        # levels that ramp was fitted on, the compensation extrapolates.
        fitted = None
        if r.pair is not None:
            fitted = r.pair.g_fitted_range_db_sl if ch == "mv" else r.pair.f_fitted_range_db_sl
        entry["masks_other_fitted_range_db_sl"] = list(fitted) if fitted else None
        entry["points_beyond_fitted_range"] = (
            int(np.count_nonzero(inp > fitted[1])) if fitted else None
        )
        for label, compensated in (("compensated", True), ("uncompensated", False)):
            perceived = r.perceived(compensated)[0 if ch == "mv" else 1]
            err = np.abs(perceived - target)
            lost = (target >= 0) & (perceived < 0)
            entry[label] = {
                "max_abs_error_db": _num(np.nanmax(err)) if np.any(np.isfinite(err)) else None,
                "points_not_felt": int(np.count_nonzero(lost)),
            }
        channels[name] = entry
    out["channels"] = channels
    return out


def _stimulus(scene: Scene, ch: str) -> str:
    if ch == "mv":
        return scene.texture.stimulus if scene.texture is not None else ""
    return scene.geometry.stimulus if scene.geometry is not None else ""


def _range(a: NDArray[np.float64]) -> list[Any] | None:
    ok = a[np.isfinite(a)]
    return [_num(ok.min()), _num(ok.max())] if ok.size else None


def _num(x: float) -> float | str | None:
    x = float(x)
    if math.isnan(x):
        return None
    if math.isinf(x):
        return "-inf" if x < 0 else "inf"
    return x


# --------------------------------------------------------------------------------------------
# Files

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
)


def points_csv(r: Rendering) -> str:
    """The per-point table as CSV text (floats round-trip exactly; −inf is a silent channel)."""
    sol = r.solution
    cols: list[Sequence[Any]] = []
    for name in POINT_COLUMNS:
        if name == "case":
            cols.append([str(int(c)) for c in sol.case])
        elif name == "status":
            cols.append(sol.status_names())
        elif name.endswith("exceeds_rating"):
            cols.append(["1" if v else "0" for v in getattr(sol, name)])
        else:
            cols.append([repr(float(v)) for v in getattr(r, name)])
    lines = [",".join(POINT_COLUMNS)]
    lines += [",".join(row) for row in zip(*cols, strict=True)]
    return "\n".join(lines) + "\n"


def write_rendering(r: Rendering, out_dir: str | Path, *, figure: bool = True) -> list[Path]:
    """Write ``points.csv``, ``summary.json`` and (optionally) ``figure4.png`` into ``out_dir``.

    Each file is written atomically and fsynced. Returns the paths written.
    """
    out = Path(out_dir)
    written = [
        write_text_atomic(out / "points.csv", points_csv(r)),
        write_text_atomic(
            out / "summary.json", json.dumps(summarize(r), indent=2, allow_nan=False) + "\n"
        ),
    ]
    if figure:
        from masking_lab.rendering.figures import figure4_png

        written.append(write_bytes_atomic(out / "figure4.png", figure4_png(r)))
    return written


def measurement_protocol(
    problems: Sequence[PairProblem], *, levels_db_sl: Sequence[float] = MEASURE_LEVELS_DB_SL
) -> dict[str, Any]:
    """A masked-threshold protocol measuring only the masking functions in ``problems``.

    One set per (target, masker, level); the staircase and timing are those of the shipped
    experiment I protocol, so the new data pool with the paper's.

    Parameters
    ----------
    problems : sequence of PairProblem
        The directions to measure (target stimulus, masker stimulus).
    levels_db_sl : sequence of float
        Masker levels, dB SL (default the paper's 5–25 dB SL).
    """
    if not problems:
        raise SolverError("nothing to measure: every masking function the scene needs is fitted")
    template = yaml.safe_load(shipped("protocols", "experiment1.yaml").read_text(encoding="utf-8"))
    stimuli = sorted({p.target for p in problems} | {p.masker for p in problems})
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
        "experiment": "measure_" + "_".join(stimuli),
        "description": f"Measures only what a scene needs and the parameters lack: {listed}, "
        f"at {', '.join(f'{lv:g}' for lv in levels_db_sl)} dB SL. Written by masking-lab "
        "render; run after the baseline of every stimulus involved.",
        "kind": "masked",
        "staircase": template["staircase"],
        "timing": template["timing"],
        "order": {"randomize": True},
        "sets": sets,
    }


def write_measurement_protocol(protocol: Mapping[str, Any], out_dir: str | Path) -> Path:
    """Validate ``protocol`` with the protocol loader and write it as ``<experiment>.yaml``."""
    from masking_lab.formats.protocol import parse_protocol

    text = (
        "# Written by masking-lab render: measures the masking a scene needs.\n"
        + yaml.safe_dump(dict(protocol), sort_keys=False, allow_unicode=True)
    )
    path = Path(out_dir) / f"{protocol['experiment']}.yaml"
    parse_protocol(text.encode("utf-8"), str(path))
    return write_text_atomic(path, text)
